"""Shared test configuration.

Tests run on 2 CPU threads (the reference machine). Fixtures that build Mitsuba scenes are
session-scoped: the first kernels compile for seconds, later renders reuse them.
"""

from __future__ import annotations

import torch

torch.set_num_threads(2)


# --- silhouette renderer fixtures (issue 3) -------------------------------------------------

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def off_centre_camera():
    """128 x 128 camera with an off-centre principal point (tests the sensor's offsets)."""
    from sq_mitsuba.geometry.camera import Camera

    return Camera(150.0, 150.0, 70.0, 57.0, 128, 128)


@pytest.fixture(scope="session")
def precise_renderer(off_centre_camera):
    """High-sample renderer (spp 256, sppp 16) at 128 x 128 for pixel and gradient checks."""
    from sq_mitsuba.render.silhouette import SilhouetteRenderer

    return SilhouetteRenderer(off_centre_camera, spp=256, sppp=16, seed=11)


@pytest.fixture(scope="session")
def renderer64():
    """Default renderer at 64 x 64 with the default camera."""
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.render.silhouette import SilhouetteRenderer

    return SilhouetteRenderer(Camera.default(64))


@pytest.fixture(scope="session")
def unit_sphere():
    """Level-4 icosphere (2,562 vertices): vertices (V, 3) float64, faces (F, 3) int64."""
    from sq_mitsuba.geometry.icosphere import icosphere

    vertices, faces = icosphere(4)
    return torch.tensor(vertices, dtype=torch.float64), torch.tensor(faces, dtype=torch.int64)
