"""Issue 35: bad input and interruptions of ``sq-mitsuba`` commands, with the real code.

Bad input is one line saying what and where, exit code 2, before any work; Ctrl-C is exit code
130 and the one line "interrupted", with nothing of Dr.Jit's generated code on the terminal.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import signal
import subprocess
import sys
import time
import warnings

import pytest
import torch
from output_checks import error_line

import sq_mitsuba.bench as bench
from sq_mitsuba.cli import EXIT_ERROR, EXIT_INTERRUPTED, TRACEBACK_ENV, main
from sq_mitsuba.geometry.camera import Camera


@pytest.fixture(autouse=True)
def no_env_traceback(monkeypatch):
    """One-line errors, whatever the shell running the tests sets."""
    monkeypatch.delenv(TRACEBACK_ENV, raising=False)


# --- bench --device (item 2) -----------------------------------------------------------------


@pytest.fixture
def no_suite_runs(monkeypatch):
    """Fails the test if a suite starts: the device must be refused before any work."""
    def started(name, options):
        raise AssertionError(f"suite {name} started with device {options.device!r}")

    monkeypatch.setattr(bench, "run_suite", started)


SUITES = [*bench.available_suites(), "all", "curves"]


def test_every_suite_of_bench_all_has_a_run_and_is_named_once():
    """`bench all` runs every suite `available_suites` lists: each must be a module with a
    `run(options)` (curves, a training run, is not one and is left out); `bench --help`
    lists each name once."""
    import importlib

    for name in bench.available_suites():
        assert callable(getattr(importlib.import_module(f"sq_mitsuba.bench.{name}"), "run",
                                None)), name
    assert "curves" not in bench.available_suites()
    assert len(SUITES) == len(set(SUITES))


@pytest.mark.parametrize("suite", SUITES)
def test_bench_refuses_a_device_that_is_not_one(suite, capsys, no_suite_runs):
    assert main(["bench", suite, "--device", "tpu"]) == EXIT_ERROR
    assert error_line(capsys) == ("sq-mitsuba bench: error: --device: 'tpu' is not a device; "
                                  "expected cpu, cuda or cuda:N")


@pytest.mark.parametrize("extra", [["--data", "d"], ["--minutes", "1"], ["--out", "o"],
                                   ["--configs", "cpu"]])
def test_bench_refuses_the_curves_options_for_another_suite(extra, capsys, no_suite_runs):
    assert main(["bench", "geometry", *extra]) == EXIT_ERROR
    assert error_line(capsys) == (f"sq-mitsuba bench: error: {extra[0]}: only used by the "
                                  "curves suite")


@pytest.mark.parametrize("device", ["gpu", "cuda:", "cuda:x", "CPU", "cuda0", ""])
def test_bench_refuses_malformed_device_names(device, capsys, no_suite_runs):
    assert main(["bench", "geometry", "--device", device]) == EXIT_ERROR
    assert "--device: " in error_line(capsys)


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
@pytest.mark.parametrize("suite", SUITES)
@pytest.mark.parametrize("device", ["cuda", "cuda:0", "cuda:3"])
def test_bench_refuses_cuda_without_cuda(suite, device, capsys, no_suite_runs):
    assert main(["bench", suite, "--device", device]) == EXIT_ERROR
    line = error_line(capsys)
    assert line.startswith(f"sq-mitsuba bench: error: --device: '{device}': CUDA is not "
                           "available"), line
    if torch.version.cuda is None:
        assert "in this torch build" in line
    assert "Traceback" not in line and "internal error" not in line


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_bench_refuses_a_gpu_index_past_the_last(capsys, no_suite_runs):
    index = torch.cuda.device_count()
    assert main(["bench", "geometry", "--device", f"cuda:{index}"]) == EXIT_ERROR
    assert "no such GPU" in error_line(capsys)


def test_library_checks_the_device_before_any_suite(no_suite_runs):
    with pytest.raises(ValueError, match="device: 'tpu' is not a device"):
        bench.BenchOptions(device="tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            next(bench.run_suites(["geometry"], bench.BenchOptions(device="cuda")))
    bench.check_device("cpu")



# --- Ctrl-C inside Dr.Jit and Mitsuba (item 7) ----------------------------------------------


@pytest.fixture
def ctrl_c_raises():
    """Python's own Ctrl-C handler for the test. A shell ignores SIGINT in what it starts in
    the background (``make test &``), and the ignored signal is inherited: these tests need
    Ctrl-C to act, as it does in a terminal."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _sigint_acts() -> None:
    """In a child process, before it runs: SIGINT to its default (the shell that started the
    tests may have ignored it, and an ignored signal survives exec)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _interrupt_while_tracing(mi):
    """A real ``dr.switch`` whose traced callable gets Ctrl-C (the process sends itself
    SIGINT), as when the user presses it while Mitsuba traces a render; returns the result."""
    import drjit as dr

    def interrupted_branch(x):
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000):  # Python code after the signal: its handler runs in here
            pass
        return x * 2

    return dr.switch(mi.UInt32([0, 1]), [interrupted_branch, lambda x: x + 1],
                     mi.Float([1.0, 2.0]))


def test_ctrl_c_inside_drjit_comes_out_disguised(ctrl_c_raises):
    """What the CLI has to recognise: Dr.Jit turns a KeyboardInterrupt raised in Python code
    it runs into a RuntimeError caused by it."""
    from sq_mitsuba.render.backend import mitsuba

    with pytest.raises(RuntimeError, match=r"drjit\.switch\(\)") as caught:
        _interrupt_while_tracing(mitsuba())
    assert isinstance(caught.value.__cause__, KeyboardInterrupt)


def test_interrupts_deferred_holds_ctrl_c_until_the_drjit_call_is_done(ctrl_c_raises):
    from sq_mitsuba.render.backend import interrupts_deferred, mitsuba

    mi = mitsuba()
    handler = signal.getsignal(signal.SIGINT)
    done = []
    with pytest.raises(KeyboardInterrupt), interrupts_deferred():
        done.append(_interrupt_while_tracing(mi))  # finishes: the Ctrl-C waits
    assert len(done) == 1
    assert signal.getsignal(signal.SIGINT) is handler
    with interrupts_deferred():  # no Ctrl-C: nothing raised
        pass
    assert signal.getsignal(signal.SIGINT) is handler


def test_cli_maps_a_disguised_ctrl_c_to_exit_130(monkeypatch, capsys, ctrl_c_raises):
    from sq_mitsuba.render.backend import mitsuba

    def run(args):
        _interrupt_while_tracing(mitsuba())

    monkeypatch.setattr(importlib.import_module("sq_mitsuba.cli.doctor"), "_run", run)
    assert main(["doctor"]) == EXIT_INTERRUPTED
    assert error_line(capsys) == "sq-mitsuba doctor: interrupted"


def _loaded(pid: int, library: str) -> bool:
    try:
        with open(f"/proc/{pid}/maps", encoding="utf-8") as maps:
            return library in maps.read()
    except OSError:
        return False


#: Lines of generated code: LLVM IR, PTX, or Python code that @dr.syntax generated.
GENERATED_CODE = re.compile(r"^\s*(%|define |ret |declare |\.visible|\.reg|def |while )", re.M)


@pytest.mark.slow  # ~15 s: four runs of the command
@pytest.mark.skipif(not os.path.exists(f"/proc/{os.getpid()}/maps"), reason="needs /proc")
def test_ctrl_c_during_mitsuba_import_and_renders_is_exit_130_and_one_line():
    """``sq-mitsuba bench render``, interrupted with SIGINT at several times from the moment
    Dr.Jit is loaded: while Mitsuba and its AD integrators are imported (where an interrupt
    used to come out as NameError, ImportError, SystemError or a C++ abort), while the scene
    is built and while silhouettes are rendered. Each time: exit code 130, the one line, and
    nothing of Dr.Jit's generated code."""
    env = {k: v for k, v in os.environ.items() if k != TRACEBACK_ENV}
    command = [sys.executable, "-m", "sq_mitsuba", "bench", "render", "--repeats", "1",
               "--warmup", "0"]
    for delay in (0.0, 0.25, 0.6, 1.5):  # Mitsuba's import, its end, the scene, the renders
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                   text=True, env=env, preexec_fn=_sigint_acts)
        try:
            start = time.monotonic()
            while not _loaded(process.pid, "libdrjit-core") and process.poll() is None:
                assert time.monotonic() - start < 60, "Dr.Jit was not loaded within 60 s"
                time.sleep(0.002)
            time.sleep(delay)
            process.send_signal(signal.SIGINT)
            out, err = process.communicate(timeout=60)
        finally:
            if process.poll() is None:
                process.kill()
                process.communicate()
        assert process.returncode == EXIT_INTERRUPTED, (delay, process.returncode, err)
        assert err == "sq-mitsuba bench: interrupted\n", (delay, err)
        assert not GENERATED_CODE.search(err) and out == "", (delay, out)


