"""``sq-mitsuba predict`` end to end on the tiny trained checkpoint: files per image, poses that
are the network's, image formats converted to the same grey input, refinement with given and
segmented masks, the shipped-model path, and one-line errors naming the file."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from output_checks import assert_picture, error_line, one_torch_thread  # noqa: F401 (autouse fixture)
from PIL import Image

from sq_mitsuba.apps.predict import OUTPUT_SUFFIXES
from sq_mitsuba.cli import main
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.model import checkpoint as checkpoint_module

SMALL_REFINE = ["--set", "refinement.steps=4", "--set", "refinement.patience=4",
                "--set", "search.grid=128", "--set", "search.screen_steps=2"]


@pytest.fixture(scope="module")
def inputs(train_dataset, tmp_path_factory):
    """One 64 px test image of the dataset as 8-bit grey, and the same pixels as RGB, 16-bit
    grey and grey + opaque alpha; its mask; and a 48 px high (other aspect) crop."""
    root = tmp_path_factory.mktemp("predict_inputs")
    model = next(line.split(",")[0] for line in
                 (train_dataset / "splits.csv").read_text().splitlines()
                 if line.endswith(",test"))
    grey = np.asarray(Image.open(train_dataset / model / "images" / "000002.png"))
    mask = np.asarray(Image.open(train_dataset / model / "masks" / "000002.png"))
    Image.fromarray(grey).save(root / "grey.png")
    Image.fromarray(np.repeat(grey[..., None], 3, axis=-1), "RGB").save(root / "rgb.png")
    Image.fromarray(grey.astype(np.uint16) * 257).save(root / "deep.png")  # 16-bit, same values
    Image.fromarray(np.stack([grey, np.full_like(grey, 255)], -1), "LA").save(root / "alpha.png")
    Image.fromarray(mask).save(root / "mask.png")
    Image.fromarray(grey[:48]).save(root / "cropped.png")
    # The middle 48 rows of the image, and the image with the other rows black: what the
    # 64 x 48 image becomes when padded back to the camera's square aspect ratio.
    Image.fromarray(grey[8:56]).save(root / "wide.png")
    Image.fromarray(mask[8:56]).save(root / "wide_mask.png")
    letterbox = grey.copy()
    letterbox[:8] = letterbox[56:] = 0
    Image.fromarray(letterbox).save(root / "letterbox.png")
    letterbox_mask = mask.copy()
    letterbox_mask[:8] = letterbox_mask[56:] = 0
    Image.fromarray(letterbox_mask).save(root / "letterbox_mask.png")
    return root


def test_predict_writes_the_networks_prediction_for_every_format(eval_checkpoint, inputs,
                                                                  tmp_path, capsys):
    names = ["grey", "rgb", "deep", "alpha"]
    out = tmp_path / "out"
    assert main(["predict", *(str(inputs / f"{n}.png") for n in names), "--checkpoint",
                 str(eval_checkpoint), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "ms per image" in printed and printed.count("network") == len(names) + 1
    predictor = load_model(eval_checkpoint)
    grey = torch.from_numpy(np.array(Image.open(inputs / "grey.png")))[None]
    expected = predictor.predict(grey)
    for name in names:
        for suffix in OUTPUT_SUFFIXES:
            assert (out / f"{name}{suffix}").stat().st_size > 0
        assert_picture(out / f"{name}.overlay.png")
        pose = json.loads((out / f"{name}.pose.json").read_text())
        # Every format becomes the same grey input, so the same prediction.
        assert pose["q_vbs2tango"] == pytest.approx(expected.quaternion[0].tolist(), abs=1e-4)
        assert pose["r_Vo2To_vbs"] == pytest.approx(expected.translation[0].tolist(), abs=1e-4)
        assert np.linalg.norm(pose["q_vbs2tango"]) == pytest.approx(1.0)
        assert pose["camera"]["Nu"] == 64 and pose["refined"] is False
        assembly = Assembly.load(out / f"{name}.assembly.json")
        assert torch.allclose(assembly.params.float(), expected.assembly.params[0:1],
                              atol=1e-4)
        glb = trimesh.load(out / f"{name}.glb")
        assert len(glb.geometry) == 2  # one mesh per primitive
        obj = trimesh.load(out / f"{name}.obj", force="mesh")
        assert obj.bounds is not None and len(obj.faces) > 0
    # The same pixels, the same overlay, whatever image was drawn before it (one renderer
    # serves them all, its samples drawn afresh for each image): a pose a last bit apart
    # may move a sample across an edge, the samples running on from image to image moved
    # dozens of edge pixels.
    first = np.asarray(Image.open(out / f"{names[0]}.overlay.png")).astype(int)
    for name in names[1:]:
        other = np.asarray(Image.open(out / f"{name}.overlay.png")).astype(int)
        assert int((other != first).any(axis=-1).sum()) <= 2, name
    modes = {n: json.loads((out / f"{n}.pose.json").read_text())["image_mode"] for n in names}
    assert modes["grey"] == "L" and modes["rgb"] == "RGB" and modes["alpha"] == "LA"
    assert modes["deep"].startswith("I")
    # The overlay's red is the network's silhouette at its pose, drawn the right way up: the
    # assembly rendered here at the image's camera, against the pixels the red tints.
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

    with torch.no_grad():
        drawn = render_assembly(Assembly(expected.assembly.params.double()),
                                expected.rotation.double(), expected.translation.double(),
                                SilhouetteRenderer(predictor.camera, spp=16), 3)[0] > 0.5
    drawn = drawn.numpy()
    overlay = np.asarray(Image.open(out / "grey.overlay.png")).astype(int)
    red = overlay[..., 0] - overlay[..., 1] > 50  # full coverage: 0.45 x 0.85 x 255 = 98
    assert drawn.shape == red.shape and drawn.sum() > 20
    assert (red & drawn).sum() / (red | drawn).sum() > 0.85


def test_predict_refines_against_a_given_and_a_segmented_mask(eval_checkpoint, inputs,
                                                               tmp_path, capsys):
    given, segmented = tmp_path / "given", tmp_path / "segmented"
    assert main(["predict", str(inputs / "grey.png"), "--checkpoint", str(eval_checkpoint),
                 "--out", str(given), "--refine", "--mask", str(inputs / "mask.png"),
                 *SMALL_REFINE, "--quiet"]) == 0
    assert "against the file mask" in capsys.readouterr().out
    assert main(["predict", str(inputs / "rgb.png"), "--checkpoint", str(eval_checkpoint),
                 "--out", str(segmented), "--refine", *SMALL_REFINE, "--quiet"]) == 0
    assert "against the segmentation mask" in capsys.readouterr().out
    for folder, stem, mask, source in ((given, "grey", str(inputs / "mask.png"), "file"),
                                       (segmented, "rgb", "segmentation", "segmentation")):
        pose = json.loads((folder / f"{stem}.pose.json").read_text())
        assert pose["refined"] is True and pose["mask"] == mask
        assert pose["mask_source"] == source  # the tiny model has no mask head
        assert 0 <= pose["search_score"] <= 1 and 0 <= pose["iou_after"] <= 1
        assert 0 < pose["search_ms"] <= pose["refine_ms"]
        assert np.linalg.norm(pose["q_vbs2tango"]) == pytest.approx(1.0)
        overlay = np.asarray(Image.open(folder / f"{stem}.overlay.png"))
        assert_picture(folder / f"{stem}.overlay.png")
        # The mask outline is drawn in yellow (255, 217, 0): the file mask's edge pixels.
        yellow = (overlay == (255, 217, 0)).all(-1)
        assert yellow.any()
        if source == "file":
            from scipy import ndimage

            target = np.asarray(Image.open(inputs / "mask.png")) > 127
            np.testing.assert_array_equal(yellow, target & ~ndimage.binary_erosion(target))


def test_a_target_size_scales_the_files_and_not_the_image(eval_checkpoint, inputs, tmp_path,
                                                          capsys):
    """--target-size L: the network reads every target at unit size, so a target L metres
    long is the scene scaled by L about the camera: the assembly and the translation written
    are L times the unit-size run's, the rotation and the overlay the same. That the scaled
    scene shows the same image is checked here on Mitsuba's silhouettes, not assumed."""
    unit, metric = tmp_path / "unit", tmp_path / "metric"
    for out, extra in ((unit, []), (metric, ["--target-size", "3.5"])):
        assert main(["predict", str(inputs / "grey.png"), "--checkpoint", str(eval_checkpoint),
                     "--out", str(out), "--refine", "--mask", str(inputs / "mask.png"),
                     *SMALL_REFINE, "--quiet", *extra]) == 0
    capsys.readouterr()
    poses = [json.loads((out / "grey.pose.json").read_text()) for out in (unit, metric)]
    assert poses[0]["target_size"] is None and poses[1]["target_size"] == 3.5
    assert "target_size" in poses[1]["convention"]
    assert poses[1]["q_vbs2tango"] == pytest.approx(poses[0]["q_vbs2tango"], abs=1e-9)
    assert poses[1]["r_Vo2To_vbs"] == pytest.approx(
        [3.5 * v for v in poses[0]["r_Vo2To_vbs"]], rel=1e-6)
    small, large = (Assembly.load(out / "grey.assembly.json") for out in (unit, metric))
    torch.testing.assert_close(large.params, small.scaled(3.5).params)
    np.testing.assert_array_equal(np.asarray(Image.open(metric / "grey.overlay.png")),
                                  np.asarray(Image.open(unit / "grey.overlay.png")))
    from sq_mitsuba.geometry.rotation import quaternion_to_matrix
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

    rotation = quaternion_to_matrix(torch.tensor([poses[0]["q_vbs2tango"]],
                                                 dtype=torch.float64))
    translation = torch.tensor([poses[0]["r_Vo2To_vbs"]], dtype=torch.float64)
    renderer = SilhouetteRenderer(load_model(eval_checkpoint).camera, spp=16)
    seen = []
    with torch.no_grad():
        for assembly, factor in ((small, 1.0), (large, 3.5)):
            renderer.reseed(7)  # the same samples for both: the pictures compare pixel by pixel
            seen.append(render_assembly(Assembly(assembly.params.double()), rotation,
                                        factor * translation, renderer, 3)[0])
    assert float(seen[0].sum()) > 20
    torch.testing.assert_close(seen[1], seen[0], atol=1e-3, rtol=0)
    # The network's reading alone (no --refine) is scaled alike.
    for out, extra in ((tmp_path / "unit_network", []),
                       (tmp_path / "metric_network", ["--target-size", "3.5"])):
        assert main(["predict", str(inputs / "grey.png"), "--checkpoint", str(eval_checkpoint),
                     "--out", str(out), "--quiet", *extra]) == 0
    unit_pose, metric_pose = (json.loads((tmp_path / f"{name}_network" / "grey.pose.json")
                                         .read_text()) for name in ("unit", "metric"))
    assert metric_pose["r_Vo2To_vbs"] == pytest.approx(
        [3.5 * v for v in unit_pose["r_Vo2To_vbs"]], rel=1e-6)
    torch.testing.assert_close(
        Assembly.load(tmp_path / "metric_network" / "grey.assembly.json").params,
        Assembly.load(tmp_path / "unit_network" / "grey.assembly.json").scaled(3.5).params)
    for bad in ("0", "-2", "nan", "1e6"):
        assert main(["predict", str(inputs / "grey.png"), "--checkpoint", str(eval_checkpoint),
                     "--out", str(tmp_path / "bad"), "--target-size", bad]) == 2
        assert error_line(capsys).startswith("sq-mitsuba predict: error: --target-size")
    with pytest.raises(SystemExit) as usage:  # not a number: argparse's usage error
        main(["predict", str(inputs / "grey.png"), "--out", str(tmp_path / "bad"),
              "--target-size", "big"])
    assert usage.value.code == 2 and "--target-size" in error_line(capsys)
    assert not (tmp_path / "bad").exists()


