"""The space scene's configuration and lighting: range checks, the sun's phase-angle
distribution, eclipses, auto exposure and the target's visibility in the rendered images."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy import stats

from sq_mitsuba.cli import main
from sq_mitsuba.config import ConfigError, apply_overrides, config_hash
from sq_mitsuba.data.frames import sample_frame, sample_pass_frame
from sq_mitsuba.data.library import generate_model
from sq_mitsuba.data.spacecraft import catalogue
from sq_mitsuba.data.spe3r import RenderOptions, load_model, render_image
from sq_mitsuba.data.spe3r.layout import IMAGES, MASKS, PROGRESS
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.io import read_json
from sq_mitsuba.render.scene_config import (
    ExposureConfig,
    IntegratorConfig,
    SceneConfig,
    SunConfig,
    scenes_dir,
)
from sq_mitsuba.render.space import LIT_FLOOR, RenderedFrame, auto_exposure, fixed_exposure

# A unit-size box (x >= y >= z): frames only need the target's extent.
BOX = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.2, 0.2) for z in (-0.15, 0.15)])


# ------------------------------------------------------------------------ configuration


def test_shipped_scene_loads_and_holds_the_defaults():
    shipped = SceneConfig.load()
    assert shipped == SceneConfig.load(scenes_dir() / "space.json") == SceneConfig()
    assert config_hash(shipped) == config_hash(SceneConfig())
    assert shipped.sun.phase_deg == (0.0, 120.0)
    assert shipped.sun.phase_distribution == "uniform_angle"
    assert shipped.eclipse.probability == 0.0
    assert shipped.exposure.mode == "auto"
    # Every comment key of the shipped file sits beside real keys, at any depth.
    raw = json.loads((scenes_dir() / "space.json").read_text())
    assert any(key.startswith("_") for key in raw["sun"])


def test_scenes_dir_of_a_checkout_on_pythonpath_that_is_not_installed():
    """Run from a checkout on PYTHONPATH (no pip install, as on a GPU machine with carried
    packages), sq_mitsuba.scenes does not exist; the scenes come from the checkout's folder.
    ``-S`` skips site's .pth files, so the editable install's mapping is not there."""
    import site
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    code = (f"import sys; sys.path[:0] = [{str(root)!r}, *{site.getsitepackages()!r}]; "
            "import importlib.util as u; print(u.find_spec('sq_mitsuba.scenes')); "
            "from sq_mitsuba.render.scene_config import scenes_dir; print(scenes_dir())")
    lines = subprocess.run([sys.executable, "-S", "-c", code], capture_output=True, text=True,
                           check=True).stdout.split()
    assert lines[0] == "None"  # not importable: the fallback is what is tested
    assert Path(lines[1]) == root / "scenes"
    assert (Path(lines[1]) / "space.json").is_file()


def test_partial_scene_files_with_comments_json_and_toml(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps({"_note": "top-level comment",
                                "sun": {"_why": "nested comment", "irradiance": 1000,
                                        "phase_deg": [10, 90]},
                                "exposure": {"mode": "fixed"}}))
    config = SceneConfig.load(path)
    assert config.sun == SunConfig(irradiance=1000.0, phase_deg=(10.0, 90.0))
    assert config.exposure == ExposureConfig(mode="fixed")
    assert config.earth == SceneConfig().earth  # untouched sections keep their defaults
    toml = tmp_path / "scene.toml"
    toml.write_text('[sun]\nphase_distribution = "uniform_sphere"\nphase_deg = [0, 180]\n')
    assert SceneConfig.load(toml).sun == SunConfig(phase_deg=(0.0, 180.0),
                                                   phase_distribution="uniform_sphere")


BAD_VALUES = [
    ({"exposure": {"reference_albedo": 0}}, "exposure.reference_albedo"),
    ({"exposure": {"reference_albedo": 1.5}}, "exposure.reference_albedo"),
    ({"sun": {"irradiance": float("nan")}}, "sun.irradiance"),
    ({"sun": {"irradiance": float("inf")}}, "sun.irradiance"),
    ({"sun": {"irradiance": 0}}, "sun.irradiance"),
    ({"integrator": {"max_depth": 0}}, "integrator.max_depth"),
    ({"integrator": {"max_depth": 1}}, "integrator.max_depth"),  # emitters only: black target
    ({"integrator": {"reconstruction_filter": "blurry"}}, "integrator.reconstruction_filter"),
    ({"stars": {"count": -10}}, "stars.count"),
    ({"stars": {"radiance": [0, 60]}}, r"stars.radiance\[0\]"),
    ({"stars": {"radiance": [60, 0.5]}}, "stars: radiance: low 60.0 is above high 0.5"),
    ({"sun": {"phase_deg": [0, 200]}}, r"sun.phase_deg\[1\]"),
    ({"sun": {"phase_deg": [120, 30]}}, "sun: phase_deg: low 120.0 is above high 30.0"),
    ({"sun": {"phase_distribution": "gaussian"}}, "sun.phase_distribution"),
    ({"eclipse": {"probability": 1.5}}, "eclipse.probability"),
    ({"eclipse": {"probability": -0.1}}, "eclipse.probability"),
    ({"earth": {"probability_in_view": float("nan")}}, "earth.probability_in_view"),
    ({"earth": {"altitude_km": [-5, 100]}}, r"earth.altitude_km\[0\]"),
    ({"earth": {"radius_km": 0}}, "earth.radius_km"),
    ({"earth": {"render_distance": 20}}, "earth: render_distance: at altitude 400 km"),
    ({"earth": {"texture": {"land_albedo": [0.5, 1.2]}}}, r"earth.texture.land_albedo\[1\]"),
    ({"pose": {"distance_scale": [0, 1]}}, r"pose.distance_scale\[0\]"),
    ({"pose": {"max_lateral_fraction": 2}}, "pose.max_lateral_fraction"),
    ({"exposure": {"mode": "manual"}}, "exposure.mode"),
    ({"exposure": {"percentile": 0}}, "exposure.percentile"),
    ({"exposure": {"auto_gain": [4, 2]}}, "exposure: auto_gain: low 4.0 is above high 2.0"),
    ({"mask": {"spp": 0}}, "mask.spp"),
    ({"sun": {"power": 1}}, "sun.power: unknown key"),
]


@pytest.mark.parametrize(("data", "field"), BAD_VALUES, ids=[f for _, f in BAD_VALUES])
def test_bad_scene_values_are_errors_naming_file_and_field(tmp_path, data, field):
    path = tmp_path / "bad_scene.json"
    path.write_text(json.dumps({"_comment": "one bad value", **data}))  # NaN -> JSON NaN
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}: {field}") as info:
        SceneConfig.load(path)
    assert "\n" not in str(info.value)


def test_configs_built_in_code_and_overrides_are_checked():
    with pytest.raises(ConfigError, match=r"^sun\.irradiance: expected a finite number"):
        SceneConfig(sun=SunConfig(irradiance=math.nan))
    with pytest.raises(ConfigError, match=r"^integrator\.max_depth"):
        dataclasses.replace(SceneConfig(), integrator=IntegratorConfig(max_depth=0))
    with pytest.raises(ConfigError, match=r"exposure\.reference_albedo"):
        apply_overrides(SceneConfig(), ["exposure.reference_albedo=0"])
    with pytest.raises(ValueError, match="phase_deg: low 90"):
        SunConfig(phase_deg=(90.0, 30.0))
    assert apply_overrides(SceneConfig(), ["sun.phase_deg=[0, 180]"]).sun.phase_deg == (0, 180)


def test_cli_refuses_a_bad_scene_before_any_work(tmp_path, capsys):
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"exposure": {"reference_albedo": 0}}))
    out = tmp_path / "out"
    assert main(["dataset", "render", "--models", str(tmp_path), "--out", str(out),
                 "--scene", str(scene), "--quiet"]) == 2
    error = capsys.readouterr().err.strip()
    assert "scene.json: exposure.reference_albedo" in error and "\n" not in error
    assert not out.exists()


# ------------------------------------------------------------------------ sun and Earth


def _frames(config: SceneConfig, count: int, model: str = "box") -> list:
    camera = Camera.default(128)
    return [sample_frame(BOX, camera, config, 3, model, i) for i in range(count)]


def _phases(frames: list) -> np.ndarray:
    """Phase angles (deg) recomputed from each frame's sun direction and translation."""
    sun = np.array([f.sun_direction for f in frames])
    to_camera = -np.array([f.translation for f in frames])
    to_camera /= np.linalg.norm(to_camera, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((sun * to_camera).sum(1), -1, 1)))


