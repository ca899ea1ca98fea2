"""Evaluating passes (``evaluate_passes``, ``sq-mitsuba eval --sequence``): one assembly from
the first N frames of each pass against each frame alone.

References: the relative rotations against angles set by hand; each method's rows against the
same method called directly on the same frames (the network's reading, ``predict_sequence``);
the summary's means against the per-frame table averaged with numpy; bad inputs refused in one
line before any work."""

from __future__ import annotations

import csv
import json
import math
import re
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch
from output_checks import one_torch_thread  # noqa: F401 (autouse fixture)

from sq_mitsuba.evaluation.passes import (
    OUTPUT_FILES,
    PassOptions,
    evaluate_passes,
    pass_groups,
    relative_rotation_errors,
)
from sq_mitsuba.geometry.rotation import axis_angle_to_matrix, quaternion_to_matrix
from sq_mitsuba.inference.loading import load_model, with_fast_path
from sq_mitsuba.inference.refine import RefineOptions
from sq_mitsuba.inference.search import SearchOptions
from sq_mitsuba.inference.sequence import SequenceOptions

FRAMES = 3
#: Small settings: a few steps everywhere (these tests check the bookkeeping, not the quality).
SMALL = PassOptions(counts=(1, 2, FRAMES), sequence=SequenceOptions(steps=3, spp=2),
                    search=SearchOptions(grid=128, screen_steps=2),
                    refinement=RefineOptions(steps=2, patience=2, shape="pose", depth="fixed"),
                    surface_points=300, volume_points=2000, silhouette_spp=4)


@pytest.fixture(scope="module")
def pass_dataset(tmp_path_factory):
    """Two generated spacecraft, one pass of 3 frames each at 64 px (both test models)."""
    from sq_mitsuba.data.library import generate_model
    from sq_mitsuba.data.spacecraft import catalogue
    from sq_mitsuba.data.spe3r import RenderOptions, render_dataset

    models = tmp_path_factory.mktemp("pass_models")
    entries = catalogue(2, 5)
    for entry in entries:
        generate_model(entry, models, points=3000)
    (models / "splits.csv").write_text("".join(f"{e.name},test\n" for e in entries))
    out = tmp_path_factory.mktemp("pass_data") / "data"
    options = RenderOptions(images_per_model=FRAMES, seed=3, resolution=64, spp=2,
                            pass_frames=FRAMES)
    assert not render_dataset(models, out, options, progress=False).failures
    return out