def test_predict_without_checkpoint_uses_the_shipped_model(eval_checkpoint, inputs, tmp_path,
                                                           monkeypatch, capsys):
    monkeypatch.setattr(checkpoint_module, "SHIPPED_MODEL", tmp_path / "absent.pt")
    assert main(["predict", str(inputs / "grey.png"), "--out", str(tmp_path / "none")]) == 2
    assert "no trained model is shipped" in error_line(capsys)
    assert not (tmp_path / "none").exists()
    monkeypatch.setattr(checkpoint_module, "SHIPPED_MODEL", eval_checkpoint)
    out = tmp_path / "shipped"
    assert main(["predict", str(inputs / "grey.png"), "--out", str(out), "--quiet"]) == 0
    pose = json.loads((out / "grey.pose.json").read_text())
    assert pose["checkpoint"] == str(eval_checkpoint)
    assert "rotation_hypotheses" not in pose  # a regressing head: its one rotation is the pose


def test_bad_inputs_are_one_line_naming_the_file(eval_checkpoint, inputs, tmp_path, capsys):
    square_camera = tmp_path / "camera.json"
    square_camera.write_text(json.dumps(load_model(eval_checkpoint).camera.to_speed_dict()))
    (tmp_path / "other").mkdir()
    shutil.copy(inputs / "grey.png", tmp_path / "other" / "grey.png")
    shutil.copy(inputs / "grey.png", tmp_path / "other" / "GREY.png")
    cases = [
        ([str(inputs / "grey.png"), str(inputs / "cropped.png")],
         ["--camera", str(square_camera)],
         f"image {inputs / 'cropped.png'}: 64 x 48 px has another aspect ratio"),
        ([str(inputs / "grey.png"), str(tmp_path / "missing.png")], [],
         str(tmp_path / "missing.png")),
        ([str(inputs / "grey.png")], ["--mask", str(inputs / "mask.png")],
         "only used with refinement"),
        ([str(inputs / "grey.png"), str(inputs / "rgb.png")],
         ["--refine", "--mask", str(inputs / "mask.png")], "1 given for 2 images"),
        ([str(inputs / "grey.png")], ["--refine", "--mask", str(inputs / "cropped.png")],
         f"mask {inputs / 'cropped.png'}: 64 x 48 px"),
        ([str(inputs / "grey.png"), str(inputs / "grey.png")], [],
         f"images: {inputs / 'grey.png'} given twice"),
        ([str(inputs / "grey.png"), str(tmp_path / "other" / "grey.png")], [],
         "one file stem 'grey'"),
        # Two names alike but for case are one file where the user copies the outputs to a
        # Mac or a Windows machine: one pose file would replace the other there.
        ([str(inputs / "grey.png"), str(tmp_path / "other" / "GREY.png")], [],
         "file stems 'grey' and 'GREY' alike but for case or Unicode form"),
        ([str(inputs / "grey.png")], ["--camera", str(tmp_path / "nocam.json")],
         f"camera {tmp_path / 'nocam.json'}: no such file"),
    ]
    # The fit's settings without --refine would be ignored: refused, as the API refuses them.
    for setting in ("search.turns=4", "refinement.steps=5", "mask=segmentation"):
        cases.append(([str(inputs / "grey.png")], ["--set", setting],
                      f"--set {setting}: only used with --refine"))
    strip = tmp_path / "strip.png"
    Image.fromarray(np.zeros((8, 64), np.uint8)).save(strip)
    cases.append(([str(strip)], [], f"image {strip}: 64 x 8 px is too far from the camera's"))
    not_an_image = tmp_path / "notes.png"
    not_an_image.write_text("not a picture")
    cases.append(([str(not_an_image)], [], f"image {not_an_image}: not an image"))
    for images, extra, expected in cases:
        out = tmp_path / "out"
        assert main(["predict", *images, "--checkpoint", str(eval_checkpoint), "--out",
                     str(out), *extra, "--quiet"]) == 2
        line = error_line(capsys)
        assert expected in line, line
        assert not out.exists()  # nothing written, not even the folder


