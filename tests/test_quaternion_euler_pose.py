"""Quaternion algebra, Euler angles and rigid poses (geometry/rotation.py, geometry/pose.py),
each against an independent reference: matrix products, Rodrigues' formula, round trips and
finite differences in float64."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from sq_mitsuba.geometry.pose import compose_poses, invert_pose, relative_pose, transform_points
from sq_mitsuba.geometry.rotation import (
    euler_angles_to_matrix,
    matrix_to_euler_angles,
    quaternion_apply,
    quaternion_invert,
    quaternion_multiply,
    quaternion_to_matrix,
    random_quaternions,
    random_rotations,
)

F64 = torch.float64
CONVENTIONS = ["".join(axes) for axes in itertools.product("XYZ", repeat=3)
               if axes[0] != axes[1] and axes[1] != axes[2]]
UNIT = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}


def rodrigues(axis: tuple[float, float, float], angle: torch.Tensor) -> torch.Tensor:
    """A turn by ``angle`` (...) about a unit ``axis``: (..., 3, 3), Rodrigues' formula."""
    x, y, z = axis
    k = torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=angle.dtype)
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return torch.eye(3, dtype=angle.dtype) + s * k + (1 - c) * (k @ k)


def test_quaternion_product_is_the_matrix_product_and_the_inverse_undoes_it(device):
    gen = torch.Generator().manual_seed(0)
    a = random_quaternions(300, gen, dtype=F64).to(device)
    b = random_quaternions(300, gen, dtype=F64).to(device)
    product = quaternion_multiply(a, b)
    torch.testing.assert_close(quaternion_to_matrix(product),
                               quaternion_to_matrix(a) @ quaternion_to_matrix(b))
    torch.testing.assert_close(product.norm(dim=-1), torch.ones(300, dtype=F64, device=device))
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64, device=device).expand(300, 4)
    torch.testing.assert_close(quaternion_multiply(a, quaternion_invert(a)), identity)
    # Not unit: the inverse of 3q is q* / 3, still the product's inverse.
    torch.testing.assert_close(quaternion_multiply(quaternion_invert(3.0 * a), 3.0 * a),
                               identity)
    torch.testing.assert_close(quaternion_to_matrix(quaternion_invert(a)),
                               quaternion_to_matrix(a).transpose(-1, -2))
    # Broadcasting: one quaternion against a batch.
    torch.testing.assert_close(quaternion_multiply(a[:1], b), quaternion_multiply(
        a[:1].expand(300, 4), b))


def test_quaternion_apply_rotates_as_the_matrix_does(device):
    gen = torch.Generator().manual_seed(1)
    q = random_quaternions(50, gen, dtype=F64).to(device)
    points = torch.randn(50, 7, 3, generator=gen, dtype=F64).to(device)
    rotated = quaternion_apply(q[:, None], points)
    expected = points @ quaternion_to_matrix(q).transpose(-1, -2)
    torch.testing.assert_close(rotated, expected)
    torch.testing.assert_close(quaternion_apply(2.5 * q[:, None], points), expected)
    # float32 points turned by a float64 quaternion come back in float64.
    assert quaternion_apply(q[:1], points[0].float()).dtype == F64


