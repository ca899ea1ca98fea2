"""Every bad input is one clear line: the cases of a trial of 323 bad inputs over the commands.

Each case runs the command as a user would and asserts: a non-zero exit (2 for bad input; 1
where a batch command reports a failed item), one line on stderr naming the file or option, no
traceback (``main`` returns), no torch advice to load files unsafely, and nothing left in
``--out`` beyond what was there before. The readers behind them live in
:mod:`sq_mitsuba.inputs` (images, torch files, cameras, tables) and the cleanup in
:mod:`sq_mitsuba.outputs`; the unit tests of both are at the end.
"""

from __future__ import annotations

import json
import os
import pickle
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from output_checks import error_line, one_torch_thread  # noqa: F401 (autouse fixture)
from PIL import Image

from sq_mitsuba.cli import main
from sq_mitsuba.evaluation.report import PAPER_TABLES
from sq_mitsuba.evaluation.scoring import METRICS
from sq_mitsuba.evaluation.tables import write_tables
from sq_mitsuba.io import atomic_path, atomic_write_json

ROOT = Path(__file__).resolve().parents[1]


class _Hostile:
    """Unpickling it would create the folder ``marker``: proof that a loader ran code."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (os.makedirs, (self.marker,))


def _run(capsys, argv, code=2):
    """Run ``sq-mitsuba argv``; returns its one error line (asserting the exit code)."""
    assert main([str(a) for a in argv]) == code
    line = error_line(capsys)
    assert "Traceback" not in line and "weights_only" not in line, line
    return line


def _entries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []


@pytest.fixture(scope="module")
def bad(eval_checkpoint, train_dataset, tmp_path_factory):
    """Bad and good input files, made once: checkpoints (NaN weights, hostile, raw pickle,
    random bytes), a 1 x 1 image and mask, a good 64 px image, a model library."""
    root = tmp_path_factory.mktemp("bad_inputs")
    payload = torch.load(eval_checkpoint, weights_only=True)
    key = next(k for k, v in payload["model"].items() if v.is_floating_point())
    payload["model"][key] = payload["model"][key].clone()
    payload["model"][key].view(-1)[0] = float("nan")
    torch.save(payload, root / "nan.pt")
    torch.save({"weights": _Hostile(root / "PWNED")}, root / "hostile.pt")
    (root / "raw.pt").write_bytes(pickle.dumps({"weights": [1.0, 2.0]}))
    (root / "random.pt").write_bytes(np.random.default_rng(0).bytes(4096))
    Image.fromarray(np.full((1, 1), 255, np.uint8)).save(root / "tiny.png")
    test_model = next(line.split(",")[0] for line in
                      (train_dataset / "splits.csv").read_text().splitlines()
                      if line.endswith(",test"))
    shutil.copyfile(train_dataset / test_model / "images" / "000002.png", root / "image.png")
    library = root / "library"
    shutil.copytree(train_dataset / test_model / "models", library / test_model / "models")
    (library / "splits.csv").write_text(f"{test_model},test\n")
    return root


# ------------------------------------------------------------------------- checkpoints


CHECKPOINT_COMMANDS = {
    "eval": lambda pt, data, bad, out: ["eval", "--checkpoint", pt, "--data", data,
                                        "--out", out, "--quiet"],
    "predict": lambda pt, data, bad, out: ["predict", bad / "image.png", "--checkpoint", pt,
                                           "--out", out, "--quiet"],
    "study": lambda pt, data, bad, out: ["study", "illumination", "--checkpoint", pt,
                                         "--models", bad / "library", "--out", out, "--quiet"],
    "demo": lambda pt, data, bad, out: ["demo", "--size", "tiny", "--checkpoint", pt,
                                        "--out", out, "--quiet"],
    "export": lambda pt, data, bad, out: ["export", "--checkpoint", pt, "--out", out / "m.pt"],
}
CHECKPOINTS = {"nan.pt": "hold NaN or infinite values (first: ",
               "hostile.pt": "refused by the safe loader",
               "raw.pt": "refused by the safe loader",
               "random.pt": "not a readable checkpoint"}


@pytest.mark.parametrize("name", CHECKPOINTS)
@pytest.mark.parametrize("command", CHECKPOINT_COMMANDS)
def test_unusable_checkpoint_is_one_line_naming_it(command, name, bad, train_dataset, tmp_path,
                                                   capsys):
    out = tmp_path / "out"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        line = _run(capsys, CHECKPOINT_COMMANDS[command](bad / name, train_dataset, bad, out))
    assert f"{bad / name}: " in line and CHECKPOINTS[name] in line, line
    assert not caught, [str(w.message) for w in caught]  # no torch warning about pickles
    assert not out.exists()
    assert not (bad / "PWNED").exists()


@pytest.mark.parametrize("name", ["hostile.pt", "raw.pt", "random.pt"])
def test_pretrained_weights_that_are_no_weights_are_one_line(name, bad):
    try:  # where the network's ImageNet loader lives
        from sq_mitsuba.model.pretrained import load_imagenet_weights
    except ImportError:
        from sq_mitsuba.model.encoder import load_imagenet_weights

    with pytest.raises(ValueError) as raised:
        load_imagenet_weights(torch.nn.Module(), bad / name)  # the file fails before the model
    message = str(raised.value)
    assert message.startswith(f"{bad / name}: not a readable ImageNet weights (")
    assert "\n" not in message and "weights_only" not in message
    assert not (bad / "PWNED").exists()


def test_train_with_hostile_pretrained_weights_is_one_line(bad, train_dataset, tmp_path, capsys):
    # What train leaves in --out on this error (a cache built first) is the trainer's part.
    line = _run(capsys, ["train", "--config", ROOT / "train" / "configs" / "tiny.toml",
                         "--data", train_dataset, "--out", tmp_path / "run", "--quiet",
                         "--set", f"network.pretrained={json.dumps(str(bad / 'hostile.pt'))}",
                         "--max-steps", "1"])
    assert f"{bad / 'hostile.pt'}: not a readable ImageNet weights" in line
    assert not (bad / "PWNED").exists()


# ------------------------------------------------------------------------------ images


def test_images_below_the_size_floor_are_refused(bad, eval_checkpoint, tmp_path, capsys):
    tiny = bad / "tiny.png"
    floor = "1 x 1 px is below the smallest image size, 8 x 8 px"
    for extra in ([], ["--refine"], ["--refine", "--mask", tiny]):
        out = tmp_path / "predict"
        line = _run(capsys, ["predict", tiny, "--checkpoint", eval_checkpoint, "--out", out,
                             "--quiet", *extra])
        assert f"image {tiny}: {floor}" in line
        assert not out.exists()
    mask = tmp_path / "img000000.png"
    shutil.copyfile(tiny, mask)
    (tmp_path / "labels.json").write_text(json.dumps([{
        "filename": "img000000.jpg", "q_vbs2tango_true": [1, 0, 0, 0],
        "r_Vo2To_vbs_true": [0, 0, 2]}]))
    line = _run(capsys, ["fit", "--masks", mask, "--poses", tmp_path / "labels.json",
                         "--out", tmp_path / "fit", "--quiet"])
    assert f"mask {mask}: {floor}" in line
    assert not (tmp_path / "fit").exists()


def test_large_images_read_without_pils_warning_up_to_the_stated_bound(tmp_path, monkeypatch):
    from PIL import Image as PILImage

    from sq_mitsuba import inputs

    path = tmp_path / "image.png"
    PILImage.fromarray(np.zeros((64, 64), np.uint8)).save(path)
    monkeypatch.setattr(PILImage, "MAX_IMAGE_PIXELS", 3000)  # 4096 px: PIL warns
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert inputs.open_image(path).size == (64, 64)
    monkeypatch.setattr(inputs, "MAX_IMAGE_PIXELS", 4095)
    with pytest.raises(ValueError, match=r"64 x 64 px is above the largest image size, 4,095"):
        inputs.open_image(path)
    monkeypatch.setattr(PILImage, "MAX_IMAGE_PIXELS", 1000)  # 4096 px: PIL refuses to open it
    # PIL's own limit is not named beside the tool's (two limits in one line): its count is.
    with pytest.raises(ValueError, match=r"image .*image\.png: 4,096 pixels, above the largest "
                                         r"image size, 4,095 pixels$"):
        inputs.open_image(path)


def test_every_reading_of_an_image_header_holds_pils_warning_back(tmp_path, monkeypatch,
                                                                  train_dataset):
    """Between PIL's warning size and the tool's bound an image reads silently everywhere its
    header is read: the mask and image reader, predict's image mode, the dataset's check."""
    from PIL import Image as PILImage

    from sq_mitsuba.apps.predict import _image_mode
    from sq_mitsuba.data.masks import read_gray_image
    from sq_mitsuba.data.spe3r import Spe3rDataset

    path = tmp_path / "image.png"
    PILImage.fromarray(np.full((64, 64), 200, np.uint8)).save(path)
    dataset = Spe3rDataset(train_dataset, "train", image_size=64)
    monkeypatch.setattr(PILImage, "MAX_IMAGE_PIXELS", 3000)  # 4096 px: PIL warns
    with warnings.catch_warnings():
        warnings.simplefilter("error", PILImage.DecompressionBombWarning)
        assert read_gray_image(path, "image").shape == (64, 64)
        assert _image_mode(path) == "L"
        dataset.check(points=False)


def test_predict_refuses_a_too_large_image_in_one_line_without_pils_warning(
        tmp_path, monkeypatch, capsys):
    """Every reading of an image's header (its mode, its memory, its frames) holds PIL's
    decompression-bomb warning back: the size bound says it, once."""
    from PIL import Image as PILImage

    from sq_mitsuba import inputs

    path = tmp_path / "image.png"
    PILImage.fromarray(np.full((64, 64), 200, np.uint8)).save(path)
    monkeypatch.setattr(PILImage, "MAX_IMAGE_PIXELS", 3000)  # 4096 px: PIL warns
    monkeypatch.setattr(inputs, "MAX_IMAGE_PIXELS", 4095)
    assert main(["predict", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err
    assert "64 x 64 px is above the largest image size, 4,095" in err


# ----------------------------------------------------------------------------- cameras


def _camera_file(path: Path, size: int, matrix_size: int) -> Path:
    """A camera.json of ``size`` px whose matrix is the default camera's at ``matrix_size``."""
    from sq_mitsuba.geometry.camera import Camera

    data = Camera.default(matrix_size).to_speed_dict()
    data["Nu"] = data["Nv"] = size
    path.write_text(json.dumps(data))
    return path


