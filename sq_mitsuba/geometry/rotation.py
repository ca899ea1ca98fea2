"""Rotation representations and rotation distances, as pure functions on batched tensors.

Convention:
    - Rotation matrices act on column vectors: ``x_out = R @ x``; shape (..., 3, 3).
    - Quaternions are scalar-first (w, x, y, z), Hamilton product, shape (..., 4); ``q`` and
      ``-q`` are the same rotation. :func:`matrix_to_quaternion` returns the one with w >= 0.
      SPE3R's ``q_vbs2tango_true`` is such a quaternion, with R = quaternion_to_matrix(q) mapping
      body to camera.
    - The 6D representation (Zhou et al. 2019) is the first two *rows* of R, flattened (the
      PyTorch3D convention); Gram-Schmidt maps any non-degenerate 6 numbers back to a rotation.
    - Euler angles name their axes in the order the rotations are applied to the frame
      (intrinsic): "ZYX" with angles (a, b, c) is R = R_z(a) @ R_y(b) @ R_x(c), the aerospace
      yaw, pitch, roll ("3-2-1"); read right to left it is the same rotation about fixed axes
      (extrinsic X, then Y, then Z). The twelve conventions: six Tait-Bryan ("XYZ", ...) and six
      proper Euler ("ZXZ", ...).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.nn import functional as F

from sq_mitsuba.checks import (
    check_broadcast,
    check_int,
    check_nonzero,
    check_rotations,
    check_tensor,
    value_checks_enabled,
)

__all__ = [
    "IDENTITY_6D",
    "axis_angle_to_matrix",
    "best_rotation",
    "degenerate_6d",
    "euler_angles_to_matrix",
    "matrix_to_axis_angle",
    "matrix_to_euler_angles",
    "matrix_to_quaternion",
    "matrix_to_rotation_6d",
    "mean_rotation",
    "quaternion_angle",
    "quaternion_apply",
    "quaternion_invert",
    "quaternion_multiply",
    "quaternion_to_matrix",
    "random_quaternions",
    "random_rotations",
    "rotation_6d_to_matrix",
    "rotation_angle",
]

IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)
"""The identity's 6D rotation (the first two rows of I): the start of every rotation head
and fit."""


def degenerate_6d(d6: Tensor) -> Tensor:
    """(...,) bool: the 6D vectors (..., 6) whose two rows are zero or parallel (no rotation:
    Gram-Schmidt has no second direction), within a relative 1e-8."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    cross = torch.linalg.vector_norm(torch.linalg.cross(a1, a2, dim=-1), dim=-1)
    return cross <= 1e-8 * a1.norm(dim=-1) * a2.norm(dim=-1) + 1e-30


def _check_matrix(name: str, matrix: Tensor) -> None:
    check_tensor(name, matrix, (3, 3))


def rotation_6d_to_matrix(d6: Tensor) -> Tensor:
    """6D representation -> rotation matrix by Gram-Schmidt.

    Args:
        d6: (..., 6), the (unnormalised) first two rows of the matrix.

    Returns:
        (..., 3, 3) rotation matrices (rows b1, b2, b1 x b2).
    """
    check_tensor("d6", d6, (6,))
    a1, a2 = d6[..., :3], d6[..., 3:]
    # F.normalize would make a zero row a rotation.
    if value_checks_enabled() and d6.numel() and bool(degenerate_6d(d6).any()):
        raise ValueError("d6: degenerate 6D rotation (zero or parallel rows)")
    b1 = F.normalize(a1, dim=-1)
    b2 = F.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-2)


def matrix_to_rotation_6d(matrix: Tensor) -> Tensor:
    """Rotation matrix (..., 3, 3) -> 6D representation (..., 6): its first two rows.

    Raises:
        ValueError: for matrices that are no rotations (``2 I`` would come back as ``I``, a
            reflection as a rotation): a value check, as every ``matrix_to_*``'s.
    """
    _check_matrix("matrix", matrix)
    check_rotations("matrix", matrix.reshape(-1, 3, 3))
    return matrix[..., :2, :].reshape(*matrix.shape[:-2], 6)


