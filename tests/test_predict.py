"""``sq-mitsuba predict`` end to end on the tiny trained checkpoint: files per image, poses that
are the network's, image formats converted to the same grey input, refinement with given and
segmented masks, the shipped-model path, and one-line errors naming the file."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh
from output_checks import assert_picture, error_line, one_torch_thread  # noqa: F401 (autouse fixture)
from PIL import Image

from sq_mitsuba.cli import main
from sq_mitsuba.evaluation.predict import OUTPUT_SUFFIXES
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.learning import checkpoint as checkpoint_module
from sq_mitsuba.learning.checkpoint import load_model

SMALL_REFINE = ["--set", "refinement.steps=4", "--set", "refinement.patience=4"]


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
    modes = {n: json.loads((out / f"{n}.pose.json").read_text())["image_mode"] for n in names}
    assert modes["grey"] == "L" and modes["rgb"] == "RGB" and modes["alpha"] == "LA"
    assert modes["deep"].startswith("I")


def test_predict_refines_against_a_given_and_a_segmented_mask(eval_checkpoint, inputs,
                                                               tmp_path, capsys):
    given, segmented = tmp_path / "given", tmp_path / "segmented"
    assert main(["predict", str(inputs / "grey.png"), "--checkpoint", str(eval_checkpoint),
                 "--out", str(given), "--refine", "--mask", str(inputs / "mask.png"),
                 *SMALL_REFINE, "--quiet"]) == 0
    assert "refined in" in capsys.readouterr().out
    assert main(["predict", str(inputs / "rgb.png"), "--checkpoint", str(eval_checkpoint),
                 "--out", str(segmented), "--refine", *SMALL_REFINE, "--quiet"]) == 0
    for folder, stem, mask in ((given, "grey", str(inputs / "mask.png")),
                               (segmented, "rgb", "segmented")):
        pose = json.loads((folder / f"{stem}.pose.json").read_text())
        assert pose["refined"] is True and pose["mask"] == mask
        assert pose["iou_after"] >= pose["iou_before"]
        assert np.linalg.norm(pose["q_vbs2tango"]) == pytest.approx(1.0)
        overlay = np.asarray(Image.open(folder / f"{stem}.overlay.png"))
        assert_picture(folder / f"{stem}.overlay.png")
        # The mask outline is drawn in yellow (255, 217, 0).
        assert ((overlay == (255, 217, 0)).all(-1)).any()


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


def test_bad_inputs_are_one_line_naming_the_file(eval_checkpoint, inputs, tmp_path, capsys):
    cases = [
        ([str(inputs / "grey.png"), str(inputs / "cropped.png")], [],
         f"image {inputs / 'cropped.png'}: 64 x 48 px has another aspect ratio"),
        ([str(inputs / "grey.png"), str(tmp_path / "missing.png")], [],
         str(tmp_path / "missing.png")),
        ([str(inputs / "grey.png")], ["--mask", str(inputs / "mask.png")],
         "only used with refinement"),
        ([str(inputs / "grey.png"), str(inputs / "rgb.png")],
         ["--refine", "--mask", str(inputs / "mask.png")], "1 given for 2 images"),
        ([str(inputs / "grey.png")], ["--refine", "--mask", str(inputs / "cropped.png")],
         f"mask {inputs / 'cropped.png'}: 64 x 48 px"),
        ([str(inputs / "grey.png"), str(inputs / "grey.png")], [], "'grey'"),
        ([str(inputs / "grey.png")], ["--camera", str(tmp_path / "nocam.json")],
         f"camera {tmp_path / 'nocam.json'}: no such file"),
    ]
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
