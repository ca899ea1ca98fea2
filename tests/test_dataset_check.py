"""`dataset check` you can trust, and a reader that names the bad file.

Fresh datasets at 64, 128 and 256 px pass with the default threshold; every kind of damage
(a shifted mask, a truncated PNG, stray files, bad labels) is found and named, each per file.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sq_mitsuba.cli import main
from sq_mitsuba.data.library import generate_model
from sq_mitsuba.data.spacecraft import catalogue
from sq_mitsuba.data.spe3r import (
    CheckOptions,
    DatasetError,
    RenderOptions,
    Spe3rDataset,
    check_dataset,
    render_dataset,
)
from sq_mitsuba.data.spe3r.check import compare_masks, edge_tolerance

IMAGES = 2
READER = {"image_size": 32, "num_surface": 10, "num_occupancy": 10}


@pytest.fixture(scope="session")
def check_library(tmp_path_factory) -> Path:
    """Two generated spacecraft (thin panels and a boom: many edge pixels)."""
    root = tmp_path_factory.mktemp("check_models")
    entries = catalogue(2, 3)
    for entry in entries:
        generate_model(entry, root, points=2000)
    (root / "splits.csv").write_text(f"{entries[0].name},train\n{entries[1].name},test\n")
    return root


@pytest.fixture(scope="session")
def fresh(check_library, tmp_path_factory):
    """Fresh datasets (default scene, so the default mask pass) by resolution, built once."""
    built: dict[int, Path] = {}

    def get(resolution: int) -> Path:
        if resolution not in built:
            out = tmp_path_factory.mktemp(f"check_{resolution}") / "data"
            options = RenderOptions(images_per_model=IMAGES, seed=4, resolution=resolution,
                                    spp=1)
            assert render_dataset(check_library, out, options, progress=False).complete
            built[resolution] = out
        return built[resolution]

    return get


def test_a_check_too_noisy_to_resolve_edges_is_refused_before_any_work(fresh):
    """At 4 samples a pixel a half-covered pixel reads as empty one time in 16: a correct
    mask's edges were flagged (IoU 0.89 on a 32 px dataset that passes at 16 or more)."""
    with pytest.raises(ValueError, match=r"^spp 4: too few samples to tell a mask's edges "
                       r"from errors; give --spp 17 or more \(default 256\)$"):
        check_dataset(fresh(64), per_model=0, spp=4, progress=False)
    assert check_dataset(fresh(64), per_model=1, spp=17, progress=False).ok


def damaged_copy(source: Path, target: Path) -> tuple[Path, str, str]:
    shutil.copytree(source, target)
    train, test = sorted(json.loads((target / "dataset.json").read_text())["models"])
    return target, train, test


@pytest.mark.parametrize("resolution", [64, 128, 256])
def test_fresh_datasets_pass_at_every_resolution(fresh, resolution):
    report = check_dataset(fresh(resolution), per_model=0, progress=False)
    assert report.ok, report.summary()
    assert len(report.iou) == 2 * IMAGES and min(report.iou) >= CheckOptions().min_iou
    assert report.decoded == 2 * 2 * IMAGES
    # The edge band is what makes the threshold hold: the plain IoU is lower (and falls below
    # 0.99 at 64 px for these thin structures).
    assert min(report.plain_iou) < 1.0 and min(report.plain_iou) <= min(report.iou)
    if resolution == 64:  # a plain IoU >= 0.99 rule would refuse this correct dataset
        assert min(report.plain_iou) < 0.99


@pytest.mark.parametrize("resolution, shift", [(64, 1), (256, 1)])
def test_a_mask_shifted_by_one_pixel_fails(fresh, tmp_path, resolution, shift):
    root, train, _ = damaged_copy(fresh(resolution), tmp_path / "shifted")
    path = root / train / "masks" / "000001.png"
    Image.fromarray(np.roll(np.asarray(Image.open(path)), shift, axis=0)).save(path)
    report = check_dataset(root, per_model=0, progress=False)
    assert [p.split(":")[0] for p in report.problems] == [f"{train}/000001.png"]
    assert "label/mask IoU" in report.problems[0]


