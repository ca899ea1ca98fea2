"""``sq-mitsuba fit`` end to end on small synthetic masks, and its input errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from sq_mitsuba.cli import main
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import matrix_to_quaternion, random_rotations
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly


@pytest.fixture(scope="module")
def fit_inputs(tmp_path_factory):
    """Two 48 x 48 masks of a box-like superquadric, labels.json and camera.json."""
    root = tmp_path_factory.mktemp("fit_inputs")
    camera = Camera.default(48)
    rotations = random_rotations(2, generator=torch.Generator().manual_seed(2),
                                 dtype=torch.float64)
    translations = torch.tensor([[0.05, 0.0, 2.0], [0.0, -0.05, 2.2]], dtype=torch.float64)
    target = Assembly.from_values(torch.tensor([[[0.4, 0.25, 0.15]]], dtype=torch.float64),
                                  torch.tensor([[[0.1, 0.1]]], dtype=torch.float64))
    with torch.no_grad():
        masks = render_assembly(target, rotations, translations,
                                SilhouetteRenderer(camera, spp=32)) > 0.5
    paths = []
    for index, mask in enumerate(masks):
        path = root / f"img{index:06d}.png"
        Image.fromarray((mask.numpy() * 255).astype(np.uint8)).save(path)
        paths.append(path)
    quaternions = matrix_to_quaternion(rotations)
    labels = [{"filename": f"img{i:06d}.jpg", "q_vbs2tango_true": quaternions[i].tolist(),
               "r_Vo2To_vbs_true": translations[i].tolist()} for i in (1, 0)]
    (root / "labels.json").write_text(json.dumps(labels))
    (root / "camera.json").write_text(json.dumps(camera.to_speed_dict()))
    return root, paths


def test_fit_command_writes_assembly_mesh_and_figure(fit_inputs, tmp_path, capsys):
    root, masks = fit_inputs
    out = tmp_path / "fit"
    code = main(["fit", "--masks", *map(str, masks), "--poses", str(root / "labels.json"),
                 "--camera", str(root / "camera.json"), "--primitives", "1", "--steps", "4",
                 "--resolution", "32", "--out", str(out), "--quiet"])
    assert code == 0
    assert "mean IoU" in capsys.readouterr().out
    assembly = Assembly.load(out / "assembly.json")
    assert assembly.params.shape == (1, 1, 16)
    assert (out / "assembly.glb").read_bytes()[:4] == b"glTF"
    assert (out / "fit.png").read_bytes()[:4] == b"\x89PNG"
    log = json.loads((out / "fit_log.json").read_text())
    assert len(log["final_iou"]) == 2 and len(log["loss_per_step"]) == 4
    from sq_mitsuba.config import from_dict
    from sq_mitsuba.inference.fit import FitOptions

    assert from_dict(FitOptions, log["options"]) == FitOptions(steps=4, resolution=32)
    assert log["masks"] == [str(p) for p in masks] and len(log["iou_per_step"][0]) == 2
    assert Camera.from_speed_dict(log["camera"]) == Camera.load(root / "camera.json")
    assert not list(out.glob(".*tmp*"))  # atomic writes leave no temporary files


def test_default_camera_keeps_square_pixels_at_any_aspect(tmp_path):
    """Without --camera, masks of 48 x 32 px are fitted with the SPEED field of view across
    their width and square pixels (fx = fy), as the SPEED camera's own 1920 x 1200 frames."""
    camera = Camera.from_fov(Camera.default().fov_x_deg, 48, 32)
    target = Assembly.from_values(torch.tensor([[[0.3, 0.2, 0.15]]], dtype=torch.float64),
                                  torch.tensor([[[0.1, 0.1]]], dtype=torch.float64))
    rotation = torch.eye(3, dtype=torch.float64)[None]
    translation = torch.tensor([[0.0, 0.0, 2.5]], dtype=torch.float64)
    with torch.no_grad():
        mask = render_assembly(target, rotation, translation,
                               SilhouetteRenderer(camera, spp=16))[0] > 0.5
    path = tmp_path / "img000000.png"
    Image.fromarray((mask.numpy() * 255).astype(np.uint8)).save(path)
    (tmp_path / "labels.json").write_text(json.dumps([
        {"filename": path.name, "q_vbs2tango_true": [1.0, 0.0, 0.0, 0.0],
         "r_Vo2To_vbs_true": translation[0].tolist()}]))
    out = tmp_path / "fit"
    assert main(["fit", "--masks", str(path), "--poses", str(tmp_path / "labels.json"),
                 "--primitives", "1", "--steps", "1", "--resolution", "24", "--out", str(out),
                 "--quiet"]) == 0
    used = Camera.from_speed_dict(json.loads((out / "fit_log.json").read_text())["camera"])
    assert (used.width, used.height) == (48, 32)
    assert used.fx == pytest.approx(used.fy) == pytest.approx(camera.fx)
    assert used.fov_x_deg == pytest.approx(Camera.default().fov_x_deg)


def test_fit_help_documents_the_input_format(capsys):
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    assert "q_vbs2tango_true" in capsys.readouterr().out


