"""The constant-rate motion of a pass, found by consensus among the frames' readings.

Reference: passes built from a known motion (``R_k = exp(k w) R_0``), their readings turned
by random half turns, a little noise added and some frames replaced by misreadings.
"""

from __future__ import annotations

import math

import pytest
import torch

from sq_mitsuba.geometry.pass_motion import constant_rate_motion
from sq_mitsuba.geometry.rotation import axis_angle_to_matrix, random_rotations, rotation_angle
from sq_mitsuba.geometry.so3_grid import half_turns


def _pass(count: int, rate_deg: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    axis = torch.randn(3, generator=generator, dtype=torch.float64)
    rate = axis / axis.norm() * math.radians(rate_deg)
    start = random_rotations(1, generator, torch.float64)[0]
    truth = axis_angle_to_matrix(torch.arange(count, dtype=torch.float64)[:, None] * rate) @ start
    noise = axis_angle_to_matrix(torch.randn(count, 3, generator=generator,
                                             dtype=torch.float64) * math.radians(3.0))
    turns = half_turns()[torch.randint(0, 4, (count,), generator=generator)]
    return truth, noise @ truth @ turns


@pytest.mark.parametrize("seed", range(6))
def test_misread_frames_are_found_and_the_motion_recovered(seed):
    truth, readings = _pass(8, rate_deg=12.0, seed=seed)
    generator = torch.Generator().manual_seed(100 + seed)
    wrong = [2, 5]
    readings[wrong] = random_rotations(2, generator, torch.float64)  # far from the motion
    motion = constant_rate_motion(readings, threshold_deg=20.0)
    assert motion.inliers.tolist() == [k not in wrong for k in range(8)]
    # The motion's rotations differ from the truth by one body-side half turn (the winning
    # pair's frame a was read with one): the relative motion is the truth's.
    relative = motion.predicted[1:] @ motion.predicted[:-1].transpose(-1, -2)
    true_relative = truth[1:] @ truth[:-1].transpose(-1, -2)
    assert float(torch.rad2deg(rotation_angle(relative, true_relative)).max()) < 4.0
    aligned = truth[:, None] @ half_turns()
    error = torch.rad2deg(rotation_angle(aligned, motion.predicted[:, None])).amin(dim=1)
    assert float(error.max()) < 8.0
    # Fitted to six readings, the motion lies nearer the truth than the readings themselves.
    own = torch.rad2deg(rotation_angle(aligned, readings[:, None])).amin(dim=1)
    keep = motion.inliers
    assert float(error[keep].mean()) < float(own[keep].mean())
    # Each agreeing reading, turned by its half turn, lies at its noise from the motion.
    turned = readings @ half_turns()[motion.turn]
    assert float(torch.rad2deg(rotation_angle(turned, motion.predicted))[
        motion.inliers].max()) < 12.0


def test_times_space_the_frames():
    """Frames at uneven times: the rate is per unit of time, the motion passes through them."""
    generator = torch.Generator().manual_seed(3)
    rate = torch.tensor([0.0, 0.1, 0.05], dtype=torch.float64)
    start = random_rotations(1, generator, torch.float64)[0]
    times = torch.tensor([0.0, 0.5, 2.0, 3.0, 4.5], dtype=torch.float64)
    truth = axis_angle_to_matrix(times[:, None] * rate) @ start
    motion = constant_rate_motion(truth, times=times)
    assert bool(motion.inliers.all())
    torch.testing.assert_close(motion.rate.abs(), rate.abs(), atol=1e-6, rtol=0)
    torch.testing.assert_close(motion.predicted @ half_turns()[motion.turn], truth,
                               atol=1e-6, rtol=0)


@pytest.mark.parametrize("call, name", [
    (lambda: constant_rate_motion(torch.eye(3)[None]), "rotation"),
    (lambda: constant_rate_motion(torch.eye(3).expand(3, 3, 3), threshold_deg=0.0),
     "threshold_deg"),
    (lambda: constant_rate_motion(torch.eye(3).expand(3, 3, 3), times=torch.zeros(3)),
     "times"),
    (lambda: constant_rate_motion(torch.full((3, 3, 3), float("nan"))), "rotation"),
    (lambda: constant_rate_motion(torch.eye(3).expand(3, 3, 3), max_rate_deg=0.0),
     "max_rate_deg"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        call()


@pytest.mark.parametrize("matrices", [torch.zeros(4, 3, 3), -torch.eye(3).expand(4, 3, 3),
                                      3 * torch.eye(3).expand(4, 3, 3)])
def test_matrices_that_are_not_rotations_are_refused(matrices):
    """Zeros, reflections and scaled rotations are not readings: a reflection would otherwise
    be "fitted" exactly."""
    with pytest.raises(ValueError, match=r"^rotation: not rotation matrices"):
        constant_rate_motion(matrices.double())


@pytest.mark.parametrize("seed", range(3))
def test_the_motion_does_not_depend_on_where_time_starts(seed):
    """The same readings at times shifted by a timestamp's size: the same motion at every
    frame, and the start still the motion's rotation at time 0."""
    _, readings = _pass(8, rate_deg=12.0, seed=seed)
    plain = constant_rate_motion(readings)
    times = torch.arange(8, dtype=torch.float64) + 1.7e9
    shifted = constant_rate_motion(readings, times=times)
    assert shifted.inliers.tolist() == plain.inliers.tolist()
    assert float(torch.rad2deg(rotation_angle(shifted.predicted, plain.predicted)).max()) < 1e-5
    torch.testing.assert_close(shifted.rate, plain.rate, atol=1e-9, rtol=0)
    at_zero = axis_angle_to_matrix(torch.arange(8, dtype=torch.float64)[:, None] * plain.rate)
    torch.testing.assert_close(at_zero @ plain.start, plain.predicted, atol=1e-9, rtol=0)


def test_a_flip_every_other_frame_is_not_read_as_a_fast_turn():
    """A target spinning slowly about the line of sight, every other reading turned half a
    turn about it (a flat target's outline looks the same): a turn of 180 + 8 deg a frame
    explains every reading exactly, the slow one half of them; the rate bound keeps the slow
    motion and outvotes the flips."""
    generator = torch.Generator().manual_seed(11)
    start = random_rotations(1, generator, torch.float64)[0]
    rate = torch.tensor([0.0, 0.0, math.radians(8.0)], dtype=torch.float64)
    times = torch.arange(8, dtype=torch.float64)
    truth = axis_angle_to_matrix(times[:, None] * rate) @ start
    flip = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))  # about z (camera)
    readings = truth.clone()
    readings[1::2] = flip @ truth[1::2]
    fast = constant_rate_motion(readings, max_rate_deg=179.0)
    slow = constant_rate_motion(readings)
    assert bool(fast.inliers.all()) and float(torch.rad2deg(fast.rate.norm())) > 170.0
    assert slow.inliers.tolist() == [True, False] * 4
    relative = slow.predicted[1:] @ slow.predicted[:-1].transpose(-1, -2)
    true_relative = truth[1:] @ truth[:-1].transpose(-1, -2)
    assert float(torch.rad2deg(rotation_angle(relative, true_relative)).max()) < 1e-6


def test_two_frames_and_times_in_any_order():
    """Two frames agree with the turn through them; times need not be sorted or positive."""
    truth, _ = _pass(2, rate_deg=10.0, seed=2)
    motion = constant_rate_motion(truth)
    assert bool(motion.inliers.all())
    torch.testing.assert_close(motion.predicted @ half_turns()[motion.turn], truth,
                               atol=1e-9, rtol=0)
    generator = torch.Generator().manual_seed(4)
    rate = torch.tensor([0.05, -0.02, 0.08], dtype=torch.float64)
    start = random_rotations(1, generator, torch.float64)[0]
    times = torch.tensor([2.0, -1.0, 0.5, -3.0, 1.0], dtype=torch.float64)
    readings = axis_angle_to_matrix(times[:, None] * rate) @ start
    motion = constant_rate_motion(readings, times=times)
    assert bool(motion.inliers.all())
    torch.testing.assert_close(motion.predicted @ half_turns()[motion.turn], readings,
                               atol=1e-6, rtol=0)


@pytest.mark.parametrize("count", [30, 60])
def test_a_long_pass_is_fitted_as_least_squares_fits_it(count):
    """A pass that turns far (60 frames at 4.4 deg: 4.6 rad) with 3 deg of noise: the motion
    is the least-squares motion through the agreeing frames (scipy's solver on the same
    residual turns, an independent reference), within a few degrees of the truth at every
    frame. The refit that treated the turns as a line in time diverged there, leaving the
    two-frame proposal 10-20 deg off."""
    import numpy as np
    from scipy.optimize import least_squares

    from sq_mitsuba.geometry.rotation import matrix_to_axis_angle

    truth, readings = _pass(count, rate_deg=4.4, seed=11)
    motion = constant_rate_motion(readings)
    assert bool(motion.inliers.all())
    turned = readings @ half_turns()[motion.turn]
    times = torch.arange(count, dtype=torch.float64)

    def motion_at(x: np.ndarray) -> torch.Tensor:
        rate, start = torch.from_numpy(x[3:]), axis_angle_to_matrix(torch.from_numpy(x[:3]))
        return axis_angle_to_matrix(times[:, None] * rate) @ start

    def residuals(x: np.ndarray) -> np.ndarray:
        return matrix_to_axis_angle(turned @ motion_at(x).transpose(-1, -2)).reshape(-1).numpy()

    start = torch.cat([matrix_to_axis_angle(motion.start[None])[0], motion.rate]).numpy()
    reference = motion_at(least_squares(residuals, start, xtol=1e-12, ftol=1e-12).x)
    apart = torch.rad2deg(rotation_angle(motion.predicted, reference))
    assert float(apart.max()) < 0.01, apart.max()
    aligned = truth[:, None] @ half_turns()
    error = torch.rad2deg(rotation_angle(aligned, motion.predicted[:, None])).amin(dim=1)
    assert float(error.max()) < 4.0, error.max()


def test_the_left_jacobian_turns_a_small_change_of_rotation_vector():
    """exp(v + e) = exp(J(v) e) exp(v) to first order, by finite differences, at small and
    large angles."""
    from sq_mitsuba.geometry.pass_motion import _left_jacobian

    vectors = torch.tensor([[1e-8, 0.0, 0.0], [0.3, -0.2, 0.1], [1.5, 2.0, -0.5]],
                           dtype=torch.float64)
    step = torch.tensor([1e-6, -2e-6, 1.5e-6], dtype=torch.float64)
    change = axis_angle_to_matrix(vectors + step) @ axis_angle_to_matrix(vectors).transpose(-1, -2)
    from sq_mitsuba.geometry.rotation import matrix_to_axis_angle

    torch.testing.assert_close(matrix_to_axis_angle(change), _left_jacobian(vectors) @ step,
                               atol=1e-11, rtol=1e-4)


def test_the_motion_is_the_same_bytes_wherever_its_arrays_lie():
    """The same readings give the same motion to the last bit, call after call with memory
    taken in between (the pass's joint fit grows a last-bit difference into poses degrees
    apart). LAPACK's default least-squares driver on the CPU (MKL's pivoted QR) gave 3 to 8
    different answers in 200 such calls; the motion's refit uses the SVD driver."""
    _, readings = _pass(8, rate_deg=12.0, seed=2)
    first = constant_rate_motion(readings)
    held = []
    for size in (1, 7, 33, 129, 1001, 4099, 3, 517):
        held.append(torch.empty(size))  # moves where the next call's arrays are allocated
        again = constant_rate_motion(readings)
        assert torch.equal(again.rate, first.rate) and torch.equal(again.start, first.start)
