"""The visible surface's depth: a dense target that does not depend on the spacecraft's family.

One image does not show how deep each part of a spacecraft is; a reader of single images
fills that in from the families it trained on, which is what does not carry to new ones (the
lab notebook, eval/experiments/README.md: "What one image shows"). The depth of the surface
the camera sees is a per-pixel target that every spacecraft has alike, and readers trained
through such 2.5D maps were found to reconstruct unseen classes better (MarrNet, Wu et al.
2017; GenRe, Zhang et al. 2018).

The target is made from what a training batch already holds, the model's surface points and
the true pose: each point is projected through K into a cell of a grid at ``stride`` pixels,
and a cell's depth is the nearest point's. No depth maps are rendered or stored, and
augmentation needs nothing of its own (it changes the pose, and the target follows it).

Convention:
    - Depth is relative to the body origin's: ``z_camera - t_z`` in metres (the models are
      about one unit across), so the head does not need the distance to the target.
    - A cell counts when at least ``min_points`` surface points fall in it; with 2,500 points a
      cell at stride 4 of a 96 px image that the target covers holds about a dozen, most of them
      on the side facing the camera. A cell whose front is thinly sampled can take a point of the
      far side: the target is noisy there, not biased everywhere.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from sq_mitsuba.checks import check_tensor

__all__ = ["cells_at_pose", "surface_depth_loss", "valid_cell_mean", "visible_depth_map"]


def cells_at_pose(points: Tensor, rotation: Tensor, translation: Tensor, camera_matrix: Tensor,
                  image_size: int, stride: int) -> tuple[Tensor, Tensor, int]:
    """Body-frame points placed at a pose and binned into the cells of a ``ceil(S / stride)``
    grid, for the visible-surface maps (this module's and
    :mod:`~sq_mitsuba.model.surface_normals`).

    Args:
        points: (B, K, 3) body frame; rotation (B, 3, 3) body -> camera; translation (B, 3).
        camera_matrix: (3, 3) or (B, 3, 3) intrinsics of the S x S image; image_size: S.
        stride: pixels per cell side.

    Returns:
        camera (B, K, 3) the points in the camera frame; flat (B, K) each point's cell as an
        index into B blocks of ``side * side + 1`` (item b's cells from ``b (side^2 + 1)``,
        row-major, then one spare cell for its points outside the grid or behind the
        camera); side.
    """
    check_tensor("points", points, (None, 3), min_dims=3)
    batch = points.shape[0]
    side = math.ceil(image_size / stride)
    k = camera_matrix.to(points).expand(batch, 3, 3)
    camera = points @ rotation.to(points).transpose(-1, -2) + translation.to(points)[:, None]
    z = camera[..., 2]
    pixel = (camera @ k.transpose(-1, -2))[..., :2] / z.clamp_min(1e-9)[..., None]
    cell = torch.floor(pixel / stride).long()  # (B, K, 2): column, row
    inside = (z > 0) & (cell >= 0).all(-1) & (cell < side).all(-1)
    index = torch.where(inside, cell[..., 1] * side + cell[..., 0], side * side)
    flat = index + torch.arange(batch, device=points.device)[:, None] * (side * side + 1)
    return camera, flat, side


def visible_depth_map(points: Tensor, rotation: Tensor, translation: Tensor,
                      camera_matrix: Tensor, image_size: int, stride: int = 4,
                      min_points: int = 1) -> tuple[Tensor, Tensor]:
    """Depth of the nearest surface point in each cell of a ``ceil(S / stride)`` grid.

    Args:
        points: (B, K, 3) surface points in the body frame.
        rotation: (B, 3, 3) body -> camera; translation: (B, 3).
        camera_matrix: (3, 3) or (B, 3, 3) intrinsics of the S x S image.
        image_size: S.
        stride: pixels per cell side.
        min_points: points a cell needs to count.

    Returns:
        depth (B, 1, h, w): ``min z_camera - t_z`` over the cell's points (0 where it does not
        count), and valid (B, 1, h, w) bool, h = w = ceil(S / stride).
    """
    camera, flat, side = cells_at_pose(points, rotation, translation, camera_matrix,
                                       image_size, stride)
    batch, z = points.shape[0], camera[..., 2]
    nearest = torch.full((batch * (side * side + 1),), torch.inf, dtype=points.dtype,
                         device=points.device)
    nearest = nearest.scatter_reduce(0, flat.flatten(), z.flatten(), reduce="amin")
    count = torch.zeros(batch * (side * side + 1), dtype=z.dtype, device=points.device)
    count = count.index_add(0, flat.flatten(), torch.ones_like(z).flatten())
    nearest = nearest.view(batch, side * side + 1)[:, :-1]
    valid = count.view(batch, side * side + 1)[:, :-1] >= min_points
    depth = torch.where(valid, nearest - translation.to(points)[:, 2:3], 0.0)
    return depth.view(batch, 1, side, side), valid.view(batch, 1, side, side)


def surface_depth_loss(predicted: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """Mean absolute depth error over each item's valid cells, then over the batch (an item
    without a valid cell counts 0).

    Args:
        predicted, target: (B, 1, h, w) depth relative to the body origin's; valid (B, 1, h, w).
    """
    if predicted.shape != target.shape or valid.shape != target.shape:
        raise ValueError(f"predicted, target, valid: expected one shape, got "
                         f"{tuple(predicted.shape)}, {tuple(target.shape)}, "
                         f"{tuple(valid.shape)}")
    return valid_cell_mean((predicted - target.to(predicted)).abs(), valid)


def valid_cell_mean(per_cell: Tensor, valid: Tensor) -> Tensor:
    """The visible-surface maps' loss reduction (this module's and
    :mod:`~sq_mitsuba.model.surface_normals`): ``per_cell`` (B, 1, h, w) averaged over each
    item's ``valid`` (B, 1, h, w) cells, then over the batch; an item without a valid cell
    counts 0."""
    weight = valid.to(per_cell.dtype)
    error = (per_cell * weight).flatten(1).sum(1)
    return (error / weight.flatten(1).sum(1).clamp_min(1.0)).mean()