def quaternion_to_matrix(quaternion: Tensor) -> Tensor:
    """Quaternion (w, x, y, z) -> rotation matrix (Hamilton convention).

    Args:
        quaternion: (..., 4), any non-zero norm (it is normalised implicitly).

    Returns:
        (..., 3, 3).
    """
    check_tensor("quaternion", quaternion, (4,))
    check_nonzero("quaternion", quaternion)
    # |q|^2 of a non-zero q under- or overflowed (float32 below about 1e-19 and above 1e19)
    # and gave NaN: such a q is divided by its largest |component| first (|q|^2 then in
    # [1, 4]); any other keeps its own values, so that its matrix is the same to the last bit.
    eps = torch.finfo(quaternion.dtype).eps if quaternion.is_floating_point() else 1e-7
    squared = (quaternion * quaternion).sum(-1, keepdim=True)
    extreme = (squared < eps) | (squared > 1 / eps) | ~torch.isfinite(squared)
    scaled = torch.where(extreme, quaternion / quaternion.abs().amax(-1, keepdim=True),
                         quaternion)
    w, x, y, z = scaled.unbind(-1)
    two_s = 2.0 / (scaled * scaled).sum(-1)
    rows = (
        1 - two_s * (y * y + z * z), two_s * (x * y - z * w), two_s * (x * z + y * w),
        two_s * (x * y + z * w), 1 - two_s * (x * x + z * z), two_s * (y * z - x * w),
        two_s * (x * z - y * w), two_s * (y * z + x * w), 1 - two_s * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(*quaternion.shape[:-1], 3, 3)


def matrix_to_quaternion(matrix: Tensor) -> Tensor:
    """Rotation matrix -> unit quaternion (w, x, y, z) with w >= 0.

    Each of the four components can be read off the diagonal; the one of largest magnitude is
    used to recover the others from the off-diagonal terms (Shepperd's method), which stays
    accurate near 180 degree rotations where w -> 0.

    Args:
        matrix: (..., 3, 3) rotation matrices (a reflection or a scaled matrix is refused:
            it has no quaternion; a value check, see :func:`~sq_mitsuba.checks.value_checks`).

    Returns:
        (..., 4).
    """
    _check_matrix("matrix", matrix)
    check_rotations("matrix", matrix.reshape(-1, 3, 3))
    m = matrix
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # 4 q_i^2 for i = w, x, y, z.
    four_sq = torch.stack([
        1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22,
    ], dim=-1)
    sum_w_x = m[..., 2, 1] - m[..., 1, 2]  # 4 w x
    sum_w_y = m[..., 0, 2] - m[..., 2, 0]  # 4 w y
    sum_w_z = m[..., 1, 0] - m[..., 0, 1]  # 4 w z
    sum_x_y = m[..., 1, 0] + m[..., 0, 1]  # 4 x y
    sum_x_z = m[..., 0, 2] + m[..., 2, 0]  # 4 x z
    sum_y_z = m[..., 2, 1] + m[..., 1, 2]  # 4 y z
    # Row i is 4 q_i * q; dividing by 4 |q_i| gives +-q.
    candidates = torch.stack([
        torch.stack([four_sq[..., 0], sum_w_x, sum_w_y, sum_w_z], dim=-1),
        torch.stack([sum_w_x, four_sq[..., 1], sum_x_y, sum_x_z], dim=-1),
        torch.stack([sum_w_y, sum_x_y, four_sq[..., 2], sum_y_z], dim=-1),
        torch.stack([sum_w_z, sum_x_z, sum_y_z, four_sq[..., 3]], dim=-1),
    ], dim=-2)
    four_abs = 2.0 * torch.sqrt(four_sq.clamp_min(0.1))  # clamp only guards unused rows
    candidates = candidates / four_abs[..., None]
    best = four_sq.argmax(dim=-1)
    index = best[..., None, None].expand(*best.shape, 1, 4)
    quaternion = candidates.gather(-2, index).squeeze(-2)
    quaternion = F.normalize(quaternion, dim=-1)
    return torch.where(quaternion[..., :1] < 0, -quaternion, quaternion)


def _check_float_dtype(dtype: object) -> None:
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise ValueError(f"dtype: expected a floating-point dtype, got {dtype}")


def random_quaternions(
    n: int,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Tensor:
    """Unit quaternions (n, 4), uniform on SO(3) (Shoemake's subgroup algorithm), w >= 0."""
    n = check_int("n", n, 0)
    _check_float_dtype(dtype)  # an integer dtype rounded every component to 0
    u = torch.rand(n, 3, generator=generator, dtype=torch.float64,
                   device=generator.device if generator is not None else device)
    r1, r2 = torch.sqrt(1.0 - u[:, 0]), torch.sqrt(u[:, 0])
    theta1, theta2 = 2.0 * math.pi * u[:, 1], 2.0 * math.pi * u[:, 2]
    q = torch.stack([r2 * torch.cos(theta2), r1 * torch.sin(theta1),
                     r1 * torch.cos(theta1), r2 * torch.sin(theta2)], dim=-1)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.to(dtype=dtype, device=device)


def random_rotations(
    n: int,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Tensor:
    """Rotation matrices (n, 3, 3), uniform on SO(3) (Shoemake's subgroup algorithm)."""
    _check_float_dtype(dtype)
    return quaternion_to_matrix(random_quaternions(n, generator, torch.float64, device)).to(
        dtype)


def rotation_angle(rotation_a: Tensor, rotation_b: Tensor) -> Tensor:
    """Angle in radians of the relative rotation ``rotation_a^T @ rotation_b``.

    Uses atan2(sin, cos) of the axis-angle form, accurate near 0 and 180 degrees where
    arccos((trace - 1) / 2) loses precision.

    Args:
        rotation_a, rotation_b: (..., 3, 3), broadcastable.

    Returns:
        (...) in [0, pi].
    """
    _check_matrix("rotation_a", rotation_a)
    _check_matrix("rotation_b", rotation_b)
    try:
        torch.broadcast_shapes(rotation_a.shape[:-2], rotation_b.shape[:-2])
    except RuntimeError:
        raise ValueError(f"rotation_a, rotation_b: shapes {tuple(rotation_a.shape)} and "
                         f"{tuple(rotation_b.shape)} do not broadcast") from None
    # Convention: rotations of two floating dtypes are compared in the wider (a float32
    # reading against float64 labels), as torch's elementwise operations would.
    dtype = torch.promote_types(rotation_a.dtype, rotation_b.dtype)
    relative = rotation_a.to(dtype).transpose(-1, -2) @ rotation_b.to(dtype)
    cos = 0.5 * (relative.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    skew = torch.stack([relative[..., 2, 1] - relative[..., 1, 2],
                        relative[..., 0, 2] - relative[..., 2, 0],
                        relative[..., 1, 0] - relative[..., 0, 1]], dim=-1)
    sin = 0.5 * torch.sqrt((skew * skew).sum(-1) + torch.finfo(skew.dtype).tiny)
    return torch.atan2(sin, cos)


def quaternion_angle(quaternion_a: Tensor, quaternion_b: Tensor) -> Tensor:
    """SPEED rotation error 2 arccos(min(1, |<q_a, q_b>|)) in radians, (..., 4) -> (...).

    Computed as 2 atan2(|q_a^* q_b| vector part, |scalar part|), the same angle, whose gradient
    stays finite where the two rotations are equal (arccos' is infinite at 1)."""
    check_tensor("quaternion_a", quaternion_a, (4,))
    check_tensor("quaternion_b", quaternion_b, (4,))
    check_nonzero("quaternion_a", quaternion_a)
    check_nonzero("quaternion_b", quaternion_b)
    check_broadcast(quaternion_a=quaternion_a, quaternion_b=quaternion_b)
    dtype = torch.promote_types(quaternion_a.dtype, quaternion_b.dtype)  # as rotation_angle
    a, b = F.normalize(quaternion_a.to(dtype), dim=-1), F.normalize(quaternion_b.to(dtype), dim=-1)
    a, b = torch.broadcast_tensors(a, b)
    (wa, va), (wb, vb) = (a[..., 0], a[..., 1:]), (b[..., 0], b[..., 1:])
    scalar = wa * wb + (va * vb).sum(-1)  # the scalar part of conj(a) b: <a, b>
    vector = wa[..., None] * vb - wb[..., None] * va - torch.linalg.cross(va, vb)
    return 2.0 * torch.atan2(torch.linalg.vector_norm(vector, dim=-1), scalar.abs())


def best_rotation(matrix: Tensor) -> Tensor:
    """The rotations F (..., 3, 3) maximising trace(F^T M) for matrices M (..., 3, 3), which
    are the rotations nearest M in the Frobenius norm (orthogonal Procrustes, Kabsch):
    U diag(1, 1, det(U V^T)) V^T from M's SVD. Where U V^T is a reflection the best rotation
    flips the weakest singular direction; flipping an axis of U V^T is proper too, but scores
    lower."""
    check_tensor("matrix", matrix, (3, 3))
    return _nearest_rotation(matrix)


def _nearest_rotation(matrix: Tensor) -> Tensor:
    u, _, vh = torch.linalg.svd(matrix)
    d = torch.sign(torch.linalg.det(u @ vh))  # +-1: U and V^T are orthogonal
    return torch.cat([u[..., :2], u[..., 2:] * d[..., None, None]], dim=-1) @ vh


def mean_rotation(rotations: Tensor) -> Tensor:
    """Chordal L2 mean (3, 3), float64, of rotations (N, 3, 3): the arithmetic mean projected
    onto SO(3) (:func:`best_rotation`'s projection, the rotation nearest it).

    Raises:
        ValueError: naming ``rotations``: another shape, none (N = 0), NaN.
    """
    check_tensor("rotations", rotations, (3, 3), min_dims=3)
    if rotations.dim() != 3 or rotations.shape[0] == 0:
        raise ValueError(f"rotations: expected (N, 3, 3) with N >= 1, got "
                         f"{tuple(rotations.shape)}")
    check_rotations("rotations", rotations)  # zeros or a reflection came back as a rotation
    return _nearest_rotation(rotations.double().mean(0))


def axis_angle_to_matrix(rotation_vector: Tensor) -> Tensor:
    """Rotation vectors (..., 3) (axis times angle, radians) -> rotation matrices (..., 3, 3),
    by the exponential of their skew-symmetric matrices (differentiable, exact at 0).

    An angle beyond pi is first wrapped into [-pi, pi] about the same axis (the same rotation):
    the exponential of a large skew matrix loses accuracy (float32: 4e-4 at 1000 rad, not
    orthonormal at 1e5) and overflows to NaN (1e10 rad; float64 1e20)."""
    w = check_tensor("rotation_vector", rotation_vector, (3,))
    # The angle in float64: a float32 norm overflows above 1e19; sin and cos reduce a huge
    # angle exactly. Angles up to pi keep w itself (factor 1), bit for bit.
    angle = torch.linalg.vector_norm(w.double(), dim=-1, keepdim=True)
    wide = angle > math.pi
    safe = torch.where(wide, angle, torch.ones_like(angle))  # no 0 / 0 in either branch
    factor = torch.where(wide, torch.atan2(torch.sin(safe), torch.cos(safe)) / safe, 1.0)
    w = w * factor.to(w.dtype)
    zero = torch.zeros_like(w[..., 0])
    skew = torch.stack([torch.stack([zero, -w[..., 2], w[..., 1]], -1),
                        torch.stack([w[..., 2], zero, -w[..., 0]], -1),
                        torch.stack([-w[..., 1], w[..., 0], zero], -1)], -2)
    return torch.linalg.matrix_exp(skew)


def matrix_to_axis_angle(matrix: Tensor) -> Tensor:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3) (axis times angle, radians,
    angle in [0, pi]): the inverse of :func:`axis_angle_to_matrix`, through the quaternion
    with w >= 0 (accurate near 0 and 180 degrees)."""
    quaternion = matrix_to_quaternion(matrix)
    sine = quaternion[..., 1:].norm(dim=-1, keepdim=True)  # sin(angle / 2)
    angle = 2.0 * torch.atan2(sine, quaternion[..., :1])
    # angle / sin(angle / 2) -> 2 as the angle -> 0.
    scale = torch.where(sine > 1e-12, angle / sine.clamp_min(1e-12), torch.full_like(sine, 2.0))
    return quaternion[..., 1:] * scale


def quaternion_multiply(quaternion_a: Tensor, quaternion_b: Tensor) -> Tensor:
    """Hamilton product ``a b`` of quaternions (..., 4), broadcast over the batch dims:
    ``quaternion_to_matrix(a b) == quaternion_to_matrix(a) @ quaternion_to_matrix(b)`` (b
    applied first). Unit inputs give a unit product; the sign is not made w >= 0 (it is the
    product's)."""
    check_tensor("quaternion_a", quaternion_a, (4,))
    check_tensor("quaternion_b", quaternion_b, (4,))
    check_broadcast(quaternion_a=quaternion_a, quaternion_b=quaternion_b)
    dtype = torch.promote_types(quaternion_a.dtype, quaternion_b.dtype)
    a, b = torch.broadcast_tensors(quaternion_a.to(dtype), quaternion_b.to(dtype))
    (wa, va), (wb, vb) = (a[..., :1], a[..., 1:]), (b[..., :1], b[..., 1:])
    w = wa * wb - (va * vb).sum(-1, keepdim=True)
    v = wa * vb + wb * va + torch.linalg.cross(va, vb, dim=-1)
    return torch.cat([w, v], dim=-1)


def quaternion_invert(quaternion: Tensor) -> Tensor:
    """The inverse (..., 4) of non-zero quaternions (..., 4): the conjugate over the squared
    norm, so that ``quaternion_multiply(q, quaternion_invert(q))`` is (1, 0, 0, 0); for a unit
    quaternion, the conjugate, the inverse rotation."""
    check_tensor("quaternion", quaternion, (4,))
    check_nonzero("quaternion", quaternion)
    conjugate = torch.cat([quaternion[..., :1], -quaternion[..., 1:]], dim=-1)
    return conjugate / (quaternion * quaternion).sum(-1, keepdim=True)


def quaternion_apply(quaternion: Tensor, points: Tensor) -> Tensor:
    """Points (..., 3) rotated by quaternions (..., 4) (normalised implicitly, as in
    :func:`quaternion_to_matrix`), broadcast over the batch dims: the same as
    ``(quaternion_to_matrix(q) @ points[..., None])[..., 0]``, without forming the matrix."""
    check_tensor("quaternion", quaternion, (4,))
    check_tensor("points", points, (3,))
    check_nonzero("quaternion", quaternion)
    batch = check_broadcast(quaternion=quaternion, points=points)
    dtype = torch.promote_types(quaternion.dtype, points.dtype)
    q = F.normalize(quaternion.to(dtype), dim=-1).expand(*batch, 4)
    w, u, p = q[..., :1], q[..., 1:], points.to(dtype).expand(*batch, 3)
    # p' = p + 2 w (u x p) + 2 u x (u x p), the sandwich q p q* written with cross products.
    twice_cross = 2.0 * torch.linalg.cross(u, p, dim=-1)
    return p + w * twice_cross + torch.linalg.cross(u, twice_cross, dim=-1)


_AXES = {"X": 0, "Y": 1, "Z": 2}


def _euler_axes(convention: str) -> tuple[int, int, int]:
    """The axis indices of an Euler convention ("ZYX", "ZXZ", ...), refusing others."""
    if (not isinstance(convention, str) or len(convention) != 3
            or any(c not in _AXES for c in convention)
            or convention[0] == convention[1] or convention[1] == convention[2]):
        raise ValueError(f"convention: expected three axes of X, Y, Z, no two in a row alike "
                         f"(e.g. 'ZYX' or 'ZXZ'), got {convention!r}")
    i, j, k = (_AXES[c] for c in convention)
    return i, j, k


def _axis_rotation(axis: int, angle: Tensor) -> Tensor:
    """Rotations (..., 3, 3) by ``angle`` (...) about the coordinate axis ``axis``."""
    cos, sin = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(angle), torch.zeros_like(angle)
    p, q = (axis + 1) % 3, (axis + 2) % 3
    entries = [[zero] * 3 for _ in range(3)]
    entries[axis][axis] = one
    entries[p][p], entries[p][q], entries[q][p], entries[q][q] = cos, -sin, sin, cos
    return torch.stack([torch.stack(row, -1) for row in entries], -2)


def euler_angles_to_matrix(angles: Tensor, convention: str = "ZYX") -> Tensor:
    """Euler angles (..., 3), radians, -> rotation matrices (..., 3, 3):
    ``R = R_{c0}(angles[..., 0]) @ R_{c1}(angles[..., 1]) @ R_{c2}(angles[..., 2])`` for the
    convention's axes c0 c1 c2 (intrinsic, see the module's convention; default "ZYX": yaw,
    pitch, roll)."""
    axes = _euler_axes(convention)
    check_tensor("angles", angles, (3,))
    first, second, third = (_axis_rotation(a, angles[..., n]) for n, a in enumerate(axes))
    return first @ second @ third


def matrix_to_euler_angles(matrix: Tensor, convention: str = "ZYX") -> Tensor:
    """Rotation matrices (..., 3, 3) -> Euler angles (..., 3), radians, the inverse of
    :func:`euler_angles_to_matrix`: the first and last in (-pi, pi], the middle in
    [-pi/2, pi/2] (Tait-Bryan) or [0, pi] (proper Euler).

    At gimbal lock (the middle angle at +-pi/2, or at 0 or pi) only the sum or difference of
    the outer two is defined: the last is then 0 and the first carries the rest, so the angles
    still give the matrix back.
    """
    i, j, k = _euler_axes(convention)
    _check_matrix("matrix", matrix)
    check_rotations("matrix", matrix.reshape(-1, 3, 3))
    m = matrix
    # The middle angle by atan2 (asin and acos lose half the digits near the lock); locked
    # where its cosine (Tait-Bryan) or sine (proper) is below a few units in the last place.
    sign = 1.0 if (j - i) % 3 == 1 else -1.0  # of the permutation (i, j, k) or (i, j, m)
    if i != k:  # Tait-Bryan
        reach = torch.hypot(m[..., j, k], m[..., k, k])  # |cos middle|
        middle = torch.atan2(sign * m[..., i, k], reach)
        first = torch.atan2(-sign * m[..., j, k], m[..., k, k])
        last = torch.atan2(-sign * m[..., i, j], m[..., i, i])
    else:  # proper Euler, m the third axis
        other = 3 - i - j
        reach = torch.hypot(m[..., j, i], m[..., other, i])  # sin middle
        middle = torch.atan2(reach, m[..., i, i])
        first = torch.atan2(m[..., j, i], -sign * m[..., other, i])
        last = torch.atan2(m[..., i, j], sign * m[..., i, other])
    locked = reach < 4 * torch.finfo(m.dtype).eps
    if bool(locked.any()):
        # The last angle 0: R = R_i(first) R_j(middle), so R_i(first) = R R_j(middle)^T.
        rest = m @ _axis_rotation(j, middle).transpose(-1, -2)
        p, q = (i + 1) % 3, (i + 2) % 3
        first = torch.where(locked, torch.atan2(rest[..., q, p], rest[..., p, p]), first)
        last = torch.where(locked, torch.zeros_like(last), last)
    return torch.stack([first, middle, last], dim=-1)