def test_relative_rotation_errors_against_angles_set_by_hand():
    """Frames turning 10 deg a step about z, read as turning 13 deg a step about z: 3 deg
    off from frame 1 on, NaN for frame 0; a common misreading of every frame costs nothing."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    truth = axis_angle_to_matrix(torch.stack([z * math.radians(10 * k) for k in range(4)]))
    read = axis_angle_to_matrix(torch.stack([z * math.radians(13 * k) for k in range(4)]))
    errors = relative_rotation_errors(read, truth)
    assert math.isnan(float(errors[0]))
    np.testing.assert_allclose(errors[1:].numpy(), [3.0, 3.0, 3.0], atol=1e-6)
    turned = truth @ axis_angle_to_matrix(torch.tensor([[0.3, -1.0, 0.2]], dtype=torch.float64))
    np.testing.assert_allclose(relative_rotation_errors(turned, truth)[1:].numpy(), 0.0,
                               atol=1e-5)


def _rows(path):
    with open(path, newline="") as file:
        return list(csv.DictReader(file))


def test_each_method_is_scored_per_frame_as_called_directly(eval_checkpoint, pass_dataset,
                                                           tmp_path):
    out = tmp_path / "passes"
    result = evaluate_passes(load_model(eval_checkpoint), pass_dataset, out, SMALL,
                             progress=False)
    assert sorted(p.name for p in result.files) == sorted(OUTPUT_FILES)
    rows = _rows(out / "per_frame.csv")
    # Two passes; N = 1: network and single; N = 2, 3: the sequence as well, a row a frame.
    assert len(rows) == 2 * (2 * 1 + 3 * 2 + 3 * FRAMES)
    assert {(r["frames"], r["method"]) for r in rows} == {
        ("1", "network"), ("1", "single"), ("2", "network"), ("2", "single"),
        ("2", "sequence"), ("3", "network"), ("3", "single"), ("3", "sequence")}

    from sq_mitsuba.data.spe3r import Spe3rDataset

    dataset = Spe3rDataset(pass_dataset, "test", image_size=64)
    groups = pass_groups(dataset)
    assert len(groups) == 2 and all(len(items) == FRAMES for items in groups.values())
    (model_index, number), items = next(iter(groups.items()))
    assert [dataset.items[i][2]["frame_in_pass"] for i in items] == [0, 1, 2]
    model = dataset.models[model_index]
    images = torch.stack([dataset[i]["image"] for i in items])
    truth = torch.stack([quaternion_to_matrix(torch.tensor(
        dataset.items[i][2]["q_vbs2tango_true"], dtype=torch.float64)) for i in items])
    predictor = with_fast_path(load_model(eval_checkpoint), True, min_target=0.0)

    def column(method, frames, name):
        return np.array([float(r[name]) if r[name] else np.nan for r in rows
                         if (r["model"], r["pass"], r["frames"], r["method"])
                         == (model, str(number), str(frames), method)])

    # The network row: its own reading's relative rotations; frame 0's shape and rotation the
    # same for N = 1 and 3 (the first N frames of the pass; the 2D IoU's samples differ).
    network = predictor.predict(images)
    np.testing.assert_allclose(column("network", FRAMES, "relative_rotation_deg")[1:],
                               relative_rotation_errors(network.rotation, truth)[1:].numpy(),
                               atol=1e-4)
    for name in ("chamfer_l1_paper", "camera_chamfer", "rotation_error_folded_deg"):
        assert column("network", 1, name)[0] == pytest.approx(column("network", FRAMES,
                                                                     name)[0], abs=1e-9)
    # The single row: each frame alone through the search and refinement.
    alone = predictor.predict(images, refine=True, search=SMALL.search,
                              refinement=SMALL.refinement)
    np.testing.assert_allclose(column("single", FRAMES, "relative_rotation_deg")[1:],
                               relative_rotation_errors(alone.rotation, truth)[1:].numpy(),
                               atol=1e-4)
    # The sequence row: predict_sequence on the same three frames.
    sequence = predictor.predict_sequence(images, ordered=True, options=SMALL.sequence)
    np.testing.assert_allclose(column("sequence", FRAMES, "relative_rotation_deg")[1:],
                               relative_rotation_errors(sequence.rotation, truth)[1:].numpy(),
                               atol=1e-4)
    # N = 2 is predict_sequence on the first two frames alone.
    pair = predictor.predict_sequence(images[:2], ordered=True, options=SMALL.sequence)
    np.testing.assert_allclose(column("sequence", 2, "relative_rotation_deg")[1:],
                               relative_rotation_errors(pair.rotation, truth[:2])[1:].numpy(),
                               atol=1e-4)
    # The summary's means are the per-frame table's.
    with open(out / "summary.csv", newline="") as file:
        summary = {(r["frames"], r["method"], r["metric"]): r for r in csv.DictReader(file)}
    for (frames, method) in (("3", "sequence"), ("1", "single")):
        values = [float(r["iou_2d"]) for r in rows
                  if (r["frames"], r["method"]) == (frames, method)]
        assert float(summary[(frames, method, "iou_2d")]["mean"]) == pytest.approx(
            np.mean(values), abs=1e-9)
    recorded = json.loads((out / "passes.json").read_text())
    assert recorded["counts"] == [1, 2, FRAMES] and len(recorded["passes"]) == 2
    assert recorded["resolution"] == 64


def test_bad_pass_evaluations_are_refused_before_any_work(eval_checkpoint, pass_dataset,
                                                         train_dataset, tmp_path):
    predictor = load_model(eval_checkpoint)
    # More frames than a pass holds.
    with pytest.raises(ValueError, match=r"^counts: 4 frames asked, but pass 0 of model "
                                         r"\S+ has 3 \(2 pass\(es\) too short\)"):
        evaluate_passes(predictor, pass_dataset, tmp_path / "a",
                        PassOptions(counts=(1, 4)), progress=False)
    # A dataset of independent images.
    with pytest.raises(ValueError, match=r"not a dataset of passes .* render one with "
                                         r"dataset render --pass-frames F"):
        evaluate_passes(predictor, train_dataset, tmp_path / "b", PassOptions(counts=(1,)),
                        progress=False)
    # An output inside the dataset.
    with pytest.raises(ValueError, match="inside the dataset folder"):
        evaluate_passes(predictor, pass_dataset, pass_dataset / "evaluation", SMALL,
                        progress=False)
    for name in ("a", "b"):
        assert not (tmp_path / name / "passes.json").exists()


def test_a_bad_frame_of_the_last_pass_is_refused_before_the_first_is_scored(
        eval_checkpoint, pass_dataset, tmp_path, monkeypatch):
    """A frame that cannot be read, of another size, or in which the network finds no target
    to fit, in the last pass scored: one line naming its file, before any pass is searched."""
    from PIL import Image

    from sq_mitsuba.data.spe3r.layout import read_splits
    from sq_mitsuba.inference.predictor import Predictor

    predictor = load_model(eval_checkpoint)
    searched = []
    monkeypatch.setattr(Predictor, "refine", lambda *a, **k: searched.append(1))
    data = tmp_path / "data"
    shutil.copytree(pass_dataset, data)
    model = sorted(read_splits(data / "splits.csv"))[-1]
    frame = sorted((data / model / "images").iterdir())[-1]
    good = frame.read_bytes()
    mask = frame.parent.parent / "masks" / frame.name
    good_mask = mask.read_bytes()
    # The image of another size than camera.json is blamed, not its mask; a mask of another
    # size than its image is.
    cases = [(good[: len(good) // 2], frame, "cannot read image"),
             (None, frame, r"32 x 32 px, but its mask and camera.json 64 x 64 px"),
             ("mask", mask, r"mask is 32 x 32 px, its image 000002.png is 64 x 64 px")]
    for k, (content, named, message) in enumerate(cases):
        frame.write_bytes(good)
        mask.write_bytes(good_mask)
        if isinstance(content, bytes):
            frame.write_bytes(content)
        else:
            Image.fromarray(np.zeros((32, 32), np.uint8)).save(named)
        with pytest.raises(ValueError, match=rf"^{re.escape(str(named))}: .*{message}"):
            evaluate_passes(predictor, data, tmp_path / f"out{k}", SMALL, progress=False)
        assert searched == [] and not (tmp_path / f"out{k}").exists()
    frame.write_bytes(good)
    mask.write_bytes(good_mask)
    # A black middle frame: named (frame 1), also when passes of two frames are all fitted.
    middle = sorted((data / model / "images").iterdir())[1]
    kept = middle.read_bytes()
    Image.fromarray(np.zeros((64, 64), np.uint8)).save(middle)
    for counts in ((1, 2, FRAMES), (1, 2)):
        with pytest.raises(ValueError, match=rf"^{re.escape(str(middle))}: frame 1 of pass 0 "
                                             r"of \S+ holds no target to fit"):
            evaluate_passes(predictor, data, tmp_path / "black", replace(SMALL, counts=counts),
                            progress=False)
        assert searched == [] and not (tmp_path / "black").exists()
    middle.write_bytes(kept)
    good_mask = mask.read_bytes()
    for path in (frame, mask):  # both of another size than camera.json's
        Image.fromarray(np.zeros((32, 32), np.uint8)).save(path)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(frame))}: 32 x 32 px, but "
                                         "camera.json describes 64 x 64 px images$"):
        evaluate_passes(predictor, data, tmp_path / "small", SMALL, progress=False)
    assert searched == []
    mask.write_bytes(good_mask)
    # Without a pass to fit (N = 1 alone) the network is not asked about the frames.
    Image.fromarray(np.zeros((64, 64), np.uint8)).save(frame)
    monkeypatch.undo()
    evaluate_passes(predictor, data, tmp_path / "single", replace(SMALL, counts=(1,)),
                    progress=False)


def test_study_passes_cli_writes_the_tables_and_refuses_in_one_line(eval_checkpoint,
                                                                    pass_dataset, tmp_path,
                                                                    capsys):
    from sq_mitsuba.cli import main

    small = ["--set", "sequence.steps=2", "--set", "sequence.spp=2", "--set", "search.grid=128",
             "--set", "search.screen_steps=2", "--set", "refinement.steps=2",
             "--set", "refinement.patience=2", "--set", "surface_points=200",
             "--set", "volume_points=1000", "--set", "silhouette_spp=2"]
    out = tmp_path / "cli"
    assert main(["study", "passes", "--data", str(pass_dataset), "--checkpoint",
                 str(eval_checkpoint), "--out", str(out), "--counts", "2", "--passes", "1",
                 "--quiet", *small]) == 0
    rows = _rows(out / "per_frame.csv")
    assert {(r["frames"], r["method"]) for r in rows} == {("2", "network"), ("2", "single"),
                                                          ("2", "sequence")}
    assert len(rows) == 3 * 2 and len({r["model"] for r in rows}) == 1
    recorded = json.loads((out / "passes.json").read_text())
    assert recorded["options"]["sequence"]["steps"] == 2 and recorded["counts"] == [2]
    # The timings, passes.json's alone: the timed methods, one pass's seconds (mean = median).
    timed = {(t["frames"], t["method"]): t for t in recorded["seconds_per_frame"]}
    assert list(timed) == [(2, "single"), (2, "sequence")]  # in the tables' order
    assert all(0 < t["mean"] == t["median"] for t in timed.values())
    assert "seconds" not in (out / "summary.csv").read_text() + (out / "per_frame.csv").read_text()
    capsys.readouterr()
    assert main(["study", "passes", "--data", str(pass_dataset), "--checkpoint",
                 str(eval_checkpoint), "--out", str(tmp_path / "long"), "--counts", "9",
                 "--quiet"]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "counts: 9 frames asked" in error
    assert main(["study", "passes", "--data", str(tmp_path / "missing"), "--out",
                 str(tmp_path / "x"), "--quiet"]) == 2
    assert "dataset folder not found" in capsys.readouterr().err


def test_pass_groups_orders_each_pass_and_refuses_a_gap():
    """Frames listed out of order come back in frame order, per (model, pass); a pass with a
    frame missing or twice is refused in one line naming it."""
    from types import SimpleNamespace

    def dataset(frames):
        return SimpleNamespace(root="data", models=["m0", "m1"], items=[
            (model, index, {"pass": number, "frame_in_pass": frame, "filename": f"{index}.png"})
            for index, (model, number, frame) in enumerate(frames)])

    groups = pass_groups(dataset([(1, 0, 2), (0, 0, 1), (1, 0, 0), (0, 0, 0), (1, 0, 1),
                                  (0, 1, 1), (0, 1, 0)]))
    assert groups == {(0, 0): [3, 1], (0, 1): [6, 5], (1, 0): [2, 4, 0]}
    with pytest.raises(ValueError, match=r"^data: pass 0 of model m0 has frames \[0, 2\], not "
                                         r"0 to 1 once each$"):
        pass_groups(dataset([(0, 0, 0), (0, 0, 2)]))
    with pytest.raises(ValueError, match=r"has frames \[0, 0\]"):
        pass_groups(dataset([(0, 0, 0), (0, 0, 0)]))


def test_pass_groups_read_independent_images_as_one_set_of_views_per_model():
    """Unordered (``views``), a dataset without pass labels is one set per model, its images in
    image order whatever the listing's order; a dataset of passes stays passes; a dataset
    that labels some images as passes and not others is refused."""
    from types import SimpleNamespace

    def dataset(items):
        return SimpleNamespace(root="data", models=["m0", "m1"], items=items)

    independent = dataset([(1, 1, {}), (0, 2, {}), (0, 0, {}), (1, 0, {}), (0, 1, {})])
    assert pass_groups(independent, views=True) == {(0, 0): [2, 4, 1], (1, 0): [3, 0]}
    with pytest.raises(ValueError, match=r"not a dataset of passes .* with --no-ordered\)$"):
        pass_groups(independent)
    passes = dataset([(0, 0, {"pass": 0, "frame_in_pass": 1}),
                      (0, 1, {"pass": 0, "frame_in_pass": 0})])
    assert pass_groups(passes, views=True) == pass_groups(passes) == {(0, 0): [1, 0]}
    with pytest.raises(ValueError, match=r"not a dataset of passes .* other images are "
                                         r"labelled as passes: render the dataset again\)$"):
        pass_groups(dataset([(0, 0, {"pass": 0, "frame_in_pass": 0}), (0, 1, {})]), views=True)


def test_independent_views_are_scored_unordered(eval_checkpoint, train_dataset, tmp_path):
    """``ordered=False`` on a dataset of independent images: the test model's first N images
    are one set, scored per frame like a pass's, its rows ordered by image."""
    predictor = load_model(eval_checkpoint)
    out = tmp_path / "views"
    evaluate_passes(predictor, train_dataset, out, replace(SMALL, counts=(1, FRAMES),
                                                           ordered=False), progress=False)
    with open(out / "per_frame.csv", newline="") as file:
        rows = list(csv.DictReader(file))
    test_model = (train_dataset / "splits.csv").read_text().splitlines()[-1].split(",")[0]
    assert {r["model"] for r in rows} == {test_model} and {r["pass"] for r in rows} == {"0"}
    sequence = [r for r in rows if r["method"] == "sequence"]
    assert [r["frame"] for r in sequence] == [str(k) for k in range(FRAMES)]
    assert sequence[0]["relative_rotation_deg"] == ""
    assert all(0 <= float(r["relative_rotation_deg"]) <= 180 for r in sequence[1:])
    assert json.loads((out / "passes.json").read_text())["options"]["ordered"] is False


