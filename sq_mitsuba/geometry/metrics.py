"""Pure metrics of shapes, silhouettes and poses, shared by training (validation) and
evaluation; each checked against its definition in the tests.

Convention: rotations map body to camera (OpenCV frame), ``x_cam = R x_body + t``;
quaternions are scalar first (w, x, y, z); angles are reported in degrees where the name says
``_deg`` and radians otherwise. Point clouds are (B, N, 3) with an optional (B, N) boolean
mask of the points that count (e.g. the predicted surface points not inside another
primitive); every metric returns one value per batch item, shape (B,).

Chamfer conventions (both reported, always named, because published numbers mix them):

- ``"paper"``: for each point the L1 (Manhattan) distance to its nearest neighbour under the
  L1 norm, averaged per direction, the two directions summed. This is PyTorch3D's
  ``chamfer_distance(norm=1)``, which the paper's evaluation uses (its Table 1 "Chamfer-L1").
- ``"occnet"``: 0.5 (mean_x min_y |x - y|_2 + mean_y min_x |x - y|_2), as Occupancy Networks,
  Neural Parts and SuperDec report.

Nearest neighbours come from a KD-tree per batch item
(:func:`sq_mitsuba.geometry.nearest.nearest_neighbours`), exact for both norms; metrics
carry no gradient (the training loss lives in :mod:`sq_mitsuba.model.losses`).
"""

from __future__ import annotations

import math
import numbers
from typing import Literal, NamedTuple

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.checks import check_nonzero, check_rotations, check_same_shape, check_tensor
from sq_mitsuba.geometry.nearest import nearest_neighbours
from sq_mitsuba.geometry.pose import transform_points
from sq_mitsuba.geometry.rotation import quaternion_angle, rotation_angle

__all__ = [
    "CHAMFER_CONVENTIONS",
    "SpeedScore",
    "camera_frame_chamfer",
    "chamfer_l1",
    "chamfer_l2",
    "mask_iou",
    "rotation_angle_deg",
    "rotation_error_deg",
    "speed_score",
    "translation_error",
    "volumetric_iou",
]

CHAMFER_CONVENTIONS = ("paper", "occnet")


def _clouds(name: str, points: Tensor, mask: Tensor | None) -> list[np.ndarray]:
    """Per batch item, the (n_b, 3) float64 points that count (``points`` checked by the
    caller, :func:`_directional_means`)."""
    array = points.detach().to("cpu", torch.float64).numpy()
    if mask is None:
        clouds = list(array)
    else:
        check_tensor(f"{name}_mask", mask, floating=False)  # a numpy mask failed in .detach()
        if mask.shape != points.shape[:-1]:
            raise ValueError(f"{name}_mask: expected shape {tuple(points.shape[:-1])}, got "
                             f"{tuple(mask.shape)}")
        keep = mask.detach().to("cpu", torch.bool).numpy()
        clouds = [a[k] for a, k in zip(array, keep, strict=True)]
    for index, cloud in enumerate(clouds):
        if len(cloud) == 0:
            raise ValueError(f"{name}: item {index} has no points")
    return clouds


def _directional_means(pred: Tensor, gt: Tensor, p: float, pred_mask: Tensor | None,
                       gt_mask: Tensor | None, power: int = 1) -> tuple[Tensor, Tensor]:
    """(B,) means of nearest distances**power pred -> gt and gt -> pred."""
    # The shapes first: an unbatched (N, 3) was read as N clouds ("batch sizes differ").
    check_tensor("pred", pred, (None, 3), min_dims=3)
    check_tensor("gt", gt, (None, 3), min_dims=3)
    if pred.shape[0] != gt.shape[0]:
        raise ValueError(f"pred, gt: batch sizes differ ({pred.shape[0]} vs {gt.shape[0]})")
    forward, backward = [], []
    for a, b in zip(_clouds("pred", pred, pred_mask), _clouds("gt", gt, gt_mask), strict=True):
        forward.append(np.mean(nearest_neighbours(a, b, p)[0] ** power))
        backward.append(np.mean(nearest_neighbours(b, a, p)[0] ** power))
    # On the inputs' device (the search runs on the CPU): a caller divides by distances there.
    return (torch.tensor(forward, dtype=torch.float64, device=pred.device),
            torch.tensor(backward, dtype=torch.float64, device=pred.device))


