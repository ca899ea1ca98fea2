"""Dataset rendering in the SPE3R layout: labels vs masks, determinism, resume, reader, light."""

from __future__ import annotations

import dataclasses
import errno
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from sq_mitsuba.cli import main
from sq_mitsuba.data import Spe3rDataset, spe3r
from sq_mitsuba.data.frames import sample_frame
from sq_mitsuba.data.library import generate_model
from sq_mitsuba.data.spacecraft import catalogue
from sq_mitsuba.data.spe3r import (
    DatasetError,
    RenderOptions,
    check_dataset,
    load_model,
    render_dataset,
)
from sq_mitsuba.data.spe3r import writer as spe3r_writer
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import quaternion_to_matrix, rotation_angle
from sq_mitsuba.io import atomic_path
from sq_mitsuba.render.scene_config import SceneConfig
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer
from sq_mitsuba.render.space import SpaceScene

RESOLUTION, SPP, IMAGES = 128, 4, 3
OPTIONS = {"images_per_model": IMAGES, "seed": 7, "resolution": RESOLUTION, "spp": SPP}
OUTPUTS = ("*/labels.json", "*/masks/*.png", "*/images/*.png")


@pytest.fixture(scope="session")
def model_library(tmp_path_factory) -> Path:
    """Two generated spacecraft (small point sets) with a train/test split."""
    root = tmp_path_factory.mktemp("models")
    entries = catalogue(2, 3)
    for entry in entries:
        generate_model(entry, root, points=3000)
    (root / "splits.csv").write_text(f"{entries[0].name},train\n{entries[1].name},test\n")
    return root


@pytest.fixture(scope="session")
def dataset(model_library, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dataset") / "data"
    summary = render_dataset(model_library, out, RenderOptions(**OPTIONS), progress=False)
    assert not summary.failures and summary.rendered == 2 * IMAGES
    return out


def read_bytes_tree(root: Path, patterns: tuple[str, ...]) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes()
            for pattern in patterns for p in sorted(root.glob(pattern))}


# ------------------------------------------------------------------------ layout and labels


def test_layout_and_labels(dataset, model_library):
    assert (dataset / "camera.json").is_file()
    camera = Camera.load(dataset / "camera.json")
    assert (camera.width, camera.height) == (RESOLUTION, RESOLUTION)
    assert (dataset / "splits.csv").read_text() == (model_library / "splits.csv").read_text()
    for model in spe3r.dataset_models(dataset):
        labels = json.loads((dataset / model / "labels.json").read_text())
        assert len(labels) == IMAGES
        for label in labels:
            assert set(label) >= {"filename", "q_vbs2tango_true", "r_Vo2To_vbs_true",
                                  "sun_direction_cam", "phase_angle_deg", "earth_in_view",
                                  "eclipse", "exposure", "seed"}
            image = np.asarray(Image.open(dataset / model / "images" / label["filename"]))
            mask = np.asarray(Image.open(dataset / model / "masks" / label["filename"]))
            assert image.dtype == np.uint8 and image.shape == (RESOLUTION, RESOLUTION)
            assert set(np.unique(mask)) <= {0, 255} and mask.any()
            assert abs(np.linalg.norm(label["q_vbs2tango_true"]) - 1) < 1e-9
        assert (dataset / model / "models" / "model_normalized.obj").is_file()
        assert not (dataset / model / ".progress").exists()


def test_labels_agree_with_masks(dataset):
    """The mesh rendered at each label pose (another renderer) reproduces the mask."""
    report = check_dataset(dataset, per_model=None, min_iou=0.99, progress=False)
    assert report.ok, report.summary()
    assert len(report.iou) == 2 * IMAGES and min(report.iou) >= 0.99


def test_projected_origin_is_where_the_label_translation_says(dataset):
    """A small sphere at the body origin, posed by the label, lands on K t within 1 px."""
    camera = Camera.load(dataset / "camera.json")
    sphere_vertices, sphere_faces = (np.asarray(a) for a in _sphere(0.03))
    renderer = SilhouetteRenderer(camera, spp=64)
    for model in spe3r.dataset_models(dataset):
        for label in json.loads((dataset / model / "labels.json").read_text()):
            rotation = quaternion_to_matrix(torch.tensor(label["q_vbs2tango_true"]))
            translation = torch.tensor(label["r_Vo2To_vbs_true"])
            posed = torch.tensor(sphere_vertices, dtype=torch.float32) @ rotation.T + translation
            coverage = renderer.render(posed[None], torch.tensor(sphere_faces))[0]
            rows, cols = torch.meshgrid(torch.arange(RESOLUTION) + 0.5,
                                        torch.arange(RESOLUTION) + 0.5, indexing="ij")
            centroid = torch.stack([(coverage * cols).sum(), (coverage * rows).sum()]) / \
                coverage.sum()
            expected = camera.project(translation[None])[0]
            assert (centroid - expected).norm() < 1.0


