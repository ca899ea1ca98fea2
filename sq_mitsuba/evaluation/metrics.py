"""Evaluation metrics, each checked against its definition in the tests.

Convention: rotations map body to camera (OpenCV frame), ``x_cam = R x_body + t``;
quaternions are scalar first (w, x, y, z); angles are reported in degrees where the name says
``_deg`` and radians otherwise.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from sq_mitsuba.checks import check_tensor
from sq_mitsuba.geometry.rotation import quaternion_angle, rotation_angle
from sq_mitsuba.render.silhouette import mask_iou

__all__ = ["SpeedScore", "mask_iou", "rotation_angle_deg", "speed_score"]


def rotation_angle_deg(rotation_a: Tensor, rotation_b: Tensor) -> Tensor:
    """:func:`rotation_angle` in degrees, the paper's rotation error E_R; shape (...)."""
    return torch.rad2deg(rotation_angle(rotation_a, rotation_b))


class SpeedScore(NamedTuple):
    """SPEED score terms: rotation error (rad), relative translation error, their sum."""

    rotation: Tensor
    translation: Tensor
    total: Tensor


def speed_score(
    quaternion_pred: Tensor,
    quaternion_true: Tensor,
    translation_pred: Tensor,
    translation_true: Tensor,
) -> SpeedScore:
    """The SPEED pose score: e_q = 2 arccos(|<q_hat, q>|), e_t = |t - t_hat| / |t|.

    Args:
        quaternion_pred, quaternion_true: (..., 4).
        translation_pred, translation_true: (..., 3).

    Returns:
        :class:`SpeedScore` of tensors of shape (...).
    """
    check_tensor("translation_pred", translation_pred, (3,))
    check_tensor("translation_true", translation_true, (3,))
    e_q = quaternion_angle(quaternion_pred, quaternion_true)
    e_t = torch.linalg.vector_norm(translation_true - translation_pred, dim=-1) / \
        torch.linalg.vector_norm(translation_true, dim=-1)
    return SpeedScore(e_q, e_t, e_q + e_t)
