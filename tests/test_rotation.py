"""Rotations: round trips, uniformity of random rotations, angle metrics and the SPEED score.

The tests that take ``device`` run on ``pytest --device`` (conftest.py): inputs are drawn on
the CPU from the same seeds, then moved."""

from __future__ import annotations

import math

import pytest
import torch

from sq_mitsuba.geometry.metrics import rotation_angle_deg, speed_score
from sq_mitsuba.geometry.rotation import (
    matrix_to_quaternion,
    matrix_to_rotation_6d,
    quaternion_angle,
    quaternion_to_matrix,
    random_quaternions,
    random_rotations,
    rotation_6d_to_matrix,
    rotation_angle,
)

F64 = torch.float64


def axis_angle_matrix(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula, an independent reference: (..., 3), (...) -> (..., 3, 3)."""
    axis = axis / axis.norm(dim=-1, keepdim=True)
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*x.shape, 3, 3)
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device)
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return eye + s * k + (1 - c) * k @ k


def test_quaternion_to_matrix_matches_rodrigues(device):
    gen = torch.Generator().manual_seed(0)
    axis = torch.randn(500, 3, generator=gen, dtype=F64).to(device)
    angle = (torch.rand(500, generator=gen, dtype=F64) * math.pi).to(device)
    unit = axis / axis.norm(dim=-1, keepdim=True)
    q = torch.cat([torch.cos(angle / 2)[:, None], torch.sin(angle / 2)[:, None] * unit], -1)
    torch.testing.assert_close(quaternion_to_matrix(q), axis_angle_matrix(axis, angle))
    # Not normalised: the same rotation.
    torch.testing.assert_close(quaternion_to_matrix(3.0 * q), axis_angle_matrix(axis, angle))


def test_quaternion_matrix_round_trip_up_to_sign(device):
    q = random_quaternions(2000, torch.Generator().manual_seed(1), dtype=F64)
    # Include near-180-degree rotations (w ~ 0) and the identity.
    q[:3] = torch.tensor([[0.0, 1.0, 0.0, 0.0], [1e-9, 0.0, 0.6, 0.8], [1.0, 0.0, 0.0, 0.0]],
                         dtype=F64)
    q = q.to(device)
    q = q / q.norm(dim=-1, keepdim=True)
    back = matrix_to_quaternion(quaternion_to_matrix(q))
    sign = torch.sign((back * q).sum(-1, keepdim=True))
    torch.testing.assert_close(back * sign, q)
    assert (back[:, 0] >= 0).all()


def test_6d_round_trip(device):
    rotations = random_rotations(1000, torch.Generator().manual_seed(2), dtype=F64,
                                 device=device)
    d6 = matrix_to_rotation_6d(rotations)
    torch.testing.assert_close(rotation_6d_to_matrix(d6), rotations)
    torch.testing.assert_close(matrix_to_rotation_6d(rotation_6d_to_matrix(d6)), d6)
    # Arbitrary 6D vectors give proper rotations.
    raw = torch.randn(1000, 6, generator=torch.Generator().manual_seed(3), dtype=F64)
    matrix = rotation_6d_to_matrix(raw.to(device))
    torch.testing.assert_close(matrix @ matrix.transpose(-1, -2), torch.eye(
        3, dtype=F64, device=device).expand(1000, 3, 3))
    torch.testing.assert_close(torch.linalg.det(matrix), torch.ones(1000, dtype=F64,
                                                                    device=device))


def test_6d_is_the_first_two_rows_and_gram_schmidt_keeps_the_first():
    """The convention by hand: a quarter turn about z, x -> y, has rows (0, -1, 0), (1, 0, 0),
    its 6D vector; a 6D vector's first row keeps its direction, the second loses its part
    along the first (columns, or the other order, would fail both)."""
    quarter = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    assert matrix_to_rotation_6d(quarter).tolist() == [0.0, -1.0, 0.0, 1.0, 0.0, 0.0]
    matrix = rotation_6d_to_matrix(torch.tensor([0.0, 3.0, 0.0, 2.0, 5.0, 0.0], dtype=F64))
    expected = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], dtype=F64)
    torch.testing.assert_close(matrix, expected, atol=1e-15, rtol=0)


def test_quaternions_follow_speeds_projection():
    """SPEED's published projection puts body points in the camera as quat2dcm(q)^T p + r,
    with quat2dcm its direction-cosine matrix of the scalar-first q, written out here from
    its formula (an independent reference): our body-to-camera matrix of q must be that."""
    q = random_quaternions(64, torch.Generator().manual_seed(8), dtype=F64)
    q0, q1, q2, q3 = q.unbind(-1)
    dcm = torch.stack([
        2 * q0**2 - 1 + 2 * q1**2, 2 * q1 * q2 + 2 * q0 * q3, 2 * q1 * q3 - 2 * q0 * q2,
        2 * q1 * q2 - 2 * q0 * q3, 2 * q0**2 - 1 + 2 * q2**2, 2 * q2 * q3 + 2 * q0 * q1,
        2 * q1 * q3 + 2 * q0 * q2, 2 * q2 * q3 - 2 * q0 * q1, 2 * q0**2 - 1 + 2 * q3**2,
    ], -1).reshape(64, 3, 3)
    torch.testing.assert_close(quaternion_to_matrix(q), dcm.transpose(-1, -2))


def test_6d_gradcheck(device):
    raw = torch.randn(4, 6, generator=torch.Generator().manual_seed(4), dtype=F64
                      ).to(device).requires_grad_()
    assert torch.autograd.gradcheck(rotation_6d_to_matrix, (raw,))


def test_random_rotations_are_uniform(device):
    n = 100_000
    rotations = random_rotations(n, torch.Generator().manual_seed(5), dtype=F64, device=device)
    # Haar measure: E[R] = 0 (each entry has variance 1/3, so the mean's std is ~0.0018).
    assert rotations.mean(0).abs().max().item() < 0.01
    # The angle of a uniform rotation has density (1 - cos t) / pi on [0, pi].
    angles = rotation_angle(torch.eye(3, dtype=F64, device=device), rotations)
    edges = torch.linspace(0, math.pi, 21, dtype=F64, device=device)
    observed = torch.histc(angles, bins=20, min=0, max=math.pi) / n
    cdf = (edges - torch.sin(edges)) / math.pi
    expected = cdf[1:] - cdf[:-1]
    assert (observed - expected).abs().max().item() < 0.005
    # Same generator seed, same rotations.
    again = random_rotations(10, torch.Generator().manual_seed(5), dtype=F64, device=device)
    torch.testing.assert_close(again, rotations[:10])


def test_rotation_angle_matches_constructed_angles(device):
    gen = torch.Generator().manual_seed(6)
    axis = torch.randn(300, 3, generator=gen, dtype=F64).to(device)
    angle = torch.linspace(0, math.pi, 300, dtype=F64, device=device)
    base = random_rotations(300, gen, dtype=F64, device=device)
    rotated = base @ axis_angle_matrix(axis, angle)
    torch.testing.assert_close(rotation_angle(base, rotated), angle, atol=1e-7, rtol=0)
    torch.testing.assert_close(rotation_angle_deg(base, rotated), torch.rad2deg(angle),
                               atol=1e-5, rtol=0)


def test_rotation_angle_gradient_finite_at_zero(device):
    rotation = random_rotations(1, torch.Generator().manual_seed(7), dtype=F64, device=device)
    raw = matrix_to_rotation_6d(rotation).clone().requires_grad_()
    angle = rotation_angle(rotation, rotation_6d_to_matrix(raw))
    (grad,) = torch.autograd.grad(angle.sum(), raw)
    assert angle.item() < 1e-6
    assert torch.isfinite(grad).all()


def test_speed_score_against_hand_values(device):
    on = {"dtype": F64, "device": device}
    q_true = torch.tensor([[1.0, 0.0, 0.0, 0.0]], **on)
    half = math.radians(30) / 2
    q_pred = torch.tensor([[math.cos(half), 0.0, 0.0, math.sin(half)]], **on)
    t_true = torch.tensor([[0.0, 0.0, 10.0]], **on)
    t_pred = torch.tensor([[0.3, 0.4, 10.0]], **on)
    score = speed_score(q_pred, q_true, t_pred, t_true)
    torch.testing.assert_close(score.rotation, torch.tensor([math.radians(30)], **on))
    torch.testing.assert_close(score.translation, torch.tensor([0.05], **on))
    torch.testing.assert_close(score.total, score.rotation + score.translation)
    # q and -q are the same attitude.
    torch.testing.assert_close(quaternion_angle(-q_pred, q_pred), torch.zeros(1, **on),
                               atol=1e-6, rtol=0)


def test_quaternion_angle_is_the_rotation_angle_with_a_finite_gradient_at_zero():
    """The angle equals the matrices' (an independent formula) over random pairs, both signs of
    q; at two equal rotations its gradient is finite (arccos' is infinite at 1), and
    elsewhere it passes gradcheck in float64."""
    from sq_mitsuba.geometry.rotation import rotation_angle

    generator = torch.Generator().manual_seed(3)
    a, b = (random_rotations(500, generator, torch.float64) for _ in range(2))
    qa, qb = matrix_to_quaternion(a), matrix_to_quaternion(b)
    for sign in (1.0, -1.0):
        torch.testing.assert_close(quaternion_angle(qa, sign * qb), rotation_angle(a, b),
                                   atol=1e-12, rtol=0)
    for dtype in (torch.float32, torch.float64):
        q = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.6, 0.8, 0.0, 0.0]], dtype=dtype,
                         requires_grad=True)
        quaternion_angle(q, 3 * q.detach()).sum().backward()
        assert bool(torch.isfinite(q.grad).all()), q.grad
    assert torch.autograd.gradcheck(quaternion_angle, (qa[:4].clone().requires_grad_(),
                                                       qb[:4].clone().requires_grad_()))


@pytest.mark.parametrize(("call", "name"), [
    (lambda: quaternion_to_matrix(torch.zeros(2, 3)), "quaternion"),
    (lambda: rotation_6d_to_matrix(torch.zeros(2, 5)), "d6"),
    (lambda: matrix_to_quaternion(torch.zeros(2, 3, 4)), "matrix"),
    (lambda: matrix_to_quaternion(torch.full((3, 3), float("nan"))), "matrix"),
    (lambda: quaternion_to_matrix(torch.ones(2, 4, dtype=torch.int32)), "quaternion"),
    (lambda: rotation_angle(torch.eye(3), torch.ones(3, 2)), "rotation_b"),
    (lambda: random_rotations(-1), "n"),
    # 2 I came back as the 6D vector of I, a reflection as that of a rotation.
    (lambda: matrix_to_rotation_6d(2 * torch.eye(3)), r"^matrix: not rotation matrices"),
    (lambda: matrix_to_rotation_6d(torch.diag(torch.tensor([1.0, 1.0, -1.0]))),
     r"^matrix: not rotation matrices \(a reflection"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()


def test_axis_angle_matches_the_quaternion_of_the_same_turn():
    """Reference: the quaternion (cos(a/2), sin(a/2) n) of a turn by a about the axis n."""
    from sq_mitsuba.geometry.rotation import axis_angle_to_matrix

    generator = torch.Generator().manual_seed(0)
    axes = torch.randn(16, 3, generator=generator, dtype=torch.float64)
    axes = axes / axes.norm(dim=1, keepdim=True)
    angles = torch.rand(16, generator=generator, dtype=torch.float64) * 3.1
    quaternions = torch.cat([torch.cos(angles / 2)[:, None],
                             torch.sin(angles / 2)[:, None] * axes], dim=1)
    torch.testing.assert_close(axis_angle_to_matrix(axes * angles[:, None]),
                               quaternion_to_matrix(quaternions))
    torch.testing.assert_close(axis_angle_to_matrix(torch.zeros(3, dtype=torch.float64)),
                               torch.eye(3, dtype=torch.float64))


def test_axis_angle_round_trip_through_the_matrix():
    """matrix_to_axis_angle inverts axis_angle_to_matrix for angles in [0, pi), at 0 and near
    pi (where the axis is still recovered, up to its sign at exactly pi)."""
    from sq_mitsuba.geometry.rotation import axis_angle_to_matrix, matrix_to_axis_angle

    generator = torch.Generator().manual_seed(1)
    axes = torch.randn(32, 3, generator=generator, dtype=torch.float64)
    axes = axes / axes.norm(dim=1, keepdim=True)
    angles = torch.rand(32, generator=generator, dtype=torch.float64) * 3.1
    angles[0], angles[1] = 0.0, math.pi - 1e-6
    vectors = axes * angles[:, None]
    torch.testing.assert_close(matrix_to_axis_angle(axis_angle_to_matrix(vectors)), vectors,
                               atol=1e-6, rtol=0)
    exact = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi], dtype=torch.float64))
    torch.testing.assert_close(matrix_to_axis_angle(exact).abs(),
                               torch.tensor([0.0, 0.0, math.pi], dtype=torch.float64))


def test_a_degenerate_6d_vector_is_refused_not_made_a_rotation():
    """F.normalize made a zero row a unit one: (0, ..., 0) became the zero matrix and parallel
    rows a rank-1 matrix, both returned as rotations."""
    for d6 in ([0.0] * 6, [1.0, 0.0, 0.0, 2.0, 0.0, 0.0]):
        with pytest.raises(ValueError, match=r"^d6: degenerate 6D rotation"):
            rotation_6d_to_matrix(torch.tensor(d6, dtype=F64))
    with pytest.raises(ValueError, match=r"^dtype: expected a floating-point dtype"):
        random_rotations(2, dtype=torch.int64)


def test_angles_name_batches_that_do_not_broadcast_and_widen_mixed_dtypes():
    rotations = random_rotations(3, torch.Generator().manual_seed(4), dtype=F64)
    with pytest.raises(ValueError, match=r"^rotation_a, rotation_b: shapes \(3, 3, 3\) and "
                                         r"\(2, 3, 3\) do not broadcast"):
        rotation_angle(rotations, rotations[:2])
    with pytest.raises(ValueError, match=r"quaternion_a=\(3, 4\), quaternion_b=\(2, 4\)"):
        quaternion_angle(torch.ones(3, 4), torch.ones(2, 4))
    q = random_quaternions(3, torch.Generator().manual_seed(5), dtype=F64)
    mixed = quaternion_angle(q.float(), q)  # was a RuntimeError from linalg.cross
    assert mixed.dtype == F64 and float(mixed.max()) < 1e-3