def test_an_input_an_output_would_overwrite_is_refused(eval_checkpoint, inputs, tmp_path,
                                                      capsys):
    """Inputs in the output folder named like an output (q.overlay.png beside q.png, an image
    called sequence.png in a pass) are refused before any work and left as they were; an
    empty --out is not taken for the working folder."""
    folder = tmp_path / "work"
    folder.mkdir()
    grey = (inputs / "grey.png").read_bytes()
    for name in ("q.png", "q.overlay.png", "sequence.png", "f2.png"):
        (folder / name).write_bytes(grey)
    runs = [(["q.png", "q.overlay.png"], [], "q.overlay.png: an output of this run would "
                                             "overwrite it"),
            # (a frame named "sequence" is refused first: its files are the pass's names)
            (["sequence.png", "f2.png"], ["--sequence"], "a frame named 'sequence' would "
                                                         "share its files' names")]
    for names, extra, expected in runs:
        before = sorted(p.name for p in folder.iterdir())
        assert main(["predict", *(str(folder / n) for n in names), *extra, "--checkpoint",
                     str(eval_checkpoint), "--out", str(folder), "--quiet"]) == 2
        assert expected in error_line(capsys)
        assert sorted(p.name for p in folder.iterdir()) == before
        assert all((folder / n).read_bytes() == grey for n in names)
    with pytest.raises(SystemExit) as exited:  # argparse's error, as one line
        main(["predict", str(folder / "q.png"), "--checkpoint", str(eval_checkpoint), "--out",
              "", "--quiet"])
    assert exited.value.code == 2
    assert capsys.readouterr().err.strip() == (
        "sq-mitsuba predict: error: argument --out: an empty path; give the output's path "
        "(see sq-mitsuba predict --help)")