def test_edge_tolerance_leaves_out_only_ambiguous_pixels():
    coverage = np.array([[0.0, 0.45, 0.6, 1.0]])
    tolerance = edge_tolerance(256, 256)
    assert 0.17 < tolerance < 0.18  # 4 sqrt(0.25 / 256 * 2)
    # The pixels at 0.45 and 0.6 may go either way; the others must agree.
    assert compare_masks(coverage, np.array([[False, True, False, True]]), tolerance)[0] == 1.0
    assert compare_masks(coverage, np.array([[True, False, True, True]]), tolerance)[0] == 0.5
    assert compare_masks(coverage, np.array([[False, False, True, True]]), 0.0) == (1.0, 1.0)


def test_truncated_and_corrupt_files_are_named(fresh, tmp_path):
    root, train, test = damaged_copy(fresh(64), tmp_path / "truncated")
    image = root / train / "images" / "000000.png"
    image.write_bytes(image.read_bytes()[: image.stat().st_size // 2])
    mask = root / test / "masks" / "000001.png"
    data = bytearray(mask.read_bytes())
    data[60] ^= 0xFF  # a flipped byte inside the image data: the chunk's CRC no longer matches
    mask.write_bytes(bytes(data))
    report = check_dataset(root, per_model=0, progress=False)
    problems = sorted(p.split(":")[0] for p in report.problems)
    assert problems == [f"{train}/images/000000.png", f"{test}/masks/000001.png"]
    assert "cannot read image" in report.problems[0]
    # A truncated samples.npz: one problem (the points' check and the mesh's materials read
    # it both), in numpy's stead not its advice to load it "unsafely".
    samples = root / test / "models" / "samples.npz"
    samples.write_bytes(samples.read_bytes()[:1000])
    named = [p for p in check_dataset(root, per_model=0, progress=False).problems
             if "samples.npz" in p]
    assert named == [f"{test}/models/samples.npz: corrupt or truncated: not a valid .npz file"]
    # The reader names the file too, in one line.
    dataset = Spe3rDataset(root, "train", **READER)
    with pytest.raises(DatasetError, match=r"images/000000\.png: cannot read image") as info:
        dataset[0]
    assert "\n" not in str(info.value)


def test_stray_files_are_reported(fresh, tmp_path):
    root, train, test = damaged_copy(fresh(64), tmp_path / "strays")
    (root / train / "images" / ".000001.ab12cd.tmp.png").write_bytes(b"\x89PNG")
    (root / ".dataset.x1y2z3.tmp.json").write_bytes(b"")
    (root / train / "models" / "notes.txt").write_bytes(b"")
    (root / test / ".progress").mkdir()
    (root / test / ".progress" / "000001.json").write_text("{}")
    report = check_dataset(root, per_model=1, progress=False)
    assert sorted(report.problems) == sorted([
        f"{train}/images/.000001.ab12cd.tmp.png: stray temporary file (left by a killed "
        f"write)",
        ".dataset.x1y2z3.tmp.json: stray temporary file (left by a killed write)",
        f"{train}/models/notes.txt: empty file",
        f"{test}/.progress/: unfinished model (a render was stopped; run it again to finish)",
    ])


def test_bad_labels_are_reported_per_entry_and_the_rest_is_checked(fresh, tmp_path):
    root, train, test = damaged_copy(fresh(64), tmp_path / "labels")
    path = root / train / "labels.json"
    labels = json.loads(path.read_text())
    labels[0]["q_vbs2tango_true"][1] = float("nan")
    labels[1]["r_Vo2To_vbs_true"] = labels[1]["r_Vo2To_vbs_true"][:2]
    path.write_text(json.dumps(labels))  # NaN is written as NaN, as Python's json does
    extra = root / test / "masks" / "000009.png"
    shutil.copy(root / test / "masks" / "000000.png", extra)
    report = check_dataset(root, per_model=0, progress=False)
    problems = "\n".join(report.problems)
    assert f"{train}/labels.json: entry 0 (000000.png): q_vbs2tango_true: not finite" \
        in problems
    assert f"{train}/labels.json: entry 1 (000001.png): r_Vo2To_vbs_true: expected a list " \
           f"of 3 numbers" in problems
    assert f"{test}/masks/000009.png: no label names it" in problems
    assert f"{train}/images/000000.png: no label" not in problems  # a bad entry names it
    assert f"{train}/labels.json: changed since dataset.json was written" in problems
    # The test model's masks were still compared with the mesh.
    assert len(report.iou) == IMAGES
    with pytest.raises(DatasetError, match=r"labels\.json: entry 0 \(000000\.png\): "
                                           r"q_vbs2tango_true: not finite"):
        Spe3rDataset(root, "train", **READER)


def test_reader_names_a_mask_of_another_size(fresh, tmp_path):
    root, train, _ = damaged_copy(fresh(64), tmp_path / "size")
    mask = root / train / "masks" / "000001.png"
    Image.open(mask).resize((48, 48)).save(mask)
    dataset = Spe3rDataset(root, "train", **READER)
    assert dataset[0]["mask"].shape == (1, 32, 32)
    with pytest.raises(DatasetError, match=r"masks/000001\.png: mask is 48 x 48 px, its "
                                           r"image 000001\.png is 64 x 64 px"):
        dataset[1]
    report = check_dataset(root, per_model=0, progress=False)
    assert [p.split(":")[0] for p in report.problems] == [f"{train}/masks/000001.png"]


def test_a_folder_that_is_no_dataset_is_bad_input_not_a_problem(tmp_path, capsys):
    """A folder with neither camera.json nor dataset.json is no dataset: exit 2 and one line
    saying so (it was exit 1 with "camera.json: missing" as a problem of the dataset), as a
    model library already is. A dataset that lost its camera.json still has problems."""
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "splits.csv").write_text("a,train\n")
    assert main(["dataset", "check", str(folder), "--quiet"]) == 2
    captured = capsys.readouterr()
    assert captured.err.strip() == (
        f"sq-mitsuba dataset: error: {folder}: not a dataset (no camera.json and no "
        "dataset.json); render one with sq-mitsuba dataset render --models LIBRARY --out DATA")
    assert "problem" not in captured.out
    with pytest.raises(DatasetError, match="not a dataset"):
        check_dataset(folder, progress=False)
    (folder / "dataset.json").write_text("{}")  # a render's, broken: problems, exit 1
    assert main(["dataset", "check", str(folder), "--quiet"]) == 1


def test_check_options_are_range_checked(fresh, capsys):
    root = fresh(64)
    for bad, message in [(["--per-model", "-3"], "--per-model: expected a value in [0, "),
                         (["--min-iou", "2"], "--min-iou: expected a value in [0, 1], got 2"),
                         (["--min-iou", "nan"], "--min-iou")]:
        assert main(["dataset", "check", str(root), *bad]) == 2
        assert message in capsys.readouterr().err
    with pytest.raises(ValueError, match="min_iou"):
        check_dataset(root, min_iou=-0.1)
    assert main(["dataset", "check", str(root), "--per-model", "1", "--quiet"]) == 0
    assert "no problems found" in capsys.readouterr().out


def test_a_check_of_more_samples_than_a_render_takes_names_the_spp_that_fits(fresh,
                                                                            monkeypatch):
    """At 8000 px the default 256 spp is 16e9 samples a render, past Mitsuba's 2^32: it failed
    as an internal error from the renderer after the first model was read. Refused with the
    spp that fits (Mitsuba's limit made that of a 64 px image at 100 spp, not 8000 px's)."""
    import sq_mitsuba.data.spe3r.check as check

    monkeypatch.setattr(check, "MAX_SAMPLES_PER_RENDER", 64 * 64 * 100)
    with pytest.raises(ValueError, match=r"^--spp 256: a render of 64 x 64 px takes at most 100 "
                                         r"samples a pixel .*; give --spp 100 or less$"):
        check_dataset(fresh(64), per_model=0, progress=False)
    assert check_dataset(fresh(64), per_model=0, spp=100, progress=False).ok
