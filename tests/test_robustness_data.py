"""Issue 35, the data side: what a new user and 585 bad inputs found, reproduced with the real
commands on the tiny session dataset (copied before it is damaged).

- bad data (a ``samples.npz`` lacking an array or holding NaN, a ``camera.json`` of another
  resolution) is one line naming the file, exit code 2, before any work, nothing left behind;
- one run at a time per output (train, eval, ``models generate``), with a lock that a killed
  run does not leave held, and no model replaced by another spacecraft of the same name;
- reading a dataset (train, eval, ``dataset check``, ``dataset preview``) leaves its folder
  byte for byte as it was;
- the minors: ``dataset check`` finds what eval would fail on and says a stopped render has
  not finished, eval refuses an output inside its dataset and leaves no stale outputs of an
  earlier run, ``train --max-steps`` always leaves a ``best.pt``, export says which data its
  baseline describes.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from output_checks import error_line, one_torch_thread  # noqa: F401 (autouse fixture)

from sq_mitsuba.cli import main
from sq_mitsuba.outputs import LOCK_NAME, OutputBusyError, lock_path, output_lock

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "train" / "configs" / "tiny.toml"
#: eval at its cheapest: no figures, two images, few points.
EVAL_FAST = ["--limit", "2", "--no-figures", "--set", "surface_points=300",
             "--set", "volume_points=2000", "--baseline-images", "2"]


def _copy(train_dataset: Path, tmp_path: Path, name: str = "data") -> Path:
    data = tmp_path / name
    shutil.copytree(train_dataset, data)
    return data


def _models(data: Path, split: str) -> list[str]:
    rows = [line.split(",") for line in (data / "splits.csv").read_text().splitlines() if line]
    return sorted(model for model, which in rows if which == split)


def _rewrite_samples(path: Path, change) -> None:
    with np.load(path) as samples:
        arrays = {key: samples[key] for key in samples.files}
    change(arrays)
    np.savez_compressed(path, **arrays)


def _digest(folder: Path) -> dict[str, str]:
    """Every file (hidden ones too) and folder under ``folder`` -> sha256 of its bytes."""
    found = {}
    for path in sorted(folder.rglob("*")):
        relative = str(path.relative_to(folder))
        found[relative] = ("folder" if path.is_dir() else
                           hashlib.sha256(path.read_bytes()).hexdigest())
    return found


def _train(data: Path, out: Path, *extra: str) -> list[str]:
    return ["train", "--config", str(TINY), "--data", str(data), "--out", str(out), "--quiet",
            *extra]


def _eval(checkpoint: Path, data: Path, out: Path, *extra: str) -> list[str]:
    return ["eval", "--checkpoint", str(checkpoint), "--data", str(data), "--out", str(out),
            *EVAL_FAST, *extra]


# ------------------------------------------------------------------- 1, 6: samples.npz


def test_eval_and_train_name_a_samples_file_that_lacks_an_array(train_dataset, eval_checkpoint,
                                                                 tmp_path, capsys):
    data = _copy(train_dataset, tmp_path)
    samples = data / _models(data, "train")[0] / "models" / "samples.npz"
    _rewrite_samples(samples, lambda arrays: arrays.pop("surface_points"))
    for argv, out in ((_eval(eval_checkpoint, data, tmp_path / "eval", "--quiet"),
                       tmp_path / "eval"),
                      (_train(data, tmp_path / "run"), tmp_path / "run")):
        assert main(argv) == 2, argv[0]
        line = error_line(capsys)
        assert str(samples) in line and "'surface_points'" in line, line
        assert not out.exists(), argv[0]  # refused before any work: nothing written


def test_train_refuses_nan_points_before_work_naming_the_file(train_dataset, tmp_path, capsys):
    data = _copy(train_dataset, tmp_path)
    samples = data / _models(data, "train")[-1] / "models" / "samples.npz"

    def poison(arrays):
        arrays["near_points"][7] = np.nan

    _rewrite_samples(samples, poison)
    out = tmp_path / "run"
    assert main(_train(data, out, "--max-steps", "2")) == 2
    line = error_line(capsys)
    assert str(samples) in line and "near_points" in line and "NaN" in line, line
    assert not out.exists()  # no run folder, no last.pt


# ------------------------------------------------------------------- camera of another size


def test_a_camera_json_of_another_resolution_is_refused(train_dataset, eval_checkpoint,
                                                        tmp_path, capsys):
    from sq_mitsuba.geometry.camera import Camera

    data = _copy(train_dataset, tmp_path)
    camera = Camera.load(data / "camera.json")
    assert (camera.width, camera.height) == (64, 64)
    (data / "camera.json").write_text(json.dumps(camera.rescaled(256, 256).to_speed_dict()))
    for argv, out in ((_train(data, tmp_path / "run"), tmp_path / "run"),
                      (_eval(eval_checkpoint, data, tmp_path / "eval", "--quiet"),
                       tmp_path / "eval")):
        assert main(argv) == 2, argv[0]
        line = error_line(capsys)
        assert str(data / "camera.json") in line and "256 x 256" in line, line
        assert "64 x 64" in line, line
        assert not out.exists()


# ------------------------------------------------------------------- 9: datasets are read only


@pytest.mark.slow  # end to end: `make test` runs it, `make test-fast` not
def test_reading_a_dataset_leaves_it_byte_identical(train_dataset, eval_checkpoint, tmp_path,
                                                    capsys):
    data = _copy(train_dataset, tmp_path)
    for stray in data.rglob("symmetries.json"):  # as the render wrote it: no records
        stray.unlink()
    before = _digest(data)
    # train (one step: stops before the first validation, so best.pt is the last state)
    run = tmp_path / "run"
    assert main(_train(data, run, "--max-steps", "1")) == 0
    out = capsys.readouterr().out
    assert _digest(data) == before, "train changed the dataset"
    assert (run / "best.pt").is_file() and (run / "last.pt").is_file()
    assert "best.pt holds the last state (step 1)" in out, out
    assert list((run / "cache" / "symmetries").glob("*.json"))  # the records live here
    assert not (run / LOCK_NAME).exists()
    # the README's next step works: eval of RUN/best.pt
    assert main(_eval(run / "best.pt", data, tmp_path / "eval", "--quiet")) == 0
    assert _digest(data) == before, "eval changed the dataset"
    assert main(["dataset", "check", str(data), "--per-model", "1", "--quiet"]) == 0
    assert _digest(data) == before, "dataset check changed the dataset"
    assert main(["dataset", "preview", str(data), "--count", "2"]) == 0
    assert _digest(data) == before, "dataset preview changed the dataset"
    assert (tmp_path / "data_preview.png").is_file()  # beside the dataset, not in it


def test_symmetries_are_cached_outside_the_model_folder(train_dataset, tmp_path):
    from sq_mitsuba.data.symmetry import model_symmetries

    data = _copy(train_dataset, tmp_path)
    model = data / _models(data, "train")[0]
    for stray in model.rglob("symmetries.json"):
        stray.unlink()
    before = _digest(model)
    cache = tmp_path / "cache"
    first = model_symmetries(model, cache_dir=cache)
    assert _digest(model) == before
    records = list(cache.glob(f"{model.name}-*.json"))
    assert len(records) == 1
    assert np.array_equal(model_symmetries(model, cache_dir=cache), first)  # read back
    assert np.array_equal(model_symmetries(model), first)  # no cache: computed, not written
    assert _digest(model) == before
    # An edited model is a new record, not the old one read back.
    _rewrite_samples(model / "models" / "samples.npz",
                     lambda arrays: arrays.update(surface_points=arrays["surface_points"][::2]))
    model_symmetries(model, cache_dir=cache)
    assert len(list(cache.glob(f"{model.name}-*.json"))) == 2


# ------------------------------------------------------------------- dataset check


def test_check_finds_points_eval_would_fail_on(train_dataset, tmp_path, capsys):
    data = _copy(train_dataset, tmp_path)
    no_file, no_key, nan = sorted(_models(data, "train") + _models(data, "test"))
    (data / no_file / "models" / "samples.npz").unlink()
    _rewrite_samples(data / no_key / "models" / "samples.npz",
                     lambda arrays: arrays.pop("uniform_inside"))

    def poison(arrays):
        arrays["surface_points"][0, 1] = np.inf

    _rewrite_samples(data / nan / "models" / "samples.npz", poison)
    assert main(["dataset", "check", str(data), "--per-model", "1", "--quiet"]) == 1
    out = capsys.readouterr().out
    assert "no problems" not in out
    assert f"problem: {no_file}/models/samples.npz: missing" in out, out
    assert f"problem: {no_key}/models/samples.npz: no array 'uniform_inside'" in out, out
    assert f"problem: {nan}/models/samples.npz: surface_points: 1 of" in out, out


def test_check_says_a_stopped_render_has_not_finished(train_dataset, tmp_path, capsys):
    data = _copy(train_dataset, tmp_path)
    manifest = json.loads((data / "dataset.json").read_text())
    manifest["state"] = "rendering"  # what a render killed part-way leaves
    (data / "dataset.json").write_text(json.dumps(manifest))
    (data / "splits.csv").unlink()  # the last model to finish writes it
    unfinished = sorted(manifest["models"])[0]  # one model stopped before its labels.json
    (data / unfinished / "labels.json").unlink()
    finished = len(manifest["models"]) - 1
    assert main(["dataset", "check", str(data), "--quiet"]) == 1
    out = capsys.readouterr().out
    assert "rendering has not finished" in out and "splits.csv: missing" in out, out
    # The models finished so far are checked all the same (they were skipped: "0 models").
    assert finished >= 2 and f"{finished} models" in out and unfinished not in out, out


def test_check_of_a_missing_folder_is_bad_input(tmp_path, capsys):
    assert main(["dataset", "check", str(tmp_path / "nowhere"), "--quiet"]) == 2
    assert "nowhere: no such folder" in error_line(capsys)
    (tmp_path / "file").write_text("x")
    assert main(["dataset", "check", str(tmp_path / "file"), "--quiet"]) == 2
    assert "not a folder" in error_line(capsys)


# ------------------------------------------------------------------- eval's output folder


def test_eval_refuses_an_output_inside_its_dataset(train_dataset, eval_checkpoint, tmp_path,
                                                   capsys):
    data = _copy(train_dataset, tmp_path)
    before = _digest(data)
    for out in (data, data / "eval"):
        assert main(_eval(eval_checkpoint, data, out, "--quiet")) == 2
        line = error_line(capsys)
        assert "inside the dataset folder" in line, line
    assert _digest(data) == before


def test_eval_rerun_leaves_no_stale_outputs_and_ignores_a_killed_runs_lock(
        train_dataset, eval_checkpoint, tmp_path, capsys):
    out = tmp_path / "eval"
    out.mkdir()
    # What an earlier run with figures, then a kill -9, left: old figures and a lock file
    # whose process is gone.
    stale = ["per_model.png", "qualitative.png", "consistency.png", "mesh_ranking.csv"]
    for name in stale:
        (out / name).write_bytes(b"from an earlier run")
    (out / LOCK_NAME).write_text("999999999 sq-mitsuba eval\n")
    # The killed run's journal says an evaluation wrote them (in a folder that never held
    # one, files of these names are someone else's: tests/test_user_files_kept.py).
    (out / ".eval_partial").mkdir()
    (out / ".eval_partial" / "run.json").write_text(
        '{"format": 3, "options": {}, "checkpoint": {}}')
    assert main(_eval(eval_checkpoint, train_dataset, out, "--no-baseline")) == 0
    captured = capsys.readouterr()
    assert "batch 1/1" in captured.err  # the bar names the batch it works on
    names = sorted(p.name for p in out.iterdir())
    assert not set(stale) & set(names), names
    assert LOCK_NAME not in names  # released, and the stale one gone with it
    assert names == sorted(["per_image.csv", "per_model.csv", "per_model.md", "summary.csv",
                            "summary.md", "eval.json"])


def test_eval_times_the_network_after_one_untimed_call(train_dataset, eval_checkpoint,
                                                       tmp_path):
    """The first call of a network compiles its kernels: it is made once, untimed, on the
    first batch, before the timed call of that batch."""
    from sq_mitsuba.evaluation.evaluate import EvalOptions, evaluate
    from sq_mitsuba.inference.loading import load_model

    predictor = load_model(eval_checkpoint)
    calls = []
    real_predict = predictor.predict

    def recording(images, *args, **kwargs):
        calls.append(images.clone())
        return real_predict(images, *args, **kwargs)

    predictor.predict = recording
    # The refinement's own settings, given without it, are not this run's (eval.json and the
    # resume identity hold the defaults: a --resume is not refused over them).
    options = EvalOptions(limit=2, figures=False, baseline=False, fast=False,
                          surface_points=300, volume_points=2000, mask="segmentation",
                          refine_ground_truth=False)
    result = evaluate(predictor, train_dataset, tmp_path / "eval", options, progress=False)
    assert result.images == 2
    assert len(calls) == 2 and calls[0].equal(calls[1])
    recorded = json.loads((tmp_path / "eval" / "eval.json").read_text())["options"]
    assert (recorded["mask"], recorded["refine_ground_truth"]) == ("network", True)


# ------------------------------------------------------------------- 3, 5: one run per output


HOLDER = """\
import sys, time
from sq_mitsuba.outputs import output_lock
with output_lock(sys.argv[1], command="the test's holder", file=sys.argv[2] == "file",
                 shared=sys.argv[2] == "shared"):
    print("locked", flush=True)
    time.sleep(300)