def test_other_size_same_aspect_ratio_is_rescaled(eval_checkpoint, inputs, tmp_path):
    grey = Image.open(inputs / "grey.png")
    grey.resize((128, 128), Image.BILINEAR).save(tmp_path / "large.png")
    out = tmp_path / "out"
    assert main(["predict", str(tmp_path / "large.png"), "--checkpoint", str(eval_checkpoint),
                 "--out", str(out), "--quiet"]) == 0
    pose = json.loads((out / "large.pose.json").read_text())
    small = load_model(eval_checkpoint).camera.rescaled(64, 64)
    assert pose["camera"]["Nu"] == 128
    assert pose["camera"]["cameraMatrix"][0][0] == pytest.approx(2 * small.fx)
    with Image.open(out / "large.overlay.png") as overlay:
        assert overlay.size == (128, 128)


@pytest.fixture
def one_drjit_thread():
    """Dr.Jit on one thread for the test: the refinement's backward pass sums silhouette
    gradients with atomic adds, whose rounding depends on how threads interleave (on a busy
    machine), and Adam turns the sign of a near-zero gradient into a full step."""
    from sq_mitsuba.training.step import mitsuba_for

    with mitsuba_for(torch.device("cpu"), deterministic=True):
        yield


def test_other_aspect_ratio_is_padded_with_black_and_reported_for_the_image(
        eval_checkpoint, inputs, tmp_path, one_drjit_thread):
    """Reference: the same picture padded by hand. A 64 x 48 image predicts and refines as
    the 64 x 64 image with 8 black rows above and below it, and its outputs are that image's,
    cut back to the 48 rows: same pose, overlay rows 8-55, camera with cy 8 px less."""
    wide, boxed = tmp_path / "wide", tmp_path / "boxed"
    refine = ["--refine", *SMALL_REFINE, "--quiet"]
    assert main(["predict", str(inputs / "wide.png"), "--checkpoint", str(eval_checkpoint),
                 "--out", str(wide), "--mask", str(inputs / "wide_mask.png"), *refine]) == 0
    assert main(["predict", str(inputs / "letterbox.png"), "--checkpoint",
                 str(eval_checkpoint), "--out", str(boxed), "--mask",
                 str(inputs / "letterbox_mask.png"), *refine]) == 0
    pose = json.loads((wide / "wide.pose.json").read_text())
    reference = json.loads((boxed / "letterbox.pose.json").read_text())
    # The two pictures reach the network equal up to float rounding; the search and the
    # refinement's steps carry that (1e-7) through to a few 1e-6.
    for key in ("q_vbs2tango", "r_Vo2To_vbs", "search_score", "iou_after"):
        assert pose[key] == pytest.approx(reference[key], abs=1e-4), key
    assert (pose["width"], pose["height"], pose["padded_to"]) == (64, 48, [64, 64])
    assert "padded with black to 64 x 64 px" in pose["warning"]
    camera, boxed_camera = pose["camera"], reference["camera"]
    assert (camera["Nu"], camera["Nv"]) == (64, 48)
    assert camera["cameraMatrix"][0] == boxed_camera["cameraMatrix"][0]
    assert camera["cameraMatrix"][1][2] == boxed_camera["cameraMatrix"][1][2] - 8
    overlay = np.asarray(Image.open(wide / "wide.overlay.png"))
    boxed_overlay = np.asarray(Image.open(boxed / "letterbox.overlay.png"))
    assert overlay.shape == (48, 64, 3)
    np.testing.assert_array_equal(overlay, boxed_overlay[8:56])


