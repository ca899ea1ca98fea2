"""Issue 35 (the API's part): a target-present score, and bad input refused in one line naming
the argument or file, before any work, with nothing half-written and no warning leaking.

References: the target-present score is checked against images whose content is known by
construction (the fixture's rendered spacecraft, the Earth rendered alone by the project's
renderer with the target moved behind the camera, black frames and noise); the errors against
the argument or file they must name."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from output_checks import error_line, one_torch_thread  # noqa: F401 (autouse fixture)
from PIL import Image

import sq_mitsuba
from sq_mitsuba.apps.predict import POSE_CONVENTION
from sq_mitsuba.cli import main
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.inference.images import DEFAULT_MIN_TARGET, prepare_images
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.inference.refine import RefineOptions
from sq_mitsuba.inference.search import SEARCH_REFINEMENT, SearchOptions

SEARCH = SearchOptions(grid=128, screen_steps=2)
REFINEMENT = dataclasses.replace(SEARCH_REFINEMENT, steps=4, patience=4)
SMALL = ["--set", "refinement.steps=4", "--set", "refinement.patience=4",
         "--set", "search.grid=128", "--set", "search.screen_steps=2"]
assert isinstance(REFINEMENT, RefineOptions)


def _test_model(root):
    return next(line.split(",")[0] for line in (root / "splits.csv").read_text().splitlines()
                if line.endswith(",test"))


@pytest.fixture(scope="module")
def scenes(train_dataset):
    """64 px images whose content is known, uint8 (N, 64, 64) each:

    - ``spacecraft``: the fixture's test model, every image (some with the Earth behind);
    - ``lit``: those of them with the Earth out of view and the target well lit (what a
      threshold segmentation can find);
    - ``black``; ``noise``: uniform in [0, 1], Gaussian noise (mean 0, sd 0.3; mean 0.1,
      sd 0.2) and sparse bright pixels, on which the mask head alone fires;
    - ``earth`` (96 px): the Earth alone, rendered with the project's renderer as the shipped
      model's training images were (96 px, 16 spp): the test model's frames with the Earth
      in view, the target moved behind the camera.
    """
    from sq_mitsuba.config import apply_overrides
    from sq_mitsuba.data.frames import sample_frame
    from sq_mitsuba.data.spe3r import RenderOptions
    from sq_mitsuba.data.spe3r.layout import load_model as load_mesh
    from sq_mitsuba.render.space import SpaceScene

    model = _test_model(train_dataset)
    labels = json.loads((train_dataset / model / "labels.json").read_text())
    spacecraft = np.stack([np.asarray(Image.open(train_dataset / model / "images" /
                                                 label["filename"])) for label in labels])
    lit = spacecraft[[not label["earth_in_view"] and label["target_visibility"] >= 0.15
                      for label in labels]]
    rng = np.random.default_rng(0)
    sparse = (rng.random((64, 64)) < 0.2) * rng.uniform(0.3, 1.0, (64, 64))
    noise = np.stack([rng.uniform(0, 1, (64, 64)), np.clip(rng.normal(0, 0.3, (64, 64)), 0, 1),
                      np.clip(rng.normal(0.1, 0.2, (64, 64)), 0, 1), sparse])
    vertices, faces, tags = load_mesh(train_dataset / model)
    config = apply_overrides(RenderOptions().scene, ("earth.probability_in_view=1",
                                                     "eclipse.probability=0"))
    camera = Camera.default(96)
    scene = SpaceScene(vertices, faces, tags, camera, config, spp=16, dataset_seed=5)
    earth = []
    for index in range(5):
        frame = sample_frame(vertices, camera, config, 5, model, index)
        assert frame.earth_in_view
        alone = scene.render(dataclasses.replace(frame, translation=(0.0, 0.0, -50.0)))
        assert not alone.mask.any()  # nothing of the target in view
        earth.append(alone.image_8bit())
    earth = np.stack(earth)
    assert (earth.reshape(len(earth), -1).max(1) > 100).sum() >= 3  # mostly a lit Earth
    return {"spacecraft": spacecraft, "lit": lit, "black": np.zeros((1, 64, 64), np.uint8),
            "noise": (noise * 255).round().astype(np.uint8), "earth": earth}


@pytest.fixture(scope="module")
def shipped():
    return sq_mitsuba.load_model()


# --- item 8: the target-present score -----------------------------------------------------


def test_the_mask_heads_score_tells_spacecraft_from_black_noise_and_the_earth(scenes, shipped):
    """The shipped model (mask head): every spacecraft image, the Earth behind or not, is a
    target; black, noise and the Earth alone are not, each by a margin."""
    scores = {name: shipped.predict(images).target_score for name, images in scenes.items()}
    for name, score in scores.items():
        assert score.shape == (len(scenes[name]),) and score.dtype.is_floating_point
        assert bool(((score >= 0) & (score <= 1)).all()), name
    assert float(scores["spacecraft"].min()) >= 0.95, scores["spacecraft"]
    for name in ("black", "noise", "earth"):
        assert float(scores[name].max()) <= 0.85, (name, scores[name])
    prediction = shipped.predict(np.concatenate([scenes["spacecraft"][:2], scenes["black"],
                                                 scenes["noise"]]))
    assert prediction.target.tolist() == [True, True] + [False] * 5
    torch.testing.assert_close(prediction.target, prediction.target_score >= 0.92)
    assert not bool(shipped.predict(scenes["earth"]).target.any())
    # The noise term decides the noise: the mask head alone fires on it (upsampled 64 -> 96
    # px, the noise forms blobs), so a score from the mask head alone would call it a target.
    with torch.inference_mode():
        x = torch.nn.functional.interpolate(torch.from_numpy(scenes["noise"])[:, None].float()
                                            / 255, size=(96, 96), mode="bilinear")
        logits = shipped.model.eval()(x, shipped.camera.rescaled(96, 96).matrix()).mask_logits
    assert float(logits.flatten(1).amax(1).sigmoid().max()) > 0.95


def test_neighbour_correlation_of_strips_and_large_images():
    """Noise has uncorrelated neighbours and a picture correlated ones, whatever the shape:
    a strip thinner than the block size (8 x 5000 px, either way) and an image above 512 px
    measured on block means."""
    from sq_mitsuba.inference.images import neighbour_correlation

    generator = torch.Generator().manual_seed(0)
    for height, width in ((8, 5000), (5000, 8), (700, 1100), (1, 3000)):
        noise = torch.rand(1, 3, height, width, generator=generator)
        ramp = torch.linspace(0, 1, height * width).reshape(1, 1, height, width).expand(
            1, 3, height, width)
        assert abs(float(neighbour_correlation(noise)[0])) < 0.05, (height, width)
        assert float(neighbour_correlation(ramp)[0]) > 0.99, (height, width)


def test_without_a_mask_head_the_segmentation_scores_the_target(scenes, eval_checkpoint):
    """A network without a mask head falls back on the image's segmentation: the lit
    spacecraft are targets, black, noise and the Earth alone are not."""
    predictor = load_model(eval_checkpoint)
    assert predictor.model.mask_head is None
    assert len(scenes["lit"]) >= 3
    assert bool(predictor.predict(scenes["lit"]).target.all())
    for name in ("black", "noise", "earth"):
        prediction = predictor.predict(scenes[name])
        assert not bool(prediction.target.any()), (name, prediction.target_score)
        assert float(prediction.target_score.max()) <= 0.5, name


def test_min_target_is_the_threshold_and_the_turned_reading_keeps_the_score(scenes, shipped,
                                                                           eval_checkpoint):
    from sq_mitsuba.inference.predictor import Predictor

    assert shipped.min_target == DEFAULT_MIN_TARGET == 0.92
    everything = Predictor(shipped.model, shipped.camera, min_target=0.0)
    assert bool(everything.predict(scenes["black"]).target.all())
    images = np.concatenate([scenes["spacecraft"][:1], scenes["black"]])
    plain = shipped.predict(images)
    turned = shipped.predict(images, turns=4)
    torch.testing.assert_close(turned.target_score, plain.target_score)
    assert turned.target.tolist() == plain.target.tolist() == [True, False]
    for bad in (1.5, -0.1, float("nan"), True, "0.5"):
        with pytest.raises(ValueError, match=r"^min_target: expected a number in \[0, 1\]"):
            Predictor(shipped.model, shipped.camera, min_target=bad)
    with pytest.raises(ValueError, match=r"^min_target: "):
        load_model(eval_checkpoint, min_target=2)


def test_refine_does_not_search_an_image_without_a_target(scenes, eval_checkpoint):
    """With refine=True an image without a target is not fitted (its scores NaN, its pose the
    start), the spacecraft beside it is; a mask the caller gives is fitted whatever the
    score (the caller says where the target is)."""
    predictor = load_model(eval_checkpoint)
    images = np.concatenate([scenes["lit"][:1], scenes["black"], scenes["noise"][:1]])
    fitted = predictor.predict(images, refine=True, search=SEARCH, refinement=REFINEMENT)
    assert fitted.target.tolist() == [True, False, False]
    assert fitted.fit.fitted.tolist() == [True, False, False]
    assert not math.isnan(float(fitted.fit.iou[0]))
    assert all(math.isnan(float(v)) for v in fitted.fit.iou[1:])
    torch.testing.assert_close(fitted.rotation[1], fitted.fit.start.rotation[1].double())
    given = torch.zeros(2, 64, 64, dtype=torch.bool)
    given[:, 20:44, 20:44] = True
    again = predictor.predict(images[:2], refine=True, mask=given, search=SEARCH,
                              refinement=REFINEMENT)
    assert again.fit.mask_source == "given" and again.fit.fitted.tolist() == [True, True]


def test_predict_reports_no_target_and_writes_its_pose_json_alone(scenes, eval_checkpoint,
                                                                  tmp_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    Image.fromarray(scenes["lit"][0]).save(folder / "craft.png")
    for name in ("black", "earth"):
        Image.fromarray(scenes[name][0]).save(folder / f"{name}.png")
    Image.fromarray(scenes["noise"][0]).save(folder / "noise.png")
    out = tmp_path / "out"
    out.mkdir()
    # An earlier run's files of black (a target then, by its pose.json): must not stay.
    (out / "black.obj").write_text("a mesh of an earlier run")
    (out / "black.pose.json").write_text(json.dumps({
        "target": True, "convention": POSE_CONVENTION, "checkpoint": str(eval_checkpoint)}))
    args = ["predict", *(str(folder / f"{n}.png") for n in ("craft", "black", "noise", "earth")),
            "--checkpoint", str(eval_checkpoint), "--out", str(out), "--quiet"]
    assert main(args) == 0
    printed = capsys.readouterr().out.splitlines()
    assert "target score" in printed[0] and "no target" not in printed[0]
    for line, name in zip(printed[1:4], ("black", "noise", "earth"), strict=True):
        assert line.startswith(str(folder / f"{name}.png")) and "no target" in line, line
    assert "3 without a target" in printed[-1] and "wrote 8 files" in printed[-1], printed
    craft = json.loads((out / "craft.pose.json").read_text())
    assert craft["target"] is True and craft["target_score"] >= 0.92
    assert craft["min_target"] == 0.92 and len(craft["q_vbs2tango"]) == 4
    for name in ("black", "noise", "earth"):
        pose = json.loads((out / f"{name}.pose.json").read_text())
        assert pose["target"] is False and pose["target_score"] < 0.92
        assert "q_vbs2tango" not in pose and "r_Vo2To_vbs" not in pose
        assert sorted(p.name for p in out.iterdir() if p.stem.startswith(name)) == \
            [f"{name}.pose.json"]
    # min_target=0 takes every image for a target.
    everything = tmp_path / "everything"
    assert main([*args[:-3], "--out", str(everything), "--set", "min_target=0", "--quiet"]) == 0
    assert json.loads((everything / "black.pose.json").read_text())["target"] is True
    assert (everything / "black.glb").is_file()


# --- minors: predict --refine, prepare_images ---------------------------------------------


def test_an_empty_network_mask_names_the_image_and_writes_nothing(scenes, tmp_path, capsys):
    """The shipped model taking every image for a target (min_target=0): a black image's
    mask is empty; the error names it, after the spacecraft before it was refined, and
    nothing is written."""
    Image.fromarray(scenes["spacecraft"][0]).save(tmp_path / "craft.png")
    Image.fromarray(scenes["black"][0]).save(tmp_path / "black.png")
    out = tmp_path / "out"
    assert main(["predict", str(tmp_path / "craft.png"), str(tmp_path / "black.png"), "--out",
                 str(out), "--refine", "--set", "min_target=0", *SMALL, "--quiet"]) == 2
    line = error_line(capsys)
    assert f"error: image {tmp_path / 'black.png'}: the network's mask of it is empty" in line, \
        line
    assert not out.exists()


def test_predict_refine_says_what_each_score_is(scenes, eval_checkpoint, tmp_path, capsys):
    Image.fromarray(scenes["lit"][0]).save(tmp_path / "craft.png")
    assert main(["predict", str(tmp_path / "craft.png"), "--checkpoint", str(eval_checkpoint),
                 "--out", str(tmp_path / "out"), "--refine", *SMALL, "--quiet"]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    pose = json.loads((tmp_path / "out" / "craft.pose.json").read_text())
    assert f"the search's soft IoU {pose['search_score']:.3f} at 64 px" in line, line
    assert f"the refined IoU {pose['iou_after']:.3f} at 64 px" in line, line
    assert pose["search_resolution"] == 64 and pose["refine_resolution"] == 64


def test_the_mask_option_help_agrees_with_the_description():
    """Without --mask: the network's mask head, or the segmentation for a model without one
    (the --mask help, the --refine help, the description and PredictOptions say the same)."""
    import argparse

    from sq_mitsuba.cli.predict import DESCRIPTION, register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    command = parser._subparsers._group_actions[0].choices["predict"]
    helps = {action.dest: " ".join(action.help.split()) for action in command._actions
             if action.help}
    description = " ".join(DESCRIPTION.split())
    assert "without --mask, the network's mask head (the image's segmentation for a model " \
           "without a mask head" in description
    assert "(default, without --mask: the network's mask head, or the image's segmentation " \
           "for a model without one" in helps["mask"]
    assert "--mask, else the network's mask head (the image's segmentation for a model " \
           "without one)" in helps["refine"]
    assert "read from the image" not in helps["refine"]


@pytest.mark.parametrize(("images", "message"), [
    (torch.zeros(1, 1, 1, dtype=torch.uint8),
     r"^images: 1 x 1 px is below the smallest image size, 8 x 8 px$"),
    (torch.zeros(1, 1, 1, dtype=torch.uint8).expand(1, 12000, 12000),
     r"^images: 12000 x 12000 px is above the largest image size"),
    (np.zeros((1, 16, 16), dtype=object), r"^images: expected uint8 or floating point, got "
                                          r"object$"),
    (torch.zeros(1, 16, 16, device="meta"), r"^images: a meta tensor \(no values\)"),
])
def test_the_api_refuses_what_the_cli_refuses_naming_images(eval_checkpoint, images, message):
    predictor = load_model(eval_checkpoint)
    with pytest.raises(ValueError, match=message) as info:
        predictor.predict(images)
    assert "\n" not in str(info.value)


def test_read_only_arrays_and_grad_tensors_predict_without_warnings(eval_checkpoint, tmp_path):
    """``np.asarray(Image.open(path))`` is read-only (torch warns once per process about such
    arrays, so a fresh interpreter checks it), as images and as masks to fit; a tensor that
    requires grad is detached; another byte order is converted."""
    image = (np.arange(64 * 64) % 251).astype(np.uint8).reshape(64, 64)
    Image.fromarray(image).save(tmp_path / "photo.png")
    code = ("import numpy as np, torch; from PIL import Image; import sq_mitsuba; "
            f"p = sq_mitsuba.load_model({str(eval_checkpoint)!r}); "
            f"a = np.asarray(Image.open({str(tmp_path / 'photo.png')!r}))[None]; "
            "assert not a.flags.writeable; p.predict(a); "
            "t = torch.rand(1, 64, 64, requires_grad=True); p.predict(t); "
            "p.predict(np.zeros((1, 64, 64), '>f4')); "
            "from types import SimpleNamespace; "
            "from sq_mitsuba.inference.pipeline import masks_to_fit; "
            "m = np.asarray(Image.open("
            f"{str(tmp_path / 'photo.png')!r}"
            "))[None] > 100; m.flags.writeable = False; "
            "masks_to_fit(SimpleNamespace(mask=None), torch.zeros(1, 1, 64, 64), m); print('ok')")
    run = subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr[-2000:]
    predictor = load_model(eval_checkpoint)
    grad = torch.from_numpy(image / 255.0).float()[None].requires_grad_(True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        prediction = predictor.predict(grad)
    assert not prediction.translation.requires_grad
    torch.testing.assert_close(prepare_images(grad), torch.from_numpy(image / 255.0).float()
                               [None, None])


def _bright_square() -> torch.Tensor:
    """(1, 96, 96) a lit square on black, at the shipped model's input size."""
    image = torch.zeros(1, 96, 96)
    image[0, 30:60, 25:70] = 0.8
    return image


