"""Training and fitting losses, each a documented function on batched tensors.

Convention: shapes are given per argument; every loss returns a scalar tensor unless its
docstring says otherwise.
"""

from __future__ import annotations

import torch
from torch import Tensor

from sq_mitsuba.checks import check_tensor

#: Per-view silhouette losses of :func:`silhouette_loss`.
SILHOUETTE_LOSSES = ("mse", "iou")


def silhouette_loss(coverage: Tensor, target: Tensor, kind: str = "mse") -> Tensor:
    """Per-view loss summed over views: ``mse`` (the paper's reprojection loss, mean over
    pixels) or ``iou`` (1 - soft IoU). coverage, target: (V, H, W)."""
    if kind == "mse":
        return ((coverage - target) ** 2).flatten(1).mean(1).sum()
    if kind == "iou":
        inter = (coverage * target).flatten(1).sum(1)
        union = (coverage + target - coverage * target).flatten(1).sum(1).clamp_min(1e-6)
        return (1 - inter / union).sum()
    raise ValueError(f"loss: expected one of {SILHOUETTE_LOSSES}, got {kind!r}")


def overlap(occupancy: Tensor, beta: float = 1.25) -> Tensor:
    """Overlap penalty (paper Eq. 18): mean over points of relu(sum_m g_m - beta).

    Args:
        occupancy: per-primitive occupancy (B, M, N).
        beta: how much summed occupancy is tolerated (1.25 in the published configuration).

    Returns:
        Scalar tensor.
    """
    check_tensor("occupancy", occupancy, (None, None), min_dims=3)
    return torch.relu(occupancy.sum(dim=1) - beta).mean()