CAMERAS = {"Nu = Nv = 100000, 64 px matrix": (100_000, 64, "far from the centre"),
           "Nu = Nv = 128, 64 px matrix": (128, 64, "far from the centre"),
           "Nu = Nv = 32, 64 px matrix": (32, 64, "far from the centre"),
           "Nu = Nv = 4": (4, 4, "below the smallest image size")}


@pytest.mark.parametrize("case", CAMERAS)
def test_inconsistent_camera_is_refused_before_any_work(case, bad, eval_checkpoint, tmp_path,
                                                        capsys):
    size, matrix_size, needle = CAMERAS[case]
    camera = _camera_file(tmp_path / "camera.json", size, matrix_size)
    out = tmp_path / "predict"
    line = _run(capsys, ["predict", bad / "image.png", "--checkpoint", eval_checkpoint,
                         "--camera", camera, "--out", out, "--quiet"])
    assert line.startswith(f"sq-mitsuba predict: error: {camera}: ") and needle in line
    assert not out.exists()
    out = tmp_path / "dataset"
    line = _run(capsys, ["dataset", "render", "--models", bad / "library", "--out", out,
                         "--camera", camera, "--images-per-model", "1", "--resolution", "32",
                         "--quiet"])
    assert f"{camera}: " in line and needle in line
    assert not out.exists()


