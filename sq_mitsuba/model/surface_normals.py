"""The visible surface's normals: a dense target from which a spacecraft's axes can be read.

Spacecraft are built along their body axes: bus faces, panels, radiators, booms and
sunshields lie in or across them, in every family alike. The normals of the surface the
camera sees therefore cluster along the three body axes as the camera sees them (a
Manhattan frame), and that frame gives the body axes up to which is which, whatever the
family (``eval/experiments/structure_axes.py``). A per-cell normal is local, as the depth of
:mod:`~sq_mitsuba.model.surface_depth` is, so a head that reads it learns from every family
alike.

The target is made from what a training batch holds, as the depth map is: each surface point
is projected through K into a cell of a grid at ``stride`` pixels, and a cell's normal is the
mean normal of its points that face the camera near the front (within a band behind the
nearest of them), turned into the camera frame by the true rotation.

Convention:
    - Normals are in the camera frame (OpenCV: x right, y down, z forward); the visible side
      faces the camera, so a target normal has z < 0. A cell's target is a mean of unit
      normals, as long as they agree (1 on a flat face, shorter at edges and on curved
      parts), and the head's prediction regresses it, so its length is a confidence
      (:func:`~sq_mitsuba.geometry.manhattan_frame.manhattan_frame` weighs cells by it).
    - The target counts only points facing the camera and within a band of the nearest of
      them: the nearest point's own normal was noise (with 2,500 points, 1 - cos = 0.25 from
      the same map made with 20,000; the band's mean, 0.05), and a thin panel's back lies
      within any band.
    - A cell counts when a point facing the camera with a normal falls in it (a dataset
      without normals gives zeros, and no cell counts).
"""

from __future__ import annotations

import torch
from torch import Tensor

from sq_mitsuba.model.surface_depth import cells_at_pose, valid_cell_mean

__all__ = ["surface_normal_loss", "visible_normal_map"]


def visible_normal_map(points: Tensor, normals: Tensor, rotation: Tensor, translation: Tensor,
                       camera_matrix: Tensor, image_size: int, stride: int = 4,
                       band: float = 0.02) -> tuple[Tensor, Tensor]:
    """Camera-frame normal of the surface seen in each cell of a ``ceil(S / stride)`` grid:
    the mean of the unit normals of the cell's points that face the camera and lie within
    ``band`` of the nearest of them, not normalised, so that its length says how alike they
    are (1 inside one flat face, less where faces meet or the surface curves).

    Args:
        points: (B, K, 3) surface points in the body frame; normals (B, K, 3) theirs (unit, or
            zero where unknown).
        rotation: (B, 3, 3) body -> camera; translation: (B, 3).
        camera_matrix: (3, 3) or (B, 3, 3) intrinsics of the S x S image.
        image_size: S.
        stride: pixels per cell side.
        band: metres behind the cell's nearest point that still count as its front (the
            models are about one unit across).

    Returns:
        normal (B, 3, h, w), camera frame, length <= 1 (0 where the cell does not count),
        and valid (B, 1, h, w) bool, h = w = ceil(S / stride).
    """
    if normals.shape != points.shape:
        raise ValueError(f"normals: expected the points' shape {tuple(points.shape)}, got "
                         f"{tuple(normals.shape)}")
    camera, flat, side = cells_at_pose(points, rotation, translation, camera_matrix,
                                       image_size, stride)
    batch, cells, z = points.shape[0], side * side, camera[..., 2]
    inside = flat % (cells + 1) < cells
    # Only points facing the camera can be seen (a thin panel's back lies within any band).
    # A cell's front is those within ``band`` of its nearest, and its target their mean
    # normal, not the nearest's own: with a few dozen points a cell, that is often a point on
    # an edge, and the target noise.
    turned = (normals.to(points) @ rotation.to(points).transpose(-1, -2)).flatten(0, 1)
    facing = (turned * camera.flatten(0, 1)).sum(-1) < 0
    nearest = torch.full((batch * (cells + 1),), torch.inf, dtype=points.dtype,
                         device=points.device)
    seen = inside.flatten() & facing
    nearest = nearest.scatter_reduce(0, flat.flatten()[seen], z.flatten()[seen], reduce="amin")
    front = (z.flatten() <= nearest[flat.flatten()] + band) & seen
    summed = torch.zeros(batch * (cells + 1), 3, dtype=points.dtype, device=points.device)
    summed = summed.index_add(0, flat.flatten()[front], turned[front])
    summed = summed.view(batch, cells + 1, 3)[:, :-1]
    number = torch.zeros(batch * (cells + 1), dtype=points.dtype, device=points.device)
    number = number.index_add(0, flat.flatten()[front],
                              (turned[front].norm(dim=-1) > 0.5).to(points.dtype))
    number = number.view(batch, cells + 1)[:, :-1]
    valid = number > 0
    normal = torch.where(valid[..., None], summed / number.clamp_min(1.0)[..., None], 0.0)
    return (normal.transpose(1, 2).reshape(batch, 3, side, side),
            valid.view(batch, 1, side, side))


def surface_normal_loss(predicted: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """Mean squared distance between the predicted and target normal vectors over each item's
    valid cells, then over the batch (an item without a valid cell counts 0). The vectors are
    not normalised: a prediction learns the target's length, how alike the cell's normals are.

    Args:
        predicted, target: (B, 3, h, w); valid (B, 1, h, w).
    """
    if predicted.shape != target.shape or valid.shape != (target.shape[0], 1,
                                                          *target.shape[2:]):
        raise ValueError(f"predicted, target, valid: expected (B, 3, h, w) twice and "
                         f"(B, 1, h, w), got {tuple(predicted.shape)}, {tuple(target.shape)}, "
                         f"{tuple(valid.shape)}")
    return valid_cell_mean((predicted - target.to(predicted)).square().sum(1, keepdim=True),
                           valid)
