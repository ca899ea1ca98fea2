"""Is one run's figure really below another's? Two evaluations of the same images, paired.

Two ``sq-mitsuba eval`` outputs (their ``per_image.csv``) on the same test images: for each
metric, the mean difference A - B over the images both scored, a 95 % bootstrap interval of
that difference, and the share of models on which A is lower. The interval resamples models,
not images, since the images of one spacecraft are not independent readings (one model's
four views share its shape). An interval that excludes 0 says the difference is not the
test set's noise; the model card's "within noise" statements are made with it.

    python eval/experiments/paired_difference.py EVAL_A EVAL_B [--metric chamfer_l1_paper ...]
        [--method network] [--resamples 5000] [--seed 0]
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

DEFAULT_METRICS = ("chamfer_l1_paper", "camera_chamfer", "iou_2d", "rotation_error_folded_deg")


def read_scores(folder: Path, method: str, metric: str) -> dict[tuple[str, str], float]:
    """``(model, image index) -> value`` of one method's metric in ``folder/per_image.csv``
    (rows with an empty value left out)."""
    path = folder / "per_image.csv"
    if not path.is_file():
        raise ValueError(f"{folder}: no per_image.csv (not an `sq-mitsuba eval` output)")
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        if metric not in (reader.fieldnames or []):
            raise ValueError(f"{path}: no column {metric!r}")
        return {(row["model"], row["index"]): float(row[metric]) for row in reader
                if row["method"] == method and row[metric] not in ("", "nan")}


def paired_difference(a: dict[tuple[str, str], float], b: dict[tuple[str, str], float],
                      resamples: int = 5000, seed: int = 0) -> dict[str, float]:
    """The paired difference A - B over the images both hold.

    Returns:
        ``mean`` (the mean over models of each model's mean image difference), ``low`` and
        ``high`` (its 95 % bootstrap interval, models resampled), ``lower_share`` (the share
        of models whose mean difference is below 0), ``models`` and ``images`` (counted).

    Raises:
        ValueError: no image in common.
    """
    common = sorted(set(a) & set(b))
    if not common:
        raise ValueError("the two evaluations share no scored image (not the same test set?)")
    per_model: dict[str, list[float]] = {}
    for key in common:
        per_model.setdefault(key[0], []).append(a[key] - b[key])
    differences = np.array([np.mean(values) for values in per_model.values()])
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(differences), (resamples, len(differences)))
    means = differences[picks].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return {"mean": float(differences.mean()), "low": float(low), "high": float(high),
            "lower_share": float((differences < 0).mean()), "models": len(differences),
            "images": len(common)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("a", type=Path, help="an `sq-mitsuba eval` output folder")
    parser.add_argument("b", type=Path, help="another, on the same images")
    parser.add_argument("--metric", nargs="+", default=list(DEFAULT_METRICS))
    parser.add_argument("--method", default="network",
                        help="the rows to compare (network, search, refined, ...)")
    parser.add_argument("--resamples", type=int, default=5000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.resamples < 1:
        print(f"{parser.prog}: --resamples: expected at least 1, got {args.resamples}",
              file=sys.stderr)
        return 2
    try:
        results = {metric: paired_difference(read_scores(args.a, args.method, metric),
                                             read_scores(args.b, args.method, metric),
                                             args.resamples, args.seed)
                   for metric in args.metric}
    except ValueError as error:
        print(f"{parser.prog}: {error}", file=sys.stderr)
        return 2
    print(f"A = {args.a}, B = {args.b} ({args.method}); A - B, 95 % interval over models:")
    for metric, r in results.items():
        verdict = "A lower" if r["high"] < 0 else "A higher" if r["low"] > 0 else "within noise"
        print(f"  {metric:26s} {r['mean']:+.4f} ({r['low']:+.4f} .. {r['high']:+.4f})  "
              f"A lower on {r['lower_share']:.0%} of {r['models']} models, "
              f"{r['images']} images: {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