def test_masks_of_another_byte_order_are_read_and_floats_outside_0_1_refused(shipped):
    """A big-endian or strided numpy mask is the same mask as its native copy (the fitted
    mask bit for bit: ``> 0.5`` of floats, ``!= 0`` of integers); a float mask outside
    [0, 1], NaN, or an array of another kind is one line naming ``mask``."""
    from sq_mitsuba.inference.pipeline import masks_to_fit

    image = _bright_square()
    reading, checked = shipped.predict(image), prepare_images(image)
    mask = np.zeros((1, 96, 96), np.float32)
    mask[0, 28:62, 22:72] = 0.8
    mask[0, 40:50, 30:40] = 0.3
    masks, usable, source = masks_to_fit(reading, checked, mask)
    assert torch.equal(masks, torch.from_numpy(mask) > 0.5) and source == "given"
    assert usable.tolist() == [True]
    for variant in (mask.astype(">f4"), mask.astype(">f8"), mask[:, ::-1].copy()[:, ::-1],
                    np.asfortranarray(mask), (mask > 0.5).astype(">i4")):
        again = masks_to_fit(reading, checked, variant)
        assert torch.equal(again[0], masks) and torch.equal(again[1], usable), variant.dtype
    for bad, message in ((np.full((1, 96, 96), -3.0, ">f4"),
                          r"mask: float values must lie in \[0, 1\], got \[-3, -3\]$"),
                         (torch.from_numpy(mask * 2), r"mask: float values must lie in \[0, 1\], "
                                                      r"got \[0, 1.6\]$"),
                         (np.full((1, 96, 96), np.nan, ">f4"), "mask: contains NaN"),
                         (np.full((1, 96, 96), "a"), "mask: expected a bool or float array, "
                                                     "got dtype <U1$")):
        with pytest.raises(ValueError, match=f"^{message}") as info:
            masks_to_fit(reading, checked, bad)
        assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match=r"^mask: float values must lie in \[0, 1\]"):
        shipped.predict(image, refine=True, mask=np.full((1, 96, 96), -3.0, ">f4"))