def _sphere(radius: float):
    from sq_mitsuba.geometry.icosphere import icosphere

    vertices, faces = icosphere(3)
    return vertices * radius, faces


def test_frame_rotations_are_uniform_and_targets_in_view():
    config = SceneConfig.load()
    camera = Camera.default(256)
    box = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.2, 0.2) for z in (-0.15, 0.15)])
    frames = [sample_frame(box, camera, config, 1, "box", i) for i in range(3000)]
    rotations = torch.tensor(np.stack([f.rotation for f in frames]))
    assert rotations.mean(0).abs().max() < 0.05  # Haar: E[R] = 0; std of the mean ~0.011
    angles = rotation_angle(torch.eye(3, dtype=torch.float64), rotations)
    observed = torch.histc(angles, bins=6, min=0, max=math.pi) / len(frames)
    edges = torch.linspace(0, math.pi, 7, dtype=torch.float64)
    cdf = (edges - torch.sin(edges)) / math.pi
    assert (observed - (cdf[1:] - cdf[:-1])).abs().max() < 0.03
    for frame in frames[:300]:
        posed = box @ frame.rotation.T + np.asarray(frame.translation)
        pixels = camera.project(torch.tensor(posed)).numpy()
        assert (pixels >= 0).all() and (pixels <= 256).all()
        assert 1.4 < frame.translation[2] < 3.0
    eclipses = np.mean([f.eclipse for f in frames])
    earth = np.mean([f.earth_in_view for f in frames])
    assert abs(eclipses - config.eclipse.probability) < 0.02
    assert abs(earth - config.earth.probability_in_view) < 0.04
    # Same seed, same frame; another index, another frame.
    assert sample_frame(box, camera, config, 1, "box", 5) == frames[5]
    assert sample_frame(box, camera, config, 1, "box", 6) != frames[5]


# ------------------------------------------------------------------------ determinism


def test_same_seed_gives_identical_labels_and_masks(dataset, model_library, tmp_path):
    again = tmp_path / "again"
    render_dataset(model_library, again, RenderOptions(**OPTIONS), progress=False)
    assert read_bytes_tree(again, OUTPUTS) == read_bytes_tree(dataset, OUTPUTS)


@pytest.mark.slow
def test_kill_and_resume_gives_identical_output(dataset, model_library, tmp_path):
    out = tmp_path / "resumed"
    command = [sys.executable, "-m", "sq_mitsuba", "dataset", "render", "--models",
               str(model_library), "--out", str(out), "--quiet",
               "--images-per-model", str(IMAGES), "--seed", str(OPTIONS["seed"]),
               "--resolution", str(RESOLUTION), "--spp", str(SPP)]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and process.poll() is None:
        if len(list(out.glob("*/.progress/*.json"))) >= 2:
            break
        time.sleep(0.02)
    assert process.poll() is None, "render finished before it could be killed"
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert not (out / spe3r.dataset_models(model_library)[-1] / "labels.json").exists()
    # The same command resumes in this process: a second interpreter would only import torch
    # and Mitsuba again (the renders are seeded per image, whatever the process).
    assert main(command[3:]) == 0
    assert read_bytes_tree(out, OUTPUTS) == read_bytes_tree(dataset, OUTPUTS)
    assert not list(out.rglob("*.tmp*"))


# ------------------------------------------------------------------------ reader


def test_reader_reads_what_the_writer_wrote(dataset):
    train, val, test = (Spe3rDataset(dataset, split, image_size=64, num_surface=500,
                                     num_occupancy=1000) for split in ("train", "val", "test"))
    assert (len(train), len(val), len(test)) == (IMAGES, 0, IMAGES)
    item = train[1]
    model = train.models[0]
    label = json.loads((dataset / model / "labels.json").read_text())[1]
    assert item["model"] == model and item["index"] == 1
    assert item["image"].shape == (1, 64, 64) and item["mask"].shape == (1, 64, 64)
    torch.testing.assert_close(item["quaternion"],
                               torch.tensor(label["q_vbs2tango_true"], dtype=torch.float32))
    torch.testing.assert_close(item["translation"],
                               torch.tensor(label["r_Vo2To_vbs_true"], dtype=torch.float32))
    full = np.asarray(Image.open(dataset / model / "masks" / label["filename"])) >= 128
    assert abs(item["mask"].mean().item() - full.mean()) < 0.01
    torch.testing.assert_close(item["camera"], Camera.load(dataset / "camera.json")
                               .rescaled(64).matrix())
    assert item["surface_points"].shape == (500, 3)
    assert item["occupancy_points"].shape == (1000, 3)
    assert item["occupancy_labels"].mean().item() == pytest.approx(0.5)
    assert item["surface_points"].abs().max() <= 0.51


