"""``sq-mitsuba bench train`` pieces: the time budget of training, the step's parts."""

from __future__ import annotations

from pathlib import Path

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


def test_the_train_suites_options_are_refused_by_the_others(capsys):
    """--batch and --step-only change the train suite alone: given to another suite they
    would be silently ignored, so they are refused before it runs."""
    for flag in (["--batch", "4"], ["--step-only"]):
        assert main(["bench", "geometry", *flag, "--repeats", "1"]) == 2
        assert capsys.readouterr().err.strip().endswith(f"{flag[0]}: only used by the train "
                                                        "suite")


def test_a_batch_this_machine_cannot_hold_is_refused_before_the_bench(capsys, monkeypatch):
    """bench train --batch took up to 4096 (about 70 GB on the CPU) and ran into the
    allocator; its step is estimated as train's is, and refused in the bench's own words."""
    from sq_mitsuba.training import step as step_module

    monkeypatch.setattr(step_module, "available_memory", lambda: 2_500_000_000)
    assert main(["bench", "train", "--step-only", "--batch", "64", "--repeats", "1"]) == 2
    line = capsys.readouterr().err.strip()
    assert line.startswith("sq-mitsuba bench: error: --batch: 64 images of ") and \
        line.endswith("this process may use; lower --batch") and "\n" not in line, line


def test_every_section_heading_is_a_command_that_parses():
    """BENCHMARKS.md's headings read as commands: the step-only section's was
    `sq-mitsuba bench train-step`, which is no suite."""
    import shlex

    from sq_mitsuba.bench import Report
    from sq_mitsuba.cli import build_parser

    for suite in ("train", "train-step", "render", "eval", "sequence"):
        heading = Report(suite).to_markdown().splitlines()[0]
        assert heading.startswith("### `sq-mitsuba bench ") and heading.endswith("`"), heading
        argv = shlex.split(heading.removeprefix("### `sq-mitsuba ").removesuffix("`"))
        build_parser().parse_args(argv)  # argparse exits on a suite or flag it does not know
    assert Report("train-step").to_markdown().startswith(
        "### `sq-mitsuba bench train --step-only`")


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
