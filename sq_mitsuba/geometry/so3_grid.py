"""Near-uniform grids of rotations and the four half turns of a body frame.

Grids serve two jobs: the cells of the rotation-classification head (one score per grid
rotation) and the global candidates of the render-and-compare search. Both need the same few
operations: build a grid of N rotations, find the cell nearest a rotation, and multiply a set
of rotations by the four half turns that leave a principal-axes body frame's axes in place.

Convention:
    - Rotations are (..., 3, 3) matrices acting on column vectors; poses map body to camera,
      ``x_cam = R x_body + t`` (OpenCV camera frame), so a turn ``S`` of the body frame acts on
      the right: the poses ``R`` and ``R @ S`` show the same object when the shape is
      invariant under ``S``.
    - Quaternions are scalar first (w, x, y, z); ``q`` and ``-q`` are one rotation.
    - The grid is a super-Fibonacci spiral (Alexa, "Super-Fibonacci Spirals", CVPR 2022):
      deterministic, any count, near-uniform on SO(3); cell ``i`` of an ``N``-grid is the same
      rotation in every call.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from sq_mitsuba.checks import check_int, check_rotations, check_tensor
from sq_mitsuba.geometry.rotation import quaternion_to_matrix

__all__ = [
    "HALF_TURNS",
    "axis_turns",
    "covering_angle_deg",
    "half_turns",
    "nearest_grid_index",
    "so3_grid",
    "super_fibonacci_quaternions",
    "with_half_turns",
]

#: The four half turns about a body frame's axes, (4, 3, 3): identity, then x, y and z.
HALF_TURNS = (
    (1.0, 1.0, 1.0),
    (1.0, -1.0, -1.0),
    (-1.0, 1.0, -1.0),
    (-1.0, -1.0, 1.0),
)
# Alexa's constants: phi = sqrt(2), psi the real root of psi^4 = psi + 4.
_PHI = math.sqrt(2.0)
_PSI = 1.533751168755204288118041


def _checked_count(count: object) -> int:
    """``count`` as a positive int (a numpy integer as Python's); a bool is refused, not
    read as 1 (``so3_grid(True)`` built a one-cell grid)."""
    return check_int("count", count)


def super_fibonacci_quaternions(count: int, dtype: torch.dtype = torch.float64) -> Tensor:
    """``count`` near-uniform unit quaternions (count, 4), scalar first, w >= 0.

    Raises:
        ValueError: ``count`` not a positive integer.
    """
    count = _checked_count(count)
    s = torch.arange(count, dtype=torch.float64) + 0.5
    radius = torch.sqrt(s / count)
    complement = torch.sqrt(1.0 - s / count)
    alpha = 2.0 * math.pi * s / _PHI
    beta = 2.0 * math.pi * s / _PSI
    q = torch.stack([radius * torch.sin(alpha), radius * torch.cos(alpha),
                     complement * torch.sin(beta), complement * torch.cos(beta)], dim=-1)
    # The spiral covers the whole 3-sphere; fold onto w >= 0 (q and -q are one rotation).
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.to(dtype)


def so3_grid(count: int, dtype: torch.dtype = torch.float64) -> Tensor:
    """``count`` near-uniform rotation matrices (count, 3, 3) (a super-Fibonacci spiral)."""
    return quaternion_to_matrix(super_fibonacci_quaternions(count, torch.float64)).to(dtype)


def covering_angle_deg(count: int) -> float:
    """Typical angle from a random rotation to its nearest cell of a ``count``-grid, degrees.

    The angle of a ball in SO(3) with volume ``pi^2 / count`` (SO(3) has volume pi^2 in the
    angle measure ``(theta - sin theta) / pi``), i.e. the radius the cells would have if they
    tiled SO(3) as balls. Measured nearest-cell angles of uniform random rotations have a
    median close to 0.8 of it and a maximum near 1.4-1.5 times it.
    """
    count = _checked_count(count)
    target = math.pi / count  # (theta - sin theta) = pi * volume fraction
    low, high = 0.0, math.pi
    for _ in range(60):  # bisection on the monotone theta - sin theta
        mid = 0.5 * (low + high)
        if mid - math.sin(mid) < target:
            low = mid
        else:
            high = mid
    return math.degrees(0.5 * (low + high))


def nearest_grid_index(rotations: Tensor, grid: Tensor) -> Tensor:
    """Index of the grid rotation nearest each rotation (smallest relative angle).

    Args:
        rotations: (..., 3, 3).
        grid: (N, 3, 3).

    Returns:
        (...) int64 indices into ``grid``. The relative angle grows as ``trace(G^T R)``
        falls, so the nearest cell maximises that trace.

    Raises:
        ValueError: naming the argument: another shape, an empty grid, or matrices that are
            not rotations (a value check: NaN read as cell 0, and the trace ranks only
            rotations by angle).
    """
    check_tensor("rotations", rotations, (3, 3))  # its shape before the reshape below
    check_rotations("rotations", rotations.reshape(-1, 3, 3))
    check_rotations("grid", grid)
    if grid.dim() != 3 or grid.shape[0] == 0:
        raise ValueError(f"grid: expected (N, 3, 3) with N >= 1, got {tuple(grid.shape)}")
    flat = rotations.reshape(-1, 9).to(grid.dtype)
    traces = flat @ grid.reshape(-1, 9).T  # (P, N): trace(G^T R) = sum(G * R)
    return traces.argmax(dim=-1).reshape(rotations.shape[:-2])


def half_turns(dtype: torch.dtype = torch.float64, device: torch.device | None = None) -> Tensor:
    """The four half turns of :data:`HALF_TURNS` as (4, 3, 3) diagonal matrices."""
    return torch.diag_embed(torch.tensor(HALF_TURNS, dtype=dtype, device=device))


def axis_turns(dtype: torch.dtype = torch.float64, device: torch.device | None = None) -> Tensor:
    """The 24 rotations that map the body axes onto themselves (the cube's rotations, the
    proper signed permutations) as (24, 3, 3), the identity first and the four half turns
    among them: ``R`` and ``R @ P`` name the same three lines in space differently (which
    axis is called x, y or z, and which end is "+").

    Convention: the body axes' names come from the target's extents (longest on x), so where
    two extents are nearly equal a reading can have every axis right and still swap two names;
    the error up to these turns measures the axes alone.
    """
    found = []
    for order in ((0, 1, 2), (1, 2, 0), (2, 0, 1), (0, 2, 1), (2, 1, 0), (1, 0, 2)):
        for signs in HALF_TURNS:
            matrix = torch.zeros(3, 3, dtype=torch.float64)
            matrix[list(order), range(3)] = torch.tensor(signs, dtype=torch.float64)
            if torch.linalg.det(matrix) < 0:  # an odd permutation: one more flip makes it proper
                matrix = -matrix
            found.append(matrix)
    return torch.stack(found).to(dtype=dtype, device=device)


def with_half_turns(rotations: Tensor) -> Tensor:
    """Every rotation times every half turn of the body frame: (..., 3, 3) -> (..., 4, 3, 3).

    ``out[..., j, :, :] = rotations @ half_turns()[j]``: the four poses that a body frame
    fixed only by its principal axes cannot tell apart.
    """
    check_tensor("rotations", rotations, (3, 3))  # numpy or (3,) failed inside torch
    turns = half_turns(rotations.dtype, rotations.device)
    return rotations[..., None, :, :] @ turns
