"""``sq-mitsuba bench SUITE``: run a benchmark suite, print it, optionally record it."""

from __future__ import annotations

import argparse

from sq_mitsuba.cli._options import add_config_options, config_from_args
from sq_mitsuba.evaluation import bench

FLAGS = {"repeats": "--repeats", "warmup": "--warmup", "threads": "--threads",
         "device": "--device"}


def register(subparsers: argparse._SubParsersAction) -> None:
    suites = bench.available_suites()
    parser = subparsers.add_parser(
        "bench", help="measure the speed figures named in the issues",
        description="Run benchmark suites; --write records them in eval/BENCHMARKS.md.")
    parser.add_argument("suite", choices=[*suites, "all"], help="which suite to run")
    add_config_options(parser, bench.BenchOptions, FLAGS)
    parser.add_argument("--write", action="store_true",
                        help="store the figures in eval/BENCHMARKS.md")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    options = config_from_args(bench.BenchOptions, args)
    for report in bench.run_suites([args.suite], options, write=args.write):
        print(report.to_markdown())
        if args.write:
            print(f"recorded in {bench.BENCHMARKS_MD}")
    return 0
