"""Icosphere: counts, closure and orientation (checked with trimesh), angles."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from sq_mitsuba.geometry.icosphere import icosphere, icosphere_angles, icosphere_faces


@pytest.mark.parametrize("level", [0, 1, 2, 3])
def test_icosphere_is_a_closed_outward_unit_sphere(level):
    vertices, faces = icosphere(level)
    assert vertices.shape == (10 * 4**level + 2, 3)
    assert faces.shape == (20 * 4**level, 3)
    np.testing.assert_allclose(np.linalg.norm(vertices, axis=1), 1.0)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.euler_number == 2
    assert mesh.volume > 0  # outward normals
    # Volume approaches the sphere's from below.
    assert 0.6 * 4 / 3 * np.pi < mesh.volume < 4 / 3 * np.pi
    assert len(np.unique(vertices.round(12), axis=0)) == len(vertices)


def test_level_3_has_642_vertices_and_angles_reproduce_them():
    vertices, _ = icosphere(3)
    assert len(vertices) == 642
    eta, omega = icosphere_angles(3, torch.float64)
    rebuilt = torch.stack([torch.cos(eta) * torch.cos(omega), torch.cos(eta) * torch.sin(omega),
                           torch.sin(eta)], -1)
    np.testing.assert_allclose(rebuilt.numpy(), vertices, atol=1e-12)
    assert icosphere_faces(3).dtype == torch.int64


def test_icosphere_rejects_bad_level():
    with pytest.raises(ValueError, match="level"):
        icosphere(-1)
    with pytest.raises(ValueError, match="level"):
        icosphere(2.5)
