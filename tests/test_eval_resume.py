"""``sq-mitsuba eval --resume`` and ``study illumination`` reruns, on the tiny trained checkpoint.

An evaluation interrupted (Ctrl-C) in its second batch keeps its first in the journal
(``--out/.eval_partial``); ``--resume`` computes the second alone and writes the same files as
a run never interrupted. A journal of other settings or another checkpoint is refused in one
line before any work; without ``--resume`` a journal is not used; a finished run leaves none.
A study rerun does not evaluate its finished sweep points again.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from output_checks import error_line, one_torch_thread, read_rows  # noqa: F401 (autouse fixture)

from sq_mitsuba.cli import main
from sq_mitsuba.evaluation import batch as batch_module
from sq_mitsuba.evaluation import evaluate as evaluate_module
from sq_mitsuba.evaluation import figures as figures_module
from sq_mitsuba.evaluation.evaluate import MESH_RANKING_FILE, OUTPUT_FILES
from sq_mitsuba.evaluation.journal import JOURNAL, RUN_FILE
from sq_mitsuba.model.checkpoint import read_checkpoint, write_checkpoint

#: Small settings (as tests/test_evaluate.py's): two batches of two val images, every method.
SMALL = ["--split", "val", "--refine", "--batch-size", "2", "--set", "mesh_ranking=4",
         "--set", "refinement.steps=3", "--set", "refinement.patience=3",
         "--set", "search.grid=128", "--set", "search.screen_steps=2",
         "--set", "surface_points=500", "--set", "volume_points=3000",
         "--set", "qualitative=2", "--set", "consistency_views=2", "--quiet"]
#: eval.json fields that are timings (the only ones a resumed run may change).
TIMINGS = ("images_per_second", "network_ms_per_image", "search_ms_per_image",
           "search_refine_ms_per_image", "loop_seconds", "wall_seconds")
BATCH_1 = f"{JOURNAL}/batch_000001.pt"


def _argv(checkpoint: Path, data: Path, out: Path, *extra: str) -> list[str]:
    return ["eval", "--checkpoint", str(checkpoint), "--data", str(data), "--out", str(out),
            *SMALL, *extra]


class Batches:
    """Records the batches evaluations compute (their numbers, in order); with ``interrupt``,
    a Ctrl-C at the first scoring of the batch after which ``interrupt(numbers)`` holds (once
    its network, search and refinement have run)."""

    def __init__(self, patch: pytest.MonkeyPatch,
                 interrupt: Callable[[list[int]], bool] | None = None) -> None:
        self.numbers: list[int] = []
        evaluate_batch, score = evaluate_module.evaluate_batch, batch_module.score

        def counted(predictor, dataset, chunk, number, *args, **kwargs):
            self.numbers.append(number)
            return evaluate_batch(predictor, dataset, chunk, number, *args, **kwargs)

        def scored(*args, **kwargs):
            if interrupt is not None and interrupt(self.numbers):
                raise KeyboardInterrupt
            return score(*args, **kwargs)

        patch.setattr(evaluate_module, "evaluate_batch", counted)
        patch.setattr(batch_module, "score", scored)

    @staticmethod
    def stop(*args, **kwargs):
        """A Ctrl-C wherever it is patched in."""
        raise KeyboardInterrupt


@pytest.fixture(scope="module")
def uninterrupted(eval_checkpoint, train_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("resume") / "whole"
    with pytest.MonkeyPatch.context() as patch:
        batches = Batches(patch)
        assert main(_argv(eval_checkpoint, train_dataset, out)) == 0
    assert batches.numbers == [1, 2]
    return out


@pytest.fixture(scope="module")
def interrupted(eval_checkpoint, train_dataset, tmp_path_factory):
    """An evaluation stopped by Ctrl-C in its second batch (after its search and refinement):
    the journal holds its identity and batch 1, and no eval.json was written."""
    out = tmp_path_factory.mktemp("resume") / "interrupted"
    with pytest.MonkeyPatch.context() as patch:
        batches = Batches(patch, _second_batch)
        assert main(_argv(eval_checkpoint, train_dataset, out)) == 130
    assert batches.numbers == [1, 2]
    assert sorted(p.name for p in (out / JOURNAL).iterdir()) == ["batch_000001.pt", RUN_FILE]
    assert not (out / "eval.json").exists() and not (out / "per_image.csv").exists()
    return out


def _second_batch(numbers: list[int]) -> bool:
    return numbers[-1] == 2


def _copy(folder: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(folder, tmp_path / folder.name))


def _no_figure(*args, **kwargs) -> Path:
    """An empty file where a figure function would draw its PNG (the first ``.png`` path it
    is given), for tests of bookkeeping that do not look at the figures: drawing them is
    seconds a run. The figures themselves are compared in
    test_resume_after_an_interrupt_writes_what_an_uninterrupted_run_does (and drawn and
    checked in tests/test_evaluate.py and tests/test_study.py)."""
    path = next(Path(a) for a in args if isinstance(a, Path) and a.suffix == ".png")
    path.write_bytes(b"")
    return path


def _tamper(path: Path) -> None:
    """Multiply every Chamfer-L1 of a journal batch by 100 (a value no run computes)."""
    data = torch.load(path, weights_only=True)
    for row in data["rows"]:
        row["chamfer_l1_paper"] *= 100.0
    torch.save(data, path)


def test_resume_after_an_interrupt_writes_what_an_uninterrupted_run_does(
        interrupted, uninterrupted, eval_checkpoint, train_dataset, tmp_path, monkeypatch,
        capsys):
    out = _copy(interrupted, tmp_path)
    batches = Batches(monkeypatch)
    assert main(_argv(eval_checkpoint, train_dataset, out, "--resume")) == 0
    assert batches.numbers == [2]  # batch 1 came from the journal
    assert "1 batch(es) resumed from the journal" in capsys.readouterr().out
    for name in (*OUTPUT_FILES, MESH_RANKING_FILE):
        if name != "eval.json":  # the tables, the ranking and the figures, byte for byte
            assert (out / name).read_bytes() == (uninterrupted / name).read_bytes(), name
    resumed, whole = (json.loads((folder / "eval.json").read_text())
                      for folder in (out, uninterrupted))
    for key in TIMINGS:
        assert resumed.pop(key) > 0 and whole.pop(key) > 0
    assert resumed == whole
    assert len(read_rows(out / "per_image.csv")) == 4 * 5
    # The journal goes once eval.json is written, resumed or not.
    assert not (out / JOURNAL).exists() and not (uninterrupted / JOURNAL).exists()


def test_resume_of_other_settings_or_another_checkpoint_is_one_line(
        interrupted, eval_checkpoint, train_dataset, tmp_path, monkeypatch, capsys):
    out = _copy(interrupted, tmp_path)
    journal = {p.name: p.read_bytes() for p in (out / JOURNAL).iterdir()}
    batches = Batches(monkeypatch)
    assert main(_argv(eval_checkpoint, train_dataset, out, "--resume",
                      "--set", "silhouette_spp=16")) == 2
    line = error_line(capsys)
    assert "option silhouette_spp: 32 there, 16 now" in line and RUN_FILE in line
    other = tmp_path / "other_run" / "checkpoint.pt"  # the same network, one weight changed
    payload = read_checkpoint(eval_checkpoint)
    name = next(k for k, v in payload["model"].items() if v.is_floating_point())
    payload["model"][name] = payload["model"][name] + 0.01
    other.parent.mkdir()
    write_checkpoint(other, payload)
    assert main(_argv(other, train_dataset, out, "--resume")) == 2
    line = error_line(capsys)
    assert "checkpoint: weights of" in line and str(other) in line
    # Batches rendered by another Mitsuba variant (the GPU's), or an identity that cannot be
    # read, are refused too.
    run_file = out / JOURNAL / RUN_FILE
    recorded = json.loads(run_file.read_text())
    here = recorded["renderer"]
    assert here.startswith("llvm_ad")
    run_file.write_text(json.dumps({**recorded, "renderer": "cuda_ad_mono"}))
    assert main(_argv(eval_checkpoint, train_dataset, out, "--resume")) == 2
    assert f"renderer: 'cuda_ad_mono' there, '{here}' now" in error_line(capsys)
    run_file.write_text("{")
    assert main(_argv(eval_checkpoint, train_dataset, out, "--resume")) == 2
    line = error_line(capsys)
    assert line.startswith(f"sq-mitsuba eval: error: {run_file}: not this evaluation's "
                           "journal (its run.json unreadable: not valid JSON")
    run_file.write_bytes(journal[RUN_FILE])
    # Refused before any work: nothing computed, the journal as it was, no outputs.
    assert batches.numbers == []
    assert {p.name: p.read_bytes() for p in (out / JOURNAL).iterdir()} == journal
    assert not (out / "eval.json").exists() and not (out / "per_image.csv").exists()
    # A batch file that cannot be read is named, not used.
    (out / BATCH_1).write_bytes(b"not a journal batch")
    assert main(_argv(eval_checkpoint, train_dataset, out, "--resume")) == 2
    line = error_line(capsys)
    assert line.startswith(f"sq-mitsuba eval: error: {out / BATCH_1}: unreadable journal batch")
    assert batches.numbers == []
    # A batch file of the right size holding another batch's images is named, not used.
    shutil.copy(interrupted / BATCH_1, out / BATCH_1)
    shutil.copy(interrupted / BATCH_1, out / JOURNAL / "batch_000002.pt")
    assert main(_argv(eval_checkpoint, train_dataset, out, "--resume")) == 2
    assert "batch_000002.pt: holds other images than batch 2" in error_line(capsys)
    assert batches.numbers == []


def test_the_identity_names_an_option_only_the_journal_has_and_hashes_what_decides_scores(
        eval_checkpoint, train_dataset, tmp_path, monkeypatch):
    """A field the journal's run had and this one lacks differs too; the stored baseline is
    part of the model (the baseline rows are scored from it); so are the model files the
    scoring reads (samples.npz: Chamfer and 3D IoU points; symmetries.json) and the package
    version."""
    import numpy as np

    from sq_mitsuba.evaluation import journal
    from sq_mitsuba.evaluation.journal import (
        checkpoint_identity,
        identity_difference,
        run_identity,
    )
    from sq_mitsuba.inference.loading import load_model

    assert identity_difference({"options": {"a": 1}}, {"options": {}}) == \
        "option a: 1 there, absent now"
    assert identity_difference({"options": {"a": 1}}, {"options": {"a": 1}}) is None
    # Only the image list is told by its length; other lists as they are.
    assert identity_difference({"options": {"counts": [1, 2, 4, 8, 16]}},
                               {"options": {"counts": [1, 2, 4, 8, 12]}}) == \
        "option counts: [1, 2, 4, 8, 16] there, [1, 2, 4, 8, 12] now"
    assert identity_difference({"images": list(range(6))}, {"images": list(range(5))}) == \
        "images: 6 images there, 5 images now"
    predictor = load_model(eval_checkpoint)
    raw = torch.zeros(1, predictor.num_primitives, 16)
    predictor.baseline = (raw, torch.eye(3)[None], torch.zeros(1, 3))
    first = checkpoint_identity(predictor)["sha256"]
    predictor.baseline = (raw + 0.5, torch.eye(3)[None], torch.zeros(1, 3))
    assert checkpoint_identity(predictor)["sha256"] != first
    data = Path(shutil.copytree(train_dataset, tmp_path / "data"))
    before = run_identity(predictor, data, {})
    assert identity_difference(before, run_identity(predictor, data, {})) is None
    model, split = (data / "splits.csv").read_text().splitlines()[-1].split(",")
    samples = data / model / "models" / "samples.npz"
    other = {"train": "test", "test": "val"}[split]  # an evaluation that never reads it
    scored = {name: run_identity(predictor, data, {"split": name}) for name in ("val", other)}
    with np.load(samples) as archive:
        arrays = dict(archive)
    arrays["surface_points"] = arrays["surface_points"][::2]
    np.savez(samples, **arrays)
    assert "samples.npz" in identity_difference(before, run_identity(predictor, data, {}))
    # Only the evaluations that score this model see it ("val": the training models' images).
    assert identity_difference(scored[other], run_identity(predictor, data,
                                                           {"split": other})) is None
    if split == "train":
        assert "samples.npz" in identity_difference(
            scored["val"], run_identity(predictor, data, {"split": "val"}))
    before = run_identity(predictor, data, {})
    (data / model / "models" / "symmetries.json").write_text("{}")
    assert "symmetries.json" in identity_difference(before, run_identity(predictor, data, {}))
    before = run_identity(predictor, data, {})
    monkeypatch.setattr(journal, "__version__", "0.0.0")  # the scoring code's version
    assert "version: " in identity_difference(before, run_identity(predictor, data, {}))


def test_without_resume_a_journal_is_not_used(interrupted, uninterrupted, eval_checkpoint,
                                              train_dataset, tmp_path, monkeypatch, capsys):
    # The tables are this test's; three of its evaluations would draw the figures.
    for name in ("plot_per_model", "plot_qualitative", "plot_consistency"):
        monkeypatch.setattr(figures_module, name, _no_figure)
    # A journal of both batches (a resumed run stopped among its writes), each tampered with.
    tampered = _copy(interrupted, tmp_path)
    with monkeypatch.context() as patch:
        patch.setattr(evaluate_module, "write_tables", Batches.stop)
        assert main(_argv(eval_checkpoint, train_dataset, tampered, "--resume")) == 130
    for number in (1, 2):
        _tamper(tampered / JOURNAL / f"batch_{number:06d}.pt")
    # With --resume the journal's batches are taken as they are: the tampering shows.
    used = _copy(tampered, tmp_path / "used")
    with monkeypatch.context() as patch:
        batches = Batches(patch)
        assert main(_argv(eval_checkpoint, train_dataset, used, "--resume")) == 0
    assert batches.numbers == []
    assert (used / "per_image.csv").read_bytes() != \
        (uninterrupted / "per_image.csv").read_bytes()
    # Without it, the run starts afresh: the journal is cleared before its first batch, so
    # that after an interrupt there --resume computes both batches, as an uninterrupted run.
    capsys.readouterr()
    with monkeypatch.context() as patch:
        batches = Batches(patch, lambda numbers: True)
        assert main(_argv(eval_checkpoint, train_dataset, tampered)) == 130
    assert batches.numbers == [1]
    assert sorted(p.name for p in (tampered / JOURNAL).iterdir()) == [RUN_FILE]
    # Said, not silent: the two finished batches discarded (--resume would have used them).
    assert "an interrupted evaluation's 2 finished batch(es) discarded" in \
        capsys.readouterr().err
    with monkeypatch.context() as patch:
        batches = Batches(patch)
        assert main(_argv(eval_checkpoint, train_dataset, tampered, "--resume")) == 0
    assert batches.numbers == [1, 2]
    assert (tampered / "per_image.csv").read_bytes() == \
        (uninterrupted / "per_image.csv").read_bytes()
    assert not (tampered / JOURNAL).exists()
    # --resume on a finished folder (no journal left) replaces nothing: one line, before any
    # work (it once evaluated from the start, over a finished run of other settings).
    finished = {p.name: p.read_bytes() for p in tampered.iterdir() if p.is_file()}
    capsys.readouterr()
    with monkeypatch.context() as patch:
        batches = Batches(patch)
        assert main(_argv(eval_checkpoint, train_dataset, tampered, "--resume")) == 2
    assert batches.numbers == []
    assert error_line(capsys) == (f"sq-mitsuba eval: error: {tampered}: --resume, but the "
                                  "evaluation there is finished (eval.json; nothing to "
                                  "resume): rerun without --resume to evaluate again, or use "
                                  "another --out")
    assert {p.name: p.read_bytes() for p in tampered.iterdir() if p.is_file()} == finished


# ------------------------------------------------------------------------------ study


#: Two poses of the one test model at phase angles 0 and 180 deg (space, earth) and in
#: eclipse; each point's evaluation two batches of one image.
STUDY = ["--poses", "2", "--step", "180", "--set", "render.resolution=64",
         "--set", "render.spp=4", "--set", "evaluation.refine=false",
         "--set", "evaluation.batch_size=1", "--set", "evaluation.surface_points=500",
         "--set", "evaluation.volume_points=2000", "--quiet"]


def test_a_study_rerun_does_not_evaluate_its_finished_points(eval_checkpoint, train_dataset,
                                                             tmp_path, monkeypatch):
    from sq_mitsuba.evaluation.study import sweep_points

    def argv(out: Path, *extra: str) -> list[str]:
        return ["study", "illumination", "--checkpoint", str(eval_checkpoint), "--models",
                str(train_dataset), "--out", str(out), *STUDY, *extra]

    def tables(out: Path) -> dict[str, bytes]:
        return {name: (out / name).read_bytes() for name in ("per_image.csv",
                                                             "illumination.csv")}

    evaluate = evaluate_module.evaluate
    calls: list[tuple[str, bool]] = []

    def counted(predictor, data_root, out_dir, *args, **kwargs):
        calls.append((Path(out_dir).name, kwargs.get("resume", False)))
        return evaluate(predictor, data_root, out_dir, *args, **kwargs)

    monkeypatch.setattr(evaluate_module, "evaluate", counted)
    # The study's figure (thirteen panels, ~5 s a drawing) is not what this test is about:
    # five of its runs would draw it.
    monkeypatch.setattr(figures_module, "plot_illumination", _no_figure)
    points = [p.name for p in sweep_points(180)]  # 0 and 180 deg, space and earth; eclipse
    whole = tmp_path / "whole"
    assert main(argv(whole)) == 0
    assert [name for name, _ in calls] == points
    expected = tables(whole)
    evaluated = {p: (whole / "evals" / p / "per_image.csv").stat().st_mtime_ns for p in points}
    # A rerun reads every point's finished evaluation back: none evaluated again (their files
    # untouched), the same tables.
    calls.clear()
    assert main(argv(whole)) == 0
    assert calls == []
    assert {p: (whole / "evals" / p / "per_image.csv").stat().st_mtime_ns
            for p in points} == evaluated
    assert tables(whole) == expected
    # A study interrupted in the second batch of its second point: the rerun skips the first
    # point, resumes the second (its first batch from the journal) and evaluates the others.
    out = tmp_path / "interrupted"
    calls.clear()
    with monkeypatch.context() as patch:
        Batches(patch, lambda numbers: len(numbers) == 4)
        assert main(argv(out)) == 130
    assert [name for name, _ in calls] == points[:2]
    calls.clear()
    with monkeypatch.context() as patch:
        batches = Batches(patch)
        assert main(argv(out)) == 0
    # The interrupted point resumed; the points not begun evaluated afresh (no journal).
    assert calls == [(points[1], True), *[(name, False) for name in points[2:]]]
    assert batches.numbers == [2, *[1, 2] * (len(points) - 2)]
    assert tables(out) == expected
    # Other evaluation settings: every point again.
    calls.clear()
    assert main(argv(whole, "--set", "evaluation.silhouette_spp=16")) == 0
    assert [name for name, _ in calls] == points
    # A study of other settings interrupted in its second point, then the first settings
    # again: the first point is evaluated again (its eval.json is of the others), the second,
    # its eval.json gone, afresh (its journal is of the others: cleared, not refused), the
    # rest read back.
    with monkeypatch.context() as patch:
        Batches(patch, lambda numbers: len(numbers) == 4)
        assert main(argv(out, "--set", "evaluation.silhouette_spp=16")) == 130
    assert (out / "evals" / points[1] / JOURNAL / "batch_000001.pt").is_file()
    (out / "evals" / points[1] / "eval.json").unlink()
    calls.clear()
    with monkeypatch.context() as patch:
        batches = Batches(patch)
        assert main(argv(out)) == 0
    assert calls == [(points[0], False), (points[1], False)]  # neither has a journal to use
    assert batches.numbers == [1, 2, 1, 2]
    assert tables(out) == expected