def test_consistent_cameras_still_load():
    from sq_mitsuba.geometry.camera import Camera

    speed = {"Nu": 1920, "Nv": 1200, "cameraMatrix": [[3003.4, 0, 960], [0, 3003.4, 600],
                                                       [0, 0, 1]]}
    assert Camera.from_speed_dict(speed).width == 1920
    off_centre = Camera(150.0, 150.0, 70.0, 57.0, 128, 128)
    assert Camera.from_speed_dict(off_centre.to_speed_dict()) == off_centre
    for resolution in (8, 64, 4096):
        camera = Camera.default(resolution)
        assert Camera.from_speed_dict(camera.to_speed_dict()) == camera


# ------------------------------------------------------------------------------ report


def _eval_folder(path: Path, split: str = "val", label: str = "run", primitives: int = 2
                 ) -> Path:
    rows = [{"model": "sat", "index": i, "method": method, "filename": "",
             **{metric: 0.1 * (i + 1) + (method == "baseline") for metric in METRICS}}
            for method in ("network", "baseline") for i in range(3)]
    write_tables(rows, path)
    atomic_write_json(path / "eval.json", {"split": split, "label": label,
                                           "num_primitives": primitives,
                                           "methods": ["network", "baseline"]})
    return path


def _edit_summary(folder: Path, edit) -> Path:
    path = folder / "summary.csv"
    path.write_text(edit(path.read_text()))
    return path


def _nan_cell(text: str) -> str:
    lines = text.splitlines(keepends=True)
    index = next(i for i, line in enumerate(lines) if line.startswith("network,iou_2d,"))
    cells = lines[index].split(",")
    cells[2] = "nan"
    lines[index] = ",".join(cells)
    return "".join(lines)


def _cut_mid_row(text: str) -> str:
    end = text.index("\n", text.index("baseline,")) - 4
    return text[:end]