def _earth_hides_sun(frame) -> bool:
    cos = float(np.dot(frame.sun_direction, frame.earth_direction))
    return cos > math.cos(math.radians(frame.earth_angular_radius_deg))


def test_default_phase_angles_are_uniform_in_0_120_without_eclipses():
    config = SceneConfig.load()
    frames = _frames(config, 1500)
    phases = _phases(frames)
    np.testing.assert_allclose(phases, [f.phase_angle_deg for f in frames], atol=1e-6)
    assert phases.min() >= 0 and phases.max() <= 120 + 1e-6
    # Uniform in the angle; the test has the power to tell it from uniform on the sphere.
    assert stats.kstest(phases, stats.uniform(0, 120).cdf).pvalue > 0.001
    sphere_cdf = lambda a: (1 - np.cos(np.radians(a))) / 1.5  # noqa: E731
    assert stats.kstest(phases, sphere_cdf).pvalue < 1e-6
    # No eclipse by default: the sun is never behind the Earth's disk.
    assert not any(f.eclipse for f in frames)
    assert not any(_earth_hides_sun(f) for f in frames)
    # The Earth still crosses the view as often as configured.
    assert abs(np.mean([f.earth_in_view for f in frames]) - 0.3) < 0.045
    # Same image, same frame; the next image, another sun.
    assert sample_frame(BOX, Camera.default(128), config, 3, "box", 7) == frames[7]
    assert frames[8].sun_direction != frames[7].sun_direction