# --- warnings as one line (minor) ------------------------------------------------------------


def test_a_missing_model_warning_is_one_clean_line(tmp_path, capsys):
    """A dataset whose splits.csv names a model without labels: Spe3rDataset's
    MissingModelWarning, then the empty split's error, each one line (no file:line prefix, no
    source line)."""
    data = tmp_path / "data"
    data.mkdir()
    (data / "camera.json").write_text(json.dumps(Camera.default(64).to_speed_dict()))
    (data / "splits.csv").write_text("ghost,test\n")
    assert main(["eval", "--data", str(data), "--out", str(tmp_path / "out"),
                 "--split", "test"]) == EXIT_ERROR
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == (f"sq-mitsuba eval: warning: {data / 'ghost' / 'labels.json'}: missing; "
                        "model ghost left out of the test split"), lines
    assert lines[1].startswith("sq-mitsuba eval: error: ") and len(lines) == 2, lines
    assert not any("MissingModelWarning" in line or ".py:" in line for line in lines)


def test_warnings_keep_pythons_format_outside_the_command(tmp_path, capsys):
    show = warnings.showwarning
    assert main(["report", str(tmp_path / "missing"), "--out", str(tmp_path / "out")]) == 2
    assert warnings.showwarning is show


# --- damaged files: one line, no numpy / torch advice (minor) -------------------------------