def test_search_and_refinement_options_are_checked_before_any_work(shipped):
    """Wrong types and out-of-bounds fields of ``search`` and ``refinement`` are one line
    naming the field (``search.turns`` against its own bound), before the turned copies run
    and whether or not any item is fitted (an empty mask: none is)."""
    from sq_mitsuba.inference.predictor import Predictor

    image, empty = _bright_square(), torch.zeros(1, 96, 96, dtype=torch.bool)
    predictor = Predictor(shipped.model, shipped.camera)
    passes = []
    run = predictor._run  # counts the images each network pass reads
    predictor._run = lambda x, matrix: passes.append(len(x)) or run(x, matrix)
    network = predictor.predict(image)
    turns = r"search\.turns: expected a value in \[1, 64\], got "
    for options, message in (
            (dict(search=SearchOptions(turns=100)), turns + "100$"),
            (dict(search=SearchOptions(turns=500)), turns + "500$"),
            (dict(search=SearchOptions(resolution=1)), r"search\.resolution: expected a value"),
            (dict(refinement=RefineOptions(steps=0, lr=-1.0)), r"refinement\.steps: expected"),
            (dict(search={"grid": 8}), r"search: expected a SearchOptions, got dict \(build one "
                 r"from it: SearchOptions\(\*\*d\)\)$"),
            (dict(refinement=SEARCH), "refinement: expected a RefineOptions, got SearchOptions$")):
        passes.clear()
        with pytest.raises(ValueError, match=f"^{message}") as info:
            predictor.refine(image, network, mask=empty, **options)
        assert "\n" not in str(info.value) and passes == [], (message, passes)
        with pytest.raises(ValueError, match=f"^{message}"):
            predictor.predict(image, refine=True, turns=1, mask=empty, **options)
        assert passes == [], (message, passes)  # not even the one pass
    fitted = predictor.refine(image, network, mask=empty, search=SEARCH, refinement=REFINEMENT)
    assert fitted.fit.fitted.tolist() == [False] and passes == [7]  # the 8 turns' 7 copies


