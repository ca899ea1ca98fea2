"""Camera intrinsics: defaults, SPEED camera.json, rescaling, project / unproject."""

from __future__ import annotations

import json
import math

import pytest
import torch

from sq_mitsuba.geometry.camera import Camera


def test_default_camera_matches_speed_field_of_view():
    camera = Camera.default()
    assert (camera.width, camera.height) == (256, 256)
    assert camera.fx == pytest.approx(400.45, abs=0.01) and camera.fy == camera.fx
    assert (camera.cx, camera.cy) == (128.0, 128.0)
    assert camera.fov_x_deg == pytest.approx(35.45, abs=0.01)


def test_project_known_points():
    camera = Camera(100.0, 120.0, 30.0, 40.0, 64, 48)
    points = torch.tensor([[0.0, 0.0, 2.0], [1.0, -0.5, 2.0]], dtype=torch.float64)
    pixels = camera.project(points)
    assert torch.allclose(pixels, torch.tensor([[30.0, 40.0], [80.0, 10.0]],
                                               dtype=torch.float64))


def test_unproject_then_project_returns_pixel_grid():
    camera = Camera(90.0, 110.0, 33.5, 28.0, 64, 48)
    grid = camera.pixel_centers(dtype=torch.float64)
    assert grid.shape == (48, 64, 2)
    assert torch.equal(grid[0, 0], torch.tensor([0.5, 0.5], dtype=torch.float64))
    depth = torch.linspace(0.5, 4.0, 64, dtype=torch.float64).expand(48, 64)
    points = camera.unproject(grid, depth)
    assert torch.allclose(points[..., 2], depth)
    assert torch.allclose(camera.project(points), grid, atol=1e-10)
    assert torch.allclose(camera.project(camera.unproject(grid, 2.0)), grid, atol=1e-10)


def test_rescaled_scales_pixel_coordinates():
    camera = Camera(400.0, 380.0, 130.0, 120.0, 256, 240)
    small = camera.rescaled(64)
    assert (small.width, small.height) == (64, 60)
    points = torch.tensor([[0.3, -0.2, 2.0], [-0.4, 0.1, 1.5]], dtype=torch.float64)
    scale = torch.tensor([64 / 256, 60 / 240], dtype=torch.float64)
    assert torch.allclose(small.project(points), camera.project(points) * scale)
    # Pixel edges scale: the image centre stays the centre.
    assert Camera.default(256).rescaled(64) == Camera.default(64)


def test_speed_camera_json_round_trip(tmp_path):
    speed = {"Nu": 1920, "Nv": 1200, "ppx": 5.86e-6, "ppy": 5.86e-6, "fx": 0.0176,
             "fy": 0.0176, "ccx": 960, "ccy": 600,
             "cameraMatrix": [[3003.41296928, 0, 960], [0, 3003.41296928, 600], [0, 0, 1]],
             "distCoeffs": [0, 0, 0, 0, 0]}
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(speed))
    camera = Camera.load(path)
    assert camera.fx == pytest.approx(3003.413, abs=1e-3) and camera.cx == 960
    # Without a matrix, focal lengths in metres over the pixel pitch.
    no_matrix = {k: v for k, v in speed.items() if k != "cameraMatrix"}
    assert Camera.from_speed_dict(no_matrix).fx == pytest.approx(camera.fx, rel=1e-6)
    assert Camera.from_speed_dict(camera.to_speed_dict()) == camera
    rescaled = camera.rescaled(256)
    assert rescaled.fx == pytest.approx(400.455, abs=1e-3) and rescaled.height == 160


def test_from_fov():
    camera = Camera.from_fov(90.0, 64, 32)
    assert camera.fx == pytest.approx(32.0) and (camera.cx, camera.cy) == (32.0, 16.0)
    assert camera.fov_x_deg == pytest.approx(90.0)
    assert math.isclose(Camera.default(128).fov_x_deg, Camera.default(256).fov_x_deg)


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"fx": 0.0}, "fx"), ({"fy": -1.0}, "fx, fy"), ({"cx": float("nan")}, "cx"),
    ({"width": 0}, "width"), ({"height": 2.5}, "height"), ({"fx": "1"}, "fx"),
])
def test_bad_intrinsics(kwargs, name):
    values = {"fx": 100.0, "fy": 100.0, "cx": 32.0, "cy": 32.0, "width": 64, "height": 64}
    values.update(kwargs)
    with pytest.raises(ValueError, match=name):
        Camera(**values)


def test_bad_arguments(tmp_path):
    camera = Camera.default(64)
    with pytest.raises(ValueError, match="points"):
        camera.project(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="pixels"):
        camera.unproject(torch.zeros(4, 3), 1.0)
    with pytest.raises(ValueError, match="depth"):
        camera.unproject(torch.zeros(4, 2), float("inf"))
    # A depth of more items than pixels made (3, 2, 3) points of (2, 2) pixels.
    with pytest.raises(ValueError, match=r"^depth: shape \(3, 2\) does not broadcast"):
        camera.unproject(torch.zeros(2, 2), torch.ones(3, 2))
    with pytest.raises(ValueError, match=r"^depth: shape \(3,\)"):
        camera.unproject(torch.zeros(2, 2), torch.ones(3))
    with pytest.raises(ValueError, match=r"^depth: expected a number or a tensor, got '5'"):
        camera.unproject(torch.zeros(2, 2), "5")
    with pytest.raises(ValueError, match="width"):
        camera.rescaled(0)
    with pytest.raises(ValueError, match="fov_x_deg"):
        Camera.from_fov(180.0, 64, 64)
    with pytest.raises(ValueError, match="camera"):
        Camera.from_speed_dict({"Nu": 64})
    bad = tmp_path / "camera.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="camera"):
        Camera.load(bad)


def test_the_metre_fields_are_checked_beside_the_matrix_and_the_pitch_named():
    """A NaN or a string in a field the matrix makes unused is still a broken file; a pitch
    that is not positive is named as the pitch, not as the focal length."""
    speed = Camera.default(64).to_speed_dict()
    for key, value in (("fx", float("nan")), ("ppx", "abc"), ("ccx", None)):
        with pytest.raises(ValueError, match=rf"^camera\.json: {key} must be"):
            Camera.from_speed_dict({**speed, key: value}, "camera.json")
    metric = {key: value for key, value in speed.items() if key != "cameraMatrix"}
    with pytest.raises(ValueError, match=r"^camera\.json: ppx \(the pixel pitch, metres\) "
                                         r"must be > 0, got -1"):
        Camera.from_speed_dict({**metric, "ppx": -1}, "camera.json")
    assert Camera.from_speed_dict(metric).fx == pytest.approx(Camera.default(64).fx, rel=1e-6)


def test_a_camera_file_of_a_field_of_view_no_camera_has_is_refused():
    """A focal length of 1e9 px (0.00001 deg across 256 px) is refused in a file as in code."""
    speed = {key: value for key, value in Camera.default(256).to_speed_dict().items()
             if key not in ("fx", "fy")}
    matrix = [[1e9, 0.0, 128.0], [0.0, 1e9, 128.0], [0.0, 0.0, 1.0]]
    with pytest.raises(ValueError, match=r"^camera\.json: cameraMatrix gives a 1\.47e-05 deg "
                                         r"field of view across x .* less than the 0\.001 deg"):
        Camera.from_speed_dict({**speed, "cameraMatrix": matrix}, "camera.json")