def test_a_mask_read_at_half_size_is_its_area_share_not_a_corner(dataset):
    """A mask downsized by two: each output pixel is on where at least half of its 2 x 2 block
    is (the brute-force area share), centred with the image and its rescaled camera; a
    nearest-neighbour resize took one corner of each block, a quarter pixel off."""
    full_size = Camera.load(dataset / "camera.json").width
    half = full_size // 2
    train = Spe3rDataset(dataset, "train", image_size=half, num_surface=10, num_occupancy=10)
    for item in range(len(train)):
        model, _, label = train.items[item]
        full = np.asarray(Image.open(dataset / train.models[model] / "masks"
                                     / label["filename"])) >= 128
        share = full.reshape(half, 2, half, 2).mean(axis=(1, 3))
        decided = np.abs(share - 0.5) > 0.1  # ties at exactly half may round either way
        got = train[item]["mask"][0].numpy() > 0.5
        assert np.array_equal(got[decided], share[decided] >= 0.5), item
        # The image with it, the same way up: near its own 2 x 2 block means (bilinear
        # reduction weighs a block's neighbours a little), far from them mirrored.
        picture = np.asarray(Image.open(dataset / train.models[model] / "images"
                                        / label["filename"])).astype(np.float64) / 255
        means = picture.reshape(half, 2, half, 2).mean(axis=(1, 3))
        image = train[item]["image"][0].numpy()
        assert np.abs(image - means).mean() < 0.5 * np.abs(image - means[:, ::-1]).mean()
        assert np.abs(image - means).mean() < 0.5 * np.abs(image - means[::-1]).mean()


def test_reader_reads_an_spe3r_shaped_fixture_with_jpg_images(tmp_path):
    """SPE3R release shape: .jpg images, SPEED camera.json in metres, no samples.npz."""
    import trimesh

    root = tmp_path / "spe3r"
    speed_camera = {"Nu": 1920, "Nv": 1200, "ppx": 5.86e-6, "ppy": 5.86e-6, "fx": 0.0176,
                    "fy": 0.0176, "ccx": 960, "ccy": 600}
    root.mkdir()
    (root / "camera.json").write_text(json.dumps(speed_camera))
    (root / "splits.csv").write_text("sat_a,train\nsat_b,test\n")
    for model in ("sat_a", "sat_b"):
        (root / model / "models").mkdir(parents=True)
        (root / model / "images").mkdir()
        (root / model / "masks").mkdir()
        trimesh.creation.box((1.0, 0.5, 0.3)).export(root / model / "models" /
                                                    "model_normalized.obj")
        labels = [{"filename": f"img{i:06d}.jpg", "q_vbs2tango_true": [1.0, 0.0, 0.0, 0.0],
                   "r_Vo2To_vbs_true": [0.0, 0.0, 2.0 + i / 1000]} for i in range(1000)]
        (root / model / "labels.json").write_text(json.dumps(labels))
        for i in (0, 450, 999):
            Image.fromarray(np.full((120, 192), i % 250, np.uint8)).save(
                root / model / "images" / f"img{i:06d}.jpg")
            Image.fromarray(np.full((120, 192), 255, np.uint8)).save(
                root / model / "masks" / f"img{i:06d}.png")
    train = Spe3rDataset(root, "train", image_size=32, num_surface=100, num_occupancy=200)
    val = Spe3rDataset(root, "val", image_size=32, num_surface=100, num_occupancy=200)
    test = Spe3rDataset(root, "test", image_size=32, num_surface=100, num_occupancy=200)
    assert (len(train), len(val), len(test)) == (800, 200, 1000)
    item = val[50]  # image 450 of sat_a
    assert item["index"] == 450 and item["model"] == "sat_a"
    assert item["translation"][2].item() == pytest.approx(2.45)
    assert item["image"].shape == (1, 32, 32)
    assert abs(item["image"].mean().item() - 450 % 250 / 255) < 0.02
    # SPEED intrinsics rescaled to 32 px: fx = 0.0176 / 5.86e-6 * 32 / 1920.
    assert item["camera"][0, 0].item() == pytest.approx(0.0176 / 5.86e-6 / 60, rel=1e-6)
    # Occupancy labels from the mesh itself: inside means inside the 1 x 0.5 x 0.3 box.
    points, labels = item["occupancy_points"], item["occupancy_labels"].bool()
    in_box = (points.abs() < torch.tensor([0.5, 0.25, 0.15])).all(-1)
    assert (in_box == labels).float().mean() > 0.99
    # The preview finds the .png masks of .jpg labels as the reader does.
    from sq_mitsuba.data.spe3r.preview import preview_dataset

    assert preview_dataset(root, tmp_path / "preview.png", count=2).stat().st_size > 0