def test_load_model_names_an_empty_path_and_an_unusable_device(eval_checkpoint):
    with pytest.raises(ValueError, match=r"^path: empty; give a checkpoint file, or None"):
        load_model("")
    with pytest.raises(ValueError, match=r"^device: 'cudax' is not a torch device"):
        load_model(eval_checkpoint, device="cudax")
    with pytest.raises(ValueError, match=r"^device: 'meta' tensors hold no values"):
        load_model(eval_checkpoint, device="meta")
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"^device: 'cuda:99' is not available"):
            load_model(eval_checkpoint, device="cuda:99")
    else:
        with pytest.raises(ValueError, match=r"^device: 'cuda' is not available \(") as info:
            load_model(eval_checkpoint, device="cuda")
        assert "\n" not in str(info.value) and "device='cpu'" in str(info.value)


# --- minors: Assembly -------------------------------------------------------------------


@pytest.fixture
def assembly():
    return Assembly.from_values(torch.full((1, 2, 3), 0.2), torch.full((1, 2, 2), 0.5))


def test_assembly_index_and_item_out_of_range_are_one_line_index_errors(assembly, tmp_path):
    with pytest.raises(IndexError, match=r"^index: 5 is out of range for an assembly batch "
                                         r"of 1$"):
        assembly[5]
    assert assembly[-1].batch_size == 1 and assembly[np.int64(0)].batch_size == 1
    assert [a.batch_size for a in Assembly(assembly.params.repeat(3, 1, 1))] == [1, 1, 1]
    for call in (lambda: assembly.save(tmp_path / "a.json", item=3),
                 lambda: assembly.export(tmp_path / "a.glb", item=3),
                 lambda: assembly.to_dict(item=-2)):
        with pytest.raises(IndexError, match=r"^item: -?\d is out of range for an assembly "
                                             r"batch of 1$"):
            call()
    assert list(tmp_path.iterdir()) == []


def test_assembly_files_refuse_unknown_versions_and_suffixes(assembly, tmp_path):
    path = assembly.save(tmp_path / "a.json")
    data = json.loads(path.read_text())
    for version in (99, None, "1", True):
        data["version"] = version
        path.write_text(json.dumps(data))
        with pytest.raises(ValueError, match=rf"^{path}: version: {version!r} is not an "
                                             "assembly format version"):
            Assembly.load(path)
    with pytest.raises(ValueError, match=r"path: .*s\.glb is not a \.json file .*use "
                                         r"export\(\)"):
        assembly.save(tmp_path / "s.glb")
    assert not (tmp_path / "s.glb").exists()


def test_assembly_write_errors_name_the_target_not_the_temporary_file(assembly, tmp_path):
    (tmp_path / "file").write_text("not a folder")
    for write, name in ((assembly.export, "m.glb"), (assembly.save, "m.json")):
        target = tmp_path / "file" / name
        with pytest.raises(OSError) as info:
            write(target)
        text = str(info.value)
        assert text.startswith(f"{target}: cannot write (") and ".tmp" not in text, text


