"""The recipe study's table: one row per training run, from its `sq-mitsuba eval` folders.

Each run folder holds ``eval_val/`` and ``eval_test/`` (``sq-mitsuba eval`` outputs). A row
gives, for val (new views of training models) and test (unknown models): the rotation error
raw, up to the four half turns of the body frame ("folded") and over the model's detected
symmetries ("sym"), each as median / mean in degrees; Chamfer-L1 in the paper's convention
and the 2D IoU at the predicted pose (means); and, from the first run's baseline rows, the
trivial baseline (its mean shape at the mean pose)::

    python eval/experiments/recipe_table.py RUNS_DIR [--names e0 e1 ...] > table.md
"""

from __future__ import annotations

import argparse
import csv
import statistics
from pathlib import Path

ROTATIONS = ("rotation_error_deg", "rotation_error_folded_deg", "rotation_error_sym_deg")
COLUMNS = ("rot raw", "rot folded", "rot sym", "Chamfer-L1", "2D IoU")


def _rows(folder: Path, method: str) -> list[dict[str, str]]:
    path = folder / "per_image.csv"
    if not path.is_file():
        return []
    with path.open(newline="", encoding="utf-8") as handle:
        return [row for row in csv.DictReader(handle) if row["method"] == method]


def _cells(rows: list[dict[str, str]]) -> list[str]:
    if not rows:
        return ["-"] * len(COLUMNS)
    cells = []
    for name in ROTATIONS:
        values = [float(row[name]) for row in rows if row.get(name)]
        cells.append(f"{statistics.median(values):.0f} / {statistics.fmean(values):.0f}"
                     if values else "-")
    for name, digits in (("chamfer_l1_paper", 3), ("iou_2d", 2)):
        values = [float(row[name]) for row in rows if row.get(name)]
        cells.append(f"{statistics.fmean(values):.{digits}f}" if values else "-")
    return cells


def table(runs: Path, names: list[str]) -> str:
    """The Markdown table of the runs ``names`` under ``runs``."""
    header = ["run"] + [f"val {c}" for c in COLUMNS] + [f"test {c}" for c in COLUMNS]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name in names:
        cells = _cells(_rows(runs / name / "eval_val", "network"))
        cells += _cells(_rows(runs / name / "eval_test", "network"))
        lines.append("| " + " | ".join([name, *cells]) + " |")
    first = runs / names[0]
    baseline = _cells(_rows(first / "eval_val", "baseline"))
    baseline += _cells(_rows(first / "eval_test", "baseline"))
    lines.append("| " + " | ".join(["trivial baseline", *baseline]) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, help="folder of run folders")
    parser.add_argument("--names", nargs="*", help="runs in order (default: every folder)")
    args = parser.parse_args()
    names = args.names or sorted(p.name for p in args.runs.iterdir() if p.is_dir())
    print(table(args.runs, names))


if __name__ == "__main__":
    main()