"""


def _hold(out: Path, kind: str = "folder") -> subprocess.Popen:
    """Another process holding the lock on ``out`` (until killed): on the folder, beside the
    output ``file``, or ``shared`` on the folder (a shard of a render)."""
    process = subprocess.Popen([sys.executable, "-c", HOLDER, str(out), kind], cwd=ROOT,
                               stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "locked"
    return process


def _hold_file(out: Path) -> subprocess.Popen:
    return _hold(out, "file")


def _hold_shared(out: Path) -> subprocess.Popen:
    return _hold(out, "shared")


def _kill(process: subprocess.Popen) -> None:
    if process.poll() is None:
        os.kill(process.pid, signal.SIGKILL)
    process.wait(timeout=30)
    process.stdout.close()


def test_a_run_into_a_locked_output_refuses_and_a_killed_holder_blocks_nothing(
        train_dataset, eval_checkpoint, tmp_path, capsys):
    out = tmp_path / "out"
    image = next(train_dataset.glob("*/images/000000.png"))
    holder = _hold(out)
    try:
        assert _digest(out) == {LOCK_NAME: _digest(out)[LOCK_NAME]}
        commands = {
            "train": _train(train_dataset, out, "--max-steps", "1"),
            # the lock's message, not "nothing to resume" (a fresh run has no last.pt yet)
            "train --resume": _train(train_dataset, out, "--resume"),
            "eval": _eval(eval_checkpoint, train_dataset, out, "--quiet"),
            "models": ["models", "generate", "--count", "1", "--points", "1000", "--out",
                       str(out)],
            # predict takes the lock through the CLI's all-or-nothing output
            "predict": ["predict", str(image), "--checkpoint", str(eval_checkpoint), "--out",
                        str(out), "--quiet"],
        }
        for name, argv in commands.items():
            assert main(argv) == 2, name
            line = error_line(capsys)
            assert f"{out}: another run is writing into this folder" in line, line
            assert f"process {holder.pid}, the test's holder" in line, line
            assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME], name  # untouched
        with pytest.raises(OutputBusyError, match="another run"), output_lock(out):
            pass
        # An output file (export): its lock lies beside it.
        target = tmp_path / "model.pt"
        file_holder = _hold_file(target)
        try:
            assert main(["export", "--checkpoint", str(eval_checkpoint), "--out",
                         str(target)]) == 2
            assert f"{target}: another run is writing into this file" in error_line(capsys)
            assert not target.exists()
        finally:
            _kill(file_holder)
    finally:
        _kill(holder)  # kill -9: no chance to clean up
    assert (out / LOCK_NAME).exists()  # its lock file stays; the lock itself died with it
    with output_lock(out) as folder:
        assert folder == out
        assert (out / LOCK_NAME).read_text().startswith(f"{os.getpid()} ")
    assert not (out / LOCK_NAME).exists()


def test_shared_holders_share_an_output_and_exclude_an_exclusive_one(tmp_path):
    """The shards of one render share their folder; a render without shards (or one that
    overwrites) holds it alone, and is refused beside a shard; the last shard out deletes
    the lock file, an earlier one leaves it to the others."""
    out = tmp_path / "data"
    shard = _hold_shared(out)
    try:
        with output_lock(out, shared=True):  # a second shard: beside the first
            assert (out / LOCK_NAME).is_file()
        assert (out / LOCK_NAME).is_file()  # not the last one out: the file stays
        # (named by the record of a shard: the last one in wrote it)
        with pytest.raises(OutputBusyError, match=r"another run is writing into this folder "
                                                  r"\(process \d+, "):
            with output_lock(out):
                pass
    finally:
        _kill(shard)
    with output_lock(out, shared=True):  # alone now: the last one out deletes it
        pass
    assert list(out.iterdir()) == []  # (the folder was the killed shard's to remove)
    holder = _hold(out)
    try:
        with pytest.raises(OutputBusyError, match="another run"), output_lock(out, shared=True):
            pass
    finally:
        _kill(holder)


def test_a_waiting_lock_waits_for_its_holder(tmp_path):
    """A short section several processes take in turn (a manifest's check and write) waits
    for the holder instead of refusing."""
    import threading
    import time

    target = tmp_path / "data" / "dataset.json"
    holder = _hold_file(target)
    threading.Timer(1.0, _kill, (holder,)).start()
    started = time.monotonic()
    with output_lock(target, file=True, wait=True):
        assert time.monotonic() - started > 0.5  # it waited for the holder's end
    assert holder.poll() is not None


def test_output_lock_is_released_on_errors_and_removes_what_it_created(tmp_path):
    new = tmp_path / "a" / "b"
    with pytest.raises(RuntimeError), output_lock(new):
        assert (new / LOCK_NAME).is_file()
        with output_lock(new):  # re-entrant in one process
            pass
        raise RuntimeError
    assert not (tmp_path / "a").exists()  # made for the lock, left empty: removed
    target = tmp_path / "models" / "model.pt"
    with output_lock(target, file=True):
        assert lock_path(target, file=True).is_file()
        target.write_text("written")
    assert sorted(p.name for p in target.parent.iterdir()) == ["model.pt"]


@pytest.mark.slow  # end to end: `make test` runs it, `make test-fast` not
def test_two_generate_runs_at_once_into_one_library_do_not_mix(tmp_path):
    from sq_mitsuba.data.spacecraft import catalogue

    # Seeds 0 and 3 both start with a model named sc000_twin_wing: other spacecraft.
    first, other = catalogue(1, 0)[0], catalogue(1, 3)[0]
    assert first.name == other.name and first.seed != other.seed
    library = tmp_path / "library"
    runs = [subprocess.Popen([sys.executable, "-m", "sq_mitsuba", "models", "generate",
                              "--count", "1", "--points", "1000", "--seed", str(seed),
                              "--out", str(library)], cwd=ROOT, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
            for seed in (0, 3)]
    results = [(run.wait(timeout=300), *run.communicate()) for run in runs]
    codes = sorted(code for code, _, _ in results)
    assert codes == [0, 2], results
    winner = 0 if results[0][0] == 0 else 3
    loser_err = next(err for code, _, err in results if code == 2)
    message = [line for line in loser_err.splitlines() if "error:" in line]
    assert len(message) == 1, loser_err
    # Refused by the lock (started together) or, had it started after the other ended, by
    # the name check: never a mix.
    assert "another run is writing" in message[0] or "another spacecraft" in message[0]
    assert sorted(p.name for p in library.iterdir()) == [first.name, "splits.csv"]
    card = json.loads((library / first.name / "models" / "model_card.json").read_text())
    assert card["catalogue_seed"] == winner
    split = (first if winner == 0 else other).split
    assert (library / "splits.csv").read_text() == f"{first.name},{split}\n"


def test_generate_never_replaces_a_model_by_another_spacecraft_of_its_name(tmp_path, capsys):
    library = tmp_path / "library"
    common = ["models", "generate", "--count", "1", "--points", "1000", "--out", str(library)]
    assert main([*common, "--seed", "0"]) == 0
    capsys.readouterr()
    before = _digest(library)
    assert main([*common, "--seed", "3"]) == 2
    line = error_line(capsys)
    name = next(p.name for p in library.iterdir() if p.is_dir())
    assert f"{library / name}: holds another spacecraft of this name" in line, line
    assert "catalogue seed 0" in line and "catalogue seed 3" in line, line
    assert _digest(library) == before  # nothing generated, nothing replaced
    assert main([*common, "--seed", "0"]) == 0  # the same spacecraft again is fine
    card = json.loads((library / name / "models" / "model_card.json").read_text())
    assert card["catalogue_seed"] == 0


# ------------------------------------------------------------------- export's baseline


def test_export_says_which_dataset_its_baseline_describes(train_dataset, eval_checkpoint,
                                                          tmp_path, capsys):
    from sq_mitsuba.model.checkpoint import read_checkpoint, write_checkpoint
    from sq_mitsuba.training.cache import dataset_fingerprint

    payload = read_checkpoint(eval_checkpoint)
    payload["dataset"] = {"root": str(train_dataset),
                          "fingerprint": dataset_fingerprint(train_dataset)}
    trained = tmp_path / "trained.pt"
    write_checkpoint(trained, payload)
    other = _copy(train_dataset, tmp_path, "other")
    labels = other / _models(other, "train")[0] / "labels.json"
    entries = json.loads(labels.read_text())
    entries[0]["exposure"] = 0.5  # another dataset: another fingerprint
    labels.write_text(json.dumps(entries))
    common = ["export", "--checkpoint", str(trained), "--baseline-images", "2"]
    assert main([*common, "--data", str(train_dataset), "--out", str(tmp_path / "a.pt")]) == 0
    out = capsys.readouterr().out
    assert "not the dataset" not in out and "baseline: the mean" in out, out
    assert main([*common, "--data", str(other), "--out", str(tmp_path / "b.pt")]) == 0
    out = capsys.readouterr().out
    assert f"{other} is not the dataset the checkpoint was trained on" in out, out
    # An exported file's baseline is kept when exported again, and never silently replaced.
    again = ["export", "--checkpoint", str(tmp_path / "a.pt")]
    assert main([*again, "--data", str(other), "--out", str(tmp_path / "c.pt")]) == 2
    assert "stores a baseline already" in error_line(capsys)
    assert not (tmp_path / "c.pt").exists()
    assert main([*again, "--out", str(tmp_path / "c.pt")]) == 0
    assert read_checkpoint(tmp_path / "c.pt")["baseline"] is not None


def test_a_refused_lock_does_not_wait(tmp_path):
    """The lock never waits: a refused run returns at once."""
    out = tmp_path / "out"
    holder = _hold(out)
    try:
        tick = time.perf_counter()
        with pytest.raises(OutputBusyError), output_lock(out):
            pass
        assert time.perf_counter() - tick < 5
    finally:
        _kill(holder)


def test_a_command_line_holding_a_name_that_is_no_utf8_takes_the_lock(tmp_path, monkeypatch):
    """`predict caf\\xe9.png` (a Latin-1 file name: surrogates in argv) failed writing the
    lock's record ("surrogates not allowed"), naming no file and leaving --out behind."""
    import sys

    monkeypatch.setattr(sys, "argv", ["sq-mitsuba", "predict", "caf\udce9.png"])
    out = tmp_path / "out"
    with output_lock(out):
        assert (lock_path(out)).read_bytes().endswith(b"sq-mitsuba predict caf\\udce9.png\n")


def _deep(root, total=4050):
    """A path of about ``total`` bytes below ``root``, in folder names of 200 bytes (not made)."""
    path = root
    while len(os.fsencode(str(path))) + 201 < total:
        path = path / ("d" * 200)
    return path / ("e" * (total - len(os.fsencode(str(path))) - 1))


def test_an_output_too_deep_or_a_name_too_long_is_refused_before_any_work(
        tmp_path, capsys, eval_checkpoint, train_dataset):
    """Near the file system's limits a run failed part-way naming a temporary file (the
    render left a dataset marked "rendering", eval its journal); a name of 242-255 bytes,
    legal itself, left no room for its temporary name."""
    from sq_mitsuba.data.spe3r.layout import DatasetError
    from sq_mitsuba.data.spe3r.writer import check_writable
    from sq_mitsuba.io import check_output_folder

    deep = _deep(tmp_path)
    with pytest.raises(ValueError, match=r"^out .*: a path of \d+ bytes, too long for what the "
                                         r"run writes below it \(paths may have \d+ bytes\)"):
        check_output_folder(deep, ["summary.csv"])
    with pytest.raises(ValueError, match=r"^x+\.pt: a name of 250 bytes, too long for its "
                                         r"temporary file"):
        check_output_folder(tmp_path, ["x" * 247 + ".pt"])
    check_output_folder(tmp_path, ["x" * 238 + ".pt"])  # 241 + 14: room enough
    with pytest.raises(DatasetError, match=r"a path of \d+ bytes, too long"):
        check_writable(_deep(tmp_path / "render", 4000), ["m" * 40])
    assert not (tmp_path / "render").exists()
    assert main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
                 "--split", "val", "--out", str(deep), "--quiet"]) == 2
    assert "too long for what the run writes below it" in error_line(capsys)
    assert not (tmp_path / ("d" * 200)).exists()


