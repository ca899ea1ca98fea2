"""Is the shape read from the image? Rank a predicted assembly against every model's mesh.

A network that reads the shape predicts, for an image of model m, an assembly that is closer to
m's mesh than to the meshes of the other models. For each prediction this module measures the
Chamfer-L1 (paper convention: L1 nearest neighbours, both directions' means summed, as
:func:`sq_mitsuba.geometry.metrics.chamfer_l1`) to the surface points of every candidate
model and reports:

- ``rank``: 1 + the number of *other* candidates strictly closer than the image's own model
  (1: its own mesh is the nearest);
- ``beaten``: the fraction of the other candidates farther than (or as far as) its own model
  (1.0: its own mesh is the nearest; 0.5: chance).

Convention: the candidates of ``sq-mitsuba eval --split val`` are the dataset's training models
(val images are new views of them), those of ``--split test`` the test models. Clouds are
(N, 3) float64 numpy arrays in the body frame of the labels; a prediction's cloud is its
primitives' surface points that lie inside no other primitive (as the eval's Chamfer-L1).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sq_mitsuba.geometry.assembly import Assembly

__all__ = ["MeshRanking", "OwnMeshRank", "assembly_clouds", "median_rank", "write_mesh_ranking"]


def assembly_clouds(assembly: Assembly, level: int = 3) -> list[np.ndarray]:
    """Per batch item, the (n_b, 3) float64 surface points of ``assembly`` that count: those
    inside no other primitive (all of them when every point is inside another)."""
    from sq_mitsuba.model.losses import counted_surface_samples

    with torch.no_grad():
        points, keep = counted_surface_samples(Assembly(assembly.params.detach().double()), level)
    points, keep = points.cpu().numpy(), keep.cpu().numpy()
    return [cloud[k] for cloud, k in zip(points, keep, strict=True)]


@dataclass(frozen=True)
class OwnMeshRank:
    """Where an image's own model ranks among the candidates (see the module docstring).

    Attributes:
        rank: 1-based rank of the own model's Chamfer-L1 among all candidates.
        beaten: fraction of the other candidates at least as far as the own model.
        own_chamfer: Chamfer-L1 to the own model; nearest_other: the smallest to any other.
    """

    rank: int
    beaten: float
    own_chamfer: float
    nearest_other: float


class MeshRanking:
    """Chamfer-L1 of predicted clouds to a fixed set of candidate clouds (one k-d tree each,
    built once).

    Args:
        clouds: the candidates' surface points, each (K_c, 3) with K_c >= 1; at least two.
    """

    def __init__(self, clouds: Sequence[np.ndarray]) -> None:
        from scipy.spatial import cKDTree

        if len(clouds) < 2:
            raise ValueError(f"clouds: expected at least 2 candidate models, got {len(clouds)}")
        self.clouds = [np.asarray(c, dtype=np.float64) for c in clouds]
        for index, cloud in enumerate(self.clouds):
            if cloud.ndim != 2 or cloud.shape[1] != 3 or len(cloud) == 0:
                raise ValueError(f"clouds[{index}]: expected shape (K, 3) with K >= 1, got "
                                 f"{cloud.shape}")
        self.trees = [cKDTree(cloud) for cloud in self.clouds]

    def __len__(self) -> int:
        return len(self.clouds)

    def chamfer(self, cloud: np.ndarray) -> np.ndarray:
        """Chamfer-L1 (paper convention) of ``cloud`` (N, 3) to every candidate: (C,)."""
        from scipy.spatial import cKDTree

        cloud = np.asarray(cloud, dtype=np.float64)
        if cloud.ndim != 2 or cloud.shape[1] != 3 or len(cloud) == 0:
            raise ValueError(f"cloud: expected shape (N, 3) with N >= 1, got {cloud.shape}")
        own_tree = cKDTree(cloud)
        out = np.empty(len(self.clouds))
        for c, (tree, candidate) in enumerate(zip(self.trees, self.clouds, strict=True)):
            forward = tree.query(cloud, k=1, p=1)[0].mean()
            backward = own_tree.query(candidate, k=1, p=1)[0].mean()
            out[c] = forward + backward
        return out

    def rank(self, cloud: np.ndarray, own: int) -> OwnMeshRank:
        """Where candidate ``own`` ranks for ``cloud`` (N, 3)."""
        if not 0 <= own < len(self.clouds):
            raise ValueError(f"own: expected a candidate index in [0, {len(self.clouds)}), "
                             f"got {own}")
        distances = self.chamfer(cloud)
        others = np.delete(distances, own)
        closer = int((others < distances[own]).sum())
        return OwnMeshRank(rank=1 + closer, beaten=1.0 - closer / len(others),
                           own_chamfer=float(distances[own]),
                           nearest_other=float(others.min()))


def median_rank(ranks: Sequence[OwnMeshRank]) -> dict[str, float]:
    """Medians over images: ``rank``, ``beaten``, and the share of images whose own mesh is
    the nearest (``top1``)."""
    if not ranks:
        raise ValueError("ranks: expected at least one image")
    return {"median_rank": float(np.median([r.rank for r in ranks])),
            "median_beaten": float(np.median([r.beaten for r in ranks])),
            "top1": float(np.mean([r.rank == 1 for r in ranks]))}


def write_mesh_ranking(dataset: Any, to_rank: Sequence[tuple[int, int, str, Assembly]],
                       path: Path, surface_points: int = 2500, level: int = 3,
                       progress: bool = True) -> dict[str, Any]:
    """Rank network predictions against every model of a dataset split and write a CSV.

    Args:
        dataset: an opened split (:class:`sq_mitsuba.data.spe3r.dataset.Spe3rDataset`); its
            models are the candidates, ``surface_points`` of each (chosen with a fixed seed).
        to_rank: per image, (image index, model index, model name, assembly of batch size 1).
        path: the CSV written (atomically): model, index, rank, beaten, own and nearest other
            Chamfer-L1.
        level: icosphere level of the primitives' surface points.

    Returns:
        :func:`median_rank`'s medians with ``candidates`` and ``images`` (for ``eval.json``).
    """
    from sq_mitsuba.io import atomic_write_text
    from sq_mitsuba.progress import progress_bar

    rng = np.random.default_rng(0)
    clouds = []
    for model_index in range(len(dataset.models)):
        surface = dataset.model_points(model_index)["surface"]
        count = min(len(surface), surface_points)
        clouds.append(surface[np.sort(rng.choice(len(surface), count, replace=False))])
    ranking = MeshRanking(clouds)
    ranks, lines = [], []
    for index, model_index, model, assembly in progress_bar(
            to_rank, unit="img", disable=not progress, dynamic_ncols=True, desc="mesh ranking"):
        rank = ranking.rank(assembly_clouds(assembly, level)[0], model_index)
        ranks.append(rank)
        lines.append([model, index, rank.rank, f"{rank.beaten:.4f}", f"{rank.own_chamfer:.5f}",
                      f"{rank.nearest_other:.5f}"])
    header = "model,index,rank,beaten,own_chamfer,nearest_other_chamfer"
    atomic_write_text(path, "\n".join([header, *(",".join(map(str, line)) for line in lines)])
                      + "\n")
    return {**median_rank(ranks), "candidates": len(ranking), "images": len(ranks)}
