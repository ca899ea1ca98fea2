"""A primitive grown where the silhouettes miss the masks: the joint fit's extra capacity.

The joint fit of a pass (:mod:`sq_mitsuba.inference.sequence`) moves the primitives the
network read; a part the reading left out (a long array or boom of a spacecraft unlike the
training set) gets no primitive, and silhouette gradients, which live on the outline, cannot
pull one there from afar. :func:`grow_primitive` adds one: the largest connected piece of mask
that no frame's silhouette covers is placed in 3D from the other frames (each of its pixels at
the depth along its ray that most frames' masks see, :func:`piece_points`), a box spans those
points along their principal axes (:func:`box_primitive`), and the assembly with it is kept if
its silhouettes at every frame's pose fit every mask better (mean soft IoU). The joint fit
then moves the new primitive with the rest.

Convention: poses map body to camera, ``x_cam = R_j x + t_j`` (OpenCV frame); depths are
searched within ``depth_span`` body units of the target's (``t_j``'s z; the dataset's models
are one unit long); pixels are (row, column), their centres at +0.5.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.checks import check_tensor
from sq_mitsuba.geometry.assembly import Assembly, ParameterRanges
from sq_mitsuba.geometry.camera import Camera

__all__ = ["box_primitive", "grow_primitive", "missed_pieces", "piece_points"]

# Keeps a new primitive's squashed fields strictly inside their ranges (the refinement moves
# raw parameters, the inverse of the squash).
_MARGIN = 1e-3


def missed_pieces(coverage: Tensor, targets: Tensor, min_pixels: int = 4,
                  count: int = 2) -> list[tuple[int, Tensor]]:
    """The ``count`` largest connected pieces of mask no silhouette covers, largest first.

    Args:
        coverage: (N, h, w) silhouettes in [0, 1]; targets: (N, h, w) masks in [0, 1].
        min_pixels: smaller pieces are left out.

    Returns:
        (frame, pixels (P, 2) long as (row, column)) per piece.
    """
    from scipy import ndimage

    missed = ((targets > 0.5) & (coverage < 0.5)).cpu().numpy()
    pieces = []
    for frame, image in enumerate(missed):
        labels, found = ndimage.label(image, np.ones((3, 3), dtype=bool))
        for label in range(1, found + 1):
            rows, columns = np.nonzero(labels == label)
            if len(rows) >= min_pixels:
                pieces.append((len(rows), frame, np.stack([rows, columns], 1)))
    pieces.sort(key=lambda piece: -piece[0])
    return [(frame, torch.from_numpy(pixels)) for _, frame, pixels in pieces[:count]]


def piece_points(pixels: Tensor, frame: int, targets: Tensor, camera: Camera,
                 rotation: Tensor, translation: Tensor, depth_span: float = 0.6,
                 depths: int = 25, grow_pixels: int = 1) -> Tensor:
    """Body-frame points (P, 3) of a missed piece, each pixel at the depth most frames agree on.

    Each pixel of the piece (P, 2) as (row, column) in ``frame`` is a ray; of ``depths``
    points along it within ``depth_span`` (body units) of the target's depth, the one that
    the most frames' masks (grown by ``grow_pixels``, for poses a few degrees off) see is
    kept (ties: the nearest the target's depth). A piece of the target lies where every
    frame sees it; at a wrong depth a turning target carries it out of the other masks.
    """
    from scipy import ndimage

    dtype = rotation.dtype
    grown = torch.from_numpy(np.stack([
        ndimage.binary_dilation(mask, iterations=grow_pixels) if grow_pixels else mask
        for mask in (targets > 0.5).cpu().numpy()]))
    uv = torch.stack([pixels[:, 1], pixels[:, 0]], 1).to(dtype) + 0.5
    rays = camera.unproject(uv, 1.0)  # (P, 3), z = 1
    offsets = torch.linspace(-depth_span, depth_span, depths, dtype=dtype)
    along = float(translation[frame, 2]) + offsets
    along = along[along > 0]
    points = rays[:, None, :] * along[None, :, None]  # (P, Z, 3) camera frame of `frame`
    body = (points - translation[frame]) @ rotation[frame]  # R^T (x - t), row vectors
    cameras = body[None] @ rotation.transpose(-1, -2)[:, None] + translation[:, None, None]
    ahead = cameras[..., 2] > 0
    # Points behind a camera are projected from just ahead of it, then left out by `ahead`.
    seen_at = camera.project(torch.cat([cameras[..., :2], cameras[..., 2:].clamp_min(1e-9)],
                                       -1)).floor().long()
    column, row = seen_at[..., 0], seen_at[..., 1]
    inside = (column >= 0) & (column < camera.width) & (row >= 0) & (row < camera.height) & ahead
    views = torch.arange(len(rotation))[:, None, None].expand_as(row)
    seen = torch.zeros_like(inside)
    seen[inside] = grown[views[inside], row[inside], column[inside]]
    votes = seen.sum(0).to(dtype) - 1e-3 * (along - float(translation[frame, 2])).abs()
    best = votes.argmax(1)
    return body[torch.arange(len(body)), best]


def box_primitive(points: Tensor, thickness: float, shape: float = 0.2,
                  ranges: ParameterRanges | None = None) -> Tensor:
    """One primitive's parameters (16,) spanning ``points`` (P, 3): the box along their
    principal axes (exponents ``shape``), each semi-axis at least ``thickness``; sizes and
    position clamped into ``ranges``."""
    ranges = ranges if ranges is not None else ParameterRanges()
    centre = points.mean(0)
    if len(points) > 2:
        _, _, vectors = torch.linalg.svd(points - centre, full_matrices=False)
        axes = vectors  # rows: principal directions, largest spread first
    else:
        axes = torch.eye(3, dtype=points.dtype)
    if torch.linalg.det(axes) < 0:
        axes = torch.cat([axes[:2], -axes[2:]])
    local = (points - centre) @ axes.T
    low, high = local.min(0).values, local.max(0).values
    centre = centre + ((low + high) / 2) @ axes
    size = ((high - low) / 2).clamp_min(thickness)
    smallest = ranges.size_min * (1 + _MARGIN)
    largest = (ranges.size_min + ranges.size_span) * (1 - _MARGIN)
    limit = ranges.translation_scale * (1 - _MARGIN)
    primitive = Assembly.from_values(size.clamp(smallest, largest)[None, None],
                                     size.new_full((1, 1, 2), shape),
                                     centre.clamp(-limit, limit)[None, None],
                                     axes.T[None, None])
    return primitive.params[0, 0]


def grow_primitive(assembly: Assembly, rotation: Tensor, translation: Tensor, targets: Tensor,
                   camera: Camera, level: int = 2, spp: int = 4, seed: int = 0,
                   pieces: int = 3, min_gain: float = 0.002) -> tuple[Assembly, float, float]:
    """The assembly with one primitive more where the silhouettes miss the masks, or as it is.

    Args:
        assembly: batch size 1, in the body frame.
        rotation: (N, 3, 3) body -> camera; translation: (N, 3).
        targets: (N, h, w) masks in [0, 1] at ``camera``'s resolution.
        camera: intrinsics at the targets' resolution.
        level, spp, seed: the primitives' meshes and the silhouettes' sampling.
        pieces: the largest missed pieces tried, one candidate each.
        min_gain: the mean soft IoU a candidate must add to be kept.

    Returns:
        The assembly (the grown one, or the given one), the mean soft IoU before and after.

    Raises:
        ValueError: one line naming ``assembly``, ``rotation``, ``translation`` or ``targets``.
    """
    from sq_mitsuba.inference.search import soft_iou
    from sq_mitsuba.render.silhouette.batch import PoseSilhouettes

    count = len(rotation)
    if assembly.batch_size != 1:
        raise ValueError(f"assembly: expected batch size 1, got {assembly.batch_size}")
    check_tensor("rotation", rotation, (count, 3, 3))
    check_tensor("translation", translation, (count, 3))
    check_tensor("targets", targets, (count, camera.height, camera.width))
    renderer = PoseSilhouettes(camera, spp=spp, seed=seed)
    rotation, translation = rotation.detach().double(), translation.detach().double()
    targets = targets.detach().double()

    def mean_iou(params: Tensor) -> tuple[float, Tensor]:
        vertices, faces = Assembly(params).merged_mesh(level)
        coverage = renderer.render(vertices[0], faces, rotation, translation).double()
        return float(soft_iou(coverage, targets).mean()), coverage

    params = assembly.params.detach().double()
    before, coverage = mean_iou(params)
    best, best_params = before, params
    for frame, pixels in missed_pieces(coverage, targets, count=pieces):
        points = piece_points(pixels, frame, targets, camera, rotation, translation)
        # Half a pixel at the target's depth: the thinnest part a silhouette can show.
        thickness = 0.5 * float(translation[frame, 2]) / (0.5 * (camera.fx + camera.fy))
        primitive = box_primitive(points, thickness)
        candidate = torch.cat([params, primitive[None, None].to(params)], dim=1)
        score, _ = mean_iou(candidate)
        if score > best:
            best, best_params = score, candidate
    if best < before + min_gain:
        return assembly, before, before
    return Assembly(best_params), before, best
