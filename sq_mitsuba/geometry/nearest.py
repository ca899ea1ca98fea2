"""Nearest neighbours between point clouds: the core of every Chamfer distance in the project.

Exact nearest neighbours come from a KD-tree per cloud (scipy's ``cKDTree``), in float64 and
without gradient; a differentiable distance then gathers the matched points and takes their
differences in torch, so the gradient flows through the matched pairs exactly as through the
``min`` of the dense (all pairs) form.

Convention: clouds are (N, 3) per item, batches (B, N, 3); an optional (B, N) bool mask says
which points count. Callers choose what an item with no point counting means (the training
loss and the validation metric keep all its points, the evaluation metrics refuse it).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["gathered_differences", "matched_indices", "nearest_neighbours"]


def nearest_neighbours(source: np.ndarray, target: np.ndarray, p: float = 2.0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """For each point of ``source`` (n, 3), its nearest point of ``target`` (k >= 1, 3) under
    the L``p`` norm: distances (n,) float64 and indices (n,) int64 into ``target``."""
    from scipy.spatial import cKDTree

    distances, indices = cKDTree(np.asarray(target, dtype=np.float64)).query(
        np.asarray(source, dtype=np.float64), k=1, p=p)
    return np.asarray(distances, dtype=np.float64), np.asarray(indices, dtype=np.int64)


def matched_indices(a: Tensor, a_keep: Tensor, b: Tensor, p: float = 2.0
                    ) -> tuple[Tensor, Tensor]:
    """Nearest-neighbour indices both ways between batches of clouds, without gradient.

    Args:
        a: (B, N, 3); a_keep: (B, N) bool, the points of ``a`` that count (each item must
            keep at least one); b: (B, K, 3), every point counts.
        p: the norm of the distances.

    Returns:
        a_to_b (B, N) int64: index into b of each point of a's nearest point (0 for points
        that do not count); b_to_a (B, K) int64: index into a of each point of b's nearest
        kept point of a. On a's device.
    """
    a_np = a.detach().to("cpu", torch.float64).numpy()
    b_np = b.detach().to("cpu", torch.float64).numpy()
    keep_np = a_keep.detach().to("cpu", torch.bool).numpy()
    a_to_b = np.zeros(keep_np.shape, dtype=np.int64)
    b_to_a = np.empty(b_np.shape[:2], dtype=np.int64)
    for item in range(len(a_np)):  # one KD-tree per item and direction
        kept = np.flatnonzero(keep_np[item])
        a_to_b[item, kept] = nearest_neighbours(a_np[item, kept], b_np[item], p)[1]
        b_to_a[item] = kept[nearest_neighbours(b_np[item], a_np[item, kept], p)[1]]
    return torch.from_numpy(a_to_b).to(a.device), torch.from_numpy(b_to_a).to(a.device)


def gathered_differences(source: Tensor, target: Tensor, index: Tensor) -> Tensor:
    """``source[b, i] - target[b, index[b, i]]``, (B, N, 3), differentiable w.r.t. both
    clouds; source (B, N, 3), target (B, K, 3), index (B, N) int64."""
    return source - target.gather(1, index[..., None].expand(-1, -1, target.shape[-1]))