def test_occupancy_of_a_model_without_samples_covers_its_whole_box(tmp_path):
    """A release mesh has no samples.npz: its occupancy points are drawn in a cube about the
    mesh's box (a cube about the origin left out the far end of a lopsided model)."""
    import trimesh

    from sq_mitsuba.data.spe3r.layout import model_points

    (tmp_path / "sat" / "models").mkdir(parents=True)
    box = trimesh.creation.box((1.6, 0.4, 0.4))
    box.apply_translation((0.5, 0.0, 0.0))  # spans x from -0.3 to 1.3
    box.export(tmp_path / "sat" / "models" / "model_normalized.obj")
    points = model_points(tmp_path / "sat")
    uniform, inside = points["points"][:50_000], points["inside"][:50_000]
    assert uniform[:, 0].min() < -0.25 and uniform[:, 0].max() > 1.25
    far = inside & (uniform[:, 0] > 0.9)  # the box's far end, outside [-0.5, 0.5]^3
    assert far.sum() > 0.2 * inside.sum()


def test_reader_errors_name_the_file(dataset, tmp_path):
    with pytest.raises(DatasetError, match=r"camera\.json"):
        Spe3rDataset(tmp_path)
    broken = tmp_path / "broken"
    shutil.copytree(dataset, broken)
    model = spe3r.dataset_models(broken)[0]
    (broken / model / "labels.json").write_text("[{not json")
    with pytest.raises(DatasetError, match=r"labels\.json"):
        Spe3rDataset(broken, "train")
    with pytest.raises(ValueError, match="split"):
        Spe3rDataset(dataset, "validation")


@pytest.mark.parametrize("index", [99, -1, 2.5])
def test_a_material_index_that_is_none_is_one_line_naming_the_samples(model_library, tmp_path,
                                                                      index):
    """An index past the material list stopped a whole render with an IndexError; a negative
    one silently lit the model as another material."""
    model = spe3r_writer.find_models(model_library)[0]
    copy = tmp_path / model
    shutil.copytree(model_library / model, copy)
    samples_path = copy / "models" / "samples.npz"
    with np.load(samples_path) as archive:
        samples = dict(archive)
    samples["face_material"] = samples["face_material"].astype(type(index))
    samples["face_material"][3] = index
    np.savez(samples_path, **samples)
    with pytest.raises(DatasetError, match=r"samples\.npz: face_material holds .* outside"):
        load_model(copy)


@pytest.mark.parametrize(("text", "message"), [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\nv 0 0 1\n", ":4: face index 0"),
    ("v 0 0 0\nv 1 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n", ":2: a vertex needs 3 coordinates"),
    ("v 0 0 x\n", ":1: 'x' is not a number"),
    ("v 0 0 0\nf -3 -2 -1\n", ":2: a relative face index reaches before"),
])
def test_an_obj_that_misnumbers_its_vertices_is_refused_naming_the_line(tmp_path, text,
                                                                      message):
    """Read on, each would put faces on other vertices than the file meant (index 0 on the
    next vertex defined, a short vertex line shifting every later index)."""
    from sq_mitsuba.data.mesh_io import read_obj

    path = tmp_path / "mesh.obj"
    path.write_text(text)
    with pytest.raises(ValueError, match=f"mesh.obj{message}"):
        read_obj(path)
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n")  # relative indices: fine
    assert read_obj(path)[1].tolist() == [[0, 1, 2]]


# ------------------------------------------------------------------------ light


@pytest.fixture(scope="session")
def lit_scene(model_library):
    model = spe3r_writer.find_models(model_library)[0]
    vertices, faces, tags = load_model(model_library / model)
    camera = Camera.default(RESOLUTION)
    config = SceneConfig.load()
    scene = SpaceScene(vertices, faces, tags, camera, config, spp=16, dataset_seed=7)
    frame = sample_frame(vertices, camera, config, 7, model, 0)
    return scene, frame


def _with_light(frame, sun: np.ndarray, earth: np.ndarray):
    """The same pose with the sun along ``sun`` and the Earth's centre along ``earth``."""
    return dataclasses.replace(
        frame, sun_direction=tuple(float(v) for v in sun / np.linalg.norm(sun)),
        earth_direction=tuple(float(v) for v in earth / np.linalg.norm(earth)),
        earth_in_view=False)