@pytest.mark.parametrize("size", [(64, 48), (48, 64), (63, 20), (20, 63), (64, 64)])
def test_padding_gives_the_cameras_aspect_ratio_and_keeps_its_pixels(size):
    from sq_mitsuba.apps.padding import padded_camera, padding_to_aspect
    from sq_mitsuba.geometry.camera import Camera

    width, height = size
    for camera in (Camera.default(64), Camera(50.0, 55.0, 31.0, 20.0, 64, 40)):
        padding = padding_to_aspect(width, height, camera)
        if (width, height) == (64, 64) and camera.width == camera.height:
            assert padding is None
            continue
        assert padding is not None
        picture = np.arange(width * height, dtype=np.float32).reshape(height, width) + 1
        padded = padding.pad(picture)
        assert padded.shape == (padding.padded_height, padding.padded_width)
        # Only one side grows, the image sits centred, and cropping undoes the padding.
        assert (padding.padded_width == width) or (padding.padded_height == height)
        assert abs(padding.top - (padding.padded_height - height) / 2) <= 0.5
        assert abs(padding.left - (padding.padded_width - width) / 2) <= 0.5
        np.testing.assert_array_equal(padding.crop(padded), picture)
        assert padded.sum() == picture.sum()
        # The padded picture's camera keeps the camera's field of view across the width and
        # its pixel aspect; the image's own camera sees the same rays through its pixels.
        ratio = padding.padded_width / padding.padded_height
        assert ratio == pytest.approx(camera.width / camera.height, rel=1 / min(width, height))
        full = padded_camera(camera, padding.padded_width, padding.padded_height)
        assert full.fx / full.width == pytest.approx(camera.fx / camera.width, rel=1e-12)
        assert full.fx / full.fy == pytest.approx(camera.fx / camera.fy, rel=1e-12)
        # The principal point at the same fraction of the picture along both axes.
        assert full.cx / full.width == pytest.approx(camera.cx / camera.width, rel=1e-12)
        assert full.cy / full.height == pytest.approx(camera.cy / camera.height, rel=1e-12)
        own = padding.crop_camera(full)
        assert (own.width, own.height) == (width, height)
        assert (own.cx, own.cy) == (full.cx - padding.left, full.cy - padding.top)
        # In pose.json's metres the crop keeps the padded picture's lens and pixel pitch.
        metres, padded_metres = own.to_speed_dict(padding.pixel_pitch_m()), full.to_speed_dict()
        for key in ("fx", "fy", "ppx", "ppy"):
            assert metres[key] == pytest.approx(padded_metres[key], rel=1e-12), key
        assert metres["fx"] / metres["ppx"] == pytest.approx(own.fx, rel=1e-12)