def chamfer_l1(pred: Tensor, gt: Tensor,
               convention: Literal["paper", "occnet"] = "paper", *,
               pred_mask: Tensor | None = None, gt_mask: Tensor | None = None) -> Tensor:
    """Chamfer-L1 (B,) between point clouds pred (B, N, 3) and gt (B, K, 3).

    ``convention``: ``"paper"`` (L1 nearest neighbours, directions summed) or ``"occnet"``
    (L2 nearest neighbours, directions averaged); see the module docstring.
    """
    if convention not in CHAMFER_CONVENTIONS:
        raise ValueError(f"convention: expected one of {CHAMFER_CONVENTIONS}, got "
                         f"{convention!r}")
    if convention == "paper":
        forward, backward = _directional_means(pred, gt, 1, pred_mask, gt_mask)
        return forward + backward
    forward, backward = _directional_means(pred, gt, 2, pred_mask, gt_mask)
    return 0.5 * (forward + backward)


def chamfer_l2(pred: Tensor, gt: Tensor, *, pred_mask: Tensor | None = None,
               gt_mask: Tensor | None = None) -> Tensor:
    """Chamfer-L2 (B,): mean squared L2 nearest distance per direction, directions summed
    (PyTorch3D's ``chamfer_distance`` default, the paper's training loss Eq. 12)."""
    forward, backward = _directional_means(pred, gt, 2, pred_mask, gt_mask, power=2)
    return forward + backward


def camera_frame_chamfer(pred_points: Tensor, pred_rotation: Tensor, pred_translation: Tensor,
                         gt_points: Tensor, gt_rotation: Tensor, gt_translation: Tensor, *,
                         pred_mask: Tensor | None = None,
                         convention: Literal["paper", "occnet"] = "occnet") -> Tensor:
    """Shape and pose scored together (B,): the predicted points placed by the predicted pose
    against the ground-truth points placed by the true pose, divided by the true distance.

    Both clouds are moved into the camera frame (``x_cam = R x_body + t``); a pose that is
    wrong only by a symmetry of the model costs nothing, a wrong shape or pose does. Dividing by
    ``|t_true|`` makes it independent of the target's range.

    Args:
        pred_points: (B, N, 3) body frame; pred_rotation (B, 3, 3); pred_translation (B, 3).
        gt_points: (B, K, 3) body frame; gt_rotation (B, 3, 3); gt_translation (B, 3).
        pred_mask: optional (B, N) points that count.
        convention: Chamfer convention (default ``"occnet"``, a plain metric distance).
    """
    for name, value, trailing in (("pred_rotation", pred_rotation, (3, 3)),
                                  ("gt_rotation", gt_rotation, (3, 3)),
                                  ("pred_translation", pred_translation, (3,)),
                                  ("gt_translation", gt_translation, (3,))):
        check_tensor(name, value, trailing)
        if value.dim() != len(trailing) + 1:  # an unbatched (3, 3) read as a batch of 3
            raise ValueError(f"{name}: expected (B, {', '.join(map(str, trailing))}), got "
                             f"{tuple(value.shape)}")
    check_rotations("pred_rotation", pred_rotation)  # a scaled "rotation" scales the points
    check_rotations("gt_rotation", gt_rotation)
    check_nonzero("gt_translation", gt_translation)
    batch = {name: value.shape[0] for name, value in (
        ("pred_points", pred_points), ("pred_rotation", pred_rotation),
        ("pred_translation", pred_translation), ("gt_points", gt_points),
        ("gt_rotation", gt_rotation), ("gt_translation", gt_translation))}
    if len(set(batch.values())) != 1:  # a (1, 3, 3) pose would broadcast over B items
        raise ValueError(f"camera_frame_chamfer: batch sizes differ: {batch}")
    dtype = torch.float64
    placed_pred = transform_points(pred_points.to(dtype), pred_rotation, pred_translation)
    placed_gt = transform_points(gt_points.to(dtype), gt_rotation, gt_translation)
    distance = torch.linalg.vector_norm(gt_translation.to(dtype), dim=-1)
    return chamfer_l1(placed_pred, placed_gt, convention, pred_mask=pred_mask) / distance


def mask_iou(prediction: Tensor, target: Tensor, threshold: float = 0.5) -> Tensor:
    """2D IoU (...,) of images (..., H, W) thresholded at ``threshold`` (an empty union gives
    1): the predicted silhouette against the mask, of one shape (no broadcasting: a (B, H, W)
    against a (B, 1, H, W) would score every pair). NaN (values or ``threshold``) is refused:
    NaN > threshold is False, so a NaN image scored as an empty one, IoU 1."""
    check_tensor("prediction", prediction, (None, None), floating=False)
    check_tensor("target", target, (None, None), floating=False)
    if isinstance(threshold, bool) or not isinstance(threshold, numbers.Real) \
            or not math.isfinite(threshold):
        raise ValueError(f"threshold: expected a finite number, got {threshold!r}")
    if prediction.shape != target.shape:
        raise ValueError(f"prediction, target: expected equal shapes (..., H, W), got "
                         f"{tuple(prediction.shape)} and {tuple(target.shape)}")
    a, b = prediction > threshold, target > threshold
    inter = (a & b).flatten(-2).sum(-1).double()
    union = (a | b).flatten(-2).sum(-1).double()
    return torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(union))