def test_an_interrupted_pass_study_takes_up_where_it_stopped(eval_checkpoint, pass_dataset,
                                                             tmp_path, monkeypatch):
    """Interrupted in its second pass, a rerun reads the first pass back (it scores only the
    second) and writes what an uninterrupted run does; other settings start afresh."""
    from sq_mitsuba.evaluation.passes import PARTIAL
    from sq_mitsuba.inference.predictor import Predictor

    options = PassOptions(**{**SMALL.__dict__, "counts": (1, 2)})
    whole = tmp_path / "whole"
    evaluate_passes(load_model(eval_checkpoint), pass_dataset, whole, options, progress=False)
    assert not (whole / PARTIAL).exists()
    sequences: list[int] = []
    real = Predictor.predict_sequence

    def interrupted(self, images, *args, **kwargs):
        sequences.append(len(images))
        if len(sequences) == 2:  # the second pass
            raise KeyboardInterrupt
        return real(self, images, *args, **kwargs)

    out = tmp_path / "out"
    with monkeypatch.context() as patch:
        patch.setattr(Predictor, "predict_sequence", interrupted)
        with pytest.raises(KeyboardInterrupt):
            evaluate_passes(load_model(eval_checkpoint), pass_dataset, out, options,
                            progress=False)
    assert len(list((out / PARTIAL).glob("*__*.json"))) == 1
    # What the interrupt left, for the unreadable rows below: the files a second run
    # interrupted in the same pass writes, without running it again.
    left = shutil.copytree(out / PARTIAL, tmp_path / "left")
    # A write killed mid-way leaves its temporary, cut short: it is no pass (it discarded
    # every kept pass when read as one).
    (out / PARTIAL / ".sc000_x__1.k3j4l5.tmp.json").write_text("[{")
    sequences.clear()
    with monkeypatch.context() as patch:
        patch.setattr(Predictor, "predict_sequence",
                      lambda self, images, *a, **k: (sequences.append(len(images)),
                                                     real(self, images, *a, **k))[1])
        evaluate_passes(load_model(eval_checkpoint), pass_dataset, out, options,
                        progress=False)
    assert sequences == [2]  # the second pass alone
    for name in ("per_frame.csv", "summary.csv", "summary.md"):  # no timing in them
        assert (out / name).read_bytes() == (whole / name).read_bytes(), name
    assert not (out / PARTIAL).exists()
    # A pass's kept rows that cannot be read, or a partial run of other settings: discarded,
    # with a warning, and the run starts afresh (stopped in its first pass here: a fresh
    # run's scores are the uninterrupted run's, above): its partial folder holds this run's
    # identity and no pass.
    shutil.copytree(left, out / PARTIAL)
    identity = (out / PARTIAL / "run.json").read_text()
    next((out / PARTIAL).glob("*__*.json")).write_text("[{")
    other = tmp_path / "other"
    (other / PARTIAL).mkdir(parents=True)
    recorded = json.loads(identity)
    recorded["options"]["split"] = "val" if recorded["options"]["split"] != "val" else "test"
    (other / PARTIAL / "run.json").write_text(json.dumps(recorded))
    (other / PARTIAL / "sc000_x__0.json").write_text("[]")

    def first_pass_stops(self, images, *args, **kwargs):
        sequences.append(len(images))
        raise KeyboardInterrupt

    for folder, cause in ((out, "unreadable: "), (other, "option split: ")):
        sequences.clear()
        with monkeypatch.context() as patch, pytest.warns(
                UserWarning, match=re.escape(f"an interrupted run's passes discarded ({cause}")):
            patch.setattr(Predictor, "predict_sequence", first_pass_stops)
            with pytest.raises(KeyboardInterrupt):
                evaluate_passes(load_model(eval_checkpoint), pass_dataset, folder, options,
                                progress=False)
        assert len(sequences) == 1, cause  # the first pass began: nothing was taken as done
        assert (folder / PARTIAL / "run.json").read_text() == identity, cause
        assert not list((folder / PARTIAL).glob("*__*.json")), cause