def test_fit_command_input_errors(fit_inputs, tmp_path, capsys):
    root, masks = fit_inputs
    base = ["fit", "--poses", str(root / "labels.json"), "--out", str(tmp_path / "o"),
            "--steps", "1", "--quiet"]
    stray = tmp_path / "other.png"
    Image.fromarray(np.zeros((48, 48), np.uint8)).save(stray)
    assert main([*base, "--masks", str(stray)]) == 2
    assert "no label" in capsys.readouterr().err
    assert main([*base, "--masks", str(tmp_path / "missing.png")]) == 2
    assert "missing.png" in capsys.readouterr().err
    bad_labels = tmp_path / "labels.json"
    bad_labels.write_text(json.dumps([{"filename": masks[0].name, "q_vbs2tango_true": [1, 0],
                                       "r_Vo2To_vbs_true": [0, 0, 2]}]))
    assert main(["fit", "--masks", str(masks[0]), "--poses", str(bad_labels),
                 "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "quaternion" in capsys.readouterr().err
    assert main([*base, "--masks", str(masks[0]), "--primitives", "0"]) == 2
    assert not (tmp_path / "o").exists()
    # An --out inside a dataset (its masks folder, say): refused before any work, so that
    # the dataset does not gain files that `dataset check` then flags.
    data = tmp_path / "data"
    (data / "m" / "masks").mkdir(parents=True)
    (data / "dataset.json").write_text("{}")
    out = data / "m" / "masks"
    assert main(["fit", "--masks", str(masks[0]), "--poses", str(root / "labels.json"),
                 "--out", str(out), "--quiet"]) == 2
    assert capsys.readouterr().err.strip().endswith(
        f"out {out}: inside the dataset folder {data.resolve()}, which fit only reads; write "
        "outside it")
    assert list(out.iterdir()) == []


# ------------------------------------------------------------------ input checks


def test_mask_formats_are_converted_then_thresholded_at_half_range(tmp_path):
    from sq_mitsuba.data.masks import read_mask

    rows, cols = np.mgrid[:20, :30]
    truth = (rows - 9.5) ** 2 / 64 + (cols - 14.5) ** 2 / 144 < 1  # an ellipse
    rgb_object, rgb_background = (200, 100, 250), (100, 120, 90)
    # ITU-R 601 luminance, by hand: 147.0 (object) and 110.6 (background) around 127.5.
    assert 0.299 * 200 + 0.587 * 100 + 0.114 * 250 > 127.5 > 0.299 * 100 + 0.587 * 120 + 0.114 * 90
    rgba = np.full((20, 30, 4), 255, np.uint8)
    rgba[..., 3] = np.where(truth, 255, 0)  # white everywhere; the background is transparent
    images = {
        "binary.png": Image.fromarray(np.where(truth, 255, 0).astype(np.uint8)),
        "edge.png": Image.fromarray(np.where(truth, 128, 127).astype(np.uint8)),
        "bilevel.png": Image.fromarray(truth),
        "rgb.png": Image.fromarray(np.where(truth[..., None], rgb_object,
                                            rgb_background).astype(np.uint8)),
        "rgba.png": Image.fromarray(rgba),
        "deep.png": Image.fromarray(np.where(truth, 32768, 32767).astype(np.uint16)),
        "palette.png": Image.fromarray(np.where(truth, 255, 0).astype(np.uint8)).convert("P"),
    }
    for name, image in images.items():
        image.save(tmp_path / name)
    assert Image.open(tmp_path / "deep.png").mode.startswith("I")  # really 16-bit on disk
    assert Image.open(tmp_path / "rgba.png").mode == "RGBA"
    for name in images:
        mask = read_mask(tmp_path / name)
        assert mask.dtype == np.bool_ and np.array_equal(mask, truth), name
    # Black and white swapped (the target black on white): read as given, and warned.
    Image.fromarray(np.where(truth, 0, 255).astype(np.uint8)).save(tmp_path / "swapped.png")
    with pytest.warns(UserWarning, match=r"swapped\.png: 100% of its border is target \(black "
                      r"and white swapped\? the target is white on black\)$"):
        assert np.array_equal(read_mask(tmp_path / "swapped.png"), ~truth)


def _refused(capsys, argv, out, *needles):
    """The command exits 2 with one line on stderr holding ``needles``, writing nothing."""
    assert main([*argv, "--out", str(out), "--quiet"]) == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1, captured.err
    assert captured.err.startswith("sq-mitsuba fit: error: ")
    for needle in needles:
        assert needle in captured.err, (needle, captured.err)
    assert captured.out == ""
    assert not out.exists()
    return captured.err


def test_bad_masks_are_refused_naming_the_file(fit_inputs, tmp_path, capsys):
    root, masks = fit_inputs
    poses = ["--poses", str(root / "labels.json")]
    out = tmp_path / "out"
    work = tmp_path / "masks"
    work.mkdir()
    empty = work / "img000000.png"
    Image.fromarray(np.zeros((48, 48), np.uint8)).save(empty)
    _refused(capsys, ["fit", "--masks", str(masks[1]), str(empty), *poses], out,
             str(empty), "empty")

    small = work / "img000001.png"
    Image.fromarray(np.pad(np.full((32, 40), 255, np.uint8), 4)).save(small)
    _refused(capsys, ["fit", "--masks", str(masks[0]), str(small), *poses], out,
             str(masks[0]), "48 x 48", str(small), "48 x 40")

    # Two masks of one stem would be fitted at one label's pose.
    twin = work / "img000000.png"
    twin.write_bytes(masks[1].read_bytes())
    _refused(capsys, ["fit", "--masks", str(masks[0]), str(twin), *poses], out,
             f"masks {masks[0]} and {twin}: one file stem 'img000000'")

    corrupt = work / "img000000.png"
    corrupt.write_bytes(masks[0].read_bytes()[:-40])  # cut inside the image data
    err = _refused(capsys, ["fit", "--masks", str(corrupt), *poses], out, str(corrupt),
                   "corrupt")
    assert "truncated" in err or "broken" in err

    corrupt.write_text("not a PNG at all")
    _refused(capsys, ["fit", "--masks", str(corrupt), *poses], out, str(corrupt),
             "not an image")


def test_bad_labels_are_refused_naming_file_and_entry(fit_inputs, tmp_path, capsys):
    root, masks = fit_inputs
    out = tmp_path / "out"
    labels = json.loads((root / "labels.json").read_text())
    assert labels[1]["filename"] == "img000000.jpg"
    bad = tmp_path / "labels.json"
    for key, value, needle in (("q_vbs2tango_true", [float("nan"), 0, 0, 1], "NaN"),
                               ("r_Vo2To_vbs_true", [0.0, 2.0], "3 numbers"),
                               ("q_vbs2tango_true", [0, 0, 0, 0], "zero norm"),
                               ("r_Vo2To_vbs_true", [0.0, 0.0, -5.0], "not in front")):
        entries = json.loads(json.dumps(labels))
        entries[1][key] = value
        bad.write_text(json.dumps(entries))  # NaN is written as the bare word NaN
        _refused(capsys, ["fit", "--masks", *map(str, masks), "--poses", str(bad)], out,
                 str(bad), "entry 1 ('img000000.jpg')", key, needle)


def test_bad_output_folder_is_refused_before_the_fit(fit_inputs, tmp_path, capsys,
                                                     monkeypatch):
    from sq_mitsuba.apps import fit_run

    root, masks = fit_inputs
    # A fit this long would run for hours: the refusal must come before it. The fit records
    # that it started and fails (a command that reached it would exit 1, not 2).
    started = []

    def fit_assembly(*args, **kwargs):
        started.append(True)
        raise RuntimeError("the fit started")

    monkeypatch.setattr(fit_run, "fit_assembly", fit_assembly)
    argv = ["fit", "--masks", *map(str, masks), "--poses", str(root / "labels.json"),
            "--steps", "1000000"]
    a_file = tmp_path / "taken"
    a_file.write_text("keep me")
    assert main([*argv, "--out", str(a_file), "--quiet"]) == 2
    assert "not a folder" in capsys.readouterr().err and a_file.read_text() == "keep me"
    _refused(capsys, argv, a_file / "sub", str(a_file), "is a file")
    if Path("/proc/self").is_dir():  # not writable, even by root
        _refused(capsys, argv, Path("/proc/sq_mitsuba_fit/out"), "cannot write")
    assert started == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]  # nothing else written


def test_absurd_resolution_and_seed_are_refused(fit_inputs, tmp_path, capsys):
    root, masks = fit_inputs
    argv = ["fit", "--masks", *map(str, masks), "--poses", str(root / "labels.json")]
    out = tmp_path / "out"
    _refused(capsys, [*argv, "--resolution", "100000"], out,
             "resolution: 100000 (100000 x 100000 px, 2 view(s)) needs about", "TiB",
             "this process may use; lower the fit's resolution")
    _refused(capsys, [*argv, "--seed", "-1"], out,
             "--seed: expected a value in [0, 2147483647], got -1")
    _refused(capsys, [*argv, "--seed", str(2**31)], out, "--seed", str(2**31))
    _refused(capsys, [*argv, "--set", "sppp=0"], out, "--set", "sppp")


def test_fit_replaces_only_its_own_files(fit_inputs, tmp_path, capsys):
    """A user's assembly.json in --out was replaced: refused now, in one line, before the fit;
    a folder an earlier fit wrote is fitted into again."""
    root, masks = fit_inputs
    args = ["fit", "--masks", *map(str, masks), "--poses", str(root / "labels.json"),
            "--primitives", "1", "--steps", "2", "--resolution", "32", "--quiet"]
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "assembly.json").write_text('{"mine": 1}')
    assert main([*args, "--out", str(mine)]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "an output of fit, but no earlier fit there wrote" in err
    assert (mine / "assembly.json").read_text() == '{"mine": 1}'
    again = tmp_path / "again"
    assert main([*args, "--out", str(again)]) == 0
    assert main([*args, "--out", str(again)]) == 0  # its own log: replaced
    (again / "fit_log.json").unlink()  # an interrupted fit: its assembly.json says it is ours
    assert main([*args, "--out", str(again)]) == 0