def volumetric_iou(pred_inside: Tensor, gt_inside: Tensor) -> Tensor:
    """3D IoU (B,) from labelled points: pred_inside, gt_inside (B, N) bool (or occupancy
    probabilities, thresholded at 0.5). Uniform points in a box around the model estimate
    the volume IoU; an empty union gives 1 (NaN is refused: it scored as outside)."""
    check_tensor("pred_inside", pred_inside, floating=False)
    check_tensor("gt_inside", gt_inside, floating=False)
    if pred_inside.shape != gt_inside.shape or pred_inside.dim() != 2:
        raise ValueError(f"pred_inside, gt_inside: expected equal shapes (B, N), got "
                         f"{tuple(pred_inside.shape)} and {tuple(gt_inside.shape)}")
    a = pred_inside > 0.5 if pred_inside.is_floating_point() else pred_inside.bool()
    b = gt_inside > 0.5 if gt_inside.is_floating_point() else gt_inside.bool()
    inter = (a & b).sum(-1).double()
    union = (a | b).sum(-1).double()
    return torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(union))


def rotation_error_deg(pred_rotation: Tensor, gt_rotation: Tensor,
                       symmetries: Tensor | None = None) -> Tensor:
    """Rotation error E_R in degrees (B,), symmetry-aware when ``symmetries`` is given.

    Args:
        pred_rotation, gt_rotation: (B, 3, 3).
        symmetries: (B, S, 3, 3) or (S, 3, 3) body-frame symmetries S of each model (the
            identity among them); the error is min over S of angle(R_pred, R_true S), since
            R_true S shows the same image. None: the raw error.
    """
    # The angle formula reads any matrix: -I gave 180 deg, 2 I gave 0 (shapes always; the
    # values a value check: one batched product and determinant, cheap beside an evaluation).
    check_rotations("pred_rotation", pred_rotation)
    check_rotations("gt_rotation", gt_rotation)
    check_same_shape(pred_rotation=pred_rotation, gt_rotation=gt_rotation)
    if symmetries is None:
        return rotation_angle_deg(pred_rotation, gt_rotation)
    check_tensor("symmetries", symmetries, (3, 3), min_dims=3)
    if pred_rotation.dim() != 3:  # (B, T, 3, 3) would pair T with S instead of the min over S
        raise ValueError(f"pred_rotation: expected (B, 3, 3) with symmetries, got "
                         f"{tuple(pred_rotation.shape)}")
    batch = pred_rotation.shape[0]
    if symmetries.dim() > 4 or symmetries.shape[-3] == 0 or (
            symmetries.dim() == 4 and symmetries.shape[0] != batch):
        raise ValueError(f"symmetries: expected (S, 3, 3) or ({batch}, S, 3, 3) with S >= 1, "
                         f"got {tuple(symmetries.shape)}")
    check_rotations("symmetries", symmetries.reshape(-1, 3, 3))
    candidates = gt_rotation[:, None] @ symmetries.to(gt_rotation.dtype)
    return rotation_angle_deg(pred_rotation[:, None], candidates).amin(dim=1)


def translation_error(pred_translation: Tensor, gt_translation: Tensor,
                      relative: bool = False) -> Tensor:
    """|t_true - t_pred| (B,) in metres, or divided by |t_true| when ``relative``."""
    check_tensor("pred_translation", pred_translation, (3,))
    check_tensor("gt_translation", gt_translation, (3,))
    check_same_shape(pred_translation=pred_translation, gt_translation=gt_translation)
    error = torch.linalg.vector_norm(gt_translation - pred_translation, dim=-1)
    if relative:
        check_nonzero("gt_translation", gt_translation)
        error = error / torch.linalg.vector_norm(gt_translation, dim=-1)
    return error


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
    check_same_shape(quaternion_pred=quaternion_pred, quaternion_true=quaternion_true)
    check_same_shape(translation_pred=translation_pred, translation_true=translation_true)
    if quaternion_pred.shape[:-1] != translation_pred.shape[:-1]:
        raise ValueError(f"quaternion_pred, translation_pred: expected the same batch shape, "
                         f"got {tuple(quaternion_pred.shape)} and {tuple(translation_pred.shape)}")
    check_nonzero("translation_true", translation_true)
    e_q = quaternion_angle(quaternion_pred, quaternion_true)
    e_t = torch.linalg.vector_norm(translation_true - translation_pred, dim=-1) / \
        torch.linalg.vector_norm(translation_true, dim=-1)
    return SpeedScore(e_q, e_t, e_q + e_t)
