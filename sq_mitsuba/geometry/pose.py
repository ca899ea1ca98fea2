"""Rigid poses (a rotation and a translation) as pure functions on batched tensors.

Convention:
    A pose ``(R, t)`` maps a frame's points into another's, ``x_out = R @ x + t``: the label
    of an image, ``x_cam = R x_body + t``, maps the target's body frame into the camera's
    (docs/conventions.md). ``R`` is (..., 3, 3), ``t`` (..., 3), their batch dims broadcast.
"""

from __future__ import annotations

import torch
from torch import Tensor

from sq_mitsuba.checks import check_rotations, check_tensor

__all__ = ["compose_poses", "invert_pose", "relative_pose", "transform_points"]


def _check_pose(rotation: Tensor, translation: Tensor, name: str = "") -> torch.Size:
    """The broadcast batch shape of a pose; ``ValueError`` naming the argument otherwise."""
    check_tensor(f"{name}rotation", rotation, (3, 3))
    check_tensor(f"{name}translation", translation, (3,))
    try:
        return torch.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    except RuntimeError:
        raise ValueError(f"{name}rotation, {name}translation: batch dims "
                         f"{tuple(rotation.shape[:-2])} and {tuple(translation.shape[:-1])} "
                         "do not broadcast") from None


def transform_points(points: Tensor, rotation: Tensor, translation: Tensor) -> Tensor:
    """Points (..., N, 3) mapped by poses: ``R @ x + t`` for each point.

    Args:
        points: (..., N, 3).
        rotation: (..., 3, 3), the points' batch dims broadcast against it.
        translation: (..., 3).

    Returns:
        (..., N, 3) in the wider of the inputs' dtypes.
    """
    check_tensor("points", points, (None, 3), min_dims=2)
    _check_pose(rotation, translation)
    dtype = torch.promote_types(torch.promote_types(points.dtype, rotation.dtype),
                                translation.dtype)
    try:
        return (points.to(dtype) @ rotation.to(dtype).transpose(-1, -2)
                + translation.to(dtype)[..., None, :])
    except RuntimeError:
        raise ValueError(f"points, rotation, translation: batch dims "
                         f"{tuple(points.shape[:-2])}, {tuple(rotation.shape[:-2])} and "
                         f"{tuple(translation.shape[:-1])} do not broadcast") from None


def invert_pose(rotation: Tensor, translation: Tensor) -> tuple[Tensor, Tensor]:
    """The inverse pose ``(R^T, -R^T t)`` (..., 3, 3), (..., 3), in the wider of the inputs'
    dtypes: it maps back what ``(R, t)`` maps (``R`` must be a rotation; its transpose is
    taken as its inverse, so anything else is refused: a value check)."""
    _check_pose(rotation, translation)
    check_rotations("rotation", rotation.reshape(-1, 3, 3))  # 2 I gave (2 I, -2 t)
    return _inverse(rotation, translation)


def _inverse(rotation: Tensor, translation: Tensor) -> tuple[Tensor, Tensor]:
    dtype = torch.promote_types(rotation.dtype, translation.dtype)  # the wider of the two
    inverse = rotation.to(dtype).transpose(-1, -2)
    return inverse, -(inverse @ translation.to(dtype)[..., None])[..., 0]


def compose_poses(rotation_a: Tensor, translation_a: Tensor, rotation_b: Tensor,
                  translation_b: Tensor) -> tuple[Tensor, Tensor]:
    """The pose ``a after b``, (..., 3, 3), (..., 3): ``x -> R_a (R_b x + t_b) + t_a``, i.e.
    ``(R_a R_b, R_a t_b + t_a)``, in the widest of the inputs' dtypes; the batch dims of
    both poses broadcast."""
    _check_pose(rotation_a, translation_a, "a: ")
    _check_pose(rotation_b, translation_b, "b: ")
    dtype = torch.promote_types(torch.promote_types(rotation_a.dtype, rotation_b.dtype),
                                torch.promote_types(translation_a.dtype, translation_b.dtype))
    rotation_a, rotation_b = rotation_a.to(dtype), rotation_b.to(dtype)
    rotation = rotation_a @ rotation_b
    translation = (rotation_a @ translation_b.to(dtype)[..., None])[..., 0] + \
        translation_a.to(dtype)
    return rotation, translation


def relative_pose(rotation_a: Tensor, translation_a: Tensor, rotation_b: Tensor,
                  translation_b: Tensor) -> tuple[Tensor, Tensor]:
    """The pose that maps frame ``a``'s output into ``b``'s: ``b after inverse(a)``, so that
    ``compose_poses(*relative_pose(a, b), *a) == b``. For two images' labels (body to camera)
    it maps the first camera's points into the second's: the camera's motion relative to the
    target between the frames. Both rotations must be rotations (a value check)."""
    _check_pose(rotation_a, translation_a, "a: ")
    _check_pose(rotation_b, translation_b, "b: ")
    check_rotations("a: rotation", rotation_a.reshape(-1, 3, 3))
    check_rotations("b: rotation", rotation_b.reshape(-1, 3, 3))
    return compose_poses(rotation_b, translation_b, *_inverse(rotation_a, translation_a))
