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

from sq_mitsuba.geometry.camera import Camera

__all__ = ["check_rotation_exact", "rotate_batch", "z_rotation"]

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


def z_rotation(angles: Tensor) -> Tensor:
    """Rotations (B, 3, 3) by ``angles`` (B,) radians about the camera's optical axis z.

    ``Rz @ (x, y, z) = (cos x - sin y, sin x + cos y, z)``: in the image (x right, y down) a
    positive angle turns content clockwise.
    """
    c, s = torch.cos(angles), torch.sin(angles)
    zero, one = torch.zeros_like(angles), torch.ones_like(angles)
    return torch.stack([c, -s, zero, s, c, zero, zero, zero, one], dim=-1).reshape(-1, 3, 3)


def rotate_batch(images: Tensor, angles: Tensor) -> Tensor:
    """Images (B, C, S, S) turned by ``angles`` (B,) radians about the image centre (bilinear,
    zeros outside), the 2D action of :func:`z_rotation` on pixel offsets from the centre.

    The output at pixel offset p samples the input at ``Rz^-1 p``. With ``align_corners=False``
    the normalised grid's origin is the continuous centre (S / 2, S / 2) and both axes share one
    scale on a square image, so the rotation is the same in normalised coordinates.
    """
    c, s = torch.cos(angles), torch.sin(angles)
    zero = torch.zeros_like(angles)
    # Inverse rotation [[c, s], [-s, c]] (grid_sample maps output to input positions).
    theta = torch.stack([c, s, zero, -s, c, zero], dim=-1).reshape(-1, 2, 3)
    grid = F.affine_grid(theta.to(images.dtype), list(images.shape), align_corners=False)
    return F.grid_sample(images, grid, mode="bilinear", padding_mode="zeros",
                         align_corners=False)