def test_a_render_holds_its_folder_alone_and_its_shards_share_it(tmp_path, capsys):
    """Two renders into one folder mixed their images (settings apart, both exit 0) or
    deleted each other's temporary files; an --overwrite deleted a running render's images.
    A render without shards now holds its folder alone, a shard shares it with shards."""
    library = tmp_path / "library"
    assert main(["models", "generate", "--count", "1", "--points", "500", "--out",
                 str(library)]) == 0
    out = tmp_path / "data"
    render = ["dataset", "render", "--models", str(library), "--out", str(out),
              "--images-per-model", "2", "--resolution", "32", "--spp", "1", "--quiet"]
    capsys.readouterr()
    shard = _hold_shared(out)  # a shard of the render, at work
    try:
        for extra in ([], ["--overwrite"]):  # alone, or clearing: refused beside a shard
            assert main([*render, *extra]) == 2
            assert f"{out}: another run is writing into this folder" in error_line(capsys)
            assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]  # nothing written
        assert main([*render, "--shard", "0/2"]) == 0  # another shard: beside it
        capsys.readouterr()
    finally:
        _kill(shard)
    holder = _hold(out)  # a render without shards, at work
    try:
        assert main([*render, "--shard", "1/2"]) == 2
        assert f"{out}: another run is writing into this folder" in error_line(capsys)
    finally:
        _kill(holder)
    assert main([*render, "--shard", "1/2"]) == 0  # the dataset completed by its other shard
    assert "splits.csv" in {p.name for p in out.iterdir()}
    assert not [p for p in out.iterdir() if p.name.endswith(LOCK_NAME) and p.name != LOCK_NAME]


def test_a_demo_into_a_folder_another_demo_writes_is_refused(tmp_path, capsys):
    """Two demos into one --out both printed "open index.html" and the folder held the last
    one's: a demo holds the lock beside its folder (which it swaps whole), from its checks
    to the swap."""
    out = tmp_path / "demo"
    out.mkdir()
    holder = _hold_file(out)  # another demo, at work
    try:
        assert main(["demo", "--size", "tiny", "--out", str(out)]) == 2
        assert f"{out}: another run is writing into this folder" in error_line(capsys)
        assert list(out.iterdir()) == []
        assert sorted(p.name for p in tmp_path.iterdir()) == [f".demo{LOCK_NAME}", "demo"]
    finally:
        _kill(holder)