def test_turned_copies_read_the_network_alone(inputs, tmp_path, capsys):
    """``--turns 8`` (the shipped model): pose.json holds ``predict(turns=8)``'s reading, not
    one reading's; with --refine, or a network without a distribution head, one line."""
    from sq_mitsuba.geometry.rotation import quaternion_to_matrix
    from sq_mitsuba.inference.loading import load_model

    out = tmp_path / "turned"
    assert main(["predict", str(inputs / "grey.png"), "--out", str(out), "--turns", "8",
                 "--quiet"]) == 0
    pose = json.loads((out / "grey.pose.json").read_text())
    assert pose["turns"] == 8
    image = torch.from_numpy(np.array(Image.open(inputs / "grey.png"))).float()[None] / 255
    predictor = load_model()
    turned, once = predictor.predict(image, turns=8), predictor.predict(image)
    written = quaternion_to_matrix(torch.tensor(pose["q_vbs2tango"], dtype=torch.float64))

    def angle(a: torch.Tensor, b: torch.Tensor) -> float:
        cos = (float(torch.trace(a.double().T @ b.double())) - 1) / 2
        return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    assert angle(written, turned.rotation[0]) < 0.1
    assert angle(turned.rotation[0], once.rotation[0]) > 0.1
    # The reading's rotation hypotheses, best first, the first its own rotation.
    listed = pose["rotation_hypotheses"]
    assert len(listed) == predictor.hypotheses == turned.rotation_hypotheses.shape[1] > 1
    assert bool((turned.rotation_scores[0] > 0).all())  # 8 separate modes: no padding here
    probabilities = [h["probability"] for h in listed]
    # (the command runs the fast path: its numbers agree to about 1e-5)
    assert probabilities == pytest.approx(turned.rotation_scores[0].tolist(), abs=1e-4)
    assert probabilities == sorted(probabilities, reverse=True) and 0 < sum(probabilities) <= 1
    for h, expected in zip(listed, turned.rotation_hypotheses[0], strict=True):
        assert angle(quaternion_to_matrix(torch.tensor(h["q_vbs2tango"], dtype=torch.float64)),
                     expected) < 0.1
    assert listed[0]["q_vbs2tango"] == pytest.approx(pose["q_vbs2tango"], abs=1e-6)
    # Without --turns the reading is the 8 copies' where the network and camera turn; --turns 1
    # reads the image once.
    assert main(["predict", str(inputs / "grey.png"), "--out", str(tmp_path / "default"),
                 "--quiet"]) == 0
    default = json.loads((tmp_path / "default" / "grey.pose.json").read_text())
    assert default["turns"] == 8 and default["q_vbs2tango"] == pose["q_vbs2tango"]
    assert main(["predict", str(inputs / "grey.png"), "--out", str(tmp_path / "once"),
                 "--turns", "1", "--quiet"]) == 0
    single = json.loads((tmp_path / "once" / "grey.pose.json").read_text())
    assert single["turns"] == 1  # recorded wherever a pose is, 1 included
    assert angle(quaternion_to_matrix(torch.tensor(single["q_vbs2tango"], dtype=torch.float64)),
                 once.rotation[0]) < 0.1
    # With --refine: the hypotheses of the reading the search started from (8 turned copies).
    assert main(["predict", str(inputs / "grey.png"), "--out", str(tmp_path / "refined"),
                 "--refine", *SMALL_REFINE, "--quiet"]) == 0
    refined = json.loads((tmp_path / "refined" / "grey.pose.json").read_text())
    assert refined["refined"] is True and refined["turns"] == 8  # the search's reading
    assert [h["probability"] for h in refined["rotation_hypotheses"]] == pytest.approx(
        probabilities, abs=1e-4)
    assert main(["predict", str(inputs / "grey.png"), "--out", str(tmp_path / "both"),
                 "--turns", "8", "--refine", "--quiet"]) == 2
    assert "turns: 8 is for the network's reading alone" in error_line(capsys)
    assert not (tmp_path / "both").exists()


def test_turned_copies_without_a_distribution_head_are_one_line(eval_checkpoint, inputs,
                                                                tmp_path, capsys):
    assert main(["predict", str(inputs / "grey.png"), "--checkpoint", str(eval_checkpoint),
                 "--out", str(tmp_path / "no"), "--turns", "8", "--quiet"]) == 2
    assert ("turns: reading the rotation from turned copies needs a rotation-distribution "
            "head") in error_line(capsys)
    assert not (tmp_path / "no").exists()
    # By default such a network reads each image once.
    assert main(["predict", str(inputs / "grey.png"), "--checkpoint", str(eval_checkpoint),
                 "--out", str(tmp_path / "once"), "--quiet"]) == 0
    assert json.loads((tmp_path / "once" / "grey.pose.json").read_text())["turns"] == 1