def test_phase_angle_changes_the_image_and_eclipse_darkens_it(lit_scene):
    scene, frame = lit_scene
    to_camera = -np.asarray(frame.translation) / np.linalg.norm(frame.translation)
    side = np.cross(to_camera, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    # The Earth off to the side (not behind the camera, where a full, sunlit Earth would
    # light the target's visible side when the sun is behind it).
    earth = np.cross(to_camera, side)
    front = scene.render(_with_light(frame, to_camera + 0.15 * side, earth))  # phase ~9 deg
    back = scene.render(_with_light(frame, -to_camera + 0.15 * side, earth))  # phase ~171 deg
    # Sun behind the Earth, whose night side faces the target: an eclipse.
    eclipse = scene.render(dataclasses.replace(_with_light(frame, earth, earth), eclipse=True))
    inside = front.mask > 0
    assert np.array_equal(front.mask, back.mask) and np.array_equal(front.mask, eclipse.mask)
    lit, backlit, dark = (r.image_8bit()[inside].astype(float) for r in (front, back, eclipse))
    assert lit.mean() > 3 * backlit.mean() and lit.mean() - backlit.mean() > 10
    assert dark.mean() < 2.0 and lit.mean() > 10 * max(dark.mean(), 0.1)


def test_each_part_renders_in_its_own_material(lit_scene):
    """Two equal plates side by side facing the camera, the sun 40 deg off the line of sight
    (no specular highlight towards the camera): the white-painted one returns the radiance of
    a Lambertian reflector of its reflectance, 0.85 E cos(40 deg) / pi (by hand), and many
    times the solar cell's (rough plastic over a 0.03 diffuse layer); with every part in one
    material the two would be equal."""
    import trimesh

    _, frame = lit_scene
    left, right = (trimesh.creation.box([0.4, 0.4, 0.05]) for _ in range(2))
    left.apply_translation([-0.25, 0.0, 0.0])
    right.apply_translation([0.25, 0.0, 0.0])
    plates = trimesh.util.concatenate([left, right])
    tags = np.array(["white_paint"] * len(left.faces) + ["solar_cell"] * len(right.faces))
    camera = Camera.default(RESOLUTION)
    config = SceneConfig.load()
    scene = SpaceScene(plates.vertices, plates.faces, tags, camera, config, spp=16)
    angle = np.radians(40.0)
    sun = np.array([0.0, np.sin(angle), -np.cos(angle)])  # towards the sun, camera frame
    head_on = dataclasses.replace(
        _with_light(frame, sun, np.array([0.0, 0.0, 1.0])),  # the Earth behind the plates
        quaternion=(1.0, 0.0, 0.0, 0.0), translation=(0.0, 0.0, 2.5), phase_angle_deg=40.0)
    rendered = scene.render(head_on)
    inside = rendered.coverage > 0.99
    half = RESOLUTION // 2
    white = rendered.radiance[:, :half][inside[:, :half]]
    solar = rendered.radiance[:, half:][inside[:, half:]]
    assert len(white) > 50 and len(solar) > 50
    lambertian = 0.85 * config.sun.irradiance * np.cos(angle) / np.pi
    assert float(np.median(white)) == pytest.approx(lambertian, rel=0.05)
    assert white.mean() > 10 * solar.mean() > 0


# ------------------------------------------------------------------------ bad input


@pytest.mark.parametrize("with_depth", [False, True])
def test_mask_pass_renders_what_the_path_integrator_renders(model_library, with_depth):
    """The lean ``target_coverage`` integrator against Mitsuba's ``path`` with max_depth 1 (in
    ``aov`` with depth too): the coverage bit for bit, on a frame with the target whole and
    one cut by the frame's edge."""
    model = spe3r_writer.find_models(model_library)[0]
    vertices, faces, tags = load_model(model_library / model)
    camera = Camera.default(48)
    config = SceneConfig.load()
    scene = SpaceScene(vertices, faces, tags, camera, config, spp=1, with_depth=with_depth)
    mi = scene.mi
    path = {"type": "path", "max_depth": 1}
    reference = mi.load_dict({"type": "aov", "aovs": "depth:depth", "integrator": path}
                             if with_depth else path)
    frame = sample_frame(vertices, camera, config, 3, model, 0)
    cut = dataclasses.replace(frame, translation=(0.35 * frame.translation[2],
                                                  *frame.translation[1:]))
    for pose in (frame, cut):
        lean, general = scene.mask_pass(pose), scene.mask_pass(pose, reference)
        coverage = 1.0 - lean[..., 0]
        assert 0 < coverage.mean() < 1
        assert coverage[:, -1].max() > 0.5 or pose is frame  # cut by the right edge
        assert np.array_equal(lean[..., 0], general[..., 0])
        # Depth: the same up to float32 rounding (one unit in the last place seen in a few
        # pixels, where the two kernels round one product differently).
        np.testing.assert_allclose(lean[..., 1:], general[..., 1:], rtol=1e-6, atol=0)


def test_a_failed_model_fails_alone_and_leaves_nothing_partial(model_library, tmp_path,
                                                               monkeypatch):
    """A model that fails mid-render (a full disk) is a failure of that model alone; it keeps
    only complete images. (A model that cannot be read is refused before any work:
    test_dataset_bookkeeping.py::test_a_broken_library_model_is_refused_before_any_work.)"""
    library = tmp_path / "library"
    shutil.copytree(model_library, library)
    good, other = spe3r_writer.find_models(library)
    real_write_png = spe3r_writer.write_png

    def disk_full_for_other(path: Path, array: np.ndarray) -> None:
        if other in str(path) and path.name == "000001.png":
            with atomic_path(path) as tmp:
                tmp.write_bytes(b"partial")
                raise OSError(errno.ENOSPC, "No space left on device")
        real_write_png(path, array)

    monkeypatch.setattr(spe3r_writer, "write_png", disk_full_for_other)
    out = tmp_path / "out"
    summary = render_dataset(library, out, RenderOptions(**OPTIONS), progress=False)
    assert summary.models_done == [good]
    assert set(summary.failures) == {other}
    assert "No space left" in summary.failures[other]
    # The failed model keeps only complete images (each with its label); nothing partial.
    assert sorted(p.name for p in (out / other / "images").iterdir()) == ["000000.png"]
    assert sorted(p.name for p in (out / other / ".progress").iterdir()) == ["000000.json"]
    assert not (out / other / "labels.json").exists()
    assert not list(out.rglob("*.tmp*"))


def test_cli_reports_failures_and_unwritable_output(model_library, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    code = main(["dataset", "render", "--models", str(model_library), "--out",
                 str(blocker / "out"), "--images-per-model", "1", "--quiet"])
    assert code == 2 and "not writable" in capsys.readouterr().err
    assert main(["dataset", "render", "--models", str(tmp_path / "nowhere"), "--out",
                 str(tmp_path / "o"), "--quiet"]) == 2
    assert main(["dataset", "render", "--models", str(model_library), "--out",
                 str(tmp_path / "o"), "--spp", "0"]) == 2


def test_check_finds_a_wrong_mask_and_preview_draws(dataset, tmp_path, capsys):
    damaged = tmp_path / "damaged"
    shutil.copytree(dataset, damaged)
    model = spe3r.dataset_models(damaged)[0]
    mask_path = damaged / model / "masks" / "000001.png"
    mask = np.asarray(Image.open(mask_path))
    Image.fromarray(np.roll(mask, 6, axis=1)).save(mask_path)  # a 6 px shift
    assert main(["dataset", "check", str(damaged), "--per-model", "0", "--quiet"]) == 1
    assert f"{model}/000001.png" in capsys.readouterr().out
    assert main(["dataset", "check", str(dataset), "--quiet"]) == 0
    out = tmp_path / "sheet.png"
    assert main(["dataset", "preview", str(dataset), "--out", str(out), "--count", "4"]) == 0
    assert Image.open(out).size[0] > 300
    capsys.readouterr()
    jpeg = tmp_path / "sheet.jpg"  # a preview is PNG: never written under another format's name
    assert main(["dataset", "preview", str(dataset), "--out", str(jpeg)]) == 2
    assert f"out {jpeg}: a preview is written as PNG" in capsys.readouterr().err
    assert not jpeg.exists()


def test_preview_refuses_bad_input_in_one_line_before_drawing(dataset, model_library,
                                                              tmp_path, capsys):
    """A preview whose --out folder cannot take it drew every image, then failed naming the
    temporary file of its atomic write; a folder that does not exist was named as its missing
    camera.json. Each is one line naming what was given, exit 2, nothing written."""
    (tmp_path / "a_file").write_text("a file, not a folder")
    empty = tmp_path / "empty"
    empty.mkdir()
    cases = [([str(dataset), "--out", str(tmp_path / "a_file" / "p.png")],
              f"out {tmp_path / 'a_file' / 'p.png'}: {tmp_path / 'a_file'} is a file, not a "
              "folder"),
             ([str(tmp_path / "nowhere")], f"{tmp_path / 'nowhere'}: no such folder"),
             ([str(empty)], f"{empty}: not a dataset (no camera.json and no dataset.json)"),
             ([str(model_library)], f"{model_library}: a model library, not a dataset")]
    if Path("/proc/self").is_dir():
        cases.append(([str(dataset), "--out", "/proc/p.png"],
                      "out /proc/p.png: cannot write in /proc ("))
    for argv, said in cases:
        capsys.readouterr()
        assert main(["dataset", "preview", *argv, "--count", "2"]) == 2, argv
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and f"error: {said}" in err and ".tmp" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "empty"]
    assert not list(empty.iterdir())


def test_exr_holds_linear_radiance_depth_and_coverage(model_library, tmp_path):
    import OpenEXR

    library = tmp_path / "one"
    library.mkdir()
    model = spe3r_writer.find_models(model_library)[0]
    shutil.copytree(model_library / model, library / model)
    out = tmp_path / "exr"
    options = RenderOptions(**{**OPTIONS, "images_per_model": 1, "exr": True})
    assert not render_dataset(library, out, options, progress=False).failures
    label = json.loads((out / model / "labels.json").read_text())[0]
    with OpenEXR.File(str(out / model / "exr" / "000000.exr")) as exr:
        channels = {name: np.asarray(c.pixels) for name, c in exr.channels().items()}
    assert set(channels) == {"Y", "Z", "A"}
    mask = np.asarray(Image.open(out / model / "masks" / "000000.png")) > 0
    np.testing.assert_array_equal(channels["A"] >= 0.5, mask)
    # Depth of the unit-size target lies within its half-extent of the label distance.
    depth = channels["Z"][mask]
    distance = np.linalg.norm(label["r_Vo2To_vbs_true"])
    assert np.all(np.abs(depth - distance) < 0.9) and np.all(channels["Z"][~mask & (
        channels["A"] == 0)] == 0)
    # The PNG is the EXR radiance tonemapped with the recorded exposure.
    from sq_mitsuba.render.space import tonemap

    image = np.asarray(Image.open(out / model / "images" / "000000.png"))
    np.testing.assert_array_equal(tonemap(channels["Y"].astype(np.float64), label["exposure"]),
                                  image)


def test_the_depth_is_camera_frame_z_not_the_distance_along_the_ray():
    """A plate facing the camera at z = 2 m has depth 2 at every pixel it covers, the corners
    included, where the ray is 9 % longer (the EXR channel 'Z' is this depth)."""
    import dataclasses

    from sq_mitsuba.render.space import SpaceScene, _warm_up_frame

    camera = Camera.default(64)
    plate = np.array([[-3.0, -3.0, 0.0], [3.0, -3.0, 0.0], [3.0, 3.0, 0.0], [-3.0, 3.0, 0.0]])
    scene = SpaceScene(plate, np.array([[0, 1, 2], [0, 2, 3]]), None, camera, SceneConfig(),
                       spp=1, with_depth=True)
    frame = dataclasses.replace(_warm_up_frame(), translation=(0.0, 0.0, 2.0))
    rendered = scene.render(frame, radiance=False)
    assert float(rendered.coverage.min()) > 0.99  # the plate fills the image
    np.testing.assert_allclose(rendered.depth, 2.0, rtol=1e-3)  # (Mitsuba: 1.999 at the centre)
    corner = np.hypot((0.5 - camera.cx) / camera.fx, (0.5 - camera.cy) / camera.fy)
    assert math.sqrt(1 + corner**2) > 1.09  # the ray length there would be 9 % off


@pytest.mark.slow
def test_parallel_workers_write_the_same_dataset(dataset, model_library, tmp_path,
                                                 monkeypatch):
    """Two workers write the single process's files; the progress bar moves by image as
    each worker finishes one (it moved by model: minutes apart at a thousand a model)."""
    import sq_mitsuba.progress

    steps: list[int] = []
    real_bar = sq_mitsuba.progress.progress_bar

    def recording_bar(*args, **kwargs):
        bar = real_bar(*args, **{**kwargs, "disable": False})
        update = bar.update
        bar.update = lambda n=1: (steps.append(n), update(n))[1]
        return bar

    monkeypatch.setattr(sq_mitsuba.progress, "progress_bar", recording_bar)
    out = tmp_path / "parallel"
    summary = render_dataset(model_library, out, RenderOptions(**OPTIONS), progress=True,
                             workers=2)
    assert not summary.failures and summary.rendered == 2 * IMAGES
    assert sum(steps) == 2 * IMAGES and max(steps) == 1, steps
    assert read_bytes_tree(out, OUTPUTS) == read_bytes_tree(dataset, OUTPUTS)
    with pytest.raises(ValueError, match="workers"):
        render_dataset(model_library, out, RenderOptions(**OPTIONS), workers=0)


def test_render_with_a_speed_camera_json(model_library, tmp_path):
    """--camera: SPEED intrinsics (1920 x 1200) rescaled to 96 px wide keep their aspect."""
    speed = {"Nu": 1920, "Nv": 1200, "ppx": 5.86e-6, "ppy": 5.86e-6, "fx": 0.0176,
             "fy": 0.0176, "ccx": 960, "ccy": 600}
    (tmp_path / "speed.json").write_text(json.dumps(speed))
    library = tmp_path / "one"
    model = spe3r_writer.find_models(model_library)[0]
    shutil.copytree(model_library / model, library / model)
    out = tmp_path / "speed"
    assert main(["dataset", "render", "--models", str(library), "--out", str(out),
                 "--camera", str(tmp_path / "speed.json"), "--resolution", "96",
                 "--images-per-model", "1", "--spp", "2", "--quiet"]) == 0
    camera = Camera.load(out / "camera.json")
    assert (camera.width, camera.height) == (96, 60)
    assert camera.fx == pytest.approx(0.0176 / 5.86e-6 / 20)
    mask = np.asarray(Image.open(out / model / "masks" / "000000.png"))
    assert mask.shape == (60, 96) and mask.any()
    # At this size a 1 px misalignment would drop the IoU far below 0.95; the rest is noise.
    assert check_dataset(out, per_model=None, min_iou=0.95, progress=False).ok


def test_scene_configuration_overrides_and_errors(tmp_path, capsys):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps({"_note": "comments are skipped", "sun": {"irradiance": 1000},
                                "earth": {"altitude_km": [500, 600]}}))
    config = SceneConfig.load(path)
    assert config.sun.irradiance == 1000.0 and config.earth.altitude_km == (500.0, 600.0)
    assert config.stars == SceneConfig().stars  # untouched sections keep their defaults
    for bad, message in [({"sun": {"power": 1}}, r"sun\.power: unknown key"),
                         ({"earth": {"altitude_km": [1]}}, r"earth\.altitude_km"),
                         ({"integrator": {"max_depth": "deep"}}, r"integrator\.max_depth"),
                         ({"pose": 3}, r"pose: expected a table")]:
        path.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=message):
            SceneConfig.load(path)
    path.write_text("{broken")
    with pytest.raises(ValueError, match=r"scene\.json: not valid JSON"):
        SceneConfig.load(path)
    assert main(["dataset", "render", "--models", str(tmp_path), "--out", str(tmp_path / "o"),
                 "--scene", str(path)]) == 2
    assert "not valid JSON" in capsys.readouterr().err


