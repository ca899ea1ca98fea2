"""``sq-mitsuba bench SUITE``: run a benchmark suite, print it, optionally record it."""

from __future__ import annotations

import argparse
from pathlib import Path

import sq_mitsuba.bench as bench
from sq_mitsuba.cli import CLIError
from sq_mitsuba.cli._options import add_config_options, config_from_args, output_path

FLAGS = {"repeats": "--repeats", "warmup": "--warmup", "threads": "--threads",
         "device": "--device", "batch": "--batch", "step_only": "--step-only"}


def register(subparsers: argparse._SubParsersAction) -> None:
    suites = bench.available_suites()
    parser = subparsers.add_parser(
        "bench", help="time the library's costly steps (rendering, geometry, data, training, "
                      "evaluation)",
        description="Run benchmark suites; --write records them in the source checkout's "
                    "eval/BENCHMARKS.md (the package's own, wherever the command runs). "
                    "'models' times one model a run, every archetype at least once: --repeats "
                    "is held between 14 and 64 models there. "
                    "'curves' trains configs for equal wall time on --data and plots held-out "
                    "Chamfer-L1 against time (--out's learning_curves.png; with --write "
                    "eval/figures/learning_curves.png); a rerun into the same --out keeps the "
                    "points measured and continues each curve from its last point.")
    parser.add_argument("suite", choices=[*suites, "all", "curves"], help="which suite to run")
    add_config_options(parser, bench.BenchOptions, FLAGS)
    parser.add_argument("--write", action="store_true",
                        help=f"store the figures in {bench.BENCHMARKS_MD}")
    curves = parser.add_argument_group("curves")
    curves.add_argument("--data", type=Path, metavar="DIR",
                        help="SPE3R-layout dataset (default: none; required by curves)")
    curves.add_argument("--minutes", type=float, metavar="M",
                        help="training wall time of each config, > 0 (default: none; "
                             "required by curves)")
    curves.add_argument("--out", type=output_path, metavar="DIR",
                        help="folder of the runs, one per config (default: none; required "
                             "by curves)")
    curves.add_argument("--configs", nargs="+", metavar="LABEL",
                        help="which of 'a', 'cpu', 'cpu, no augmentation' (default: all)")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    options = config_from_args(bench.BenchOptions, args)
    try:  # before any suite starts: a device torch cannot use is bad input
        bench.check_device(options.device)
    except ValueError as error:
        raise CLIError(f"--{error}") from None
    if args.suite == "curves":
        return _curves(args)
    for flag, value in (("--data", args.data), ("--minutes", args.minutes), ("--out", args.out),
                        ("--configs", args.configs)):
        if value is not None:  # would be silently ignored by every other suite
            raise CLIError(f"{flag}: only used by the curves suite")
    if args.suite not in ("train", "all"):  # the train suite's own options
        for flag, used in (("--batch", options.batch is not None),
                           ("--step-only", options.step_only)):
            if used:
                raise CLIError(f"{flag}: only used by the train suite")
    for report in bench.run_suites([args.suite], options, write=args.write):
        print(report.to_markdown())
        if args.write:
            print(f"recorded in {bench.BENCHMARKS_MD}")
    return 0


def _curves(args: argparse.Namespace) -> int:
    from sq_mitsuba.bench.curves import check_curves_output, run_curves

    for name, flag in FLAGS.items():  # run_curves takes none of them: refused, not ignored
        if hasattr(args, name):  # the options are absent from args unless given
            raise CLIError(f"{flag}: not used by the curves suite")
    for flag, value in (("--data", args.data), ("--minutes", args.minutes),
                        ("--out", args.out)):
        if value is None:
            raise CLIError(f"{flag}: required by the curves suite")
    if not args.minutes > 0:
        raise CLIError(f"--minutes: expected > 0, got {args.minutes}")
    try:  # before any training: said as the option the user gave ("--out ...")
        check_curves_output(args.data, args.out)
    except ValueError as error:
        message = str(error)
        raise CLIError(f"--{message}" if message.startswith("out") else message) from None
    print(run_curves(args.data, args.out, args.minutes, args.configs, write=args.write))
    return 0
