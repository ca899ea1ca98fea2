"""How ``sq-mitsuba`` reports errors: bad input in one line (exit 2), a bug in one line naming it
an internal error (exit 1) with the hint to rerun with ``--traceback``, and with ``--traceback``
(before the command) or ``SQ_MITSUBA_TRACEBACK=1`` the exception itself, traceback and all."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys

import pytest
from output_checks import error_line

from sq_mitsuba.cli import EXIT_ERROR, EXIT_INTERNAL, TRACEBACK_ENV, main


def _report(tmp_path, *options):
    """``sq-mitsuba [options] report <missing folder> --out <tmp>/out``: a real bad input."""
    return [*options, "report", str(tmp_path / "not_an_eval"), "--out", str(tmp_path / "out")]


@pytest.fixture
def no_env_traceback(monkeypatch):
    """The tests' own setting of SQ_MITSUBA_TRACEBACK, whatever the shell running them has."""
    monkeypatch.delenv(TRACEBACK_ENV, raising=False)


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, no_env_traceback):
    assert main(_report(tmp_path)) == EXIT_ERROR == 2
    line = error_line(capsys)
    assert line.startswith("sq-mitsuba report: error: ") and "not_an_eval" in line
    assert "Traceback" not in line and "internal error" not in line
    assert not (tmp_path / "out").exists()


def test_a_torchrun_process_names_its_rank_in_its_error(tmp_path, capsys, monkeypatch,
                                                        no_env_traceback):
    """Every process of a torchrun run prints its own errors (one may fail alone): those of
    ranks > 0 say whose they are; rank 0's, like a one-process run's, read as ever."""
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("RANK", "3")
    assert main(_report(tmp_path)) == EXIT_ERROR
    assert error_line(capsys).startswith("sq-mitsuba report (rank 3 of 4): error: ")
    monkeypatch.setenv("RANK", "0")
    assert main(_report(tmp_path)) == EXIT_ERROR
    assert error_line(capsys).startswith("sq-mitsuba report: error: ")
    # A malformed variable: one line naming it, before any work, the speaker untagged.
    monkeypatch.setenv("LOCAL_RANK", "zero")
    assert main(_report(tmp_path)) == EXIT_ERROR
    assert error_line(capsys) == ("sq-mitsuba report: error: LOCAL_RANK: expected an integer "
                                  ">= 0 (set by the launcher, e.g. torchrun), got 'zero'")


@pytest.mark.parametrize("argv, command, message", [
    ([], "sq-mitsuba", "the following arguments are required: COMMAND"),
    (["bogus"], "sq-mitsuba", "argument COMMAND: invalid choice: 'bogus'"),
    (["predict", "x.png", "--out", ""], "sq-mitsuba predict",
     "argument --out: an empty path"),
    (["dataset", "render", "--models", "m", "--out", "o", "--spp", "many"],
     "sq-mitsuba dataset render", "argument --spp: invalid int value: 'many'"),
    (["eval", "--data", "d", "--out", "o", "--no-such-option"], "sq-mitsuba eval",
     "unrecognized arguments: --no-such-option"),  # the command whose help lists its options
    (["study", "passes", "--data", "d", "--out", "o", "--refien", "2"], "sq-mitsuba study passes",
     "unrecognized arguments: --refien 2"),
], ids=["no-command", "unknown-command", "bad-value", "bad-type-of-an-action", "unknown-option",
        "unknown-option-of-a-subcommand"])
def test_a_usage_error_is_one_line_and_exit_2(argv, command, message, capsys):
    """argparse's own errors too: one line naming the command and where to read more, not the
    usage block before it."""
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == EXIT_ERROR
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(f"{command}: error: {message}")
    assert lines[0].endswith(f"(see {command} --help)")


def test_traceback_flag_raises_the_bad_input_error(tmp_path, capsys, no_env_traceback):
    with pytest.raises(FileNotFoundError, match="not_an_eval"):
        main(_report(tmp_path, "--traceback"))
    assert capsys.readouterr().err == ""  # the exception, not the one line as well
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value", ["1", "yes", "true"])
def test_environment_variable_raises_the_bad_input_error(value, tmp_path, monkeypatch):
    monkeypatch.setenv(TRACEBACK_ENV, value)
    with pytest.raises(FileNotFoundError, match="not_an_eval"):
        main(_report(tmp_path))