# --- minors: files, cameras, conflicting options ------------------------------------------


def test_float_images_and_masks_with_pixels_not_finite_are_refused(eval_checkpoint, tmp_path,
                                                                   capsys):
    """A float TIFF with a NaN or an infinite pixel, as an image or a mask, is one line naming
    it before any work (clipping would silently make it black or white)."""
    from PIL import Image

    from sq_mitsuba.data.masks import read_gray_image, read_mask

    good = np.full((16, 16), 0.25, np.float32)
    Image.fromarray(good, mode="F").save(tmp_path / "good.tiff")
    assert read_gray_image(tmp_path / "good.tiff") == pytest.approx(np.full((16, 16), 0.25))
    for name, value in (("nan.tiff", np.nan), ("inf.tiff", np.inf)):
        bad = good.copy()
        bad[3, 4] = value
        Image.fromarray(bad, mode="F").save(tmp_path / name)
        with pytest.raises(ValueError, match=f"^image {tmp_path / name}: 1 pixel"):
            read_gray_image(tmp_path / name)
        with pytest.raises(ValueError, match=f"^mask {tmp_path / name}: 1 pixel"):
            read_mask(tmp_path / name)
    out = tmp_path / "out"
    Image.fromarray(np.full((64, 64), 90, np.uint8)).save(tmp_path / "first.png")
    assert main(["predict", str(tmp_path / "first.png"), str(tmp_path / "nan.tiff"),
                 "--checkpoint", str(eval_checkpoint), "--out", str(out), "--quiet"]) == 2
    assert f"image {tmp_path / 'nan.tiff'}: 1 pixel(s) not finite" in error_line(capsys)
    assert not out.exists()


def test_a_mask_all_background_or_all_target_is_refused_in_one_line(tmp_path):
    """Neither has an outline to fit; an all-white mask is most often one with black and
    white swapped. One target pixel, or one background pixel, is a mask."""
    from PIL import Image

    from sq_mitsuba.data.masks import read_mask

    for value, message in ((0, "empty"), (255, "full")):
        pixels = np.full((16, 16), value, np.uint8)
        Image.fromarray(pixels).save(tmp_path / f"{message}.png")
        with pytest.raises(ValueError, match=rf"^mask {tmp_path / message}\.png: {message} "):
            read_mask(tmp_path / f"{message}.png")
        pixels[3, 4] = 255 - value
        Image.fromarray(pixels).save(tmp_path / f"{message}.png")
        if value:  # target on every border pixel: read, and warned as swapped
            with pytest.warns(UserWarning, match="100% of its border is target"):
                assert int(read_mask(tmp_path / f"{message}.png").sum()) == 255
        else:
            assert int(read_mask(tmp_path / f"{message}.png").sum()) == 1


def test_an_obj_with_a_face_past_its_vertices_or_a_nan_vertex_is_one_line(tmp_path):
    from sq_mitsuba.data.mesh_io import read_obj

    path = tmp_path / "bad.obj"
    triangle = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"
    for text, message in ((triangle + "f 1 2 3\nf 1 2 7\n", ": triangle 1 refers to a vertex it "
                                                            "does not have (the file has 3"),
                          (triangle + "f 1 2 -4\n", ":4: a relative face index reaches before"),
                          (triangle.replace("v 1 0 0", "v nan 0 0") + "f 1 2 3\n",
                           ": a vertex is not finite")):
        path.write_text(text)
        with pytest.raises(ValueError, match=re.escape(f"{path}{message}")):
            read_obj(path)
    path.write_text(triangle + "f 1 2 3\nf -1 -2 -3\n")  # negative indices count from the end
    assert read_obj(path)[1].tolist() == [[0, 1, 2], [2, 1, 0]]


def test_a_folder_is_reported_as_a_folder(eval_checkpoint, tmp_path, capsys):
    from sq_mitsuba.data.masks import read_gray_image
    from sq_mitsuba.data.mesh_io import read_obj

    folder = tmp_path / "photos.png"
    folder.mkdir()
    with pytest.raises(IsADirectoryError, match=f"^image {folder}: is a folder, not a file$"):
        read_gray_image(folder)
    device = Path("/dev/null")  # exists, but not a file: reading a device may never end
    if device.exists():
        with pytest.raises(ValueError, match=r"^image /dev/null: not a regular file"):
            read_gray_image(device)
    with pytest.raises(IsADirectoryError, match=f"^{folder}: is a folder, not a mesh file$"):
        read_obj(folder)
    out = tmp_path / "out"
    assert main(["predict", str(folder), "--checkpoint", str(eval_checkpoint), "--out",
                 str(out), "--quiet"]) == 2
    assert f"image {folder}: is a folder" in error_line(capsys)
    assert not out.exists()


def test_a_multi_frame_gif_is_refused(eval_checkpoint, tmp_path, capsys):
    frames = [Image.fromarray(np.full((32, 32), level, np.uint8)) for level in (0, 200)]
    gif = tmp_path / "movie.gif"
    frames[0].save(gif, save_all=True, append_images=frames[1:])
    out = tmp_path / "out"
    assert main(["predict", str(gif), "--checkpoint", str(eval_checkpoint), "--out", str(out),
                 "--quiet"]) == 2
    assert f"image {gif}: holds 2 frames" in error_line(capsys)
    assert not out.exists()


SPEED = {"Nu": 256, "Nv": 256, "ppx": 4.4e-5, "ppy": 4.4e-5, "fx": 0.0176, "fy": 0.0176,
         "cameraMatrix": [[400.0, 0.0, 128.0], [0.0, 400.0, 128.0], [0.0, 0.0, 1.0]],
         "distCoeffs": [0, 0, 0, 0, 0]}


