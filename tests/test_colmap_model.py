"""The pass's COLMAP model: it reads back as written, and its poses, read with COLMAP's own
conventions (a Hamilton quaternion world -> camera, x right, y down, z forward, pixel centres
at half-integers), project an assembly onto the pixels Mitsuba draws it on at those poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from output_checks import one_torch_thread  # noqa: F401 (autouse fixture)

from sq_mitsuba.apps.colmap_model import COLMAP_FILES, read_colmap_model, write_colmap_model
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import matrix_to_quaternion, random_rotations
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly


def _hamilton_matrix(q: np.ndarray) -> np.ndarray:
    """COLMAP's rotation of a unit quaternion (w, x, y, z), written out by hand."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _poses(count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    rotations = random_rotations(count, generator, torch.float64)
    translations = torch.tensor([[0.05, -0.03, 1.6]], dtype=torch.float64) + 0.05 * torch.randn(
        count, 3, generator=generator, dtype=torch.float64)
    return rotations, translations


def test_a_colmap_model_reads_back_as_written(tmp_path):
    camera = Camera(401.5, 398.25, 130.5, 120.0, 256, 240)
    rotations, translations = _poses(4, seed=0)
    quaternions = matrix_to_quaternion(rotations)
    names = ["f0.png", "f1.png", "f2.png", "f3.png"]
    files = write_colmap_model(tmp_path / "colmap", camera, names, quaternions, translations)
    assert [f.name for f in files] == list(COLMAP_FILES) and all(f.is_file() for f in files)
    read_camera, images = read_colmap_model(tmp_path / "colmap")
    assert read_camera == camera
    assert [name for name, _, _ in images] == names
    for (_, q, t), quaternion, translation in zip(images, quaternions, translations, strict=True):
        np.testing.assert_allclose(q, quaternion.numpy(), atol=1e-15)
        np.testing.assert_allclose(t, translation.numpy(), atol=1e-15)
    # Two lines an image (the second empty: no keypoints), and no 3D points.
    lines = [line for line in (tmp_path / "colmap" / "images.txt").read_text().splitlines()
             if not line.startswith("#")]
    assert len(lines) == 8 and lines[1::2] == [""] * 4 and lines[0].split()[0] == "1"
    points = (tmp_path / "colmap" / "points3D.txt").read_text().splitlines()
    assert all(line.startswith("#") for line in points)


def test_colmap_poses_project_the_assembly_where_mitsuba_draws_it(tmp_path):
    """Every surface point of an assembly, projected through the model's quaternion (by
    COLMAP's formula, not the project's) and its PINHOLE intrinsics, lands on the silhouette
    Mitsuba renders at the same pose, and the two cover the same box to a pixel."""
    camera = Camera.default(96)
    assembly = Assembly.from_values(
        size=torch.tensor([[[0.22, 0.12, 0.10], [0.32, 0.08, 0.02]]], dtype=torch.float64),
        shape=torch.tensor([[[0.2, 0.2], [0.1, 0.1]]], dtype=torch.float64),
        translation=torch.tensor([[[0.0, 0.0, 0.0], [0.25, 0.08, 0.0]]], dtype=torch.float64))
    rotations, translations = _poses(3, seed=1)
    write_colmap_model(tmp_path, camera, ["a.png", "b.png", "c.png"],
                       matrix_to_quaternion(rotations), translations)
    read_camera, images = read_colmap_model(tmp_path)
    with torch.no_grad():
        drawn = render_assembly(Assembly(assembly.params.expand(3, -1, -1)), rotations,
                                translations, SilhouetteRenderer(camera, spp=16), 3) > 0.5
    points = assembly.surface_points(3).double().reshape(-1, 3).numpy()
    for k, (_, q, t) in enumerate(images):
        seen = points @ _hamilton_matrix(q).T + t
        u = read_camera.fx * seen[:, 0] / seen[:, 2] + read_camera.cx
        v = read_camera.fy * seen[:, 1] / seen[:, 2] + read_camera.cy
        mask = drawn[k].numpy()
        grown = mask.copy()  # a point on the outline may fall in the pixel beside it
        grown[1:] |= mask[:-1]
        grown[:-1] |= mask[1:]
        grown[:, 1:] |= mask[:, :-1]
        grown[:, :-1] |= mask[:, 1:]
        column, row = np.floor(u).astype(int), np.floor(v).astype(int)
        assert float(grown[row, column].mean()) > 0.99, k
        rows, columns = np.nonzero(mask)
        assert abs(u.min() - columns.min()) < 1.5 and abs(u.max() - (columns.max() + 1)) < 1.5
        assert abs(v.min() - rows.min()) < 1.5 and abs(v.max() - (rows.max() + 1)) < 1.5
    # The check tells the layouts apart: the quaternion read as (x, y, z, w) misses.
    q = images[0][1]
    wrong = points @ _hamilton_matrix(np.roll(q, -1)).T + images[0][2]
    column = np.floor(read_camera.fx * wrong[:, 0] / wrong[:, 2] + read_camera.cx).astype(int)
    row = np.floor(read_camera.fy * wrong[:, 1] / wrong[:, 2] + read_camera.cy).astype(int)
    inside = (column >= 0) & (column < 96) & (row >= 0) & (row < 96)
    hits = drawn[0].numpy()[row[inside], column[inside]]
    assert float(hits.sum()) / len(points) < 0.9


@pytest.mark.parametrize("change, message", [
    ({"names": ["a.png", "a.png"]}, "given once"),
    ({"names": ["a frame.png", "b.png"]}, "without white space"),
    ({"quaternions": [[1.0, 0, 0, 0]]}, "expected (2, 4) and (2, 3)"),
    ({"quaternions": [[2.0, 0, 0, 0], [1.0, 0, 0, 0]]}, "quaternion 0 has length 2"),
    ({"translations": [[0, 0, math.nan], [0, 0, 1.0]]}, "every value must be finite"),
])
def test_bad_model_input_is_one_line_and_writes_nothing(tmp_path, change, message):
    arguments = {"names": ["a.png", "b.png"], "quaternions": [[1.0, 0, 0, 0]] * 2,
                 "translations": [[0, 0, 1.0]] * 2, **change}
    with pytest.raises(ValueError) as error:
        write_colmap_model(tmp_path / "colmap", Camera.default(64), **arguments)
    assert message in str(error.value) and "\n" not in str(error.value)
    assert not (tmp_path / "colmap").exists()


def test_reading_a_model_that_is_not_one_says_which_file(tmp_path):
    with pytest.raises(ValueError, match=r"cameras\.txt: no such file"):
        read_colmap_model(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 SIMPLE_RADIAL 64 64 50 32 32 0.1\n")
    (tmp_path / "images.txt").write_text("")
    with pytest.raises(ValueError, match="expected one PINHOLE camera"):
        read_colmap_model(tmp_path)
