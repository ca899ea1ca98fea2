"""Does the network read a new spacecraft better than looking one up in its training library?

On evenly spread test images (e.g. the held-out families), the body-frame Chamfer-L1 (the
paper's) to each image's true surface of five answers:

* **reading**: the network's assembly, as read;
* **library constant**: one library spacecraft for every image, the one nearest to the test
  surfaces on average among those that are some test surface's near candidates (chosen with
  the truth);
* **feature look-up**: the true surface of the library image whose shape latent (z_sq, the
  input of the superquadric generators) is nearest to the test image's, by cosine;
* **reading look-up**: the library spacecraft nearest to the network's reading;
* **nearest in the library** (an oracle): the library spacecraft nearest to the image's own
  true surface; no answer drawn from the library can do better. With ``--turns``, also the
  nearest when the truth may be turned by any of the 24 axis-aligned rotations (the body
  frame's labels and ends given free). With ``--sizes N...``, also the nearest among N
  library spacecraft drawn at random (nested subsets): how the oracle falls as the library
  grows; ``--size-draws K`` repeats the draw with K random orders and prints their range,
  ``--plot PNG`` draws it.

The library is a training dataset (its train split): every model's surface, and, for the
feature look-up, LIBRARY_IMAGES of its images spread evenly. A library is ranked for each
cloud by coarse clouds of COARSE_POINTS points, the CANDIDATES nearest then measured exactly.

    .venv/bin/python eval/experiments/library_coverage.py --checkpoint MODEL --data DIR \
        --library TRAIN_DIR [--images 96] [--library-images 400] [--turns] \
        [--sizes 100 300 1000 [--size-draws 5] [--plot sizes.png]]
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from spread_images import open_spread_images, readings_and_truths, thinned

from sq_mitsuba.evaluation.split import collate, open_split
from sq_mitsuba.geometry.so3_grid import axis_turns

#: Points of the coarse clouds that rank a library before the exact distances.
COARSE_POINTS = 200
#: Library spacecraft per cloud whose exact distance is computed (the coarse ranking's first).
CANDIDATES = 12


class Cloud:
    """A (1, P, 3) cloud with its KD trees built once, full and coarse (COARSE_POINTS of its
    points drawn evenly: a reading's points come primitive by primitive): the paper's
    Chamfer-L1 as :func:`spread_images.distance` computes it, exactly or roughly."""

    def __init__(self, cloud: torch.Tensor) -> None:
        self.points = cloud[0].numpy()
        self.tree = cKDTree(self.points)
        step = max(1, len(self.points) // COARSE_POINTS)
        self.coarse_points = self.points[::step]
        self.coarse_tree = cKDTree(self.coarse_points)

    def distance(self, other: Cloud) -> float:
        forward = self.tree.query(other.points, k=1, p=1)[0].mean()
        backward = other.tree.query(self.points, k=1, p=1)[0].mean()
        return float(forward + backward)

    def rough_distance(self, other: Cloud) -> float:
        forward = self.coarse_tree.query(other.coarse_points, k=1, p=1)[0].mean()
        backward = other.coarse_tree.query(self.coarse_points, k=1, p=1)[0].mean()
        return float(forward + backward)


def rough_distances(cloud: Cloud, library: list[Cloud]) -> np.ndarray:
    """(len(library),) the coarse clouds' distances from ``cloud`` to every library cloud."""
    return np.array([cloud.rough_distance(c) for c in library])


def to_library(cloud: Cloud, library: list[Cloud], rough: np.ndarray | None = None
               ) -> np.ndarray:
    """(len(library),) the exact distance to the CANDIDATES library clouds nearest by the
    coarse clouds, infinity to the rest: enough for a nearest and for the rows' look-ups,
    which only need the distance to one given spacecraft (computed exactly where missing).
    ``rough``: :func:`rough_distances` of ``cloud``, when already computed."""
    rough = rough_distances(cloud, library) if rough is None else rough
    exact = np.full(len(library), np.inf)
    for j in np.argsort(rough)[:CANDIDATES]:
        exact[j] = cloud.distance(library[j])
    return exact


def nearest_by_size(clouds: list[Cloud], library: list[Cloud], rough: np.ndarray,
                    sizes: list[int], seed: int = 0,
                    measured: dict[tuple[int, int], float] | None = None
                    ) -> dict[int, np.ndarray]:
    """For each library size n in ``sizes``: (len(clouds),) the exact distance from each
    cloud to its nearest among the first n library clouds of one random order (seeded), so
    the smaller libraries are nested in the larger ones, as if the generator had made only
    n spacecraft. ``rough``: (len(clouds), len(library)) the coarse distances; each subset is
    ranked by them and its CANDIDATES nearest measured exactly, as :func:`to_library` does.
    ``measured``: exact distances by (cloud, library cloud) already known, filled in as
    they are computed (shared between calls, each pair is measured once)."""
    order = np.random.default_rng(seed).permutation(len(library))
    measured = {} if measured is None else measured

    def exact(i: int, j: int) -> float:
        if (i, j) not in measured:
            measured[i, j] = clouds[i].distance(library[j])
        return measured[i, j]

    nearest = {}
    for size in sizes:
        members = order[:size]
        nearest[size] = np.array([
            min(exact(i, int(j)) for j in members[np.argsort(rough[i, members])[:CANDIDATES]])
            for i in range(len(clouds))])
    return nearest


def nearest_turned(truth: torch.Tensor, library: list[Cloud]) -> float:
    """The exact distance from a (1, P, 3) cloud, turned by any of the 24 axis-aligned
    rotations, to its nearest library cloud: the CANDIDATES (turn, library cloud) pairs
    nearest by the coarse clouds, measured exactly."""
    turned = [Cloud(truth @ turn.T) for turn in axis_turns()]
    rough = np.array([[t.rough_distance(c) for c in library] for t in turned])
    pairs = np.argsort(rough, axis=None)[:CANDIDATES]
    return min(turned[k // len(library)].distance(library[k % len(library)]) for k in pairs)


@contextlib.contextmanager
def shape_latents(predictor) -> Iterator[list[torch.Tensor]]:
    """A list that collects the network's z_sq (B, latent), the generators' input, of every
    batch the predictor reads while the context is open, in order."""
    captured: list[torch.Tensor] = []
    hook = predictor.model.latent_head.register_forward_hook(
        lambda _module, _inputs, output: captured.append(output[0].detach().double()))
    try:
        yield captured
    finally:
        hook.remove()


def unit_rows(latents: list[torch.Tensor]) -> torch.Tensor:
    """(N, latent) the collected latents, each scaled to unit length (for the cosine)."""
    return torch.nn.functional.normalize(torch.cat(latents), dim=1)


def main() -> None:
    # This script's own option joins the shared ones (spread_images parses sys.argv).
    extra = argparse.ArgumentParser(add_help=False)
    # Not required under --help, which the shared parser prints (this one has no help).
    extra.add_argument("--library", required=not {"-h", "--help"} & set(sys.argv[1:]))
    extra.add_argument("--library-images", type=int, default=400)
    extra.add_argument("--turns", action="store_true")
    extra.add_argument("--sizes", type=int, nargs="+", default=[])
    extra.add_argument("--size-draws", type=int, default=1)
    extra.add_argument("--plot")
    own, rest = extra.parse_known_args()
    sys.argv = [sys.argv[0], *rest]
    spread = open_spread_images(__doc__.split("\n\n")[0])
    if own.library_images < 1:
        raise SystemExit("--library-images: need at least 1")
    if any(size < 1 for size in own.sizes):
        raise SystemExit(f"--sizes: every size must be at least 1, got {own.sizes}")
    if own.size_draws < 1:
        raise SystemExit(f"--size-draws: need at least 1, got {own.size_draws}")
    if own.plot and not own.sizes:
        raise SystemExit("--plot: draws the oracle against --sizes, which is not given")
    rng = np.random.default_rng(0)
    library = open_split(own.library, "train", spread.predictor.image_size, 2000)
    picks = np.linspace(0, len(library) - 1, min(own.library_images, len(library))).round()
    library_models: list[str] = []
    with shape_latents(spread.predictor) as library_latents:
        for start in range(0, len(picks), 32):
            batch = collate([library[int(i)] for i in picks[start:start + 32]])
            spread.predictor.predict(batch["image"])
            library_models.extend(batch["model"])
    # Every model's surface, whether or not one of its images was picked: one item each.
    first_item: dict[int, int] = {}
    for item, (model_index, _index, _label) in enumerate(library.items):
        first_item.setdefault(model_index, item)
    surfaces: dict[str, Cloud] = {}
    for item in first_item.values():
        entry = library[item]
        surfaces[entry["model"]] = Cloud(thinned(entry["surface_points"], rng))
    names = sorted(surfaces)
    if any(size > len(names) for size in own.sizes):
        raise SystemExit(f"--sizes: the library holds {len(names)} spacecraft, "
                         f"fewer than {max(own.sizes)}")

    truths: list[torch.Tensor] = []
    truth_clouds: list[Cloud] = []
    reading_clouds: list[Cloud] = []
    # The readings' own network pass gives their latents: each test image is read once.
    with shape_latents(spread.predictor) as test_latents:
        for _model, reading, truth in readings_and_truths(spread, rng):
            truths.append(truth)
            truth_clouds.append(Cloud(truth))
            reading_clouds.append(Cloud(reading))

    # (test images, library models): every truth and every reading against every surface.
    clouds = [surfaces[m] for m in names]
    truth_rough = np.array([rough_distances(c, clouds) for c in truth_clouds])
    truth_to_library = np.array([to_library(c, clouds, rough)
                                 for c, rough in zip(truth_clouds, truth_rough, strict=True)])
    nearest_to_reading = [int(to_library(c, clouds).argmin()) for c in reading_clouds]
    nearest_image = (unit_rows(test_latents) @ unit_rows(library_latents).T).argmax(1).numpy()
    looked_up = [names.index(library_models[j]) for j in nearest_image]
    # The library constant: the best over the whole library would need every pair measured
    # exactly; the candidates found for some test surface stand in for it, each then scored
    # exactly against every test surface.
    found = sorted({int(j) for row in truth_to_library for j in np.flatnonzero(np.isfinite(row))})
    constant = min(found, key=lambda j: np.mean([c.distance(clouds[j]) for c in truth_clouds]))

    def exact(index: int, library_index: int) -> float:
        value = truth_to_library[index, library_index]
        return value if np.isfinite(value) else truth_clouds[index].distance(
            clouds[library_index])

    rows = range(len(truths))
    figures = {
        "reading": np.array([r.distance(t)
                             for r, t in zip(reading_clouds, truth_clouds, strict=True)]),
        "library constant": np.array([exact(i, constant) for i in rows]),
        "feature look-up": np.array([exact(i, looked_up[i]) for i in rows]),
        "reading look-up": np.array([exact(i, nearest_to_reading[i]) for i in rows]),
        "nearest in the library (oracle)": truth_to_library.min(1),
    }
    if own.turns:
        figures["nearest in the library, any axis turn (oracle)"] = np.array(
            [nearest_turned(truth, clouds) for truth in truths])
    sizes = sorted(set(own.sizes))
    # (draws, sizes): the oracle's mean over the images for each random order of the library.
    # The pairs the oracle row measured, and every pair one order measures, serve the others.
    measured = {(int(i), int(j)): float(truth_to_library[i, j])
                for i, j in zip(*np.nonzero(np.isfinite(truth_to_library)), strict=True)}
    by_draw = []
    for draw in range(own.size_draws):
        nearest = nearest_by_size(truth_clouds, clouds, truth_rough, sizes, seed=draw,
                                  measured=measured)
        by_draw.append([nearest[size].mean() for size in sizes])
        if draw == 0:
            for size, values in nearest.items():
                figures[f"nearest among {size} of the library (oracle)"] = values
    by_draw = np.array(by_draw)
    print(f"{len(truths)} images of {spread.args.data} ({spread.args.split}) against "
          f"{len(names)} spacecraft of {own.library} ({len(picks)} of its images), "
          f"{spread.args.checkpoint}")
    print("| answer | body-frame Chamfer-L1 mean | median |")
    print("|---|---|---|")
    for name, values in figures.items():
        print(f"| {name} | {values.mean():.4f} | {np.median(values):.4f} |")
    if sizes and own.size_draws > 1:
        print(f"\nThe oracle's mean over {own.size_draws} random orders of the library:")
        print("| library spacecraft | mean over the orders | lowest | highest |")
        print("|---|---|---|---|")
        for column, size in enumerate(sizes):
            draws = by_draw[:, column]
            print(f"| {size} | {draws.mean():.4f} | {draws.min():.4f} | {draws.max():.4f} |")
    if own.plot:
        plot_sizes(own.plot, sizes, by_draw, figures, f"{len(truths)} images of "
                   f"{spread.args.data}, library {own.library}")


def plot_sizes(path: str, sizes: list[int], by_draw: np.ndarray,
               figures: dict[str, np.ndarray], title: str) -> None:
    """The oracle's mean against the library's size (the orders' mean, their range as a
    bar), beside the reading's and the library constant's means, in a PNG at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sq_mitsuba.io import atomic_path

    means = by_draw.mean(0)
    figure, axis = plt.subplots(figsize=(5.5, 3.6))
    # Clipped at 0: where every order gives the same mean, rounding can leave -1e-17.
    spread = np.clip([means - by_draw.min(0), by_draw.max(0) - means], 0.0, None)
    axis.errorbar(sizes, means, yerr=spread,
                  fmt="o-", capsize=3, label="nearest library spacecraft (oracle)")
    for name, style in (("reading", "--"), ("library constant", ":")):
        axis.axhline(figures[name].mean(), color="grey", linestyle=style, label=name)
    axis.set_xscale("log")
    axis.set_xticks(sizes, [str(size) for size in sizes])
    axis.set_xlabel("library spacecraft")
    axis.set_ylabel("body-frame Chamfer-L1, mean")
    axis.set_title(title, fontsize=7)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7)
    figure.tight_layout()
    with atomic_path(Path(path)) as tmp:
        figure.savefig(tmp, dpi=110, format="png")
    plt.close(figure)


if __name__ == "__main__":
    main()