def _projected_extent(points: np.ndarray, frame, camera: Camera) -> tuple[float, float]:
    """Smallest distance in pixels from the image's edge of the frame's projected points, by
    brute-force projection (independent of the sampler's own test)."""
    cam = points @ frame.rotation.T + np.asarray(frame.translation)
    u = camera.fx * cam[:, 0] / cam[:, 2] + camera.cx
    v = camera.fy * cam[:, 1] / cam[:, 2] + camera.cy
    return min(u.min(), v.min(), camera.width - u.max(), camera.height - v.max()), cam[:, 2].min()


def test_every_frame_of_a_pass_holds_the_whole_target():
    """A long rod tumbling 10-15 deg a frame left the image in a third of its passes (the start
    frame framed it, a turned frame did not): the pass is moved back as a whole until every
    frame holds it, and one that fits is left as drawn (its last frame at the start's
    distance)."""
    rod = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])
    camera, config, count = Camera.default(64), SceneConfig(), 8
    moved = 0
    for seed in range(12):
        start = sample_frame(rod, camera, config, seed, "rod", 0)
        frames = [sample_pass_frame(rod, camera, config, seed, "rod", k, count,
                                    tumble_deg=(10.0, 15.0)) for k in range(count)]
        for frame in frames:
            edge, nearest = _projected_extent(rod, frame, camera)
            assert nearest > 0 and edge >= config.pose.margin_px - 1e-9
        # Still one pass: the same line of sight, closing in, the first frame the image's.
        np.testing.assert_allclose(frames[0].rotation, start.rotation, atol=1e-12)
        directions = np.array([f.translation for f in frames])
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        np.testing.assert_allclose(directions, directions[:1].repeat(count, 0), atol=1e-12)
        scale = frames[-1].translation[2] / start.translation[2]
        assert scale >= 1 - 1e-12
        moved += scale > 1 + 1e-9
    assert 0 < moved < 12  # some passes had to move back, some did not