def test_passes_are_frames_of_one_tumble_in_order(model_library, dataset, tmp_path):
    """``--pass-frames 3``: each model's images are one pass; its first frame is the frame an
    independent dataset of the same seed draws for image 0, and between consecutive frames the
    target turns by one rotation (a constant tumble) while the camera closes in."""
    out = tmp_path / "passes"
    assert main(["dataset", "render", "--models", str(model_library), "--out", str(out),
                 "--images-per-model", str(IMAGES), "--seed", "7", "--resolution",
                 str(RESOLUTION), "--spp", str(SPP), "--pass-frames", str(IMAGES),
                 "--quiet"]) == 0
    for model_dir in sorted(p for p in out.iterdir() if (p / "labels.json").is_file()):
        labels = json.loads((model_dir / "labels.json").read_text())
        single = json.loads((dataset / model_dir.name / "labels.json").read_text())
        assert [(e["pass"], e["frame_in_pass"]) for e in labels] == [(0, k) for k in
                                                                    range(IMAGES)]
        assert labels[0]["q_vbs2tango_true"] == single[0]["q_vbs2tango_true"]
        # Every frame has its own seed (its own render noise), the first the image's 0.
        seeds = [e["seed"] for e in labels]
        assert seeds[0] == single[0]["seed"] and len(set(seeds)) == IMAGES
        rotations = quaternion_to_matrix(torch.tensor([e["q_vbs2tango_true"] for e in labels],
                                                      dtype=torch.float64))
        steps = [rotations[k + 1] @ rotations[k].T for k in range(IMAGES - 1)]
        torch.testing.assert_close(steps[0], steps[1], atol=1e-9, rtol=0)
        angle = float(rotation_angle(rotations[1:2], rotations[0:1])[0])
        assert math.radians(3.0) - 1e-9 <= angle <= math.radians(15.0) + 1e-9
        # Closing in to the start frame's distance, reached at the last frame.
        depths = [e["r_Vo2To_vbs_true"][2] for e in labels]
        assert depths == sorted(depths, reverse=True)
        assert depths[-1] == pytest.approx(single[0]["r_Vo2To_vbs_true"][2], rel=1e-9)
    # The pass length is part of the dataset's identity: resuming with another is refused.
    assert main(["dataset", "render", "--models", str(model_library), "--out", str(out),
                 "--images-per-model", str(IMAGES), "--seed", "7", "--resolution",
                 str(RESOLUTION), "--spp", str(SPP), "--quiet"]) == 2


