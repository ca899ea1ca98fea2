"""Icosphere tessellation and its (eta, omega) angles, cached per level.

Superquadric meshes reuse the icosphere's faces: every superquadric surface is the image of the
unit sphere under a continuous, orientation-preserving map of (eta, omega), so mapping the
icosphere's vertices keeps the mesh closed (watertight) and outward-facing.

Convention: unit sphere, faces counter-clockwise seen from outside (outward normals);
eta = asin(z) is the latitude in [-pi/2, pi/2] and omega = atan2(y, x) the longitude in
(-pi, pi]. Level n has 10 * 4**n + 2 vertices and 20 * 4**n faces (642 and 1280 at n = 3).
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from sq_mitsuba.checks import check_int

__all__ = ["icosphere", "icosphere_angles", "icosphere_faces"]

MAX_LEVEL = 7


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    golden = (1.0 + 5.0 ** 0.5) / 2.0
    vertices = []
    for s1 in (-1.0, 1.0):
        for s2 in (-golden, golden):
            vertices += [(s1, s2, 0.0), (0.0, s1, s2), (s2, 0.0, s1)]
    vertices = np.asarray(vertices)
    # Faces are the vertex triples at mutual distance 2 (the edge length); orient outward.
    distance = np.linalg.norm(vertices[:, None] - vertices[None], axis=-1)
    adjacent = np.isclose(distance, 2.0)
    faces = [
        (i, j, k)
        for i in range(12) for j in range(i + 1, 12) for k in range(j + 1, 12)
        if adjacent[i, j] and adjacent[j, k] and adjacent[i, k]
    ]
    faces = np.asarray(faces)
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inward = (normal * tri.mean(axis=1)).sum(-1) < 0
    faces[inward] = faces[inward][:, ::-1]
    return vertices / np.linalg.norm(vertices, axis=-1, keepdims=True), faces


def _subdivide(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split each triangle into four at its edge midpoints, projected to the sphere."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    unique_edges, edge_index = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True)
    midpoints = vertices[unique_edges].mean(axis=1)
    midpoints /= np.linalg.norm(midpoints, axis=-1, keepdims=True)
    mid = edge_index.reshape(3, -1).T + len(vertices)  # (F, 3): mid of edges 01, 12, 20
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new_faces = np.concatenate([
        np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1),
        np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1),
    ])
    return np.concatenate([vertices, midpoints]), new_faces


def _checked_level(level: object) -> int:
    """``level`` as an int in [0, MAX_LEVEL] (a numpy integer as Python's), else one line.

    Checked before any cache is read: ``True == 1`` and ``hash(True) == hash(1)``, so a bool
    would find level 1's entry and pass for it."""
    return check_int("level", level, 0, MAX_LEVEL)


def icosphere(level: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere subdivided ``level`` times.

    Returns:
        vertices (V, 3) float64 and faces (F, 3) int64, read-only arrays.
    """
    return _icosphere(_checked_level(level))


@functools.cache
def _icosphere(level: int) -> tuple[np.ndarray, np.ndarray]:
    vertices, faces = _icosahedron()
    for _ in range(level):
        vertices, faces = _subdivide(vertices, faces)
    faces = faces.astype(np.int64)
    vertices.flags.writeable = False
    faces.flags.writeable = False
    return vertices, faces


@functools.cache
def _angles_numpy(level: int) -> tuple[np.ndarray, np.ndarray]:
    vertices, _ = _icosphere(level)
    eta = np.arcsin(np.clip(vertices[:, 2], -1.0, 1.0))
    omega = np.arctan2(vertices[:, 1], vertices[:, 0])
    return eta, omega


@functools.cache
def _angles_tensors(level: int, dtype: torch.dtype, device: str | torch.device
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    eta, omega = _angles_numpy(level)
    return (torch.tensor(eta, dtype=dtype, device=device),
            torch.tensor(omega, dtype=dtype, device=device))


def icosphere_angles(
    level: int = 3, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"
) -> tuple[torch.Tensor, torch.Tensor]:
    """(eta, omega) of the icosphere's vertices as tensors (V,): copies of tensors cached per
    level, dtype and device (on a GPU a copy there, not a transfer; the cached tensors
    themselves were returned before, and one in-place edit changed every later call's)."""
    eta, omega = _angles_tensors(_checked_level(level), dtype, device)
    return eta.clone(), omega.clone()


def icosphere_faces(level: int = 3, device: str | torch.device = "cpu") -> torch.Tensor:
    """Faces (F, 3) int64 of the icosphere as a tensor: a copy of one cached per level and
    device, as :func:`icosphere_angles` (the cached tensor itself was returned before, and a
    caller's in-place edit of ``Assembly.meshes()``'s faces turned every later mesh)."""
    return _faces_tensor(_checked_level(level), device).clone()


@functools.cache
def _faces_tensor(level: int, device: str | torch.device) -> torch.Tensor:
    return torch.tensor(_icosphere(level)[1], device=device)