@pytest.mark.parametrize(("change", "message"), [
    ({"cameraMatrix": [[400.0, 2.0, 128.0], [0.0, 400.0, 128.0], [0.0, 0.0, 1.0]]},
     r"cameraMatrix\[0\]\[1\] \(the skew\) is 2"),
    ({"distCoeffs": [-0.22, 0.51, 0.0, 0.0, -0.13]}, r"distCoeffs .* describe a lens "
                                                     "distortion"),
    ({"cameraMatrix": [[400.0, 0.0, 128.0], [0.0, 400.0, 128.0], [0.0, 0.0, 2.0]]},
     r"cameraMatrix's last row is \[0.0, 0.0, 2.0\]; an intrinsic matrix's is \[0, 0, 1\]"),
    ({"cameraMatrix": [["400", 0.0, 128.0], [0.0, 400.0, 128.0], [0.0, 0.0, 1.0]]},
     r"cameraMatrix\[0\]\[0\] must be a number, got '400' \(a string"),
    ({"fx": 0.02}, r"fx / ppx = 454.545 px, but cameraMatrix\[0\]\[0\] = 400 px; the matrix "
                   "is what is read: make the two agree, or remove fx"),
    ({"ccy": 100}, r"ccy = 100 px, but cameraMatrix\[1\]\[2\] = 128 px"),
    ({"Nu": 256.5}, r"Nu must be a whole number of pixels, got 256.5"),
    ({"Nv": "256"}, r"Nv must be a number, got '256' \(a string"),
])
def test_predict_refuses_a_camera_it_would_misread(eval_checkpoint, tmp_path, capsys, change,
                                                   message):
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({**SPEED, **change}))
    with pytest.raises(ValueError, match=f"^{camera}: {message}"):
        Camera.load(camera)
    image = tmp_path / "image.png"
    Image.fromarray(np.zeros((256, 256), np.uint8)).save(image)
    out = tmp_path / "out"
    assert main(["predict", str(image), "--checkpoint", str(eval_checkpoint), "--camera",
                 str(camera), "--out", str(out), "--quiet"]) == 2
    line = error_line(capsys)
    assert str(camera) in line and "\n" not in line
    assert not out.exists()


def test_a_zero_distortion_and_whole_float_sizes_are_fine():
    camera = Camera.from_speed_dict({**SPEED, "Nu": 256.0, "distCoeffs": [0.0] * 5})
    assert camera == Camera(400.0, 400.0, 128.0, 128.0, 256, 256)


@pytest.mark.parametrize(("extra", "needle"), [
    (["--no-refine", "--set", "refine=true"], "--set refine=true: refine is also given by "
                                              "--refine / --no-refine; give it once"),
    (["--level", "2", "--set", "level=3"], "--set level=3: level is also given by --level"),
    (["--set", "search.grid=64", "--set", "search.grid=128"],
     "--set search.grid=128: search.grid is also given by --set search.grid=64"),
])
def test_predict_refuses_an_option_given_twice(eval_checkpoint, tmp_path, capsys, extra,
                                               needle):
    image = tmp_path / "image.png"
    Image.fromarray(np.zeros((64, 64), np.uint8)).save(image)
    out = tmp_path / "out"
    assert main(["predict", str(image), "--checkpoint", str(eval_checkpoint), "--out",
                 str(out), *extra, "--quiet"]) == 2
    assert needle in error_line(capsys)
    assert not out.exists()