@pytest.mark.parametrize("low, high", [(0.0, 180.0), (30.0, 60.0)])
def test_uniform_sphere_phase_distribution(low, high):
    config = apply_overrides(SceneConfig(), [f"sun.phase_deg=[{low}, {high}]",
                                             'sun.phase_distribution="uniform_sphere"'])
    phases = _phases(_frames(config, 800, model=f"sphere{low}"))
    assert phases.min() >= low - 1e-6 and phases.max() <= high + 1e-6
    c_low, c_high = math.cos(math.radians(low)), math.cos(math.radians(high))
    sphere_cdf = lambda a: (c_low - np.cos(np.radians(a))) / (c_low - c_high)  # noqa: E731
    assert stats.kstest(phases, sphere_cdf).pvalue > 0.001
    assert stats.kstest(phases, stats.uniform(low, high - low).cdf).pvalue < 0.01


def test_eclipse_probability_is_configurable():
    config = apply_overrides(SceneConfig(), ["eclipse.probability=0.4"])
    frames = _frames(config, 400, model="eclipses")
    eclipses = np.array([f.eclipse for f in frames])
    assert abs(eclipses.mean() - 0.4) < 0.08  # binomial sd 0.025
    # The flag agrees with the geometry: the sun behind the Earth's disk exactly then.
    assert [_earth_hides_sun(f) for f in frames] == eclipses.tolist()


# ------------------------------------------------------------------------ exposure, visibility


def test_auto_exposure_maps_the_percentile_to_white_within_the_gain_range():
    config = ExposureConfig(mode="auto", percentile=99.0, auto_white=1.0, auto_gain=(0.25, 16))
    inside = np.zeros((11, 11), bool)
    inside.ravel()[:101] = True
    radiance = np.full((11, 11), 1e6)  # outside the mask: ignored, however bright
    radiance.ravel()[:101] = np.arange(101) * 0.002  # 99th percentile of 0..100: 99
    fixed = 4.0
    assert auto_exposure(radiance, inside, fixed, config) == pytest.approx(1 / (99 * 0.002))
    half_white = dataclasses.replace(config, auto_white=0.5)
    assert auto_exposure(radiance, inside, fixed, half_white) == pytest.approx(0.5 / 0.198)
    assert auto_exposure(radiance * 1e-4, inside, fixed, config) == fixed * 16  # dim: capped
    assert auto_exposure(radiance * 1e3, inside, fixed, config) == fixed * 0.25  # glint
    assert auto_exposure(np.zeros((11, 11)), inside, fixed, config) == fixed * 16  # eclipse
    assert auto_exposure(radiance, np.zeros((11, 11), bool), fixed, config) == fixed
    assert fixed_exposure(SceneConfig()) == pytest.approx(math.pi / (1361.0 * 0.9))


