"""Project plumbing: libLLVM discovery, lazy imports, atomic files, the CLI and bench reports."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from sq_mitsuba import llvm
from sq_mitsuba.cli import main
from sq_mitsuba.evaluation.bench import BenchOptions, Report, Timing, write_report
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
