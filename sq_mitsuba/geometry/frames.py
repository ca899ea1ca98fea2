"""Orthonormal frames built from a direction (numpy), shared by scene sampling and rendering."""

from __future__ import annotations

import numpy as np


def unit_vector(v: np.ndarray) -> np.ndarray:
    """``v`` (..., 3) divided by its length."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def orthonormal_basis(direction: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) with columns (e1, e2, d): d = unit ``direction``, right-handed."""
    axis = unit_vector(np.asarray(direction, dtype=np.float64))
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = unit_vector(np.cross(axis, helper))
    return np.stack([e1, np.cross(axis, e1), axis], axis=1)
