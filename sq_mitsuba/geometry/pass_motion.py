"""The motion of a pass of images: one constant-rate turn found among the frames' readings.

Frames taken in order along a pass see a tumbling target turn steadily: over the seconds of a
pass a free body's angular velocity barely changes, and an inertially pointed camera adds
little turn of its own. So the frames' body -> camera rotations lie near one constant-rate
motion, ``R_k = exp(k [w]) R_0`` with ``w`` a rotation vector (radians per frame) in the
camera frame. A frame's reading far from the motion that most frames agree on is a misreading
(one image cannot always tell a spacecraft's axes apart); the motion then gives a better
start for that frame than its own reading. :func:`constant_rate_motion` finds the motion by
consensus: every pair of frames, each reading taken with any of the four half turns of its
body frame, proposes a motion, the one that most frames agree with (within a threshold; a
truncated squared error, MSAC) wins, and is then fitted to the agreeing frames.

Convention: rotations map body to camera (``x_cam = R x_body``); a frame's half turn ``S``
acts on the body side (``R S``: :func:`~sq_mitsuba.geometry.so3_grid.half_turns`); frames
are equally spaced in time unless ``times`` says otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from sq_mitsuba.checks import check_tensor
from sq_mitsuba.geometry.rotation import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    rotation_angle,
)
from sq_mitsuba.geometry.so3_grid import half_turns

__all__ = ["PassMotion", "constant_rate_motion"]


@dataclass(frozen=True)
class PassMotion:
    """A constant-rate motion and how the frames' readings agree with it.

    Attributes:
        rate: (3,) rotation vector per unit of time, in the camera frame.
        start: (3, 3) the motion's rotation at time 0: ``R(t) = exp(t [rate]) start``.
        predicted: (N, 3, 3) the motion at each frame's time.
        turn: (N,) index into ``half_turns()`` of the half turn of each frame's reading that
            lies nearest the motion.
        error_deg: (N,) angle between each frame's reading (so turned) and the motion.
        inliers: (N,) bool, ``error_deg`` within the threshold.
    """

    rate: Tensor
    start: Tensor
    predicted: Tensor
    turn: Tensor
    error_deg: Tensor
    inliers: Tensor


def _predicted(rate: Tensor, start: Tensor, times: Tensor) -> Tensor:
    """(H, 3) rates, (H, 3, 3) starts, (N,) times -> (H, N, 3, 3) rotations of the motions."""
    return axis_angle_to_matrix(times[None, :, None] * rate[:, None, :]) @ start[:, None]


def _agreement(readings: Tensor, predicted: Tensor) -> tuple[Tensor, Tensor]:
    """(N, 4, 3, 3) readings with their half turns, (H, N, 3, 3) motions -> the angle (H, N)
    of each frame's nearest half turn to each motion, in radians, and that turn's index."""
    angles = rotation_angle(readings[None], predicted[:, :, None])  # (H, N, 4)
    return angles.min(dim=-1)


def _refit(rate: Tensor, start: Tensor, readings: Tensor, times: Tensor,
           iterations: int = 30) -> tuple[Tensor, Tensor]:
    """The motion (rate (3,), start (3, 3)) nearest the agreeing frames' readings (K, 3, 3) at
    their times (K,), in the chordal sense, from the pair's motion: the pair's own noise
    otherwise grows along the pass with the distance from the pair."""
    rate = rate.clone().requires_grad_(True)
    turn = torch.zeros(3, dtype=torch.float64, requires_grad=True)  # start <- exp(turn) start
    optimiser = torch.optim.LBFGS([rate, turn], max_iter=iterations,
                                  line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        optimiser.zero_grad()
        motion = axis_angle_to_matrix(times[:, None] * rate) @ axis_angle_to_matrix(turn) @ start
        loss = (motion - readings).square().sum()
        loss.backward()
        return loss

    with torch.enable_grad():
        optimiser.step(closure)
    return rate.detach(), axis_angle_to_matrix(turn.detach()) @ start


def constant_rate_motion(rotation: Tensor, threshold_deg: float = 25.0,
                         times: Tensor | None = None, max_rate_deg: float = 45.0) -> PassMotion:
    """The constant-rate motion that most of N ordered frames' rotation readings agree with.

    Every ordered pair of frames (a, b), frame a's reading as it is and frame b's with each of
    its four half turns, proposes the motion through both; each frame agrees with a motion
    by its nearest half turn. The motion of least truncated squared angle (MSAC: each frame
    costs ``min(angle, threshold)^2``) wins; its rate and start are then fitted to the
    agreeing frames' readings (least squares, chordal), and the agreement measured again.

    Args:
        rotation: (N, 3, 3) body -> camera rotation of each frame, N >= 2, any float dtype.
        threshold_deg: a frame within this angle of a motion agrees with it.
        times: (N,) the frames' times (default 0, 1, ..., N - 1).
        max_rate_deg: the fastest turn considered, degrees per unit of time: frames of a pass
            are taken close enough to follow the target, and readings that alternate between
            half turns would otherwise be explained by a turn of nearly 180 deg per frame.
            When no pair proposes a turn this slow, every proposal is considered.

    Returns:
        :class:`PassMotion`, float64 on the CPU; the motion's body frame is frame a's reading
        for the winning pair, so turned by ``half_turns()[turn[k]]`` frame k's reading
        matches ``predicted[k]`` where it agrees.

    Raises:
        ValueError: one line naming ``rotation``, ``times``, ``threshold_deg`` or
            ``max_rate_deg``.
    """
    check_tensor("rotation", rotation, (3, 3))
    if rotation.dim() != 3 or len(rotation) < 2:
        raise ValueError(f"rotation: expected (N, 3, 3) with N >= 2, got {tuple(rotation.shape)}")
    if not 0.0 < threshold_deg < 180.0:
        raise ValueError(f"threshold_deg: expected in (0, 180), got {threshold_deg}")
    if not max_rate_deg > 0.0:
        raise ValueError(f"max_rate_deg: expected > 0, got {max_rate_deg}")
    rotation = rotation.detach().double().cpu()
    count = len(rotation)
    times = torch.arange(count, dtype=torch.float64) if times is None else \
        torch.as_tensor(times, dtype=torch.float64).cpu()
    if tuple(times.shape) != (count,) or not bool(torch.isfinite(times).all()):
        raise ValueError(f"times: expected ({count},) finite values, got {tuple(times.shape)}")
    readings = rotation[:, None] @ half_turns()  # (N, 4, 3, 3)
    first, second = torch.triu_indices(count, count, offset=1)
    gap = times[second] - times[first]
    if bool((gap == 0).any()):
        raise ValueError("times: two frames share a time")
    # (P * 4,) hypotheses: frame a's reading as it is, frame b's with each half turn.
    start_a = rotation[first].repeat_interleave(4, dim=0)
    end_b = readings[second].flatten(0, 1)
    rate = matrix_to_axis_angle(end_b @ start_a.transpose(-1, -2)) / \
        gap.repeat_interleave(4)[:, None]
    start = axis_angle_to_matrix(-times[first].repeat_interleave(4)[:, None] * rate) @ start_a
    angles, _ = _agreement(readings, _predicted(rate, start, times))
    threshold = math.radians(threshold_deg)
    cost = angles.clamp_max(threshold).square().sum(dim=1)
    slow = rate.norm(dim=1) <= math.radians(max_rate_deg)
    if bool(slow.any()):
        cost = torch.where(slow, cost, torch.full_like(cost, math.inf))
    best = int(cost.argmin())
    rate, start = rate[best:best + 1], start[best:best + 1]
    angles, turn = _agreement(readings, _predicted(rate, start, times))
    agree = angles[0] <= threshold
    rate, start = _refit(rate[0], start[0], readings[agree, turn[0][agree]], times[agree])
    predicted = _predicted(rate[None], start[None], times)
    angles, turn = _agreement(readings, predicted)
    return PassMotion(rate=rate, start=start, predicted=predicted[0], turn=turn[0],
                      error_deg=torch.rad2deg(angles[0]),
                      inliers=angles[0] <= threshold)