def test_pose_json_leaves_out_the_padding_of_a_short_hypothesis_list():
    """A distribution with fewer separate modes than the predictor lists fills the list with
    rotations of probability 0 (``rotation_grid.rotation_hypotheses``); pose.json keeps the
    real ones, best first, and a regressing head's reading lists none."""
    from types import SimpleNamespace

    from sq_mitsuba.apps.predict import _rotation_hypotheses
    from sq_mitsuba.geometry.so3_grid import so3_grid
    from sq_mitsuba.model.rotation_grid import rotation_hypotheses

    grid = so3_grid(576)
    logits = torch.full((1, len(grid)), -torch.inf)
    logits[0, 10], logits[0, 400] = 2.0, 1.0  # two modes, every other cell impossible
    rotations, scores = rotation_hypotheses(logits, grid, 8)
    assert scores.shape == (1, 8) and int((scores > 0).sum()) == 2
    reading = SimpleNamespace(rotation_log_probabilities=logits.log_softmax(-1),
                              rotation_hypotheses=rotations, rotation_scores=scores)
    listed = _rotation_hypotheses(reading)
    assert [h["probability"] for h in listed] == pytest.approx(
        [1 / (1 + math.exp(-1.0)), 1 / (1 + math.exp(1.0))])
    assert _rotation_hypotheses(SimpleNamespace(rotation_log_probabilities=None)) is None


def test_a_large_images_overlay_silhouette_is_rendered_smaller_and_lands_in_place():
    """An image wider than OVERLAY_MAX_SIDE has its overlay's silhouettes rendered at that
    size and resized back: where the full-size render puts them (the pixel-centre convention
    kept through Camera.rescaled and the resize), to within the edges' pixels."""
    from sq_mitsuba.apps.overlay import OVERLAY_MAX_SIDE, overlay_camera, resized_coverage
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

    camera = Camera.default(256).rescaled(int(1.5 * OVERLAY_MAX_SIDE), OVERLAY_MAX_SIDE)
    small = overlay_camera(camera)
    assert (small.width, small.height) == (OVERLAY_MAX_SIDE, round(OVERLAY_MAX_SIDE / 1.5))
    assert overlay_camera(small) == small  # at or below the size: the camera itself
    params = torch.zeros(1, 2, 16)
    params[0, :, :3] = torch.tensor([[0.5, 0.12, 0.1], [0.1, 0.3, 0.2]])
    params[0, :, 3:5] = 0.2
    params[0, 1, 5:8] = torch.tensor([0.2, 0.1, 0.0])
    params[0, :, 8:14] = torch.tensor([1.0, 0, 0, 0, 1, 0])
    rotation = torch.eye(3)[None]
    translation = torch.tensor([[0.3, -0.2, 4.0]])
    full, reduced = (render_assembly(Assembly(params), rotation, translation,
                                     SilhouetteRenderer(c, spp=4), level=3)[0].numpy()
                     for c in (camera, small))
    resized = resized_coverage(reduced, camera.width, camera.height)
    assert resized.shape == full.shape and resized.dtype == np.float32
    inside, outside = full > 0.5, resized > 0.5
    iou = (inside & outside).sum() / (inside | outside).sum()
    assert iou > 0.97, iou
    # Shifted by two pixels, it would not be: the test can tell a misplaced resize.
    shifted = np.roll(outside, 3, axis=1)
    assert (inside & shifted).sum() / (inside | shifted).sum() < iou - 0.01


def test_the_overlay_blends_as_the_formula_says():
    """overlay_image (float32, in place) against the formula in float64: the image dimmed to
    0.8, each coverage blended in its colour at 45 %, the mask's edge on top."""
    from sq_mitsuba.apps.overlay import MASK_COLOUR, overlay_image

    rng = np.random.default_rng(0)
    image = rng.random((20, 30))
    layers = [(rng.random((20, 30)), (1.0, 0.15, 0.1)), (rng.random((20, 30)), (0.1, 0.9, 0.2))]
    outline = np.zeros((20, 30), bool)
    outline[5:15, 8:22] = True
    expected = np.repeat(image[..., None], 3, axis=-1) * 0.8
    for coverage, colour in layers:
        alpha = 0.45 * coverage[..., None]
        expected = expected * (1 - alpha) + alpha * np.asarray(colour)
    edge = outline.copy()
    edge[6:14, 9:21] = False
    expected[edge] = MASK_COLOUR
    expected = (np.clip(expected, 0, 1) * 255 + 0.5).astype(np.uint8)
    got = overlay_image(image, layers, outline)
    assert got.dtype == np.uint8 and got.shape == (20, 30, 3)
    assert np.abs(got.astype(int) - expected).max() <= 1


