"""How near the truth is the best of the network's first k rotation hypotheses?

A distribution head's reading lists its distinct modes, best first (``rotation_hypotheses``,
written into ``pose.json`` by ``sq-mitsuba predict``). A tracker or a structure-from-motion run
that can test a few starts gains from them if the truth is often near one of the first few.
On evenly spread test images this prints, for k = 1, 2, 4, ... K, the folded rotation error
(up to the four half turns, as ``sq-mitsuba eval``'s) of the best of the first k hypotheses:
its median and the share of images within 20 and 30 deg. The choice of the best is an oracle
(the truth picks it): the figure says what the list holds, not what a method reaches.

    .venv/bin/python eval/experiments/hypotheses_coverage.py --checkpoint MODEL --data DIR \
        [--split test] [--images 96] [--turns 8]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch
from spread_images import folded_error_deg, open_spread_images

from sq_mitsuba.evaluation.split import collate


def add_turns(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--turns", type=int, default=8,
                        help="read the rotation from this many in-plane turned copies (1: one "
                             "reading; a distribution head only)")


def best_of_first(errors: np.ndarray) -> np.ndarray:
    """(N, K) errors of each image's K hypotheses -> (N, K): column k - 1 the least of the
    first k."""
    return np.minimum.accumulate(errors, axis=1)


def main() -> None:
    spread = open_spread_images(__doc__.split("\n\n")[0], add_arguments=add_turns)
    predictor, turns = spread.predictor, spread.args.turns
    try:
        predictor.check_turns(turns, spread.camera)
    except ValueError as error:  # a regressing head, or a camera that cannot turn: one line
        sys.exit(str(error))
    rows = []
    for start in range(0, len(spread.chosen), 16):
        batch = collate([spread.dataset[int(i)] for i in spread.chosen[start:start + 16]])
        reading = predictor.predict(batch["image"], spread.camera, turns=turns)
        for k in range(len(batch["model"])):
            truth = batch["rotation"][k]
            rows.append([folded_error_deg(h, truth) for h in reading.rotation_hypotheses[k]])
    best = best_of_first(np.array(rows))
    count = best.shape[1]
    print(f"{len(rows)} images of {spread.args.data} ({spread.args.split}), "
          f"{spread.args.checkpoint}, {turns} turned cop{'y' if turns == 1 else 'ies'}; "
          f"{count} hypotheses an image")
    for k in sorted({1, 2, 4, 8, count} & set(range(1, count + 1))):
        column = best[:, k - 1]
        print(f"first {k}: median {np.median(column):.1f} deg, within 20 deg "
              f"{np.mean(column < 20):.0%}, within 30 deg {np.mean(column < 30):.0%}")


if __name__ == "__main__":
    with torch.inference_mode():
        main()
