"""One model's figures for the model card's generalisation table, from the four evaluations
``generalisation.sh`` writes (``EVAL/NAME_heldout``, ``_heldout_refined``, ``_infamily``,
``_infamily_refined``; a missing one prints as "-").

    python3 eval/experiments/generalisation_row.py EVAL NAME

The leave-family-out body-frame Chamfer-L1 is given against the trivial baseline the
checkpoint stores (its margin below it, the issue's target 35 %), the camera-frame Chamfer as
a multiple of the baseline's (target 0.55 x), the 2D IoU of the network and after the search +
refinement, and the folded rotation's median for the network and after the search; then the
in-family check (Chamfer-L1 / 2D IoU / refined 2D IoU / the network's folded rotation). A
checkpoint without a baseline (exported without --data) prints its figures with "(no
baseline)" in place of the margin and the ratio.
Standard library only, so it runs without the project installed.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path


def read_summary(folder: Path) -> dict[tuple[str, str], dict[str, float]]:
    """(method, metric) -> {"mean": .., "median": ..} of ``folder/summary.csv``; {} if absent."""
    path = folder / "summary.csv"
    if not path.is_file():
        return {}
    table = {}
    with path.open() as handle:
        for row in csv.DictReader(handle):
            table[row["method"], row["metric"]] = {
                key: float(row[key]) for key in ("mean", "median") if row[key] not in ("", None)}
    return table


def figure(table: dict, method: str, metric: str, stat: str = "mean", digits: int = 3) -> str:
    value = table.get((method, metric), {}).get(stat)
    return "-" if value is None else f"{value:.{digits}f}"


def row(eval_dir: Path, name: str) -> str:
    """The model card's row for ``name`` (markdown, without the run's description)."""
    held = read_summary(eval_dir / f"{name}_heldout")
    held_refined = read_summary(eval_dir / f"{name}_heldout_refined")
    family = read_summary(eval_dir / f"{name}_infamily")
    family_refined = read_summary(eval_dir / f"{name}_infamily_refined")
    parts = ["-"] * 5
    if held:
        chamfer = held["network", "chamfer_l1_paper"]["mean"]
        camera = held["network", "camera_chamfer"]["mean"]
        # A checkpoint exported without --data stores no baseline: its figures stand alone.
        parts[0], parts[1] = f"{chamfer:.4f} (no baseline)", f"{camera:.4f} (no baseline)"
        if ("baseline", "chamfer_l1_paper") in held and ("baseline", "camera_chamfer") in held:
            base = held["baseline", "chamfer_l1_paper"]["mean"]
            camera_base = held["baseline", "camera_chamfer"]["mean"]
            parts[0] = f"{chamfer:.4f} ({100 * (1 - chamfer / base):.1f} % below {base:.3f})"
            parts[1] = f"{camera:.4f} ({camera / camera_base:.2f} x)"
    parts[2] = (f"{figure(held, 'network', 'iou_2d')} / "
                f"{figure(held_refined, 'refined', 'iou_2d')}")
    parts[3] = (f"{figure(held, 'network', 'rotation_error_folded_deg', 'median', 1)} / "
                f"{figure(held_refined, 'search', 'rotation_error_folded_deg', 'median', 1)} deg")
    parts[4] = (f"{figure(family, 'network', 'chamfer_l1_paper')} / "
                f"{figure(family, 'network', 'iou_2d')} / "
                f"{figure(family_refined, 'refined', 'iou_2d')} / "
                f"{figure(family, 'network', 'rotation_error_folded_deg', 'median', 1)} deg")
    return f"| {name} | " + " | ".join(parts) + " |"


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print("usage: generalisation_row.py EVAL NAME [NAME...]", file=sys.stderr)
        return 2
    eval_dir = Path(argv[0])
    if not eval_dir.is_dir():
        print(f"generalisation_row.py: not a folder: {eval_dir}", file=sys.stderr)
        return 2
    print("| run | leave-family-out body-frame Chamfer-L1 | camera-frame (x baseline) | "
          "2D IoU network / refined | folded rotation network / search | "
          "in family: Chamfer / IoU / refined IoU / folded (network) |")
    print("|---|---|---|---|---|---|")
    for name in argv[1:]:
        print(row(eval_dir, name))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