@pytest.fixture(scope="module")
def one_model_library(tmp_path_factory):
    """A library of one generated spacecraft (ROOT/<model>/models/...)."""
    from sq_mitsuba.data.library import generate_model
    from sq_mitsuba.data.spacecraft import catalogue

    root = tmp_path_factory.mktemp("library")
    generate_model(catalogue(1, 5)[0], root, points=500)
    return root


def _copy_library(source, target):
    import shutil

    shutil.copytree(source, target)
    return target


def test_models_preview_refuses_a_corrupt_samples_archive(one_model_library, tmp_path,
                                                          capsys):
    root = _copy_library(one_model_library, tmp_path / "lib")
    (samples,) = root.glob("*/models/samples.npz")
    samples.write_bytes(os.urandom(512))  # no zip, no .npy: numpy would try to unpickle it
    assert main(["models", "preview", str(root), "--size", "16", "--spp", "1"]) == EXIT_ERROR
    line = error_line(capsys)
    assert line == (f"sq-mitsuba models: error: {samples}: corrupt or truncated: not a valid "
                    ".npz file")
    assert "pickle" not in line and not (root / "contact_sheet.png").exists()


@pytest.mark.parametrize("cut", [10, 40, 2000])
def test_a_truncated_checkpoint_is_one_line_without_torch_internals(cut, tmp_path, capsys):
    """Cut short, torch's zip reader fails with "... This is an internal miniz error. If you
    are seeing this error..." or "[Errno 22] Invalid argument", by where the cut falls."""
    path = tmp_path / "run" / "checkpoint.pt"
    path.parent.mkdir()
    torch.save({"model": {"weight": torch.zeros(1000)}}, path)
    path.write_bytes(path.read_bytes()[:-cut])
    assert main(["export", "--checkpoint", str(path), "--out",
                 str(tmp_path / "out.pt")]) == EXIT_ERROR
    line = error_line(capsys)
    assert line == (f"sq-mitsuba export: error: {path}: not a readable checkpoint (corrupt or "
                    "truncated: not a valid .pt file)"), line
    assert "miniz" not in line and "PytorchStreamReader" not in line


# --- models preview --out (minor) ------------------------------------------------------------


def test_models_preview_writes_the_format_its_suffix_names(one_model_library, tmp_path,
                                                           capsys):
    out = tmp_path / "sheet.jpg"
    assert main(["models", "preview", str(one_model_library), "--out", str(out),
                 "--size", "16", "--spp", "1"]) == 0
    assert out.read_bytes()[:3] == b"\xff\xd8\xff"  # JPEG, not PNG bytes
    from PIL import Image

    with Image.open(out) as image:
        assert image.format == "JPEG"


