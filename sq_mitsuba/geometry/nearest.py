"""Nearest neighbours between point clouds: the core of every Chamfer distance in the project.

Exact nearest neighbours come from one of two searches, without gradient; a differentiable
distance then gathers the matched points and takes their differences in torch, so the gradient
flows through the matched pairs exactly as through the ``min`` of the dense (all pairs) form.

- ``"kdtree"``: a KD-tree per cloud (scipy's ``cKDTree``) on the host, in float64, one item
  and direction at a time. The CPU's search: O((N + K) log(N + K)) per item.
- ``"dense"``: every pairwise distance of the batch at once in torch, on the clouds' device
  (chunks of at most :data:`DENSE_CHUNK` distances, so memory stays bounded), and the argmin
  of each row and column. The GPU's search: one launch per chunk, no host synchronisation,
  nothing copied to the host. For p = 2 the distances come from ``|a|^2 - 2 a.b + |b|^2``
  (matrix products), so two neighbours whose distances differ by less than the dtype's
  rounding (about 1e-7 of the squared coordinates in float32) may be swapped: the matched
  distance is then the same to that rounding.

Convention: clouds are (N, 3) per item, batches (B, N, 3); an optional (B, N) bool mask says
which points count. Callers choose what an item with no point counting means (the training
loss and the validation metric keep all its points, the evaluation metrics refuse it).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
from torch import Tensor

__all__ = ["DENSE_CHUNK", "METHODS", "euclidean", "gathered_differences", "matched_indices",
           "nearest_method", "nearest_neighbours"]

#: The searches of :func:`matched_indices`.
METHODS = ("kdtree", "dense")
#: Most pairwise distances the dense search holds at once (64 Mi: 256 MiB in float32).
DENSE_CHUNK = 1 << 26

NearestMethod = Literal["kdtree", "dense"]


def nearest_neighbours(source: np.ndarray, target: np.ndarray, p: float = 2.0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """For each point of ``source`` (n, 3), its nearest point of ``target`` (k >= 1, 3) under
    the L``p`` norm: distances (n,) float64 and indices (n,) int64 into ``target``."""
    from scipy.spatial import cKDTree

    distances, indices = cKDTree(np.asarray(target, dtype=np.float64)).query(
        np.asarray(source, dtype=np.float64), k=1, p=p)
    return np.asarray(distances, dtype=np.float64), np.asarray(indices, dtype=np.int64)


def nearest_method(device: torch.device, method: str | None = None) -> NearestMethod:
    """The search :func:`matched_indices` runs on ``device``: ``method`` when given, else
    ``"kdtree"`` on the CPU (the faster there, see eval/BENCHMARKS.md) and ``"dense"`` on any
    other device (no copy to the host, no synchronisation)."""
    if method is None:
        return "kdtree" if device.type == "cpu" else "dense"
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS} or None, got {method!r}")
    return method  # type: ignore[return-value]


def matched_indices(a: Tensor, a_keep: Tensor, b: Tensor, p: float = 2.0,
                    method: str | None = None) -> tuple[Tensor, Tensor]:
    """Nearest-neighbour indices both ways between batches of clouds, without gradient.

    Args:
        a: (B, N, 3); a_keep: (B, N) bool, the points of ``a`` that count (each item must
            keep at least one); b: (B, K, 3), every point counts.
        p: the norm of the distances (1 or 2 with ``"dense"``; any with ``"kdtree"``).
        method: ``"kdtree"``, ``"dense"`` or None (:func:`nearest_method`: by a's device).

    Returns:
        a_to_b (B, N) int64: index into b of each point of a's nearest point (0 for points
        that do not count); b_to_a (B, K) int64: index into a of each point of b's nearest
        kept point of a. On a's device.
    """
    if nearest_method(a.device, method) == "dense":
        return _dense_indices(a.detach(), a_keep.to(a.device), b.detach().to(a.device), p)
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


def _pair_distances(a: Tensor, b: Tensor, p: float) -> Tensor:
    """Monotone stand-ins for the L``p`` distances of a (B, n, 3) to b (B, K, 3), (B, n, K):
    squared distances by matrix products for p = 2 (argmins only need the order), exact
    absolute sums for p = 1."""
    if p == 2.0:
        # |a|^2 - 2 a.b + |b|^2 as one batched product: no (B, n, K, 3) intermediate.
        squared = torch.baddbmm(b.square().sum(-1)[:, None, :], a, b.transpose(1, 2),
                                alpha=-2.0)
        return squared.add_(a.square().sum(-1)[:, :, None])
    return torch.cdist(a, b, p=1.0)


@torch.no_grad()
def _dense_indices(a: Tensor, keep: Tensor, b: Tensor, p: float) -> tuple[Tensor, Tensor]:
    """:func:`matched_indices` by all pairwise distances, in chunks of items and of a's rows
    of at most :data:`DENSE_CHUNK` distances; b's nearest kept point of a is the running
    minimum over the row chunks (the first index wins ties, as one argmin would)."""
    if p not in (1.0, 2.0):
        raise ValueError(f"p: the dense search supports p = 1 or 2, got {p}")
    batch, count = a.shape[:2]
    targets = b.shape[1]
    a_to_b = torch.zeros(batch, count, dtype=torch.int64, device=a.device)
    b_to_a = torch.zeros(batch, targets, dtype=torch.int64, device=a.device)
    rows = max(1, min(count, DENSE_CHUNK // max(1, targets)))
    items = max(1, DENSE_CHUNK // max(1, rows * targets))
    for first in range(0, batch, items):
        part = slice(first, first + items)
        best = torch.full((min(items, batch - first), targets), float("inf"), dtype=a.dtype,
                          device=a.device)
        for start in range(0, count, rows):
            span = slice(start, start + rows)
            distances = _pair_distances(a[part, span], b[part], p)  # (items, rows, K)
            kept = keep[part, span]
            a_to_b[part, span] = torch.where(kept, distances.argmin(2), 0)
            # Points of a that do not count are nobody's neighbour.
            distances.masked_fill_(~kept[:, :, None], float("inf"))
            value, index = distances.min(1)  # (items, K)
            better = value < best  # strict: an earlier chunk keeps its tie
            best = torch.where(better, value, best)
            b_to_a[part] = torch.where(better, index + start, b_to_a[part])
    return a_to_b, b_to_a


def gathered_differences(source: Tensor, target: Tensor, index: Tensor) -> Tensor:
    """``source[b, i] - target[b, index[b, i]]``, (B, N, 3), differentiable w.r.t. both
    clouds; source (B, N, 3), target (B, K, 3), index (B, N) int64."""
    return source - target.gather(1, index[..., None].expand(-1, -1, target.shape[-1]))


def euclidean(squared_distances: Tensor) -> Tensor:
    """Distances from squared distances (any shape), with a finite gradient at 0:
    ``sqrt(d^2 + 1e-12)``, 1e-6 for a coincident pair, far below any sample spacing."""
    return torch.sqrt(squared_distances + 1e-12)