@pytest.mark.parametrize(("argv", "needle"), [
    (["fit", "--masks", "m.png", "--poses", "p.json", "--out", "o", "--steps", "5", "--set",
      "steps=7"], "--set steps=7: steps is also given by --steps; give it once"),
    (["eval", "--checkpoint", "c.pt", "--data", "d", "--out", "o", "--refine", "--set",
      "refine=false"], "--set refine=false: refine is also given by --refine / --no-refine"),
    (["eval", "--checkpoint", "c.pt", "--data", "d", "--out", "o", "--set", "search.grid=64",
      "--set", "search=null"], "--set search=null: search.grid is also given by --set"),
])
def test_every_command_refuses_a_field_given_twice(tmp_path, monkeypatch, capsys, argv, needle):
    """A field set by its option and by --set (or by --set twice) is one line before any
    work, in every command: the later would silently win."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert needle in error_line(capsys)
    assert not (tmp_path / "o").exists()


def test_eval_names_a_dataset_folder_that_is_not_there(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    for data, message in ((tmp_path / "absent", "dataset folder not found"),
                          (tmp_path / "file", "not a folder (a dataset is a folder)")):
        assert main(["eval", "--data", str(data), "--out", str(tmp_path / "o"), "--quiet"]) == 2
        assert error_line(capsys).endswith(f"{data}: {message}")
        assert main(["train", "--config", str(Path(__file__).parents[1] / "train" / "configs"
                                              / "tiny.toml"), "--data", str(data), "--out",
                     str(tmp_path / "t")]) == 2
        assert error_line(capsys).endswith(f"{data}: {message}")
    assert not (tmp_path / "o").exists() and not (tmp_path / "t").exists()


@pytest.mark.parametrize("label", ["a\nb", "a|b", " "])
def test_eval_refuses_a_label_that_would_break_the_reports_tables(tmp_path, monkeypatch, capsys,
                                                                 label):
    monkeypatch.chdir(tmp_path)
    assert main(["eval", "--checkpoint", "c.pt", "--data", "d", "--out", "o", "--label",
                 label]) == 2
    assert "expected one line without '|'" in error_line(capsys)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("quaternion", "translation", "needle"), [
    ([2.0, 0.0, 0.0, 0.0], [0.0, 0.0, 2.0], "q_vbs2tango_true has norm 2, not 1"),
    ([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1e9], "puts the object at z = 1e+09 m"),
    # Beside the image: no assembly at that origin reaches the mask (it fitted IoU 0, exit 0).
    ([1.0, 0.0, 0.0, 0.0], [50.0, 0.0, 10.0], "px beside its mask, where an assembly reaches"),
])
def test_fit_refuses_a_pose_that_is_not_one(tmp_path, capsys, quaternion, translation, needle):
    mask = np.zeros((48, 48), np.uint8)
    mask[14:34, 10:38] = 255
    Image.fromarray(mask).save(tmp_path / "img000000.png")
    labels = tmp_path / "labels.json"
    labels.write_text(json.dumps([{"filename": "img000000.jpg", "q_vbs2tango_true": quaternion,
                                   "r_Vo2To_vbs_true": translation}]))
    out = tmp_path / "out"
    assert main(["fit", "--masks", str(tmp_path / "img000000.png"), "--poses", str(labels),
                 "--out", str(out), "--quiet"]) == 2
    line = error_line(capsys)
    assert str(labels) in line and "img000000" in line and needle in line, line
    assert not out.exists()


# --- minors: a reading of other images ----------------------------------------------------


def test_read_turns_and_refine_refuse_a_reading_of_other_images(scenes, shipped,
                                                                eval_checkpoint):
    """The prediction stores a fingerprint of the network's input (8 x 8 block means), so
    ``read_turns`` and ``refine`` tell a reading of other images of the same shape and camera;
    the same pixels as uint8 or float are the same images."""
    images, other = scenes["spacecraft"][:2], scenes["spacecraft"][2:4]
    reading = shipped.predict(images)
    assert reading.fingerprint.shape == (2, 1, 8, 8)
    shipped.read_turns(images.astype(np.float32) / 255, reading, 2)  # the same images
    with pytest.raises(ValueError, match=r"^prediction: a reading of other images than these "
                                         r"2 \(its fingerprint differs\)"):
        shipped.read_turns(other, reading, 2)
    tiny = load_model(eval_checkpoint)
    network = tiny.predict(other)
    with pytest.raises(ValueError, match=r"^network: a reading of other images than these 2"):
        tiny.refine(images, network)


def test_pixels_a_viewer_would_show_otherwise_are_read_as_stored_with_a_warning(tmp_path):
    """An EXIF orientation is not applied (a camera calibrated on the sensor's raster stays
    the image's camera), and a 16-bit file holding 12-bit data is read on the 16-bit range:
    both say so in one line, and the pixels are the file's own."""
    from sq_mitsuba.data.masks import read_gray_image

    pixels = np.zeros((24, 32), np.uint8)
    pixels[4:10, 6:20] = 200
    image = Image.fromarray(pixels)
    exif = image.getexif()
    exif[274] = 6  # a phone held upright: the viewer turns the stored pixels 90 deg clockwise
    image.save(tmp_path / "portrait.jpg", exif=exif, quality=100)
    with pytest.warns(UserWarning, match=r"portrait.jpg: its EXIF orientation \(turned 90 deg "
                                         r"clockwise\) is not applied: read as stored, 32 x 24 px"):
        read = read_gray_image(tmp_path / "portrait.jpg")
    assert read.shape == (24, 32) and read[6, 10] > 0.7 and read[20, 28] < 0.05
    twelve = np.zeros((16, 16), np.uint16)
    twelve[4:12, 4:12] = 4000  # bright in 12 bits, 6 % of 16
    Image.fromarray(twelve).save(tmp_path / "twelve.png")
    with pytest.warns(UserWarning, match="a 16-bit image whose brightest pixel is 4000 of 65535"):
        assert read_gray_image(tmp_path / "twelve.png").max() == pytest.approx(4000 / 65535)
    with warnings.catch_warnings():  # a full 16-bit image and a plain 8-bit one: no word
        warnings.simplefilter("error")
        Image.fromarray(twelve * 16).save(tmp_path / "sixteen.png")
        read_gray_image(tmp_path / "sixteen.png")
        Image.fromarray(pixels).save(tmp_path / "plain.jpg")
        read_gray_image(tmp_path / "plain.jpg")


def test_a_file_that_is_no_torch_file_says_so(tmp_path):
    """torch's own error for a text file is a pickle opcode's "KeyError: 101"; an empty file
    and a text file are named for what they are."""
    from sq_mitsuba.inputs import load_torch_file

    (tmp_path / "notes.pt").write_text("epoch 3, loss 0.2\n")
    (tmp_path / "empty.pt").write_bytes(b"")
    with pytest.raises(ValueError, match=r"notes.pt: not a readable checkpoint \(not a torch "
                                         r"file: it starts with b'epoch 3,'\)$"):
        load_torch_file(tmp_path / "notes.pt", "checkpoint")
    with pytest.raises(ValueError, match=r"empty.pt: not a readable checkpoint \(an empty "
                                         r"file\)$"):
        load_torch_file(tmp_path / "empty.pt", "checkpoint")


def test_a_protocol_0_pickle_is_still_named_as_refused_by_the_safe_loader(tmp_path):
    """A text-looking file that is a pickle (protocol 0) keeps the safe loader's reason."""
    import pickle

    from sq_mitsuba.inputs import load_torch_file

    (tmp_path / "old.pt").write_bytes(pickle.dumps(slice(1, 2), protocol=0))
    with pytest.raises(ValueError, match=r"old.pt: not a readable checkpoint \(refused by the "
                                         r"safe loader"):
        load_torch_file(tmp_path / "old.pt", "checkpoint")


# --- what a new user of the API got wrong (a user review, 2026-12-01) -------------------------


def test_a_colour_image_is_refused_with_the_mean_as_the_hint_and_channels_warned():
    """(H, W, 3), (1, H, W, 3) and (1, 3, H, W) cannot be grey batches: refused, naming the
    channels' axis and the mean to take. (3, H, W) can (three grey images), so it is read as
    such, but warned where the three are as alike as one picture's channels; three views of
    a scene are not warned."""
    rgb = np.random.default_rng(0).random((32, 40, 3)).astype(np.float32)
    rgba = torch.from_numpy(np.concatenate([rgb, np.ones_like(rgb[..., :1])], -1) * 255)
    for array, axis, hint in ((rgb, 2, "images.mean(axis=2)[None]"),
                              (rgb[None], 3, "images.mean(axis=3)"),
                              (rgb.transpose(2, 0, 1)[None], 1, "images.mean(axis=1)"),
                              (rgba.to(torch.uint8), 2, "images[..., :3].float().mean(2)[None] "
                                                        "/ 255")):
        with pytest.raises(ValueError, match=rf"^images: expected shape \(B, H, W\) or \(B, 1, "
                           rf"H, W\) \(grey\), got {re.escape(str(tuple(array.shape)))}: colour "
                           rf"channels along axis {axis}\? give their mean, e.g. "
                           rf"{re.escape(hint)}$"):
            prepare_images(array)
        grey = prepare_images(eval(hint, {"images": array}))  # the hint runs, as grey images
        assert grey.shape[-2:] == (32, 40) and float(grey.max()) <= 1.0
    ramp = torch.linspace(0, 1, 40).expand(32, 40)
    channels = torch.stack([0.9 * ramp, 0.8 * ramp + 0.1, 0.7 * ramp])  # one picture, tinted
    with pytest.warns(UserWarning, match=r"^images: 3 images alike as the channels of one "
                      r"colour image \(shape \(3, 32, 40\) read as \(B, H, W\): 3 grey images\); "
                      r"for one colour image give its mean over the channels, e.g. "
                      r"images.mean\(0\)\[None\]$"):
        assert prepare_images(channels).shape == (3, 1, 32, 40)
    views = torch.stack([ramp, ramp.flip(-1), ramp.flip(-2) ** 2])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert prepare_images(views).shape == (3, 1, 32, 40)


def test_numpy_scalars_count_and_switch_as_python_numbers(shipped, scenes):
    image = scenes["spacecraft"][:1]
    reference = shipped.predict(image, turns=1)
    read = shipped.predict(image, turns=np.int64(1), refine=np.bool_(False))
    assert read.turns == 1 and type(read.turns) is int
    torch.testing.assert_close(read.rotation, reference.rotation, rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"^refine: expected True or False, got 'yes'$"):
        shipped.predict(image, refine="yes")


def test_a_prediction_prints_in_a_line_and_its_items_and_factors_are_named(shipped, scenes):
    prediction = shipped.predict(scenes["spacecraft"][:2])
    text = repr(prediction)
    assert text.startswith("Prediction(2 images of ") and "network reading" in text
    assert "\n" not in text and len(text) < 300  # the dataclass's own repr: 15,000 characters
    assert repr(shipped).startswith("Predictor(source=") and "image_size=96" in repr(shipped)
    with pytest.raises(IndexError, match=r"^item: 5 is out of range for an assembly batch of 2$"):
        prediction.item_assembly(5)
    for number in (torch.tensor(2.5), torch.tensor(2), np.float32(2.5)):  # one number each
        torch.testing.assert_close(prediction.scaled(number).translation,
                                   prediction.scaled(float(number)).translation, rtol=0, atol=0)
    for factor, got in (("2", "'2'"), (torch.ones(3), r"a tensor of shape \(3,\)")):
        with pytest.raises(ValueError, match=rf"^factor: expected one number for the whole "
                           rf"batch \(the target's longest side in metres\), got {got}$"):
            prediction.scaled(factor)


def test_the_pass_names_its_options_and_an_empty_mask_given_before_any_search(shipped, scenes):
    """Options of the wrong type or with a bad field are named as the argument
    (``options``, ``options.steps``); a mask given empty for a frame is refused before any
    frame is searched, naming the mask, not the images (with the masks given)."""
    import inspect

    from sq_mitsuba.inference import SequenceOptions

    assert {"ordered", "mask", "options", "relative_rotations"} <= set(
        inspect.signature(type(shipped).predict_sequence).parameters)
    frames = scenes["spacecraft"][:2]
    with pytest.raises(ValueError, match=r"^options: expected a SequenceOptions, got dict \(build "
                       r"one from it: SequenceOptions\(\*\*d\)\)$"):
        shipped.predict_sequence(frames, options={"steps": 5})
    with pytest.raises(ValueError, match=r"^options\.steps: "):
        shipped.predict_sequence(frames, options=SequenceOptions(steps=0))
    masks = np.zeros((2, *frames.shape[-2:]), np.uint8)
    masks[0, 20:40, 20:40] = 255
    # (After the search an empty mask would be "images: frame 1 has no target in its mask".)
    with pytest.raises(ValueError, match=r"^mask: frame 1's mask holds no target pixel; leave "
                       r"the frame out of the sequence, or give a mask of its target$"):
        shipped.predict_sequence(frames, mask=masks)


def test_rotations_of_two_dtypes_reflections_and_no_rotations_at_all():
    from sq_mitsuba.geometry.metrics import rotation_error_deg
    from sq_mitsuba.geometry.rotation import matrix_to_quaternion, mean_rotation, random_rotations
    from sq_mitsuba.render.silhouette.renderer import assembly_camera_vertices

    rotations = random_rotations(4, torch.Generator().manual_seed(3), torch.float64)
    labels = random_rotations(4, torch.Generator().manual_seed(4), torch.float64)
    mixed = rotation_error_deg(rotations.float(), labels)  # a float32 reading, float64 labels
    assert mixed.dtype == torch.float64
    torch.testing.assert_close(mixed, rotation_error_deg(rotations.float().double(), labels))
    reflection = torch.diag(torch.tensor([1.0, 1.0, -1.0]))[None]
    with pytest.raises(ValueError, match=r"^matrix: not rotation matrices \(a reflection among "
                       r"them: determinant -1\)$"):
        matrix_to_quaternion(reflection)
    with pytest.raises(ValueError, match=r"^matrix: not rotation matrices \(\|R\^T R - I\| up "
                       r"to 3, tolerance 0.001\)$"):
        matrix_to_quaternion(2 * torch.eye(3))
    with pytest.raises(ValueError, match=r"^rotations: expected \(N, 3, 3\) with N >= 1, got "
                       r"\(0, 3, 3\)$"):
        mean_rotation(rotations[:0])
    with pytest.raises(ValueError, match=r"^rotation: not rotation matrices \(\|R\^T R - I\| up "
                       r"to 3"):  # a scaled pose would draw a scaled assembly
        assembly_camera_vertices(Assembly.from_values(torch.full((1, 1, 3), 0.2),
                                                      torch.full((1, 1, 2), 0.5)),
                                 2 * torch.eye(3)[None], torch.tensor([[0.0, 0.0, 3.0]]))
    with pytest.raises(ValueError, match=r"^resolution \(pixels a side\): expected a positive "
                       r"integer, got '256'$"):
        Camera.default("256")
    assert Camera.default(np.int64(256)) == Camera.default(256)
