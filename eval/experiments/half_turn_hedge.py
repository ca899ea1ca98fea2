"""Does the network hedge over the ends of the body axes?

An image of an unknown spacecraft shows its axes but often not which end of each is "+", while
the training's Chamfer term compares the reading with the true surface in the true body frame,
ends included. A reader unsure of the ends lowers that term by answering with a shape that
looks the same after a half turn about each axis (bodies at the centre, discs and needles
through the origin). On evenly spread test images this measures, for each body-frame reading
S and its model's true surface G (Chamfer-L1, the paper's, on thinned surface samples):

* **asymmetry** ``a(X)``: the mean over the three half turns h (180 deg about x, y, z) of
  Chamfer-L1(X, h X); 0 for a shape the half turns leave unchanged. Readings far more
  symmetric than their truths (``a(S) / a(G)`` well below 1) are the hedge;
* **as read / ends folded**: Chamfer-L1(S, G), and its minimum over G and its three half
  turns, i.e. the reading scored as if the ends it chose were the truth's;
* **the perfect hedge**: Chamfer-L1 of G's half-turn-symmetric hull (G and its three half
  turns together) against G: what a reader that knows the shape but not the ends would lose
  by hedging.

    .venv/bin/python eval/experiments/half_turn_hedge.py --checkpoint MODEL --data DIR [--images 96]
"""

from __future__ import annotations

import numpy as np
import torch
from spread_images import distance, open_spread_images, readings_and_truths, thinned

#: The three half turns about the body axes, as the diagonal they multiply points by.
HALF_TURNS = torch.tensor([[1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]],
                          dtype=torch.float64)


def asymmetry(cloud: torch.Tensor) -> float:
    """Mean Chamfer-L1 between a (1, P, 3) cloud and its three half turns."""
    return float(np.mean([distance(cloud, cloud * turn) for turn in HALF_TURNS]))


def folded(reading: torch.Tensor, truth: torch.Tensor) -> float:
    """Chamfer-L1 of the reading against the truth at its best of the four half-turn labels."""
    return min(distance(reading, truth * turn) for turn in
               torch.cat([torch.ones(1, 3, dtype=torch.float64), HALF_TURNS]))


def symmetric_hull(cloud: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    """The cloud and its three half turns together, thinned back to POINTS."""
    union = torch.cat([cloud[0]] + [cloud[0] * turn for turn in HALF_TURNS])
    return thinned(union, rng)


def main() -> None:
    spread = open_spread_images(__doc__.split("\n\n")[0])
    rng = np.random.default_rng(0)
    rows: list[tuple[float, float, float, float, float]] = []
    for _, reading, truth in readings_and_truths(spread, rng):
        rows.append((asymmetry(reading), asymmetry(truth), distance(reading, truth),
                     folded(reading, truth), distance(symmetric_hull(truth, rng), truth)))
    table = np.array(rows)
    read_asym, true_asym, as_read, ends_folded, hedge = table.mean(0)
    print(f"{len(rows)} images of {spread.args.data} ({spread.args.split}), "
          f"{spread.args.checkpoint}")
    print(f"asymmetry under the half turns: readings {read_asym:.4f}, truths {true_asym:.4f} "
          f"({read_asym / true_asym:.2f} x); median per image "
          f"{np.median(table[:, 0] / table[:, 1]):.2f} x")
    print(f"Chamfer-L1 as read {as_read:.4f}, ends folded {ends_folded:.4f} "
          f"({1 - ends_folded / as_read:.1%} lower); the perfect hedge (the truth's "
          f"half-turn-symmetric hull) {hedge:.4f}")


if __name__ == "__main__":
    main()