def test_a_pass_dataset_opens_at_its_own_resolution(pass_dataset):
    """``image_size=None``: the images as rendered (camera.json's width), what the pass study
    reads whatever the network's input size."""
    from sq_mitsuba.data.spe3r import Spe3rDataset

    dataset = Spe3rDataset(pass_dataset, "test", image_size=None, num_surface=10,
                           num_occupancy=2)
    assert dataset.image_size == dataset.camera.width == 64
    assert dataset[0]["image"].shape == (1, 64, 64)
    with pytest.raises(ValueError, match="image_size: expected a positive integer"):
        Spe3rDataset(pass_dataset, "test", image_size=0)


def test_the_frame_check_reads_frames_as_a_pass_fits_them(pass_dataset, tmp_path, monkeypatch):
    """The check before the study reads each pass through the network from as many turned
    copies as ``predict_sequence``'s own frames do (:data:`FRAMES_SEARCH`), so it refuses the
    frames the fit would; and it names a frame's file whatever its extension."""
    import contextlib

    from PIL import Image

    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.evaluation import passes
    from sq_mitsuba.inference.predictor import Predictor
    from sq_mitsuba.inference.sequence import FRAMES_SEARCH
    from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet

    data = tmp_path / "data"
    shutil.copytree(pass_dataset, data)
    dataset = Spe3rDataset(data, "test", image_size=None, num_surface=10, num_occupancy=2)
    torch.manual_seed(0)
    network = SuperquadricNet(NetworkConfig(
        encoder="efficientnet_lite0", latent="spatial", pose_head="grid", mask_head=True,
        image_size=64, rotation_cells=72, num_primitives=2, latent_dim=16, hidden_dim=16,
        spatial_channels=16)).eval()
    predictor = Predictor(network, dataset.camera)
    assert predictor.can_turn(dataset.camera) and FRAMES_SEARCH.turns > 1
    turns = []
    original = Predictor.predict

    def recording(self, images, camera=None, **kwargs):
        turns.append(kwargs.get("turns"))
        return original(self, images, camera, **kwargs)

    monkeypatch.setattr(Predictor, "predict", recording)
    groups = passes.pass_groups(dataset)
    with contextlib.suppress(ValueError):  # an untrained mask head may see no target
        passes._check_frames(predictor, dataset, groups, sequences=True, progress=False)
    assert turns and set(turns) == {FRAMES_SEARCH.turns}
    # A frame stored as JPEG where its label says .png: its own file is named.
    item = next(iter(groups.values()))[1]
    png = dataset.image_file(item)
    Image.open(png).convert("L").save(png.with_suffix(".jpg"))
    png.unlink()
    assert dataset.image_file(item) == png.with_suffix(".jpg")


def test_a_pass_study_refuses_a_folder_another_command_wrote(eval_checkpoint, pass_dataset,
                                                           tmp_path):
    """Into an eval's folder the study wrote its summary.csv and summary.md over the eval's
    (report then refused the folder): a file of an output's name where no pass study wrote
    is refused before any work; a folder a study wrote is taken up again."""
    folder = tmp_path / "eval"
    folder.mkdir()
    (folder / "summary.csv").write_text("method,metric\n")
    (folder / "eval.json").write_text("{}")
    with pytest.raises(ValueError, match=r"summary.csv: an output of study passes, but no "
                                         r"earlier pass study there wrote it; move it"):
        evaluate_passes(load_model(eval_checkpoint), pass_dataset, folder, SMALL,
                        progress=False)
    assert (folder / "summary.csv").read_text() == "method,metric\n"
