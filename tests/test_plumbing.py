"""Project plumbing: libLLVM discovery, lazy imports, atomic files, the CLI and bench reports."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from sq_mitsuba import llvm
from sq_mitsuba.bench import BenchOptions, Report, Timing, write_report
from sq_mitsuba.cli import main
from sq_mitsuba.io import atomic_path, atomic_write_json


@pytest.mark.parametrize(("name", "major"), [
    ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1", 15),
    ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", 19),
    ("/usr/lib/llvm-18/lib/libLLVM.so", 18),
    ("/usr/lib/libfoo.so", None),
])
def test_llvm_version_parsing(name, major):
    assert llvm.llvm_major_version(name) == major


def test_a_usable_libllvm_is_installed():
    """`make setup` installs libllvm19 when missing; Dr.Jit then reports a version >= 17."""
    found = llvm.find_libllvm()
    assert found is not None and llvm.llvm_major_version(found) >= llvm.MIN_LLVM_MAJOR
    code = ("import sq_mitsuba, drjit as dr; v = dr.detail.llvm_version(); "
            "assert v[0] >= 17, v; print(v[0])")
    env = {k: v for k, v in os.environ.items() if k != llvm.ENV_VAR}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True)
    assert int(out.stdout) >= 17


def test_missing_libllvm_is_one_clear_error(monkeypatch, tmp_path):
    monkeypatch.delenv(llvm.ENV_VAR, raising=False)
    monkeypatch.setattr(llvm, "_SEARCH_GLOBS", (str(tmp_path / "libLLVM*.so*"),))
    monkeypatch.delitem(sys.modules, "drjit", raising=False)
    with pytest.raises(llvm.LLVMNotFoundError, match="libllvm19"):
        llvm.configure_llvm(required=True)
    assert llvm.configure_llvm(required=False) is None


def test_user_choice_of_libllvm_is_kept(monkeypatch):
    monkeypatch.setenv(llvm.ENV_VAR, "/opt/my/libLLVM-20.so")
    assert llvm.configure_llvm() == Path("/opt/my/libLLVM-20.so")


def test_importing_the_package_and_geometry_does_not_import_mitsuba():
    code = ("import sys, sq_mitsuba, sq_mitsuba.geometry.assembly, "
            "sq_mitsuba.geometry.superquadric, sq_mitsuba.geometry.rotation, "
            "sq_mitsuba.geometry.icosphere, sq_mitsuba.geometry.camera; "
            "assert 'mitsuba' not in sys.modules and 'drjit' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.json"
    atomic_write_json(target, {"a": 1})
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("crash mid-write")
    assert target.read_text() == '{\n  "a": 1\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]
    # Not the 0600 of a temporary file: the usual permissions under the umask.
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask


def test_write_report_replaces_only_its_section(tmp_path):
    path = tmp_path / "BENCHMARKS.md"
    options = BenchOptions(repeats=1)
    write_report(Report("alpha", [Timing("op", [0.001], target_s=0.002)], options=options), path)
    write_report(Report("beta", [Timing("op", [0.5])], options=options), path)
    write_report(Report("alpha", [Timing("op", [0.003], target_s=0.002)], options=options), path)
    text = path.read_text()
    assert text.count("bench:alpha:start") == 1 and text.count("bench:beta:start") == 1
    assert "| op | 3.00 |" in text and "| op | 1.00 |" not in text and "| NO |" in text
    assert "| op | 500.00 |" in text


def test_cli_bench_geometry_runs(capsys):
    assert main(["bench", "geometry", "--repeats", "1", "--warmup", "0"]) == 0
    out = capsys.readouterr().out
    assert "occupancy + overlap fwd+bwd, dual (fused)" in out and "dual / primal" in out


def test_cli_rejects_bad_options(capsys):
    assert main(["bench", "geometry", "--repeats", "0"]) == 2
    assert "error" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["bench", "no-such-suite"])


def test_value_checks_switch_off_in_a_block_shape_and_dtype_checks_stay():
    import torch

    from sq_mitsuba.checks import check_tensor, value_checks, value_checks_enabled

    bad = torch.tensor([[0.0, float("nan"), 1.0]])
    assert value_checks_enabled()
    with pytest.raises(ValueError, match="x: contains NaN"):
        check_tensor("x", bad, (3,))
    with value_checks(False):
        assert not value_checks_enabled()
        assert check_tensor("x", bad, (3,)) is bad
        with pytest.raises(ValueError, match=r"x: expected shape \(\.\.\., 4\)"):
            check_tensor("x", bad, (4,))
        with pytest.raises(ValueError, match="x: expected a floating-point dtype"):
            check_tensor("x", torch.zeros(2, 3, dtype=torch.int64), (3,))
        with value_checks(True):  # nested blocks restore the outer setting
            with pytest.raises(ValueError, match="NaN"):
                check_tensor("x", bad, (3,))
        assert check_tensor("x", bad, (3,)) is bad
    with pytest.raises(ValueError, match="NaN"):  # back on after the block
        check_tensor("x", bad, (3,))


@pytest.mark.parametrize(("value", "checked"), [("0", False), ("OFF", False), ("no", False),
                                                 ("1", True), ("", True), ("yes", True)])
def test_value_checks_environment_words(monkeypatch, value, checked):
    from sq_mitsuba import checks

    monkeypatch.setenv(checks.CHECKS_ENV, value)
    assert checks._checks_from_environment() is checked
    monkeypatch.setenv(checks.CHECKS_ENV, "maybe")
    with pytest.warns(UserWarning, match="maybe"):
        assert checks._checks_from_environment() is True


def test_value_checks_environment_variable_is_read_once():
    code = ("import os, torch\n"
            "from sq_mitsuba import checks\n"
            "os.environ['SQ_MITSUBA_CHECKS'] = '1'  # after the import: must not matter\n"
            "bad = torch.tensor([float('nan'), 0.0, 0.0])\n"
            "checks.check_tensor('x', bad, (3,))\n"
            "try:\n    checks.check_tensor('x', bad, (4,))\nexcept ValueError as e:\n"
            "    print(e)\n")
    env = {**os.environ, "SQ_MITSUBA_CHECKS": "0"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout
    assert out == "x: expected shape (..., 4), got (3,)\n"


def test_doctor_render_self_test(capsys):
    assert main(["doctor", "--render"]) == 0
    out = capsys.readouterr().out
    line = next(row for row in out.splitlines() if "silhouette:" in row)
    covered = float(line.split("sphere: ")[1].split(" px")[0])
    exact = float(line.split("(exact ")[1].split(")")[0])
    # The sphere (radius 0.3 at 2 m) seen by the default 64 px camera: a disc of radius
    # f r / sqrt(d^2 - r^2) pixels, computed here independently of the library.
    import math

    from sq_mitsuba.geometry.camera import Camera

    focal = Camera.default(64).fx
    assert exact == pytest.approx(math.pi * (focal * 0.3 / math.sqrt(2**2 - 0.3**2)) ** 2,
                                  abs=0.06)
    assert abs(covered - exact) < 0.03 * exact and "gradient finite" in line
    assert out.rstrip().endswith("ok: the renderer can run")


def test_cli_errors_are_one_line(capsys):
    from sq_mitsuba.cli import CLIError, _one_line

    assert _one_line(CLIError("first\n  second\n")) == "first; second"
    assert _one_line(ValueError()) == "ValueError"
    assert main(["bench", "geometry", "--threads", "0"]) == 2
    err = capsys.readouterr().err
    assert err == "sq-mitsuba bench: error: --threads: expected a value in [1, 1024], got 0\n"


def test_benchmarks_are_recorded_in_the_repository_eval_folder():
    from pathlib import Path

    from sq_mitsuba import bench

    repository = Path(__file__).resolve().parents[1]
    assert bench.BENCHMARKS_MD == repository / "eval" / "BENCHMARKS.md"
    assert bench.BENCHMARKS_MD.is_file()
