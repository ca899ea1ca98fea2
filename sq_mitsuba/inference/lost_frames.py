"""Frames a pass's joint fit lost, placed again with the shared shape.

The joint fit (:func:`~sq_mitsuba.inference.sequence.fit_sequence`) keeps the step with the
best mean IoU over the frames, so one frame can end far from its mask while the others gain:
once a frame's silhouette leaves its mask the soft IoU gives it no gradient back (measured:
one frame of 88 of frames given unordered, moved 0.25 m sideways to 2D IoU 0 where the frame
alone reached 0.56). :func:`place_lost_frames` refits such a frame's pose alone, the shared
shape held, from the pose it started the joint fit with, and keeps the result where it fits
the frame's mask better.

Convention: poses map body to camera, ``x_cam = R x + t``; tensors float64.
"""

from __future__ import annotations

from dataclasses import replace

from torch import Tensor

from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.inference.refine import RefineOptions, refine_pose_and_shape

__all__ = ["LOST_FRACTION", "lost_frames", "place_lost_frames"]

#: A frame is lost when the joint fit leaves it below this fraction of the IoU its own fit
#: reached against the same mask (its own reading's shape, at its refinement's resolution:
#: the joint fit's, 64 px, unless a caller gives ``predict_sequence`` another refinement).
LOST_FRACTION = 0.5


def lost_frames(iou: Tensor, own_iou: Tensor) -> Tensor:
    """(N,) bool: the frames whose IoU after the joint fit ``iou`` (N,) is below
    :data:`LOST_FRACTION` of their own fit's ``own_iou`` (N,)."""
    return iou < LOST_FRACTION * own_iou


def place_lost_frames(assembly: Assembly, rotation: Tensor, translation: Tensor, iou: Tensor,
                      own_iou: Tensor, start_rotation: Tensor, start_translation: Tensor,
                      masks: Tensor, camera: Camera, options: RefineOptions
                      ) -> tuple[Tensor, Tensor, Tensor]:
    """The joint fit's poses with every lost frame (:func:`lost_frames`) refitted alone.

    Args:
        assembly: the shared assembly, batch size 1, held.
        rotation: (N, 3, 3), translation: (N, 3): the poses after the joint fit.
        iou: (N,) each frame's IoU after the joint fit; own_iou: (N,) after its own fit.
        start_rotation: (N, 3, 3), start_translation: (N, 3): the poses the joint fit started
            from, where a lost frame's refit starts.
        masks: (N, H, W) the frames' masks at ``camera``'s resolution.
        options: the refit's settings (its ``shape`` is taken as "pose": the shape is held).

    Returns:
        rotation (N, 3, 3), translation (N, 3) and iou (N,), a lost frame's replaced where its
        refit fits its mask better (IoU at ``options.resolution``).
    """
    lost = lost_frames(iou, own_iou)
    if not bool(lost.any()):
        return rotation, translation, iou
    count = int(lost.sum())
    placed = refine_pose_and_shape(
        Assembly(assembly.params.detach().expand(count, -1, -1)), start_rotation[lost],
        start_translation[lost], masks[lost], camera, replace(options, shape="pose"))
    better = placed.iou_after.to(iou) > iou[lost]
    rows = lost.nonzero()[:, 0][better]
    rotation, translation, iou = rotation.clone(), translation.clone(), iou.clone()
    rotation[rows] = placed.rotation[better].to(rotation)
    translation[rows] = placed.translation[better].to(translation)
    iou[rows] = placed.iou_after[better].to(iou)
    return rotation, translation, iou
