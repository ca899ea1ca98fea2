"""Does the network read each spacecraft's own shape, or one shape for all of them?

On evenly spread test images of a dataset, each image's body-frame reading (the network's
assembly, its kept surface samples) is compared with the true surfaces of every model in the
set (Chamfer-L1, the paper's), which gives two figures:

* **spread**: the mean Chamfer-L1 between the readings of two images of different models,
  against the same mean between their true surfaces. A reader that answers every image alike
  has a spread near 0; one as varied as the spacecraft, near the truth's;
* **own-model rank**: where the image's own model falls when every model's surface is ranked
  by its distance to the reading (1: nearest; chance: the middle, (models + 1) / 2), and how
  often it is first.

    .venv/bin/python eval/experiments/reading_spread.py --checkpoint MODEL --data DIR [--images 96]
"""

from __future__ import annotations

import numpy as np
import torch
from spread_images import distance, open_spread_images, readings_and_truths


def own_model_ranks(distances: np.ndarray, own: np.ndarray) -> np.ndarray:
    """(images,) rank of each image's own model, 1 = nearest, among the models' surfaces by
    their distance to its reading: one more than the models strictly nearer (ties favour
    the own model). distances: (images, models); own: (images,) model index per image."""
    own_distance = distances[np.arange(len(own)), own]
    return 1 + (distances < own_distance[:, None]).sum(1)


def main() -> None:
    spread = open_spread_images(__doc__.split("\n\n")[0], min_images=2)
    args = spread.args
    rng = np.random.default_rng(0)
    readings: list[torch.Tensor] = []
    models: list[str] = []
    truths: dict[str, torch.Tensor] = {}
    for model, reading, truth in readings_and_truths(spread, rng):
        readings.append(reading)
        models.append(model)
        truths.setdefault(model, truth)
    names = sorted(truths)
    if len(names) < 2:
        raise SystemExit(f"{args.data} ({args.split}): the images chosen show one model; the "
                         "spread and the ranks need two or more")
    # Each reading against every model's surface: (images, models).
    to_truth = np.array([[distance(r, truths[m]) for m in names] for r in readings])
    own = np.array([names.index(m) for m in models])
    rank = own_model_ranks(to_truth, own)
    pairs = [(i, j) for i in range(len(readings)) for j in range(i + 1, len(readings))
             if models[i] != models[j]]
    pick = rng.choice(len(pairs), min(2000, len(pairs)), replace=False)
    read_spread = np.mean([distance(readings[pairs[p][0]], readings[pairs[p][1]]) for p in pick])
    true_spread = np.mean([distance(truths[models[pairs[p][0]]], truths[models[pairs[p][1]]])
                           for p in pick])
    print(f"{len(readings)} images of {len(names)} models of {args.data} ({args.split}), "
          f"{args.checkpoint}")
    print(f"own-model Chamfer-L1 {to_truth[np.arange(len(own)), own].mean():.4f}; spread of "
          f"the readings {read_spread:.4f} against the truths' {true_spread:.4f} "
          f"({read_spread / true_spread:.2f} x)")
    print(f"own-model rank: median {np.median(rank):.0f}, mean {rank.mean():.1f} of "
          f"{len(names)} (chance {(len(names) + 1) / 2:.1f}); first {np.mean(rank == 1):.1%} "
          f"(chance {1 / len(names):.1%})")


if __name__ == "__main__":
    main()