def _paper_with(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "paper.toml"
    path.write_text(text)
    return path


def _paper_edited(tmp_path: Path, old: str, new: str) -> Path:
    """The shipped paper tables with their first ``old`` replaced by ``new``."""
    return _paper_with(tmp_path, PAPER_TABLES.read_text().replace(old, new, 1))


REPORT_CASES = {
    "paper missing": lambda f, t: (["--paper", t / "nope.toml"], t / "nope.toml", "no such file"),
    "paper empty": lambda f, t: (["--paper", _paper_with(t, "")], t / "paper.toml",
                                 "no rows in table1 or table2"),
    "paper is a training config": lambda f, t: (
        ["--paper", ROOT / "train" / "configs" / "a.toml"], ROOT / "train" / "configs" / "a.toml",
        "unknown key"),
    "paper has NaN": lambda f, t: (
        ["--paper", _paper_edited(t, "[0.054, 0.026]", "[nan, 0.026]")],
        t / "paper.toml", "table1.a.val.chamfer_l1: expected a finite number"),
    "paper has a number as text": lambda f, t: (
        ["--paper", _paper_edited(t, "[0.054, 0.026]", '["0.054", 0.026]')],
        t / "paper.toml", "table1.a.val.chamfer_l1: expected a number, got the text '0.054'"),
    "paper has a negative Chamfer": lambda f, t: (
        ["--paper", _paper_edited(t, "[0.054, 0.026]", "[-5, 0.026]")],
        t / "paper.toml", "table1.a.val.chamfer_l1: mean -5 outside [0, inf]"),
    "paper has an IoU above 1": lambda f, t: (
        ["--paper", _paper_edited(t, "iou_2d = [0.594, 0.183]", "iou_2d = [59.4, 0.183]")],
        t / "paper.toml", "table1.a.val.iou_2d: mean 59.4 outside [0, 1]"),
    "paper syntax error": lambda f, t: (["--paper", _paper_with(t, "[table1\nlabel = 1\n")],
                                        t / "paper.toml", "malformed TOML"),
    "summary has NaN": lambda f, t: ([], _edit_summary(f, _nan_cell),
                                     "network iou_2d mean: expected a finite number"),
    "summary empty": lambda f, t: ([], _edit_summary(f, lambda text: ""), "empty"),
    "summary header only": lambda f, t: ([], _edit_summary(f, lambda text: text.split("\n")[0]),
                                         "no rows"),
    "summary cut mid-row": lambda f, t: ([], _edit_summary(f, _cut_mid_row), "cut short"),
    "summary cut at a row": lambda f, t: (
        [], _edit_summary(f, lambda text: text[:text.index("baseline,")]),
        "no baseline row for chamfer_l1_paper"),
    "eval.json other split": lambda f, t: (
        [], f / "eval.json",
        atomic_write_json(f / "eval.json", {"split": "train", "num_primitives": 2})
        or "neither 'val' nor 'test'"),
    "folder twice": lambda f, t: ([f], f, "a second val evaluation of the run 'run'"),
}


@pytest.mark.parametrize("case", REPORT_CASES)
def test_report_is_strict_about_what_it_was_given(case, tmp_path, capsys):
    folder = _eval_folder(tmp_path / "run" / "val")
    extra, named, needle = REPORT_CASES[case](folder, tmp_path)
    out = tmp_path / "report"
    line = _run(capsys, ["report", folder, *extra, "--out", out])
    assert str(named) in line and needle in line, line
    assert not out.exists()


def test_report_shows_m_in_table_2_and_refuses_a_file_as_out(tmp_path, capsys):
    folder = _eval_folder(tmp_path / "run" / "val", primitives=2)
    out = tmp_path / "report"
    assert main(["report", str(folder), "--out", str(out)]) == 0
    markdown = (out / "report.md").read_text()
    table2 = markdown[markdown.index("## Table 2"):]
    assert "| run | M |" in table2 and "| run | 2 |" in table2
    assert "| paper M = 8 | 8 |" in table2
    assert "| run | 2 |" not in markdown[:markdown.index("## Table 2")]  # Table 1: no M
    import csv

    rows = list(csv.reader((out / "report.csv").read_text().splitlines()))
    assert rows[0][:3] == ["table", "run", "M"] and any(r[1:3] == ["run", "2"] for r in rows)
    capsys.readouterr()
    blocker = tmp_path / "a_file"
    blocker.write_text("mine")
    line = _run(capsys, ["report", folder, "--out", blocker])
    assert f"out {blocker}: exists and is not a folder" in line
    assert blocker.read_text() == "mine"


# ------------------------------------------------------------------------------- study


def test_study_names_the_library_file_of_a_bad_model(bad, eval_checkpoint, tmp_path, capsys):
    library = tmp_path / "library"
    shutil.copytree(bad / "library", library)
    model = next(p for p in library.iterdir() if p.is_dir())
    out = tmp_path / "study"
    mesh = model / "models" / "model_normalized.obj"
    mesh.write_text("v 0 0 0\nf 1 1 1\n")
    line = _run(capsys, ["study", "illumination", "--checkpoint", eval_checkpoint,
                         "--models", library, "--out", out, "--quiet"])
    assert f"{mesh}: not a usable mesh" in line
    assert not out.exists()
    shutil.copyfile(bad / "library" / model.name / "models" / "model_normalized.obj", mesh)
    symmetries = model / "models" / "symmetries.json"
    symmetries.write_text("{not json")
    line = _run(capsys, ["study", "illumination", "--checkpoint", eval_checkpoint,
                         "--models", library, "--out", out, "--quiet"])
    assert f"{symmetries}: not valid JSON" in line  # the library's file, not the staged copy
    assert not out.exists()


def _per_image_text(phase: str) -> str:
    from sq_mitsuba.evaluation.tables import COLUMNS

    row = {column: "" for column in COLUMNS}
    row.update({"model": "sat", "index": "3", "method": "network", "phase_angle_deg": phase,
                "earth_in_view": "False", "eclipse": "False",
                **{metric: "0.5" for metric in METRICS}})
    return ",".join(COLUMNS) + "\n" + ",".join(row[c] for c in COLUMNS) + "\n"


STUDY_EVAL_CASES = {
    "NaN phase angle": (_per_image_text("nan"),
                        "phase_angle_deg of sat image 3: expected a finite number"),
    "cut short": (_per_image_text("40")[:-30], "cut short"),
    "empty": ("", "empty"),
}


@pytest.mark.parametrize("case", STUDY_EVAL_CASES)
def test_study_of_a_bad_evaluation_names_file_and_column(case, tmp_path, capsys):
    text, needle = STUDY_EVAL_CASES[case]
    folder = tmp_path / "eval"
    folder.mkdir()
    (folder / "per_image.csv").write_text(text)
    (folder / "eval.json").write_text("{}")  # a finished evaluation's (its last file)
    out = tmp_path / "lighting"
    line = _run(capsys, ["study", "illumination", "--eval", folder, "--out", out])
    assert f"{folder / 'per_image.csv'}: " in line and needle in line, line
    assert not out.exists()


# ----------------------------------------------------------------- export, models, dataset


def _labels_for(mask: Path, path: Path) -> Path:
    """A labels file posing ``mask`` 3 m in front of the camera."""
    path.write_text(json.dumps([{"filename": mask.name, "q_vbs2tango_true": [1, 0, 0, 0],
                                 "r_Vo2To_vbs_true": [0, 0, 3]}]))
    return path


def test_no_output_overwrites_an_input(bad, eval_checkpoint, train_dataset, tmp_path, capsys):
    """Every input file a command reads (a camera, relative rotations, a fit's masks and poses,
    the checkpoints an export reads) is refused as an output before any work, and kept."""
    out = tmp_path / "out"
    out.mkdir()
    shutil.copyfile(bad / "image.png", out / "a.png")
    shutil.copyfile(bad / "image.png", out / "b.png")
    camera = out / "a.pose.json"  # a camera file named like a.png's pose
    shutil.copyfile(train_dataset / "camera.json", camera)
    rotations = out / "sequence.assembly.json"
    rotations.write_text(json.dumps([[1, 0, 0, 0], [1, 0, 0, 0]]))
    mask = out / "fit.png"  # a mask named like the fit's figure
    Image.fromarray(np.pad(np.full((20, 28), 255, np.uint8), ((22, 22), (18, 18)))).save(mask)
    labels = _labels_for(mask, out / "labels.json")
    checkpoint = out / "model.pt"
    shutil.copyfile(eval_checkpoint, checkpoint)
    kept = {path: path.read_bytes() for path in out.iterdir()}
    model = ["--checkpoint", checkpoint]
    runs = [(["predict", out / "a.png", "--camera", camera, *model], camera),
            (["predict", out / "a.png", out / "b.png", "--sequence", "--relative-rotations",
              rotations, *model], rotations),
            (["fit", "--masks", mask, "--poses", labels, "--steps", "2"], mask)]
    for argv, victim in runs:
        line = _run(capsys, [*argv, "--out", out])
        assert line.endswith(f"{victim}: an output of this run would overwrite it; write "
                             "elsewhere (--out)"), line
    line = _run(capsys, ["export", "--checkpoint", checkpoint, "--out", checkpoint])
    assert line.endswith(f"{checkpoint}: an output of this run would overwrite it; write "
                         "elsewhere (--out)"), line
    assert {path: path.read_bytes() for path in out.iterdir()} == kept


def test_a_folder_in_an_outputs_place_is_refused_before_the_work(bad, tmp_path, capsys):
    """A folder where a command would write one of its files stops it before the work, with
    nothing of its own written (it was found only when writing that file, after the fit)."""
    mask = tmp_path / "view.png"
    Image.fromarray(np.pad(np.full((20, 28), 255, np.uint8), ((22, 22), (18, 18)))).save(mask)
    labels = _labels_for(mask, tmp_path / "labels.json")
    runs = [(["fit", "--masks", mask, "--poses", labels, "--steps", "2"], "fit.png"),
            (["predict", bad / "image.png"], "image.overlay.png")]
    for argv, name in runs:
        out = tmp_path / f"out_{argv[0]}"
        (out / name).mkdir(parents=True)
        line = _run(capsys, [*argv, "--out", out])
        assert line.endswith(f"{out / name}: an output of this run, but a folder (or another "
                             "non-file) is there; move it or write elsewhere (--out)"), line
        assert _entries(out) == [name]
    # A file where a run writes a folder of its files (predict --sequence's colmap/).
    from sq_mitsuba.io import check_output_folder

    out = tmp_path / "out_sequence"
    out.mkdir()
    (out / "colmap").write_text("not a folder")
    with pytest.raises(ValueError) as error:
        check_output_folder(out, ["sequence.glb", "colmap/cameras.txt"])
    assert str(error.value) == (f"{out / 'colmap'}: the run writes cameras.txt into this "
                                "folder, but a file is there; move it or write elsewhere (--out)")
    check_output_folder(out, ["sequence.glb", "colmap.txt"])  # beside it: nothing refused


def test_export_to_a_folder_is_refused_before_the_work(eval_checkpoint, tmp_path, capsys):
    folder = tmp_path / "exports"
    folder.mkdir()
    line = _run(capsys, ["export", "--checkpoint", eval_checkpoint, "--out", folder])
    assert f"out {folder}: is a folder" in line and "Errno" not in line
    assert _entries(folder) == []


@pytest.mark.parametrize("action", ["generate", "import"])
def test_models_refuse_an_unusable_out_up_front(action, bad, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("mine")
    mesh = next((bad / "library").glob("*/models/model_normalized.obj"))
    argv = (["models", "generate", "--count", "1"] if action == "generate"
            else ["models", "import", mesh])
    line = _run(capsys, [*argv, "--out", blocker / "library"])
    assert f"{blocker} is a file, not a folder" in line and "Errno" not in line
    assert blocker.read_text() == "mine"


def test_import_of_a_picture_named_obj_is_a_failure_naming_it(tmp_path, capsys):
    picture = tmp_path / "photo.obj"
    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(picture, format="JPEG")
    out = tmp_path / "library"
    assert main(["models", "import", str(picture), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert str(picture) in err
    assert "ModuleNotFoundError" not in err and "Traceback" not in err
    assert not list(out.glob("*/models/*.obj"))


def test_damaged_labels_of_a_dataset_say_what_to_do(train_dataset, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(train_dataset, data)
    model = sorted(p.parent.name for p in data.glob("*/labels.json"))[0]
    (data / model / "labels.json").write_text("[{")
    models = tmp_path / "models"
    for folder in data.glob("*/models"):
        shutil.copytree(folder, models / folder.parent.name / "models")
    shutil.copyfile(data / "splits.csv", models / "splits.csv")
    settings = json.loads((data / "dataset.json").read_text())["settings"]
    argv = ["dataset", "render", "--models", models, "--out", data, "--quiet",
            "--images-per-model", "10", "--seed", settings["seed"],
            "--resolution", settings["resolution"], "--spp", settings["spp"]]
    assert main([str(a) for a in argv]) == 1
    printed = [line for line in capsys.readouterr().out.splitlines() if "FAILED" in line]
    assert len(printed) == 1
    assert f"{data / model / 'labels.json'}: not valid JSON" in printed[0]
    assert f"delete {data / model} and run again" in printed[0]
    shutil.rmtree(data / model)  # as the message says: the model is rendered anew
    assert main([str(a) for a in argv]) == 0
    assert (data / model / "labels.json").read_bytes() == \
        (train_dataset / model / "labels.json").read_bytes()


# ------------------------------------------------------------------------------ outputs


def test_a_data_error_during_eval_leaves_no_out(train_dataset, eval_checkpoint, tmp_path,
                                                capsys):
    data = tmp_path / "data"
    shutil.copytree(train_dataset, data)
    model = next(line.split(",")[0] for line in (data / "splits.csv").read_text().splitlines()
                 if line.endswith(",train"))
    victim = data / model / "images" / "000004.png"  # image 4 is in the val split
    victim.write_bytes(victim.read_bytes()[:100])
    out = tmp_path / "eval"
    line = _run(capsys, ["eval", "--checkpoint", eval_checkpoint, "--data", data, "--out", out,
                         "--no-baseline", "--no-figures", "--quiet"])
    assert f"{victim}: cannot read image" in line
    assert not out.exists()  # not even the empty folder


# A failing run of each command whose --out is all or nothing: (argv, file the error names).
GUARDED = {
    "eval": lambda bad, ck, out: (["eval", "--checkpoint", ck, "--data", bad / "nothing",
                                   "--out", out], bad / "nothing"),
    "predict": lambda bad, ck, out: (["predict", bad / "image.png", bad / "tiny.png",
                                      "--checkpoint", ck, "--out", out], bad / "tiny.png"),
    "fit": lambda bad, ck, out: (["fit", "--masks", bad / "tiny.png", "--poses",
                                  bad / "nothing.json", "--out", out], bad / "nothing.json"),
    "report": lambda bad, ck, out: (["report", bad / "nothing", "--out", out], bad / "nothing"),
    "study": lambda bad, ck, out: (["study", "illumination", "--checkpoint", ck, "--models",
                                    bad / "nothing", "--out", out], bad / "nothing"),
}


@pytest.mark.parametrize("command", GUARDED)
def test_a_failed_run_leaves_out_as_it_was_and_removes_stray_temporaries(
        command, bad, eval_checkpoint, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("kept")
    stray = out / ".qualitative.k2j4_x9q.tmp.png"  # a kill mid-write leaves such a file
    stray.write_bytes(b"")
    argv, named = GUARDED[command](bad, eval_checkpoint, out)
    line = _run(capsys, [*argv, "--quiet"] if command != "report" else argv)
    assert str(named) in line
    assert _entries(out) == ["mine.txt"]


def test_export_removes_its_own_stray_temporaries_only(bad, eval_checkpoint, tmp_path, capsys):
    out = tmp_path / "model.pt"
    strays = [tmp_path / ".model.a1b2c3d4.tmp.pt", tmp_path / ".other.a1b2c3d4.tmp.pt"]
    for stray in strays:
        stray.write_bytes(b"")
    line = _run(capsys, ["export", "--checkpoint", bad / "nan.pt", "--out", out])
    assert str(bad / "nan.pt") in line
    assert _entries(tmp_path) == [".other.a1b2c3d4.tmp.pt"]  # another file's is not its own


def test_raw_operating_system_errors_read_as_file_and_cause():
    from sq_mitsuba.cli import _one_line

    rename = IsADirectoryError(21, "Is a directory", "/x/.model.a1b2c3d4.tmp.pt", None, "/x/out")
    assert _one_line(rename) == "/x/out: is a directory"
    assert _one_line(PermissionError(13, "Permission denied", "/x/report.md")) == \
        "/x/report.md: permission denied"
    assert _one_line(FileNotFoundError("checkpoint: no such file a.pt")) == \
        "checkpoint: no such file a.pt"


def test_atomic_temporaries_are_recognised_and_only_they(tmp_path):
    from sq_mitsuba.outputs import TEMPORARY_NAME, remove_stray_temporaries

    names = []
    for target in ("last.pt", "qualitative.png", "labels.json", "notes"):
        with pytest.raises(RuntimeError), atomic_path(tmp_path / target) as tmp:
            names.append(tmp.name)  # the name of atomic_path's own temporary file
            raise RuntimeError
    assert all(TEMPORARY_NAME.fullmatch(name) for name in names), names
    for name in (".hidden", "last.pt", ".last.pt", "a.tmp.pt", ".last.abc.tmp.pt"):
        assert not TEMPORARY_NAME.fullmatch(name), name
    strays = [tmp_path / name for name in names]
    for path in strays:
        path.write_bytes(b"")  # what a kill mid-write leaves
    (tmp_path / "last.pt").write_text("kept")
    assert sorted(remove_stray_temporaries(tmp_path, of="last.pt")) == [strays[0]]
    assert sorted(remove_stray_temporaries(tmp_path)) == sorted(strays[1:])
    assert _entries(tmp_path) == ["last.pt"]


def test_all_or_nothing_removes_what_a_failed_run_added(tmp_path):
    from sq_mitsuba.outputs import all_or_nothing

    new = tmp_path / "new" / "deeper"
    with pytest.raises(ValueError), all_or_nothing(new):
        (new / "sub").mkdir(parents=True)
        (new / "file.txt").write_text("partial")
        raise ValueError("bad input")
    assert not (tmp_path / "new").exists()  # the parents it created go too
    old = tmp_path / "old"
    old.mkdir()
    (old / "before.txt").write_text("kept")
    with pytest.raises(ValueError), all_or_nothing(old):
        (old / "before.txt").write_text("replaced")  # atomic writes replace whole files
        (old / "added").mkdir()
        raise ValueError("bad input")
    assert _entries(old) == ["before.txt"]
    with pytest.raises(KeyboardInterrupt), all_or_nothing(old):
        (old / "resumable").mkdir()
        raise KeyboardInterrupt
    assert _entries(old) == ["before.txt", "resumable"]  # Ctrl-C keeps what was written
    # Ctrl-C inside Dr.Jit comes out as a RuntimeError caused by it: still kept.
    with pytest.raises(RuntimeError), all_or_nothing(old):
        (old / "rendered").mkdir()
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ctrl_c:
            raise RuntimeError("drjit.switch(): encountered an exception") from ctrl_c
    assert _entries(old) == ["before.txt", "rendered", "resumable"]
    with all_or_nothing(old):
        (old / "done.txt").write_text("ok")
    assert "done.txt" in _entries(old)
    # Finished work a rerun resumes (a journal) stays after any failure, with the folder the
    # run made for it: out of memory or a disk error after hours must not take it along.
    # Bad input (a ValueError) leaves nothing, the journal included.
    for error, kept in ((MemoryError, [".eval_partial"]), (OSError, [".eval_partial"]),
                        (RuntimeError, [".eval_partial"]), (ValueError, [])):
        fresh = tmp_path / f"fresh_{error.__name__}"
        with pytest.raises(error), all_or_nothing(fresh, keep=(".eval_partial",)):
            (fresh / ".eval_partial").mkdir()
            (fresh / ".eval_partial" / "batch_000001.pt").write_text("a finished batch")
            (fresh / "per_image.csv").write_text("partial")
            raise error("late failure")
        assert _entries(fresh) == kept, error
    with pytest.raises(MemoryError), all_or_nothing(old, keep=(".eval_partial",)):
        (old / ".eval_partial").mkdir()
        (old / "added.txt").write_text("partial")
        raise MemoryError
    assert ".eval_partial" in _entries(old) and "added.txt" not in _entries(old)
    # Nothing of it written yet: the folder the run made goes as before.
    with pytest.raises(MemoryError), all_or_nothing(tmp_path / "none",
                                                    keep=(".eval_partial",)):
        (tmp_path / "none" / "per_image.csv").write_text("partial")
        raise MemoryError
    assert not (tmp_path / "none").exists()


# --------------------------------------------------------------- normal runs print no warnings


def test_mask_sample_counts_are_squares_the_stratified_sampler_takes_as_they_are():
    import math

    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.render.space import mask_samples

    for spp in (1, 16, 64, 100):
        for resolution in (8, 48, 96, 100, 128, 200, 256, 1000):
            count = mask_samples(spp, Camera.default(resolution))
            wanted = max(spp, math.ceil(spp * (256 / resolution) ** 2))
            side = math.isqrt(count)
            # The smallest square at or above the proportional count: what Mitsuba's
            # stratified sampler rounds any count up to.
            assert side * side == count and (side - 1) ** 2 < wanted <= count


def test_dataset_render_and_predict_print_no_warnings(bad, eval_checkpoint, tmp_path, capfd):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # 48 px: the mask pass wants 1,821 samples per pixel, which Mitsuba's sampler would
        # round to 1,849 with a warning.
        assert main(["dataset", "render", "--models", str(bad / "library"), "--out",
                     str(tmp_path / "data"), "--images-per-model", "1", "--resolution", "48",
                     "--spp", "1", "--quiet"]) == 0
        assert main(["predict", str(bad / "image.png"), "--checkpoint", str(eval_checkpoint),
                     "--out", str(tmp_path / "predict"), "--refine", "--set",
                     "refinement.steps=2", "--quiet"]) == 0
    printed = capfd.readouterr()
    assert not caught, [str(w.message) for w in caught]
    assert "warn" not in printed.err.lower() and "warn" not in printed.out.lower(), printed


def test_the_training_loss_renders_without_a_grad_warning(renderer64):
    """The per-item loss loop a render worker of the training loss runs (grad mode on, as in
    a fresh process)."""
    from sq_mitsuba.geometry.icosphere import icosphere

    sphere, faces = icosphere(2)
    vertices = (0.3 * torch.tensor(sphere, dtype=torch.float32)
                + torch.tensor([0.0, 0.0, 2.0]))[None].repeat(2, 1, 1)
    renderer64._prepare(vertices, torch.tensor(faces))
    with warnings.catch_warnings(), torch.enable_grad():
        warnings.simplefilter("error")
        losses, _, grad = renderer64._loss_items(
            vertices, 0, range(2), lambda coverage, index: coverage.square().mean(),
            requires_grad=True)
    assert bool((losses > 0).all()) and bool(grad.abs().sum() > 0)


def test_the_demo_page_names_the_shipped_model_without_this_machines_path():
    from sq_mitsuba.apps.demo_files import shown_model
    from sq_mitsuba.model.checkpoint import SHIPPED_MODEL

    shown = shown_model(str(SHIPPED_MODEL))
    assert "sq_mitsuba/model/weights/model.pt" in shown
    assert str(SHIPPED_MODEL.parents[2]) not in shown  # the checkout's absolute path
    assert shown_model("") == shown
    assert shown_model("runs/cpu/best.pt") == "runs/cpu/best.pt"


def test_quaternion_lists_are_normalised_and_bad_ones_are_one_line(tmp_path):
    """``inputs.check_quaternions`` on a file ``io.read_json`` parsed (as ``predict
    --relative-rotations`` reads one): rounding within the tolerance is normalised away; a file
    missing, not JSON, of the wrong count or with a short, infinite or far-from-unit entry is
    refused in one line naming it."""
    from sq_mitsuba.inputs import UNIT_TOLERANCE, check_quaternions
    from sq_mitsuba.io import read_json

    def read(path):
        return check_quaternions(read_json(path), 2, "image", str(path))

    path = tmp_path / "q.json"
    near = [1.0 + 0.5 * UNIT_TOLERANCE, 0.0, 0.0, 0.0]
    path.write_text(json.dumps([near, [0.5, 0.5, 0.5, 0.5]]))
    quaternions = read(path)
    assert quaternions[0] == [1.0, 0.0, 0.0, 0.0] and quaternions[1] == [0.5, 0.5, 0.5, 0.5]
    with pytest.raises(FileNotFoundError):
        read(tmp_path / "absent.json")
    unit = [1, 0, 0, 0]
    for text, message in ((json.dumps({"q": unit}), "got a dict"),
                          (json.dumps([unit]), "1 quaternion for 2 images"),
                          (json.dumps([unit, [1, 0, 0, 0.2]]), "quaternion 1: expected unit"),
                          ("[[1, 0, 0, 0], [Infinity, 0, 0, 0]]", "1: expected a finite"),
                          (json.dumps([unit, [True, 0, 0, 0]]), "quaternion 1: expected a finite"),
                          (json.dumps([unit, ["1", 0, 0, 0]]), "quaternion 1: expected a number, "
                                                              "got the text '1'"),
                          (json.dumps([unit, [1, 0, 0]]), "quaternion 1: expected [w, x, y, z]"),
                          ("[[1, 0, 0, 0], ", "not valid JSON"),
                          ("", "an empty file, not JSON"), ("\n  \n", "an empty file"),
                          ("[" * 100_000 + "]" * 100_000, "nested too deeply")):
        path.write_text(text)
        with pytest.raises(ValueError, match=re.escape(message)) as info:
            read(path)
        assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)
    with pytest.raises(ValueError, match=r"^/dev/null: not a regular file"):
        read_json("/dev/null")  # a device could block, or never end (/dev/urandom)


def test_an_image_of_a_mode_without_grey_is_named_as_an_image_not_a_mask(tmp_path):
    """A picture PIL cannot turn grey (a CIELAB TIFF) is refused naming what it was given as."""
    from sq_mitsuba.data.masks import read_gray_image, read_mask

    path = tmp_path / "lab.tiff"
    Image.new("LAB", (16, 16)).save(path)
    for reader, what in ((read_gray_image, "image"), (read_mask, "mask")):
        with pytest.raises(ValueError, match=rf"^{what} {re.escape(str(path))}: cannot convert "
                                             r"PIL mode 'LAB' to gray"):
            reader(path)


def test_a_dataset_image_with_pixels_not_finite_is_refused(tmp_path):
    """A float TIFF in a dataset's place of an image: its NaN would become a grey value."""
    from sq_mitsuba.data.spe3r.layout import DatasetError, read_gray

    path = tmp_path / "000004.png"
    pixels = np.full((16, 16), 0.5, np.float32)
    pixels[3, 4] = np.nan
    Image.fromarray(pixels, "F").save(path, format="TIFF")
    with pytest.raises(DatasetError, match=rf"^{re.escape(str(path))}: 1 pixel\(s\) not finite"):
        read_gray(path)
    Image.fromarray(np.nan_to_num(pixels), "F").save(path, format="TIFF")
    assert read_gray(path).shape == (16, 16)


def test_an_image_beyond_the_machines_memory_is_refused_before_it_is_read(bad, tmp_path,
                                                                        capsys, monkeypatch):
    """predict estimates an image's memory from its header (PREDICT_BYTES_PER_PIXEL) and
    refuses one this machine cannot hold, before decoding it or starting the network."""
    from sq_mitsuba import machine
    from sq_mitsuba.apps.predict import PREDICT_BYTES_PER_PIXEL
    from sq_mitsuba.inference.turned_copies import TURN_COPY_BYTES

    pixels = 64 * 64  # the fixture's image
    monkeypatch.setattr(machine, "available_memory", lambda: pixels * PREDICT_BYTES_PER_PIXEL - 1)
    out = tmp_path / "out"
    line = _run(capsys, ["predict", bad / "image.png", "--out", out])
    assert (f"image {bad / 'image.png'}: 64 x 64 px (64 bytes a pixel) needs about 256 KiB of "
            "memory, more than the 256 KiB this process may use; scale it down") in line, line
    assert not out.exists()
    # Room for the image, and for its reading's 8 turned copies (the default: 7 beside it).
    monkeypatch.setattr(machine, "available_memory",
                        lambda: pixels * PREDICT_BYTES_PER_PIXEL + 7 * TURN_COPY_BYTES)
    assert main(["predict", str(bad / "image.png"), "--out", str(out), "--quiet"]) == 0
    # An image too long to be padded to the camera's square is refused for what it is (its
    # side below the minimum, its aspect ratio), not for the memory its padding would take.
    monkeypatch.setattr(machine, "available_memory", lambda: 2**30)
    for width, height, message in ((40000, 4, "below the smallest image size, 8 x 8 px"),
                                   (40000, 30, "too far from the camera's aspect ratio")):
        Image.fromarray(np.full((height, width), 90, np.uint8)).save(tmp_path / "long.png")
        line = _run(capsys, ["predict", tmp_path / "long.png", "--out", tmp_path / "long"])
        assert message in line and "memory" not in line, line
    assert not (tmp_path / "long").exists()


def test_a_model_library_given_for_a_dataset_is_named_as_such(tmp_path):
    """eval, train and preview read datasets; a model library (the step before) is told apart
    from a broken dataset, with the command that makes one."""
    from sq_mitsuba.data.spe3r import Spe3rDataset

    (tmp_path / "sc000_x" / "models").mkdir(parents=True)
    (tmp_path / "sc000_x" / "models" / "model_card.json").write_text("{}")
    (tmp_path / "splits.csv").write_text("sc000_x,train\n")
    with pytest.raises(ValueError, match=r"camera\.json: missing; .* is a model library, not "
                                         r"a dataset: render one with sq-mitsuba dataset "
                                         r"render --models"):
        Spe3rDataset(tmp_path, "train")
    (tmp_path / "sc000_x" / "models" / "model_card.json").unlink()
    with pytest.raises(ValueError, match=r"camera\.json: missing$"):
        Spe3rDataset(tmp_path, "train")


def test_a_rendered_dataset_without_its_samples_is_said_not_silently_sampled(train_dataset,
                                                                             tmp_path):
    """The SPE3R release has no samples.npz and its meshes are sampled, silently; a dataset
    sq-mitsuba rendered (dataset.json) has them, and its scores are on them: a model that
    lost its samples is said once, naming the file and the count."""
    from sq_mitsuba.data.spe3r import Spe3rDataset

    data = Path(shutil.copytree(train_dataset, tmp_path / "data"))
    dataset = Spe3rDataset(data, "train", image_size=64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dataset.check()  # every samples.npz there: nothing said
    model = dataset.models[dataset.items[0][0]]
    samples = data / model / "models" / "samples.npz"
    samples.unlink()
    with pytest.warns(UserWarning, match=rf"^{re.escape(str(samples))}: missing \(1 model\(s\) "
                      r"of .*, a dataset sq-mitsuba rendered\): their points are sampled"):
        dataset.check()
    (data / "dataset.json").unlink()  # as the release: no manifest, sampled without a word
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Spe3rDataset(data, "train", image_size=64).check()


def test_a_checkpoints_bad_camera_is_named_once(bad, eval_checkpoint, tmp_path, capsys):
    payload = torch.load(eval_checkpoint, weights_only=True)
    payload["camera"]["Nu"] = -5
    path = tmp_path / "badcam.pt"
    torch.save(payload, path)
    line = _run(capsys, ["predict", bad / "image.png", "--checkpoint", path, "--out",
                         tmp_path / "out"])
    assert f"{path}: camera: Nu" in line and "camera: camera" not in line, line
    assert not (tmp_path / "out").exists()
