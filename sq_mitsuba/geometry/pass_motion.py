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

from sq_mitsuba.checks import check_rotations
from sq_mitsuba.geometry.rotation import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    rotation_angle,
)
from sq_mitsuba.geometry.so3_grid import with_half_turns

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


def _left_jacobian(vector: Tensor) -> Tensor:
    """(K, 3) rotation vectors -> (K, 3, 3) the left Jacobian of SO(3) at each:
    ``exp(v + e) = exp(J(v) e) exp(v)`` to first order in ``e``."""
    angle = vector.norm(dim=-1)[:, None, None]
    small = angle < 1e-6
    safe = torch.where(small, torch.ones_like(angle), angle)
    first = torch.where(small, torch.full_like(angle, 0.5), (1 - torch.cos(safe)) / safe**2)
    second = torch.where(small, torch.full_like(angle, 1 / 6), (safe - torch.sin(safe)) / safe**3)
    x, y, z = vector.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(-1, 3, 3)
    return torch.eye(3, dtype=vector.dtype) + first * skew + second * skew @ skew


def _refit(rate: Tensor, start: Tensor, readings: Tensor, times: Tensor,
           iterations: int = 8) -> tuple[Tensor, Tensor]:
    """The motion (rate (3,), start (3, 3)) nearest the agreeing frames' readings (K, 3, 3) at
    their times (K,), from the pair's motion: the pair's own noise otherwise grows along the
    pass with the distance from the pair. Gauss-Newton on the residual turns ``r_k`` (each
    reading is ``exp([r_k]) R(t_k)``): turning the start by ``a`` and adding ``d`` to the
    rate turns frame k's motion by ``exp(t_k [w]) a + t_k J(t_k w) d`` (J: SO(3)'s left
    Jacobian), which the step fits to the ``r_k`` by least squares; exact to first order
    however far the pass turns (a step that treated the turns as a line in ``t_k`` diverged
    on passes turning more than about 2 rad)."""
    for _ in range(iterations):
        turn = axis_angle_to_matrix(times[:, None] * rate)  # (K, 3, 3)
        residual = matrix_to_axis_angle(readings @ (turn @ start).transpose(-1, -2))  # (K, 3)
        jacobian = torch.cat([turn, times[:, None, None] * _left_jacobian(times[:, None] * rate)],
                             dim=-1)  # (K, 3, 6)
        # Convention: the SVD driver. The CPU default (gelsy, MKL's pivoted QR) is not
        # repeatable: its last bits change with where the arrays lie in memory, and the pass's
        # joint fit grows that into other poses from run to run.
        step = torch.linalg.lstsq(jacobian.reshape(-1, 6), residual.reshape(-1, 1),
                                  driver="gelsd").solution[:, 0]
        start, rate = axis_angle_to_matrix(step[:3]) @ start, rate + step[3:]
        if float(step.norm()) < 1e-12:
            break
    return rate, start


def _msac_cost(readings: Tensor, rate: Tensor, start: Tensor, times: Tensor,
               threshold: float) -> Tensor:
    """(H,) truncated squared angle of H motions over the frames, in chunks of hypotheses so
    that memory stays linear in them (each chunk holds (h, N, 4, 3, 3) matrices)."""
    chunk = max(1, 2**15 // len(readings))
    costs = []
    for k in range(0, len(rate), chunk):
        angles, _ = _agreement(readings, _predicted(rate[k:k + chunk], start[k:k + chunk], times))
        costs.append(angles.clamp_max(threshold).square().sum(dim=1))
    return torch.cat(costs)


def constant_rate_motion(rotation: Tensor, threshold_deg: float = 25.0,
                         times: Tensor | None = None, max_rate_deg: float = 45.0) -> PassMotion:
    """The constant-rate motion that most of N ordered frames' rotation readings agree with.

    Every pair of frames a < b (by index) close enough in time that a turn at
    ``max_rate_deg`` stays under half a turn between them (all pairs if none is), frame a's
    reading as it is and
    frame b's with each of its four half turns, proposes the motion through both; each frame
    agrees with a motion by its nearest half turn. The motion of least truncated squared angle
    (MSAC: each frame costs ``min(angle, threshold)^2``) wins; its rate and start are then
    fitted to the agreeing frames' readings (least squares of the angles), kept only if that lowers
    the cost within the rate bound, and the agreement measured again.

    Args:
        rotation: (N, 3, 3) body -> camera rotation of each frame, N >= 2, any float dtype.
        threshold_deg: a frame within this angle of a motion agrees with it.
        times: (N,) the frames' times, distinct, in any order (default 0, 1, ..., N - 1).
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
    check_rotations("rotation", rotation)
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
    readings = with_half_turns(rotation)  # (N, 4, 3, 3)
    first, second = torch.triu_indices(count, count, offset=1)
    gap = times[second] - times[first]
    if bool((gap == 0).any()):
        raise ValueError("times: two frames share a time")
    # Fitted about the frames' mean time: the refit's Jacobian grows with |t|, and timestamps
    # far from 0 left it ill-conditioned (the result moved with the origin of time).
    origin = times.mean()
    times = times - origin
    near = gap.abs() * max_rate_deg < 180.0  # the pair's turn read without wrapping
    if bool(near.any()):
        first, second, gap = first[near], second[near], gap[near]
    # (P * 4,) hypotheses: frame a's reading as it is, frame b's with each half turn.
    start_a = rotation[first].repeat_interleave(4, dim=0)
    end_b = readings[second].flatten(0, 1)
    rate = matrix_to_axis_angle(end_b @ start_a.transpose(-1, -2)) / \
        gap.repeat_interleave(4)[:, None]
    start = axis_angle_to_matrix(-times[first].repeat_interleave(4)[:, None] * rate) @ start_a
    threshold, bound = math.radians(threshold_deg), math.radians(max_rate_deg)
    cost = _msac_cost(readings, rate, start, times, threshold)
    slow = rate.norm(dim=1) <= bound
    if bool(slow.any()):
        cost = torch.where(slow, cost, torch.full_like(cost, math.inf))
    best = int(cost.argmin())
    rate, start = rate[best], start[best]
    angles, turn = _agreement(readings, _predicted(rate[None], start[None], times))
    agree = angles[0] <= threshold
    fitted_rate, fitted_start = _refit(rate, start, readings[agree, turn[0][agree]],
                                       times[agree])
    fitted_cost = _msac_cost(readings, fitted_rate[None], fitted_start[None], times, threshold)
    if float(fitted_cost[0]) <= float(cost[best]) and (
            float(fitted_rate.norm()) <= bound or not bool(slow.any())):
        rate, start = fitted_rate, fitted_start
    predicted = _predicted(rate[None], start[None], times)
    angles, turn = _agreement(readings, predicted)
    return PassMotion(rate=rate, start=axis_angle_to_matrix(-origin * rate) @ start,
                      predicted=predicted[0], turn=turn[0],
                      error_deg=torch.rad2deg(angles[0]),
                      inliers=angles[0] <= threshold)