def test_visibility_is_the_mean_and_lit_share_of_the_mask():
    coverage = np.zeros((4, 4))
    coverage[:2] = 1.0
    coverage[2, 0] = 0.5  # counts as inside (coverage >= 0.5), as in the mask
    coverage[2, 1] = 0.49
    radiance = np.zeros((4, 4))
    radiance[0] = 1.0  # 4 white pixels
    radiance[1, 0] = 0.5 / 255  # tonemaps to grey 6: below the lit floor
    radiance[1, 1] = 0.2  # grey 124
    radiance[2, 1] = radiance[3] = 1.0  # outside the mask
    frame = RenderedFrame(radiance, coverage, None, 1.0)
    grey = frame.image_8bit()
    # sRGB by hand: 12.92 * 0.5 = 6.46 -> 6; 1.055 * 0.2 ** (1 / 2.4) - 0.055 = 0.4845 -> 124.
    assert (grey[1, 0], grey[1, 1]) == (6, 124) and 6 < LIT_FLOOR <= 124
    mean, lit = frame.visibility()
    assert mean == pytest.approx((4 * 255 + 6 + 124) / 9 / 255)  # 9 pixels inside
    assert lit == pytest.approx(5 / 9)
    extras = frame.label_extras()
    assert extras["exposure"] == 1.0 and extras["target_lit_fraction"] == round(5 / 9, 6)
    assert RenderedFrame(radiance, np.zeros((4, 4)), None, 1.0).visibility() == (0.0, 0.0)


# ------------------------------------------------------------------------ acceptance


MODELS, IMAGES_PER_MODEL, RESOLUTION, SPP, MASK_SPP = 8, 16, 128, 8, 16


@pytest.fixture(scope="module")
def eight_models(tmp_path_factory) -> Path:
    """Eight generated spacecraft of different archetypes (small point sets)."""
    root = tmp_path_factory.mktemp("scene_models")
    for entry in catalogue(MODELS, 0):
        generate_model(entry, root, points=2000)
    return root


@pytest.mark.slow
def test_default_scene_shows_the_target_and_labels_record_it(eight_models, tmp_path):
    """8 models x 16 images, 128 px, default scene: at most 3 % of the images have a target
    whose mean grey level is below 10/255; each label's visibility and exposure agree with the
    image and mask files written beside it.

    The mask pass at MASK_SPP samples per pixel at 256 px (64 spp at 128 px) rather than the
    default 64 (256 spp at 128 px, 70 % of this test's time): the mask only marks the target's
    pixels, its outline a little noisier (the same dark share, 1 image of 128, and median grey
    60 as with the default); the sun, Earth, stars and exposure are the default scene's."""
    from sq_mitsuba.render.space import SpaceScene

    config = apply_overrides(SceneConfig.load(), [f"mask.spp={MASK_SPP}"])
    camera = Camera.default(RESOLUTION)
    options = RenderOptions(images_per_model=IMAGES_PER_MODEL, seed=0, resolution=RESOLUTION,
                            spp=SPP, scene=config)
    fixed = fixed_exposure(config)
    means, phases, gains = [], [], []
    for model in sorted(p.name for p in eight_models.iterdir() if p.is_dir()):
        vertices, faces, tags = load_model(eight_models / model)
        scene = SpaceScene(vertices, faces, tags, camera, config, spp=SPP, dataset_seed=0)
        out = tmp_path / model
        for index in range(IMAGES_PER_MODEL):
            render_image(scene, vertices, options, model, index, out)
            name = f"{index:06d}"
            label = read_json(out / PROGRESS / f"{name}.json")
            image = np.asarray(Image.open(out / IMAGES / f"{name}.png")).astype(float)
            inside = np.asarray(Image.open(out / MASKS / f"{name}.png")) > 0
            target = image[inside]
            assert label["target_visibility"] == pytest.approx(target.mean() / 255, abs=1e-6)
            assert label["target_lit_fraction"] == pytest.approx(np.mean(target >= 10),
                                                                 abs=1e-6)
            gain = label["exposure"] / fixed
            assert 0.25 - 1e-9 <= gain <= 16 + 1e-9
            if 0.25 + 1e-6 < gain < 16 - 1e-6:
                # Auto exposure: the target's brightest 1 % (its 99th percentile) is white.
                assert np.mean(target == 255) >= 0.01 - 1 / len(target)
            means.append(target.mean())
            phases.append(label["phase_angle_deg"])
            gains.append(gain)
    means = np.array(means)
    dark = float(np.mean(means < 10))
    histogram = np.histogram(phases, bins=np.arange(0, 181, 15))[0]
    print(f"\ntarget mean grey: median {np.median(means):.1f}, share < 10/255: {dark:.3f}; "
          f"auto gain median {np.median(gains):.2f}; phase histogram (15 deg bins from 0): "
          f"{histogram.tolist()}")
    assert len(means) == MODELS * IMAGES_PER_MODEL
    assert dark <= 0.03
    assert max(phases) <= 120 + 1e-6 and histogram[8:].sum() == 0


