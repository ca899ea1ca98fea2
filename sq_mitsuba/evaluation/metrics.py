"""The evaluation metrics, kept under this name for existing callers: they live in
:mod:`sq_mitsuba.geometry.metrics`, where training's validation uses them too."""

from sq_mitsuba.geometry.metrics import (
    CHAMFER_CONVENTIONS,
    SpeedScore,
    camera_frame_chamfer,
    chamfer_l1,
    chamfer_l2,
    mask_iou,
    rotation_angle_deg,
    rotation_error_deg,
    speed_score,
    translation_error,
    volumetric_iou,
)

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