@pytest.mark.parametrize("name", ["sheet.gif", "sheet", "sheet.png.txt"])
def test_models_preview_refuses_a_suffix_it_cannot_write(name, one_model_library, tmp_path,
                                                         capsys):
    out = tmp_path / name
    assert main(["models", "preview", str(one_model_library), "--out", str(out)]) == EXIT_ERROR
    line = error_line(capsys)
    assert line.startswith(f"sq-mitsuba models: error: --out: '{out}' has "), line
    assert ".png, .jpg" in line and not out.exists()


@pytest.mark.parametrize("extra", [["--repeats", "3"], ["--warmup", "1"], ["--threads", "2"],
                                   ["--device", "cpu"], ["--batch", "4"], ["--step-only"]])
def test_bench_curves_refuses_the_options_it_does_not_use(extra, capsys, monkeypatch):
    """run_curves takes none of the timing suites' options: refused, as the other suites
    refuse the curves' options, before any training."""
    import sq_mitsuba.bench.curves as curves

    def started(*args, **kwargs):
        raise AssertionError("the curves started")

    monkeypatch.setattr(curves, "run_curves", started)
    assert main(["bench", "curves", *extra, "--data", "d", "--minutes", "1",
                 "--out", "o"]) == EXIT_ERROR
    assert error_line(capsys) == (f"sq-mitsuba bench: error: {extra[0]}: not used by the "
                                  "curves suite")


def test_a_library_a_file_and_a_missing_folder_are_named_for_what_they_are(train_dataset,
                                                                           tmp_path, capsys):
    """A new user's slips (a review, 2026-12-01): a model library given to dataset check, a
    file given as a dataset's output folder, a folder that is not there given to report."""
    import shutil

    library = tmp_path / "library"  # what models generate writes: model folders, no camera
    for card in train_dataset.glob("*/models/model_card.json"):
        shutil.copytree(card.parent, library / card.parent.parent.name / "models")
    assert main(["dataset", "check", str(library)]) == EXIT_ERROR
    assert error_line(capsys).endswith(f"{library}: a model library, not a dataset: render one "
                                       f"with sq-mitsuba dataset render --models {library} "
                                       "--out DATA (or check a library's models with sq-mitsuba "
                                       "models preview)")
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")
    assert main(["dataset", "render", "--models", str(library), "--out", str(a_file),
                 "--images-per-model", "1", "--quiet"]) == EXIT_ERROR
    assert error_line(capsys).endswith(f"{a_file}: exists and is not a folder; give a folder "
                                       "to render into")
    assert a_file.read_text() == "mine"
    assert main(["report", str(tmp_path / "nowhere"), "--out", str(tmp_path / "r")]) == 2
    assert error_line(capsys).endswith(f"{tmp_path / 'nowhere'}: no such folder")
    assert main(["report", str(a_file), "--out", str(tmp_path / "r")]) == 2
    assert error_line(capsys).endswith(f"{a_file}: not a folder (give an evaluation folder, as "
                                       "`sq-mitsuba eval --out` wrote it)")
    assert not (tmp_path / "r").exists()


def test_the_machine_line_says_threads_beyond_the_cores_as_such():
    """--threads 64 on 2 cores was written "64 of 2 cores used"."""
    cores = os.cpu_count()
    line = bench.machine_description(bench.BenchOptions(threads=cores + 62, device="cpu"))
    assert f"{cores + 62} threads on {cores} cores" in line
    assert f"1 of {cores} cores used" in bench.machine_description(
        bench.BenchOptions(threads=1, device="cpu"))


def test_train_max_steps_0_says_it_trained_nothing_and_wrote_no_checkpoint(train_dataset,
                                                                           tmp_path, capsys):
    """--max-steps 0 checks everything and builds the caches (its documented use): its summary
    says no step ran and no checkpoint exists to resume, not "trained 0/N steps; wrote OUT"."""
    from pathlib import Path

    tiny = Path(__file__).resolve().parents[1] / "train" / "configs" / "tiny.toml"
    out = tmp_path / "run"
    assert main(["train", "--config", str(tiny), "--data", str(train_dataset), "--out",
                 str(out), "--max-steps", "0", "--quiet"]) == 0
    said = capsys.readouterr().out.strip()
    assert said == ("--max-steps 0: checked the config and the dataset and built the caches, "
                    "then stopped before the first step; no checkpoint written, so nothing to "
                    f"--resume (training into {out} again starts the run)")
    assert not list(out.glob("*.pt"))
