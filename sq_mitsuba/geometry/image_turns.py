"""Turning images in their plane: the 2D rotation about the image centre and the camera
rotation about the optical axis that it equals.

Training's rotation augmentation and the predictor's reading of turned copies
(``Predictor.predict(turns=T)``) both turn images; the labels (or the readings) turn with them
by :func:`z_rotation`.

Convention: a positive angle turns image content clockwise on screen (x right, y down): a point
at pixel offset (dx, dy) from the centre moves to ``(cos dx - sin dy, sin dx + cos dy)``. The
turn equals a camera roll only when the principal point is the image centre and ``fx = fy``
(:func:`check_rotation_exact`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from sq_mitsuba.checks import check_tensor
from sq_mitsuba.geometry.camera import Camera

__all__ = ["check_rotation_exact", "rotate_batch", "turned_back_mask", "z_rotation"]

_PRINCIPAL_POINT_TOLERANCE_PX = 1e-3
_FOCAL_TOLERANCE = 1e-6


def check_rotation_exact(camera: Camera) -> None:
    """Raise ``ValueError`` unless in-plane rotation keeps labels exact for ``camera``: a square
    image, the principal point at its centre and ``fx = fy``."""
    if camera.width != camera.height:
        raise ValueError(f"augment.rotation: needs a square image, got {camera.width} x "
                         f"{camera.height}")
    if (abs(camera.cx - camera.width / 2) > _PRINCIPAL_POINT_TOLERANCE_PX
            or abs(camera.cy - camera.height / 2) > _PRINCIPAL_POINT_TOLERANCE_PX):
        raise ValueError(f"augment.rotation: needs the principal point at the image centre "
                         f"({camera.width / 2}, {camera.height / 2}), got ({camera.cx}, "
                         f"{camera.cy}); switch the rotation off for this camera")
    if abs(camera.fx - camera.fy) > _FOCAL_TOLERANCE * camera.fx:
        raise ValueError(f"augment.rotation: needs fx = fy, got {camera.fx} and {camera.fy}; "
                         "switch the rotation off for this camera")


def _check_angles(angles: Tensor, count: int | None = None) -> None:
    """``angles`` (count,) floating (any count when None); a (2, 2) came back as 4 turns."""
    check_tensor("angles", angles, (None,))
    if angles.dim() != 1 or (count is not None and len(angles) != count):
        raise ValueError(f"angles: expected shape ({'B' if count is None else count},), got "
                         f"{tuple(angles.shape)}")


def z_rotation(angles: Tensor) -> Tensor:
    """Rotations (B, 3, 3) by ``angles`` (B,) radians about the camera's optical axis z.

    ``Rz @ (x, y, z) = (cos x - sin y, sin x + cos y, z)``: in the image (x right, y down) a
    positive angle turns content clockwise.
    """
    _check_angles(angles)
    c, s = torch.cos(angles), torch.sin(angles)
    zero, one = torch.zeros_like(angles), torch.ones_like(angles)
    return torch.stack([c, -s, zero, s, c, zero, zero, zero, one], dim=-1).reshape(-1, 3, 3)


def rotate_batch(images: Tensor, angles: Tensor) -> Tensor:
    """Images (B, C, S, S) turned by ``angles`` (B,) radians about the image centre (bilinear,
    zeros outside), the 2D action of :func:`z_rotation` on pixel offsets from the centre.

    The output at pixel offset p samples the input at ``Rz^-1 p``. With ``align_corners=False``
    the normalised grid's origin is the continuous centre (S / 2, S / 2) and both axes share one
    scale on a square image, so the rotation is the same in normalised coordinates (on
    another it is not a turn: refused).
    """
    # Logits may be infinite (turned_back_mask's): shapes and dtypes only.
    check_tensor("images", images, (None, None, None, None), finite=False)
    if images.dim() != 4 or images.shape[-1] != images.shape[-2]:
        raise ValueError(f"images: expected square images (B, C, S, S), got "
                         f"{tuple(images.shape)}")
    _check_angles(angles, images.shape[0])
    c, s = torch.cos(angles), torch.sin(angles)
    zero = torch.zeros_like(angles)
    # Inverse rotation [[c, s], [-s, c]] (grid_sample maps output to input positions).
    theta = torch.stack([c, s, zero, -s, c, zero], dim=-1).reshape(-1, 2, 3)
    grid = F.affine_grid(theta.to(images.dtype), list(images.shape), align_corners=False)
    return F.grid_sample(images, grid, mode="bilinear", padding_mode="zeros",
                         align_corners=False)


def turned_back_mask(mask: Tensor, turned_logits: Tensor, angles: Tensor, height: int,
                     width: int) -> Tensor:
    """The mean over turned copies of an image of a mask probability (B, H, W): the unturned
    copy's ``mask`` (B, H, W) with the turned copies' logits ((T - 1) B, 1, s, s), copy-major,
    turned back by their ``angles`` (T - 1,) and scaled to ``height`` x ``width``, each where
    it covers the image (a turned copy leaves the corners out).

    The copies are scaled up one at a time: all at once held 2 (T - 1) images' worth of floats
    (2 GB for a 4,000 px image and 8 copies).

    Raises:
        ValueError: naming the argument whose shape does not match the others'.
    """
    check_tensor("mask", mask, (None, height, width), min_dims=3)
    if mask.dim() != 3:
        raise ValueError(f"mask: expected shape (B, {height}, {width}), got {tuple(mask.shape)}")
    if check_tensor("angles", angles).dim() != 1:
        raise ValueError(f"angles: expected shape (T - 1,), got {tuple(angles.shape)}")
    batch = mask.shape[0]
    check_tensor("turned_logits", turned_logits, (len(angles) * batch, 1, None, None),
                 min_dims=4, finite=False)
    undo = -angles.to(turned_logits).repeat_interleave(batch).float()
    logits = rotate_batch(turned_logits.float(), undo)
    covered = rotate_batch(torch.ones_like(logits), undo)
    weighted, weights = torch.zeros_like(mask), torch.zeros_like(mask)
    for copy in range(len(angles)):
        rows = slice(copy * batch, (copy + 1) * batch)
        logit, cover = (F.interpolate(t[rows], size=(height, width), mode="bilinear",
                                      align_corners=False)[:, 0] for t in (logits, covered))
        cover = cover.clamp(0, 1).to(mask)
        weighted += cover * logit.sigmoid().to(mask)
        weights += cover
    return (mask + weighted) / (1 + weights)
