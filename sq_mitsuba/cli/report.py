"""``sq-mitsuba report EVAL_DIR...``: evaluation folders in the layout of the paper's tables."""

from __future__ import annotations

import argparse
from pathlib import Path

from sq_mitsuba.cli._options import input_file_path, output_path


def register(subparsers: argparse._SubParsersAction) -> None:
    from sq_mitsuba.evaluation.report import PAPER_TABLES

    parser = subparsers.add_parser(
        "report", help="collate evaluations into the paper's Tables 1 and 2",
        description="Collate folders written by `sq-mitsuba eval` (one split of one run each) "
                    "into report.md and report.csv in the layout of the paper's Tables 1 and "
                    "2, with the paper's published numbers beside ours: in each column the "
                    "best of our methods' rows in bold (the baseline and the refinement "
                    "against the true mask, references, are not ranked) and, apart, the best "
                    "of the paper's rows in "
                    "italics. A run's row is labelled as its eval.json records (sq-mitsuba "
                    "eval --label); its val and test must be of one model (two exports in one "
                    "folder share a default label: name them apart).")
    parser.add_argument("folders", nargs="+", type=Path, metavar="EVAL_DIR",
                        help="evaluation folders (holding eval.json and summary.csv)")
    parser.add_argument("--out", type=output_path, required=True, metavar="DIR",
                        help="output folder for report.md and report.csv")
    parser.add_argument("--paper", type=input_file_path, default=None, metavar="TOML",
                        help="the paper's published tables, read strictly; its [source] "
                             "must state chamfer_convention = \"paper\", the convention "
                             "compared (default: "
                             f"{PAPER_TABLES.relative_to(PAPER_TABLES.parents[1])} of a source "
                             "checkout, when present)")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from sq_mitsuba.evaluation.report import write_report

    path = write_report(args.folders, args.out, args.paper)
    print(f"wrote {path} and {path.with_suffix('.csv')}")
    return 0