def test_a_second_pass_into_one_folder_leaves_nothing_of_the_first(eval_checkpoint, inputs,
                                                                   tmp_path, capsys):
    """Frames of an earlier pass that this one lacks, and a single image's assembly of one of
    its stems, are of another assembly than sequence.assembly.json: removed. Files of single
    images of other stems stay."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("a", "b", "c"):
        shutil.copy(inputs / "grey.png", frames / f"{name}.png")
    out = tmp_path / "out"

    def sequence(*names: str) -> None:
        assert main(["predict", *(str(frames / f"{n}.png") for n in names), "--sequence",
                     "--fit", "steps=2", "--checkpoint", str(eval_checkpoint), "--out",
                     str(out), "--quiet"]) == 0

    sequence("a", "b", "c")
    assert (out / "c.pose.json").is_file() and (out / "c.overlay.png").is_file()
    (out / "a.glb").write_text("a single image's assembly")
    (out / "z.pose.json").write_text(json.dumps({"image": "z.png"}))  # a single image's
    (out / "z.glb").write_text("z's assembly")
    capsys.readouterr()
    sequence("a", "b")
    # c's pose and overlay, and a's single-image GLB: said, not removed silently.
    assert "(and removed 3 of an earlier pass)" in capsys.readouterr().out
    names = {p.name for p in out.iterdir() if not p.name.startswith(".")}
    assert names == {"sequence.assembly.json", "sequence.glb", "sequence.png", "colmap",
                     "a.pose.json", "a.overlay.png", "b.pose.json", "b.overlay.png",
                     "z.pose.json", "z.glb"}, names
    assert json.loads((out / "a.pose.json").read_text())["sequence"]["frames"] == 2


def test_the_summary_averages_refine_times_over_the_refined_images(monkeypatch, tmp_path,
                                                                    capsys):
    """An image without a target is not refined: its zero times are not averaged in."""
    from sq_mitsuba.apps import predict as predict_app
    from sq_mitsuba.apps.predict import PredictRecord

    records = [PredictRecord(Path("a.png"), [], 2.0, refine_ms=3000.0, search_ms=1000.0,
                             mask_source="file", iou_before=0.5, iou_after=0.6),
               PredictRecord(Path("b.png"), [], 2.0, target=False, target_score=0.1)]
    monkeypatch.setattr(predict_app, "predict_images", lambda *args, **kwargs: records)
    assert main(["predict", "a.png", "b.png", "--refine", "--out", str(tmp_path / "o"),
                 "--quiet"]) == 0
    summary = capsys.readouterr().out.splitlines()[-1]
    assert ("search 1000 ms, search + refinement 3000 ms per refined image; 1 without a "
            "target") in summary, summary


def test_a_run_stopped_between_an_images_files_leaves_no_old_pose_beside_new_ones(
        eval_checkpoint, inputs, tmp_path, monkeypatch, capsys):
    """A rerun that fails while exporting an image's GLB (a full disk, an interrupt) must not
    leave the first run's pose.json beside its new assembly: the pose goes first and is
    written last, as the mark of a complete set."""
    out = tmp_path / "out"
    run = ["predict", str(inputs / "grey.png"), "--checkpoint", str(eval_checkpoint),
           "--out", str(out), "--quiet"]
    assert main(run) == 0
    assert (out / "grey.pose.json").is_file()
    real_export = Assembly.export

    def failing_export(self, path, *args, **kwargs):
        if str(path).endswith(".glb"):
            raise OSError(28, "No space left on device")
        return real_export(self, path, *args, **kwargs)

    monkeypatch.setattr(Assembly, "export", failing_export)
    assert main([*run, "--target-size", "2"]) != 0
    capsys.readouterr()
    assert (out / "grey.assembly.json").is_file()  # the new run's, written before the GLB
    assert not (out / "grey.pose.json").exists()
    monkeypatch.setattr(Assembly, "export", real_export)
    assert main([*run, "--target-size", "2"]) == 0
    assert json.loads((out / "grey.pose.json").read_text())["image"].endswith("grey.png")


def test_options_and_output_are_checked_before_any_image_is_decoded(eval_checkpoint, tmp_path,
                                                                    capsys, monkeypatch):
    """A wrong option is said before every image is decoded (over thousands of full-size
    frames that took minutes): no image is read for it."""
    import sq_mitsuba.apps.predict as predict_module

    def no_decoding(*args, **kwargs):
        raise AssertionError("images decoded before the options were checked")

    monkeypatch.setattr(predict_module, "_check_inputs", no_decoding)
    image = tmp_path / "a.png"
    Image.fromarray(np.zeros((64, 64), np.uint8)).save(image)
    assert main(["predict", str(image), "--refine", "--turns", "4", "--checkpoint",
                 str(eval_checkpoint), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert "turns: 4 is for the network's reading alone" in error_line(capsys)
    (tmp_path / "file").write_text("a file, not a folder")
    assert main(["predict", str(image), "--checkpoint", str(eval_checkpoint), "--out",
                 str(tmp_path / "file"), "--quiet"]) == 2
    assert str(tmp_path / "file") in error_line(capsys)
