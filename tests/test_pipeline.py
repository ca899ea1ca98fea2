"""The one inference pipeline: ``Predictor.predict(images, refine=True)`` is what ``sq-mitsuba
predict --refine`` writes and what ``eval --refine`` scores, and it refuses bad input in one
line.

References: the CLI's files (``predict``) and the evaluation's per-image table (``eval``),
each produced by its own command from the same checkpoint and images; the rotation error is
recomputed here from the ground-truth labels."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from output_checks import one_torch_thread  # noqa: F401 (autouse fixture)
from PIL import Image

from sq_mitsuba.cli import main
from sq_mitsuba.data.spe3r import Spe3rDataset
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.metrics import rotation_error_deg
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.inference.refine import RefineOptions
from sq_mitsuba.inference.search import SEARCH_REFINEMENT, SearchOptions

#: The small search and refinement of these tests, as ``--set`` options and as options.
SMALL = {"refinement.steps": 4, "refinement.patience": 4, "search.grid": 128,
         "search.screen_steps": 2}
SEARCH = SearchOptions(grid=128, screen_steps=2)
REFINEMENT = RefineOptions(**{**{f.name: getattr(SEARCH_REFINEMENT, f.name) for f in
                                 SEARCH_REFINEMENT.__dataclass_fields__.values()},
                              "steps": 4, "patience": 4})


def _set(options: dict) -> list[str]:
    return [arg for key, value in options.items() for arg in ("--set", f"{key}={value}")]


@pytest.fixture
def one_drjit_thread():
    """Dr.Jit on one thread: the refinement's backward pass sums gradients with atomic adds,
    whose rounding depends on how threads interleave; two runs must take the same steps."""
    from sq_mitsuba.training.step import mitsuba_for

    with mitsuba_for(torch.device("cpu"), deterministic=True):
        yield


def _test_image(dataset_root):
    model = next(line.split(",")[0] for line in
                 (dataset_root / "splits.csv").read_text().splitlines()
                 if line.endswith(",test"))
    return dataset_root / model / "images" / "000002.png"


def test_predict_refine_is_what_the_cli_writes(eval_checkpoint, train_dataset, tmp_path,
                                               one_drjit_thread):
    image = _test_image(train_dataset)
    out = tmp_path / "cli"
    assert main(["predict", str(image), "--checkpoint", str(eval_checkpoint), "--out", str(out),
                 "--refine", *_set(SMALL), "--quiet"]) == 0
    pose = json.loads((out / f"{image.stem}.pose.json").read_text())
    written = Assembly.load(out / f"{image.stem}.assembly.json")

    pixels = torch.from_numpy(np.array(Image.open(image)))[None]
    fitted = load_model(eval_checkpoint, fast=True).predict(
        pixels, refine=True, search=SEARCH, refinement=REFINEMENT)
    torch.testing.assert_close(fitted.assembly.params.float(), written.params.float(),
                               atol=1e-5, rtol=1e-5)
    assert pose["q_vbs2tango"] == pytest.approx(fitted.quaternion[0].tolist(), abs=1e-6)
    assert pose["r_Vo2To_vbs"] == pytest.approx(fitted.translation[0].tolist(), abs=1e-6)
    assert pose["iou_after"] == pytest.approx(float(fitted.fit.iou[0]), abs=1e-9)
    assert pose["search_score"] == pytest.approx(float(fitted.fit.search_score[0]), abs=1e-9)
    # This network has no mask head: both fitted the image's own segmentation.
    assert pose["mask_source"] == fitted.fit.mask_source == "segmentation"


@pytest.mark.slow  # end to end: `make test` runs it, `make test-fast` not
def test_predict_refine_is_what_eval_refine_scores(eval_checkpoint, train_dataset, tmp_path,
                                                   one_drjit_thread):
    out = tmp_path / "eval"
    assert main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
                 "--split", "val", "--out", str(out), "--refine", "--no-baseline",
                 "--no-figures", *_set({**SMALL, "refine_ground_truth": "false",
                                         "surface_points": 500, "volume_points": 3000}),
                 "--quiet"]) == 0
    with open(out / "per_image.csv", newline="") as file:
        rows = [row for row in csv.DictReader(file) if row["method"] == "refined"]

    dataset = Spe3rDataset(train_dataset, "val", image_size=64, num_surface=10,
                           num_occupancy=2)
    items = [dataset[i] for i in range(len(dataset))]
    images = torch.stack([item["image"] for item in items])
    truth = torch.stack([item["rotation"] for item in items]).double()
    predictor = load_model(eval_checkpoint, fast=True)
    fitted = predictor.predict(images, dataset.camera.rescaled(64, 64), refine=True,
                               search=SEARCH, refinement=REFINEMENT)
    assert len(rows) == len(items) == 4
    errors = rotation_error_deg(fitted.rotation, truth)
    for k, row in enumerate(rows):
        assert (row["model"], int(row["index"])) == (items[k]["model"], int(items[k]["index"]))
        # Blank where the segmentation found no usable target: not fitted, NaN here.
        assert (row["refine_iou_after"] == "") == (not bool(fitted.fit.fitted[k]))
        if row["refine_iou_after"]:
            assert float(row["refine_iou_after"]) == pytest.approx(float(fitted.fit.iou[k]),
                                                                   abs=1e-9)
        assert float(row["rotation_error_deg"]) == pytest.approx(float(errors[k]), abs=1e-6)
    assert bool(fitted.fit.fitted.any())
    mean = sum(float(row["rotation_error_deg"]) for row in rows) / len(rows)
    assert mean == pytest.approx(float(errors.mean()), abs=1e-6)


def test_the_refined_pose_is_the_same_to_the_last_bit_on_many_threads(eval_checkpoint,
                                                                     train_dataset):
    """Several Dr.Jit threads sum the silhouettes' samples and gradients in the order of their
    timing, and Adam turns a near-zero gradient's sign into a full step: the search and the
    refinement render on one thread by default (``RefineOptions.deterministic``), so two runs
    on a machine of four threads agree to the last bit, and its threads are left as they were."""
    import drjit as dr

    image = torch.from_numpy(np.array(Image.open(_test_image(train_dataset))))[None]
    predictor = load_model(eval_checkpoint)
    network = predictor.predict(image)
    before = dr.thread_count()
    dr.set_thread_count(4)
    try:
        runs = [predictor.refine(image, network, search=SEARCH,
                                 refinement=replace(REFINEMENT, steps=12, patience=12))
                for _ in range(3)]
        assert dr.thread_count() == 4
    finally:
        dr.set_thread_count(before)
    for run in runs[1:]:
        assert torch.equal(run.rotation, runs[0].rotation)
        assert torch.equal(run.translation, runs[0].translation)
        assert torch.equal(run.fit.candidate_scores, runs[0].fit.candidate_scores)


def test_a_pass_is_the_same_to_the_last_bit_on_many_threads(eval_checkpoint, train_dataset):
    """The pass's joint fit (refine_pose_and_shape, called directly) renders on one thread as
    well: two passes of the same frames on four threads agree bit for bit."""
    import drjit as dr

    from sq_mitsuba.inference.loading import with_fast_path
    from sq_mitsuba.inference.sequence import SequenceOptions

    folder = _test_image(train_dataset).parent
    frames = torch.stack([torch.from_numpy(np.array(Image.open(folder / f"{k:06d}.png")))
                          for k in range(3)])
    predictor = with_fast_path(load_model(eval_checkpoint), False, min_target=0.0)
    before = dr.thread_count()
    dr.set_thread_count(4)
    try:
        runs = [predictor.predict_sequence(frames, options=SequenceOptions(steps=8, spp=4),
                                           search=SEARCH, refinement=REFINEMENT)
                for _ in range(2)]
    finally:
        dr.set_thread_count(before)
    assert torch.equal(runs[0].assembly.params, runs[1].assembly.params)
    assert torch.equal(runs[0].rotation, runs[1].rotation)
    assert torch.equal(runs[0].translation, runs[1].translation)


def test_the_fit_records_what_was_fitted_and_keeps_the_networks_reading(eval_checkpoint,
                                                                        train_dataset):
    image = torch.from_numpy(np.array(Image.open(_test_image(train_dataset))))[None]
    predictor = load_model(eval_checkpoint)
    network = predictor.predict(image)
    fitted = predictor.predict(image, refine=True, search=SEARCH, refinement=REFINEMENT)
    torch.testing.assert_close(fitted.network.assembly.params, network.assembly.params)
    torch.testing.assert_close(fitted.network.rotation, network.rotation)
    fit = fitted.fit
    assert fit.turns == 1  # a regressing head cannot read turned copies
    assert fit.mask.shape == (1, 64, 64) and fit.mask.dtype == torch.bool and fit.mask.any()
    assert bool(fit.fitted[0]) and 0 < float(fit.iou[0]) <= 1
    # The scores of every candidate are kept; the best one is the search's pick.
    assert fit.candidates.shape[:2] == fit.candidate_scores.shape and fit.candidates.shape[1] > 4
    assert fit.seconds >= fit.search_seconds > 0
    # The pose is a rotation, the pixel and depth follow the translation.
    rotation = fitted.rotation[0]
    torch.testing.assert_close(rotation.T @ rotation, torch.eye(3, dtype=rotation.dtype),
                               atol=1e-9, rtol=0)
    torch.testing.assert_close(fitted.depth, fitted.translation[:, 2])
    torch.testing.assert_close(fitted.pixel, fitted.camera.project(fitted.translation))
    # At a target 4 m long every length scales, the network's and the search's with it; the
    # pixel is still where the translation projects (the image is the same).
    metric = fitted.scaled(4.0)
    for scaled, unit in ((metric, fitted), (metric.network, fitted.network),
                         (metric.fit.start, fitted.fit.start)):
        torch.testing.assert_close(scaled.assembly.params, unit.assembly.scaled(4.0).params)
        torch.testing.assert_close(scaled.translation, 4.0 * unit.translation)
        torch.testing.assert_close(scaled.depth, 4.0 * unit.depth)
        assert torch.equal(scaled.rotation, unit.rotation) and torch.equal(scaled.pixel,
                                                                           unit.pixel)
    torch.testing.assert_close(metric.fit.search_translation, 4.0 * fit.search_translation)
    torch.testing.assert_close(metric.pixel, metric.camera.project(metric.translation))
    assert torch.equal(metric.fit.mask, fit.mask) and torch.equal(metric.fit.iou, fit.iou)
    assert metric.scale == 4.0 and metric.network.scale == 4.0 and fitted.scale == 1.0
    for bad in (float("nan"), 0.0, torch.tensor([4.0]), True):  # one factor for the batch
        with pytest.raises(ValueError, match=r"^factor: "):
            fitted.scaled(bad)
    # The fits work at the network's unit size: a scaled reading is refused, not refined.
    with pytest.raises(ValueError, match=r"^network: scaled to a target of 4 m"):
        predictor.refine(image, network.scaled(4.0), search=SEARCH, refinement=REFINEMENT)
    with pytest.raises(ValueError, match=r"^reuse: scaled to a target of 4 m"):
        predictor.refine(image, network, reuse=metric.fit)
    # A second fit to another mask reuses the start and returns the other mask's fit.
    other = torch.zeros(1, 64, 64, dtype=torch.bool)
    other[0, 20:44, 16:48] = True
    again = predictor.refine(image, network, mask=other, search=SEARCH, refinement=REFINEMENT,
                             reuse=fit)
    assert again.fit.mask_source == "given" and torch.equal(again.fit.mask, other)
    assert again.fit.start is fit.start
    # A fit of other images, or from other turned copies, is not reused.
    flipped = image.flip(-1)
    with pytest.raises(ValueError, match=r"^reuse: expected the fit of these 1 images"):
        predictor.refine(flipped, predictor.predict(flipped), mask=other, search=SEARCH,
                         refinement=REFINEMENT, reuse=fit)
    with pytest.raises(ValueError, match=r"^reuse: "):
        predictor.refine(image, network, mask=other, turns=fit.turns + 1, reuse=fit)
    # Nor a fit under another camera (its start's depth and pixels are that camera's).
    from sq_mitsuba.geometry.camera import Camera

    wider = Camera.from_fov(50.0, 64, 64)
    with pytest.raises(ValueError, match=r"^reuse: .* under this camera"):
        predictor.refine(image, predictor.predict(image, wider), wider, mask=other,
                         search=SEARCH, refinement=REFINEMENT, reuse=fit)


def test_an_empty_mask_keeps_the_start_with_nan_scores(eval_checkpoint, train_dataset):
    image = torch.from_numpy(np.array(Image.open(_test_image(train_dataset))))[None]
    predictor = load_model(eval_checkpoint)
    images = image.repeat(2, 1, 1)
    masks = torch.zeros(2, 64, 64, dtype=torch.bool)
    masks[1, 16:48, 16:48] = True
    fitted = predictor.predict(images, refine=True, mask=masks, search=SEARCH,
                               refinement=REFINEMENT)
    assert fitted.fit.fitted.tolist() == [False, True]
    assert math.isnan(float(fitted.fit.iou[0])) and not math.isnan(float(fitted.fit.iou[1]))
    torch.testing.assert_close(fitted.rotation[0], fitted.fit.start.rotation[0].double())


@pytest.mark.parametrize("kwargs, message", [
    ({"mask": "segmentation"}, "mask: only used with refine=True"),
    ({"refine": "yes"}, "refine: expected True or False"),
    ({"refine": True, "mask": "outline"}, "mask: expected 'network', 'segmentation'"),
    ({"refine": True, "mask": torch.zeros(1, 32, 32)}, r"mask: expected shape \(1, 64, 64\)"),
    ({"refine": True, "mask": torch.full((1, 64, 64), float("nan"))}, "mask: contains NaN"),
    ({"refine": True, "mask": [[0]]}, "mask: expected 'network', 'segmentation', a tensor"),
    ({"refine": True, "turns": 4}, "turns: reading the rotation from turned copies needs"),
])
def test_bad_pipeline_input_is_one_line_naming_the_argument(eval_checkpoint, kwargs, message,
                                                            monkeypatch):
    from sq_mitsuba.inference import pipeline

    def no_turned_copies(*args, **kwargs):  # a bad mask is refused before they run
        raise AssertionError("the turned copies ran before the input was checked")

    monkeypatch.setattr(pipeline, "search_start", no_turned_copies)
    predictor = load_model(eval_checkpoint)
    with pytest.raises(ValueError, match=message) as info:
        predictor.predict(torch.zeros(1, 64, 64), **kwargs)
    assert "\n" not in str(info.value)


def test_refine_refuses_a_reading_of_other_images(eval_checkpoint):
    predictor = load_model(eval_checkpoint)
    network = predictor.predict(torch.zeros(2, 64, 64))
    with pytest.raises(ValueError, match="network: expected this predictor's own reading"):
        predictor.refine(torch.zeros(1, 64, 64), network)


def test_the_fitted_mask_prefers_the_networks_mask_head():
    """The mask fitted: the prediction's mask head when it has one (thresholded at 0.5), else
    the threshold segmentation of the image; an empty mask is not usable."""
    from types import SimpleNamespace

    from sq_mitsuba.inference.pipeline import masks_to_fit

    images = torch.zeros(2, 1, 16, 16)
    images[0, 0, 4:9, 5:12] = 0.8  # a lit target; image 1 is black (nothing to segment)
    head = torch.zeros(2, 16, 16)
    head[:, 2:6, 3:7] = 0.9
    head[1] = 0.2  # the head sees nothing in image 1
    masks, usable, source = masks_to_fit(SimpleNamespace(mask=head), images, "network")
    assert source == "network" and usable.tolist() == [True, False]
    assert torch.equal(masks, head > 0.5)
    for prediction, wanted in ((SimpleNamespace(mask=None), "network"),
                               (SimpleNamespace(mask=head), "segmentation")):
        masks, usable, source = masks_to_fit(prediction, images, wanted)
        assert source == "segmentation" and usable.tolist() == [True, False]
        assert int(masks[0].sum()) == 5 * 7 and not bool(masks[1].any())