@pytest.mark.parametrize("value", ["", "0", "false", "no"])
def test_environment_variable_off_keeps_the_one_line(value, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(TRACEBACK_ENV, value)
    assert main(_report(tmp_path)) == EXIT_ERROR
    assert "not_an_eval" in error_line(capsys)


def _doctor():
    """The module of ``sq-mitsuba doctor``, whose ``_run`` the tests replace by a bug."""
    return importlib.import_module("sq_mitsuba.cli.doctor")


def _raise_bug(args):
    raise RuntimeError("step 3 of the bug\nsecond line")


@pytest.mark.parametrize("error", [RuntimeError("a bug"), KeyError("key"), TypeError()])
def test_internal_error_is_one_line_exit_1_with_the_hint(error, monkeypatch, capsys,
                                                         no_env_traceback):
    def broken(args):
        raise error

    monkeypatch.setattr(_doctor(), "_run", broken)
    assert main(["doctor"]) == EXIT_INTERNAL == 1
    line = error_line(capsys)
    name = type(error).__name__
    assert line.startswith(f"sq-mitsuba doctor: internal error: {name}"), line
    assert "--traceback" in line and TRACEBACK_ENV in line
    if str(error):
        assert str(error) in line
    else:
        assert f"{name}:" not in line  # no empty message after the name


def test_internal_error_message_is_joined_into_one_line(monkeypatch, capsys, no_env_traceback):
    monkeypatch.setattr(_doctor(), "_run", _raise_bug)
    assert main(["doctor"]) == EXIT_INTERNAL
    assert "RuntimeError: step 3 of the bug; second line" in error_line(capsys)


def test_internal_error_with_traceback_propagates(monkeypatch, capsys, no_env_traceback):
    monkeypatch.setattr(_doctor(), "_run", _raise_bug)
    with pytest.raises(RuntimeError, match="step 3 of the bug"):
        main(["--traceback", "doctor"])
    monkeypatch.setenv(TRACEBACK_ENV, "1")
    with pytest.raises(RuntimeError, match="step 3 of the bug"):
        main(["doctor"])
    assert capsys.readouterr().err == ""


def test_internal_error_still_removes_the_failed_runs_output(tmp_path, monkeypatch, capsys,
                                                            no_env_traceback):
    def half_done(args):
        args.out.mkdir(parents=True, exist_ok=True)  # the output lock may have made it
        (args.out / "report.md").write_text("half")
        raise KeyError("missing column")

    monkeypatch.setattr(importlib.import_module("sq_mitsuba.cli.report"), "_run", half_done)
    argv = ["report", str(tmp_path), "--out", str(tmp_path / "new" / "out")]
    assert main(argv) == 1
    assert "internal error: KeyError: 'missing column'" in error_line(capsys)
    assert not (tmp_path / "new").exists()
    with pytest.raises(KeyError, match="missing column"):  # and so does --traceback
        main(["--traceback", *argv])
    assert not (tmp_path / "new").exists()


def test_interrupt_stays_exit_130(monkeypatch, capsys, no_env_traceback):
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(_doctor(), "_run", interrupted)
    assert main(["doctor"]) == 130
    assert error_line(capsys) == "sq-mitsuba doctor: interrupted"
    assert main(["--traceback", "doctor"]) == 130  # with the traceback printed above
    err = capsys.readouterr().err
    assert "Traceback" in err and err.strip().endswith("sq-mitsuba doctor: interrupted")


def test_an_interrupted_resumable_command_says_how_to_continue(monkeypatch, capsys, tmp_path,
                                                               no_env_traceback):
    """eval and train keep what they did (a journal, last.pt): the line says how to go on."""
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(importlib.import_module("sq_mitsuba.cli.eval"), "_run", interrupted)
    assert main(["eval", "--data", "d", "--out", "o"]) == 130
    assert error_line(capsys) == ("sq-mitsuba eval: interrupted (the same command with "
                                  "--resume continues from its journal in --out)")
    # By action: models generate resumes; models import would import a file twice.
    models = importlib.import_module("sq_mitsuba.cli.models")
    monkeypatch.setattr(models, "_generate", interrupted)
    monkeypatch.setattr(models, "_import", interrupted)
    assert main(["models", "generate", "--out", "lib"]) == 130
    assert error_line(capsys).endswith("interrupted (the same command again takes up where it "
                                       "stopped)")
    assert main(["models", "import", "a.obj", "--out", "lib"]) == 130
    assert error_line(capsys) == "sq-mitsuba models: interrupted"
    # train: --resume only where a step was saved (last.pt), else the way to start again.
    monkeypatch.setattr(importlib.import_module("sq_mitsuba.cli.train"), "_run", interrupted)
    run = tmp_path / "run"
    assert main(["train", "--config", "c.toml", "--data", "d", "--out", str(run)]) == 130
    assert error_line(capsys) == ("sq-mitsuba train: interrupted (no step was saved yet: the "
                                  "same command without --resume starts it again)")
    run.mkdir()
    (run / "best.pt").write_bytes(b"")  # a validation's save before the first last.pt
    assert main(["train", "--config", "c.toml", "--data", "d", "--out", str(run)]) == 130
    assert error_line(capsys) == ("sq-mitsuba train: interrupted (no last.pt was saved: move "
                                  "best.pt away to start again there, or choose another --out)")
    (run / "last.pt").write_bytes(b"")
    assert main(["train", "--config", "c.toml", "--data", "d", "--out", str(run)]) == 130
    assert error_line(capsys) == ("sq-mitsuba train: interrupted (the same command with "
                                  "--resume continues from last.pt)")


def test_a_terminated_run_stops_as_an_interrupted_one(tmp_path):
    """SIGTERM (``kill``, ``timeout``) is handled as Ctrl-C: one line, exit 130, the lock
    released and a folder the run made but wrote nothing into removed (killed outright, it
    left the folder holding a stale lock file)."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "out"
    code = ("import time\n"
            "from sq_mitsuba.cli import main\n"
            "import sq_mitsuba.cli.report as report\n"
            "def slow(args):\n"
            "    print('started', flush=True)\n"
            "    time.sleep(60)\n"
            "report._run = slow\n"
            f"raise SystemExit(main(['report', {str(tmp_path)!r}, '--out', {str(out)!r}]))\n")
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "started"
    assert (out / ".sq-mitsuba.lock").exists()
    process.send_signal(signal.SIGTERM)
    started = time.monotonic()
    _, err = process.communicate(timeout=30)
    assert time.monotonic() - started < 10
    assert process.returncode == 130, err
    assert err.strip().splitlines()[-1] == "sq-mitsuba report: interrupted"
    assert not out.exists()


def test_traceback_flag_goes_before_the_command(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main([*_report(tmp_path), "--traceback"])
    assert stop.value.code == 2
    assert "unrecognized arguments: --traceback" in capsys.readouterr().err


def test_top_level_help_documents_the_traceback_switches(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--traceback" in out and f"{TRACEBACK_ENV}=1" in out
    assert "internal error" in out


def test_a_process_prints_pythons_traceback_with_the_flag(tmp_path):
    """End to end, as the console script runs ``main``: exit 2 with one line, and with
    --traceback Python's own report of the uncaught exception (exit 1)."""
    code = "import sys; from sq_mitsuba.cli import main; sys.exit(main(sys.argv[1:]))"
    env_free = {k: v for k, v in os.environ.items() if k != TRACEBACK_ENV}
    plain = subprocess.run([sys.executable, "-c", code, *_report(tmp_path)],
                           capture_output=True, text=True, env=env_free)
    assert plain.returncode == 2 and plain.stderr.count("\n") == 1, plain.stderr
    loud = subprocess.run([sys.executable, "-c", code, *_report(tmp_path, "--traceback")],
                          capture_output=True, text=True, env=env_free)
    assert loud.returncode == 1
    assert loud.stderr.startswith("Traceback (most recent call last):")
    assert loud.stderr.strip().splitlines()[-1].startswith("FileNotFoundError: ")


@pytest.mark.parametrize("name", ["stdout", "stderr"])  # | head, or 2>&1 | head
@pytest.mark.parametrize("buffering", [1, -1])  # line-buffered (as PYTHONUNBUFFERED), blocks
def test_a_closed_stdout_keeps_a_finished_runs_output(buffering, name, tmp_path, monkeypatch,
                                                      no_env_traceback):
    """``sq-mitsuba ... | true``: the summary cannot be shown, but the run is done; its files
    stay and it exits 0 (a BrokenPipeError used to count as a failure and delete them). The
    same for stderr, where progress bars and warnings go (``2>&1 | head -1``)."""
    def finished(args):
        args.out.mkdir(parents=True, exist_ok=True)
        print("a line while working", file=getattr(sys, name))
        (args.out / "report.md").write_text("done")
        print("wrote 1 file", file=getattr(sys, name))
        return 0

    read, write = os.pipe()
    os.close(read)  # the reader has gone
    stream = open(write, "w", buffering=buffering)
    monkeypatch.setattr(sys, name, stream)
    monkeypatch.setattr(importlib.import_module("sq_mitsuba.cli.report"), "_run", finished)
    try:
        assert main(["report", str(tmp_path), "--out", str(tmp_path / "out")]) == 0
        print("after the run", file=stream)  # silenced for good: no error at exit either
        stream.flush()
    finally:
        monkeypatch.undo()
        stream.close()
    assert (tmp_path / "out" / "report.md").read_text() == "done"


def test_a_stdout_that_cannot_be_written_for_another_reason_is_an_error(tmp_path, monkeypatch,
                                                                         capsys,
                                                                         no_env_traceback):
    """Only a closed pipe is silenced: a stdout whose last flush fails otherwise (a full disk
    behind ``> out.txt``) ends in one line and exit code 2, not in a silent success."""
    import errno
    import io

    class FullDisk(io.StringIO):
        def flush(self) -> None:
            if self.getvalue():
                raise OSError(errno.ENOSPC, "No space left on device")

    def finished(args):
        args.out.mkdir(parents=True, exist_ok=True)
        print("wrote 1 file")
        return 0

    monkeypatch.setattr(importlib.import_module("sq_mitsuba.cli.report"), "_run", finished)
    monkeypatch.setattr(sys, "stdout", FullDisk())
    with pytest.raises(SystemExit) as stopped:
        main(["report", str(tmp_path), "--out", str(tmp_path / "out")])
    monkeypatch.undo()
    assert stopped.value.code == 2
    assert capsys.readouterr().err.strip().endswith("No space left on device")


@pytest.mark.parametrize("setting", ["refinement.steps=5", "search.grid=576", "mask=segmentation",
                                     "refine_ground_truth=false"])
def test_eval_refuses_the_fits_settings_without_refine(setting, tmp_path, capsys):
    """They would act on nothing: one line before any work (predict says the same)."""
    assert main(["eval", "--data", str(tmp_path / "d"), "--out", str(tmp_path / "o"),
                 "--set", setting]) == EXIT_ERROR
    assert error_line(capsys) == f"sq-mitsuba eval: error: --set {setting}: only used with --refine"
    assert not (tmp_path / "o").exists()


def test_demo_refuses_training_settings_without_train(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "d"), "--set", "training.models=5"]) == EXIT_ERROR
    assert error_line(capsys) == ("sq-mitsuba demo: error: --set training.models=5: only used "
                                  "with --train")
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize(("command", "flag"), [
    (["predict", "{file}/", "--out", "{out}"], "IMAGE"),
    (["predict", "{file}", "--camera", "{file}/", "--out", "{out}"], "--camera"),
    (["fit", "--masks", "{file}", "--poses", "{file}/", "--out", "{out}"], "--poses"),
    (["train", "--config", "{file}/", "--data", "{out}", "--out", "{out}"], "--config"),
    (["models", "import", "{file}/", "--out", "{out}"], "MESH"),
])
def test_an_input_file_written_with_a_trailing_separator_is_refused(command, flag, tmp_path,
                                                                    capsys):
    """``predict img.png/`` read the file ``img.png``, which the system itself would not open
    as written (``Path`` strips the separator): refused by argparse, in one line, before
    anything is read or written."""
    existing = tmp_path / "input.png"
    existing.write_bytes(b"")
    argv = [part.format(file=existing, out=tmp_path / "out") for part in command]
    with pytest.raises(SystemExit) as exited:
        main(argv)
    assert exited.value.code == 2
    line = error_line(capsys)
    assert flag in line and "ends in a separator, a folder; give the file to read" in line, line
    assert not (tmp_path / "out").exists()
