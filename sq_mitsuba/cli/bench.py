"""``sq-mitsuba bench SUITE``: run a benchmark suite, print it, optionally record it."""

from __future__ import annotations

import argparse

from sq_mitsuba.evaluation import bench


def register(subparsers: argparse._SubParsersAction) -> None:
    suites = bench.available_suites()
    parser = subparsers.add_parser(
        "bench", help="measure the speed figures named in the issues",
        description="Run benchmark suites; --write records them in eval/BENCHMARKS.md.")
    parser.add_argument("suite", choices=[*suites, "all"], help="which suite to run")
    parser.add_argument("--repeats", type=int, default=20, help="timed runs (default 20)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed runs first (default 3)")
    parser.add_argument("--threads", type=int, default=2,
                        help="torch CPU threads (default 2, the reference machine)")
    parser.add_argument("--device", default="cpu", help="torch device (cpu or cuda)")
    parser.add_argument("--write", action="store_true",
                        help="store the figures in eval/BENCHMARKS.md")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import torch

    if args.repeats < 1 or args.warmup < 0 or args.threads < 1:
        raise ValueError("--repeats and --threads must be >= 1, --warmup >= 0")
    torch.set_num_threads(args.threads)
    options = bench.BenchOptions(repeats=args.repeats, warmup=args.warmup,
                                 threads=args.threads, device=args.device)
    names = bench.available_suites() if args.suite == "all" else [args.suite]
    for name in names:
        report = bench.run_suite(name, options)
        print(report.to_markdown())
        if args.write:
            bench.write_report(report)
            print(f"recorded in {bench.BENCHMARKS_MD}")
    return 0
