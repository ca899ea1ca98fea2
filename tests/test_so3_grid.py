"""SO(3) grids: uniformity, nearest-cell lookup against brute force, the four half turns and
the 24 turns of the axes."""

from __future__ import annotations

import math

import pytest
import torch

from sq_mitsuba.geometry.metrics import rotation_error_deg
from sq_mitsuba.geometry.rotation import random_rotations, rotation_angle
from sq_mitsuba.geometry.so3_grid import (
    axis_turns,
    covering_angle_deg,
    half_turns,
    nearest_grid_index,
    so3_grid,
    super_fibonacci_quaternions,
    with_half_turns,
)


def test_grid_is_rotations_and_deterministic() -> None:
    grid = so3_grid(500)
    assert grid.shape == (500, 3, 3)
    eye = torch.eye(3, dtype=grid.dtype).expand_as(grid)
    torch.testing.assert_close(grid @ grid.transpose(-1, -2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(grid), torch.ones(500, dtype=grid.dtype))
    assert torch.equal(grid, so3_grid(500))
    q = super_fibonacci_quaternions(500)
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(500, dtype=q.dtype))


@pytest.mark.parametrize("count", [72, 576, 4608])
def test_grid_covers_so3_uniformly(count: int) -> None:
    """Random rotations lie near a cell, as a uniform tiling predicts; no region is empty."""
    grid = so3_grid(count)
    probes = random_rotations(3000, generator=torch.Generator().manual_seed(1),
                              dtype=torch.float64)
    index = nearest_grid_index(probes, grid)
    nearest = torch.rad2deg(rotation_angle(probes, grid[index]))
    radius = covering_angle_deg(count)
    assert 0.6 * radius < float(nearest.median()) < 0.95 * radius
    assert float(nearest.max()) < 1.65 * radius
    # Every cell is the nearest of some probes in proportion to its volume (no clumps):
    # with 3000 probes over 72 cells the busiest cell gets well under 3x its share.
    if count == 72:
        counts = torch.bincount(index, minlength=count).double()
        assert float(counts.max()) < 3.0 * 3000 / count


def test_nearest_index_matches_brute_force() -> None:
    grid = so3_grid(300)
    probes = random_rotations(50, generator=torch.Generator().manual_seed(2),
                              dtype=torch.float64)
    angles = rotation_angle(probes[:, None], grid[None])  # (50, 300)
    assert torch.equal(nearest_grid_index(probes, grid), angles.argmin(dim=1))
    assert nearest_grid_index(probes.reshape(5, 10, 3, 3), grid).shape == (5, 10)
    with pytest.raises(ValueError, match="grid"):
        nearest_grid_index(probes, grid[0])


def test_covering_angle_inverts_the_volume() -> None:
    for count in (1, 10, 1000):
        theta = math.radians(covering_angle_deg(count))
        assert math.isclose(theta - math.sin(theta), math.pi / count, rel_tol=1e-9)
    with pytest.raises(ValueError):
        covering_angle_deg(0)
    with pytest.raises(ValueError):
        so3_grid(0)


def test_half_turns_are_the_axis_flips() -> None:
    turns = half_turns()
    torch.testing.assert_close(turns @ turns, torch.eye(3, dtype=turns.dtype).expand(4, 3, 3))
    torch.testing.assert_close(torch.linalg.det(turns), torch.ones(4, dtype=turns.dtype))
    angles = torch.rad2deg(rotation_angle(turns, torch.eye(3, dtype=turns.dtype).expand(4, 3, 3)))
    torch.testing.assert_close(angles, torch.tensor([0.0, 180.0, 180.0, 180.0],
                                                    dtype=turns.dtype), atol=1e-4, rtol=0)
    rotations = random_rotations(6, generator=torch.Generator().manual_seed(3),
                                 dtype=torch.float64)
    expanded = with_half_turns(rotations)
    assert expanded.shape == (6, 4, 3, 3)
    # A half turn of the body frame flips two body axes as seen from the camera.
    torch.testing.assert_close(expanded[:, 1, :, 0], rotations[:, :, 0])
    torch.testing.assert_close(expanded[:, 1, :, 1], -rotations[:, :, 1])


def test_axis_turns_are_the_cube_group() -> None:
    turns = axis_turns()
    eye = torch.eye(3, dtype=turns.dtype)
    assert turns.shape == (24, 3, 3)
    torch.testing.assert_close(turns[:4], half_turns())
    torch.testing.assert_close(torch.linalg.det(turns), torch.ones(24, dtype=turns.dtype))
    # Signed permutations: one +-1 per row and column.
    assert bool((turns.abs().sum(1) == 1).all()) and bool((turns.abs().sum(2) == 1).all())
    # A group of 24 distinct elements: every product is one of them.
    keys = {tuple(t.flatten().tolist()) for t in turns}
    assert len(keys) == 24
    products = (turns[:, None] @ turns[None]).reshape(-1, 3, 3)
    assert {tuple(t.flatten().tolist()) for t in products} == keys
    # Every rotation lies within 62.8 deg of one of them (the cube group's covering radius;
    # 200,000 random rotations reach 62.5), and a relabelled reading is exact.
    rotations = random_rotations(2000, generator=torch.Generator().manual_seed(5),
                                 dtype=torch.float64)
    error = rotation_error_deg(rotations, eye.expand(2000, 3, 3), turns)
    assert float(error.max()) <= 62.81
    relabelled = rotations @ turns[torch.arange(2000) % 24]
    torch.testing.assert_close(rotation_error_deg(relabelled, rotations, turns),
                               torch.zeros(2000, dtype=torch.float64), atol=1e-4, rtol=0)
