"""``sq-mitsuba bench train`` pieces: the time budget of training and the learning curves."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from sq_mitsuba.cli import main
from sq_mitsuba.config import apply_overrides
from sq_mitsuba.training.config import load_train_config
from sq_mitsuba.training.train import train

TINY = Path(__file__).resolve().parents[1] / "train" / "configs" / "tiny.toml"


def test_max_seconds_stops_after_the_step_that_runs_out_and_resume_continues(
        train_dataset, tmp_path):
    config = apply_overrides(load_train_config(TINY), ["checkpoint_every=0"])
    first = train(config, train_dataset, tmp_path / "run", progress=False, max_seconds=1e-3)
    assert first.steps == 1 < first.total_steps
    assert first.last_checkpoint == tmp_path / "run" / "last.pt"
    assert first.last_checkpoint.is_file() and first.train_seconds > 0
    second = train(config, train_dataset, tmp_path / "run", resume=True, progress=False,
                   max_seconds=1e-3)
    assert second.steps == 2 and len(second.losses) == 1


def test_learning_curves_on_the_tiny_dataset(train_dataset, tmp_path):
    from sq_mitsuba.bench.train import (
        curves_report,
        learning_curves,
        plot_learning_curves,
    )

    tiny = load_train_config(TINY)
    configs = {"tiny": tiny, "tiny, no augmentation": apply_overrides(
        tiny, ["augment.probability=0"])}
    curves = learning_curves(train_dataset, tmp_path / "runs", minutes=2 / 60, points=2,
                             val_images=2, progress=False, configs=configs)
    assert [c.label for c in curves] == list(configs)
    for curve in curves:
        assert 1 <= len(curve.seconds) <= 2
        assert curve.seconds == sorted(curve.seconds) and curve.seconds[0] > 0
        assert curve.steps == sorted(curve.steps) and curve.steps[0] >= 1
        assert all(math.isfinite(v) and v > 0 for v in curve.chamfer_l1)
    assert (tmp_path / "runs" / "tiny_no_augmentation" / "last.pt").is_file()
    png = plot_learning_curves(curves, tmp_path / "curves.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = curves_report(curves, 2 / 60, train_dataset, png)
    rows = [line for line in table.splitlines() if line.startswith("| tiny")]
    assert len(rows) == sum(len(c.seconds) for c in curves)


def test_only_a_recorded_run_draws_the_repository_figure(tmp_path):
    from sq_mitsuba.bench.train import CURVES_PNG, curves_figure_path

    assert curves_figure_path(tmp_path, write=False) == tmp_path / "learning_curves.png"
    assert curves_figure_path(tmp_path, write=True) == CURVES_PNG
    assert CURVES_PNG.parent.name == "figures" and CURVES_PNG.parent.parent.name == "eval"


def test_learning_curves_refuse_bad_input(tmp_path):
    from sq_mitsuba.bench.train import learning_curves

    with pytest.raises(ValueError, match="minutes"):
        learning_curves(tmp_path, tmp_path / "out", minutes=0)
    with pytest.raises(ValueError, match="unknown 'b'"):
        learning_curves(tmp_path, tmp_path / "out", minutes=1, labels=["b"])
    with pytest.raises(ValueError, match="dataset folder not found"):
        learning_curves(tmp_path / "none", tmp_path / "out", minutes=1)


def test_cli_curves_needs_data_minutes_and_out(tmp_path, capsys):
    assert main(["bench", "curves", "--minutes", "1", "--out", str(tmp_path)]) == 2
    assert "--data: required by the curves suite" in capsys.readouterr().err


def test_the_train_suites_options_are_refused_by_the_others(capsys):
    """--batch and --step-only change the train suite alone: given to another suite they
    would be silently ignored, so they are refused before it runs."""
    for flag in (["--batch", "4"], ["--step-only"]):
        assert main(["bench", "geometry", *flag, "--repeats", "1"]) == 2
        assert capsys.readouterr().err.strip().endswith(f"{flag[0]}: only used by the train "
                                                        "suite")


def test_decomposed_step_applies_the_same_update_as_the_training_step():
    """The timed parts of ``bench train`` add up to the loop's step: same parameters after;
    one part per weighted loss term of the registry."""
    import torch

    from sq_mitsuba.bench.train import STEP_PARTS, StepBench
    from sq_mitsuba.training.step import mitsuba_for

    # Adam eps 1e-5: at tiny.toml's 1e-8 a weight whose gradient is near 0 moves by lr times
    # its sign, so the two summation orders' last-bit differences become whole steps.
    config = apply_overrides(load_train_config(TINY), ["loss.weights.occupancy=1.0",
                                                       "loss.weights.overlap=0.1",
                                                       "data.num_occupancy=256",
                                                       "optim.eps=1e-5"])
    with mitsuba_for(torch.device("cpu"), True):
        whole, cut = StepBench(config), StepBench(config)
        before = [p.detach().clone() for p in whole.model.parameters()]
        whole.step(3)
        parts = cut.timed_parts(3)
    assert list(parts) == [*STEP_PARTS[:2], *config.loss.enabled(), STEP_PARTS[2]]
    assert all(seconds >= 0 for seconds in parts.values())
    assert parts["reprojection"] > 0 and parts["chamfer"] > 0 and parts["occupancy"] > 0
    moved = 0
    for start, a, b in zip(before, whole.model.parameters(), cut.model.parameters(),
                           strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
        moved += int(not torch.equal(start, a))
    assert moved > 10  # the step changed the network