@pytest.mark.parametrize("with_depth", [False, True], ids=["image-mask", "with-depth"])
def test_an_image_does_not_depend_on_being_its_scenes_first(eight_models, with_depth):
    """A render before a scene's parameters are first updated differs from later ones in the
    last bits (measured: without the scene's warm-up, the same frame's image changes by
    whether it came first): so frame 1 rendered first in a new scene is, bit for bit, frame 1
    rendered after frame 0 in another. This is what lets a killed and resumed dataset render
    (a new scene per model) write the bytes an uninterrupted one does.

    The depth (EXR 'Z') is the exception, to float32 rounding: Dr.Jit's threads add a pixel's
    depth samples into the film in the order they finish (measured: on one thread the depth
    is the same bit for bit, on two it moves by about one float32 step at 2 m)."""
    from sq_mitsuba.render.space import SpaceScene

    model = sorted(p for p in eight_models.iterdir() if p.is_dir())[0]
    vertices, faces, tags = load_model(model)
    camera, config = Camera.default(48), SceneConfig.load()
    frames = [sample_frame(vertices, camera, config, 0, model.name, index) for index in (0, 1)]

    def scene() -> SpaceScene:
        return SpaceScene(vertices, faces, tags, camera, config, spp=4, with_depth=with_depth)

    first = scene().render(frames[1])
    later = scene()
    later.render(frames[0])
    second = later.render(frames[1])
    for name in ("radiance", "coverage", "depth"):
        a, b = getattr(first, name), getattr(second, name)
        assert (a is None) == (b is None) == (name == "depth" and not with_depth), name
        if name == "depth" and a is not None:
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)
        elif a is not None:
            assert a.tobytes() == b.tobytes(), name


def test_material_tags_are_names_or_indices_and_an_unknown_one_is_refused():
    """An unknown tag rendered the default grey unnoticed (a MATERIALS index read as the
    string "0", a misspelt name)."""
    from sq_mitsuba.render.materials import MATERIALS
    from sq_mitsuba.render.space import SpaceScene, _face_tags

    assert _face_tags(np.array([0, 2]), 2).tolist() == [MATERIALS[0], MATERIALS[2]]
    assert _face_tags(None, 2).tolist() == ["default", "default"]
    vertices = np.array([[0.0, 0, 3], [1, 0, 3], [0, 1, 3], [0, 0, 4]])
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    camera, config = Camera.default(16), SceneConfig()
    for tags, message in ((np.array(["gold-mli"] * 4), "'gold-mli': no such material"),
                          (np.array([0, 1, 2, 99]), "indices outside the materials"),
                          (np.array(["gold_mli"] * 3), "one tag per face")):
        with pytest.raises(ValueError, match=message):
            SpaceScene(vertices, faces, tags, camera, config, spp=1)


@pytest.mark.parametrize("text, said", [("", "an empty file, not JSON"),
                                        ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
                                        ("[1, 2]", "expected an object of materials by tag"),
                                        ('{"gold": {}}', "needs a 'default' material")])
def test_a_bad_materials_file_is_one_line_naming_it(tmp_path, text, said):
    """A deeply nested file ended as an internal error (the parser's RecursionError)."""
    from sq_mitsuba.render.space import load_materials

    path = tmp_path / "materials.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: .*{re.escape(said)}"):
        load_materials(path)