def test_quaternion_operations_have_the_finite_difference_gradients():
    gen = torch.Generator().manual_seed(2)
    a = random_quaternions(4, gen, dtype=F64).requires_grad_()
    b = random_quaternions(4, gen, dtype=F64).requires_grad_()
    points = torch.randn(4, 3, generator=gen, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(quaternion_multiply, (a, b))
    assert torch.autograd.gradcheck(quaternion_invert, (a,))
    assert torch.autograd.gradcheck(quaternion_apply, (a, points))


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_euler_angles_are_the_product_of_turns_about_the_named_axes(convention):
    """Reference: R = R_c0(a0) R_c1(a1) R_c2(a2) by Rodrigues' formula, for all twelve
    conventions; the inverse brings back the angles within their ranges and, at gimbal lock,
    angles that give the same matrix."""
    gen = torch.Generator().manual_seed(3)
    angles = (torch.rand(200, 3, generator=gen, dtype=F64) * 2 - 1) * math.pi
    proper = convention[0] == convention[2]
    angles[:, 1] = (angles[:, 1].abs() if proper else angles[:, 1] / 2)  # the middle's range
    reference = (rodrigues(UNIT[convention[0]], angles[:, 0])
                 @ rodrigues(UNIT[convention[1]], angles[:, 1])
                 @ rodrigues(UNIT[convention[2]], angles[:, 2]))
    matrix = euler_angles_to_matrix(angles, convention)
    torch.testing.assert_close(matrix, reference)
    torch.testing.assert_close(matrix_to_euler_angles(matrix, convention), angles)
    # Any rotation comes back through its angles.
    rotations = random_rotations(200, gen, dtype=F64)
    back = euler_angles_to_matrix(matrix_to_euler_angles(rotations, convention), convention)
    torch.testing.assert_close(back, rotations)
    # Gimbal lock: the middle angle at its ends; the outer two share one turn.
    middle = (0.0, math.pi) if proper else (math.pi / 2, -math.pi / 2)
    locked = torch.tensor([[0.4, middle[0], -1.1], [2.0, middle[1], 0.7]], dtype=F64)
    read = matrix_to_euler_angles(euler_angles_to_matrix(locked, convention), convention)
    torch.testing.assert_close(euler_angles_to_matrix(read, convention),
                               euler_angles_to_matrix(locked, convention))
    assert (read[:, 2] == 0).all()
    # Near the lock (1e-6 rad in float64, 1e-4 in float32) the angles still give the matrix
    # back to the dtype's precision (asin and a fixed threshold lost half the digits there).
    for dtype, off, tolerance in ((F64, 1e-6, 1e-12), (torch.float32, 1e-4, 3e-7)):
        near = locked.clone()
        near[:, 1] += torch.tensor([off, -off], dtype=F64) * (1 if proper else -1)
        matrix = euler_angles_to_matrix(near, convention).to(dtype)
        back = euler_angles_to_matrix(matrix_to_euler_angles(matrix, convention), convention)
        assert float((back - matrix).abs().max()) < tolerance, (dtype, off)


def test_euler_angles_gradcheck_and_the_aerospace_default():
    angles = torch.tensor([[0.3, -0.4, 1.2]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(euler_angles_to_matrix, (angles,))
    # Yaw 90 deg alone turns x onto y (a turn about z).
    yaw = euler_angles_to_matrix(torch.tensor([math.pi / 2, 0.0, 0.0], dtype=F64))
    torch.testing.assert_close(yaw @ torch.tensor([1.0, 0.0, 0.0], dtype=F64),
                               torch.tensor([0.0, 1.0, 0.0], dtype=F64))


@pytest.mark.parametrize("convention", ["XX", "XXY", "ZYY", "abc", "XYZW"])
def test_an_euler_convention_that_is_none_is_refused(convention):
    with pytest.raises(ValueError, match="convention"):
        euler_angles_to_matrix(torch.zeros(3), convention)
    with pytest.raises(ValueError, match="convention"):
        matrix_to_euler_angles(torch.eye(3), convention)


def test_poses_compose_invert_and_relate_as_their_4x4_matrices(device):
    gen = torch.Generator().manual_seed(4)
    ra, rb = (random_rotations(20, gen, dtype=F64).to(device) for _ in range(2))
    ta, tb = (torch.randn(20, 3, generator=gen, dtype=F64).to(device) for _ in range(2))

    def homogeneous(rotation, translation):
        matrix = torch.zeros(*rotation.shape[:-2], 4, 4, dtype=F64, device=device)
        matrix[..., :3, :3], matrix[..., :3, 3], matrix[..., 3, 3] = rotation, translation, 1
        return matrix

    points = torch.randn(20, 5, 3, generator=gen, dtype=F64).to(device)
    moved = transform_points(points, ra, ta)
    ones = torch.ones(20, 5, 1, dtype=F64, device=device)
    torch.testing.assert_close(
        moved, (torch.cat([points, ones], -1) @ homogeneous(ra, ta).transpose(-1, -2))[..., :3])
    torch.testing.assert_close(transform_points(moved, *invert_pose(ra, ta)), points)
    torch.testing.assert_close(homogeneous(*compose_poses(ra, ta, rb, tb)),
                               homogeneous(ra, ta) @ homogeneous(rb, tb))
    torch.testing.assert_close(homogeneous(*compose_poses(*relative_pose(ra, ta, rb, tb), ra, ta)),
                               homogeneous(rb, tb))
    # The widest dtype wins: a float64 translation is not rounded to float32 points' dtype.
    far = torch.tensor([1e8 + 1.0, 0.0, 0.0], dtype=F64, device=device)
    eye = torch.eye(3, device=device)
    assert transform_points(torch.zeros(1, 3, device=device), eye, far)[0, 0] == 1e8 + 1.0
    assert invert_pose(eye, far)[1][0] == -(1e8 + 1.0)
    assert compose_poses(eye, far, eye, torch.zeros(3, device=device))[1][0] == 1e8 + 1.0


@pytest.mark.parametrize(("call", "name"), [
    (lambda: transform_points(torch.zeros(5, 2), torch.eye(3), torch.zeros(3)), "points"),
    (lambda: transform_points(torch.zeros(5, 3), torch.eye(4), torch.zeros(3)), "rotation"),
    (lambda: transform_points(torch.zeros(2, 5, 3), torch.eye(3).expand(3, 3, 3),
                              torch.zeros(3)), "do not broadcast"),
    (lambda: invert_pose(torch.eye(3).expand(2, 3, 3), torch.zeros(3, 3)), "do not broadcast"),
    (lambda: compose_poses(torch.eye(3), torch.zeros(3), torch.eye(3), torch.zeros(2)),
     "b: translation"),
    (lambda: quaternion_multiply(torch.zeros(2, 4), torch.zeros(3, 4)), "do not broadcast"),
    (lambda: quaternion_invert(torch.zeros(4)), "quaternion"),
    (lambda: quaternion_apply(torch.ones(4), torch.zeros(2)), "points"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()