def test_a_pass_lies_whole_in_one_split():
    """Passes of 12 frames over 40 images: each pass takes its first frame's split (the pass
    of frames 12-23 straddled val's 16-19), and a dataset without passes keeps the index rule."""
    from sq_mitsuba.data.spe3r import is_validation
    from sq_mitsuba.data.spe3r.dataset import split_index

    count, frames = 40, 12
    val = [k for k in range(count)
           if is_validation(split_index(k, {"frame_in_pass": k % frames}), count)]
    assert val == [36, 37, 38, 39]  # the pass that starts at 36; 12-23 all train
    for start in range(0, count, frames):
        chosen = {is_validation(split_index(k, {"frame_in_pass": k - start}), count)
                  for k in range(start, min(start + frames, count))}
        assert len(chosen) == 1, start
    assert [k for k in range(count) if is_validation(split_index(k, {}), count)] == \
        [16, 17, 18, 19, 36, 37, 38, 39]


def test_a_model_named_as_a_datasets_own_file_is_refused_before_any_work(model_library,
                                                                        tmp_path):
    """A model folder called splits.csv would stand where the dataset writes that file:
    refused in one line naming it, no dataset folder made."""
    library = tmp_path / "library"
    shutil.copytree(model_library, library)
    shutil.copytree(library / spe3r_writer.find_models(library)[0], library / "camera.json")
    out = tmp_path / "out"
    with pytest.raises(DatasetError, match=r"camera.json: a model named as a dataset's own "
                                           r"file \(dataset.json, camera.json"):
        render_dataset(library, out, RenderOptions(**OPTIONS), progress=False)
    assert not out.exists()
