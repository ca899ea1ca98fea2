"""Rendering backend: variant choice, kernel cache, kernel counter, doctor."""

from __future__ import annotations

import os

import pytest

from sq_mitsuba.render import backend


def test_variant_is_an_ad_mono_variant():
    mi = backend.mitsuba()
    assert mi.variant() in backend.PREFERRED_VARIANTS
    assert backend.active_variant() == mi.variant()
    assert backend.mitsuba() is mi  # idempotent


def test_kernel_cache_is_configured():
    backend.mitsuba()
    assert os.environ.get(backend.CACHE_ENV)


def test_unknown_variant_raises_one_clear_error(monkeypatch):
    with pytest.raises(ValueError, match=r"^variant='no_such_variant': not a variant "):
        backend.mitsuba("no_such_variant")
    # A variant Mitsuba has but the tool cannot render with fails here, not inside a render.
    monkeypatch.setenv(backend.VARIANT_ENV, "scalar_rgb")
    with pytest.raises(ValueError, match=r"^SQ_MITSUBA_VARIANT='scalar_rgb': not a variant "
                                         r"sq-mitsuba renders with; use cuda_ad_mono or "
                                         r"llvm_ad_mono"):
        backend.mitsuba()


def test_a_bad_variant_in_the_environment_stops_every_command_first(monkeypatch, tmp_path,
                                                                     capsys):
    from output_checks import error_line

    from sq_mitsuba.cli import main

    monkeypatch.setenv(backend.VARIANT_ENV, "bogus")
    out = tmp_path / "library"
    assert main(["models", "generate", "--count", "1", "--out", str(out)]) == 2
    assert error_line(capsys).startswith("sq-mitsuba models: error: SQ_MITSUBA_VARIANT='bogus'")
    assert not out.exists()


def test_describe_reports_versions_and_device():
    info = backend.describe()
    for key in ("mitsuba", "drjit", "variant", "device"):
        assert info[key]
    if info["variant"].startswith("llvm"):
        assert int(info["llvm"].split(".")[0]) >= 17


def test_count_kernels_sees_compilation_then_reuse():
    mi = backend.mitsuba()
    import drjit as dr

    def compute(scale: float) -> None:
        x = dr.arange(mi.Float, 1000)
        dr.eval(dr.sin(x * dr.opaque(mi.Float, scale)) + 0.123456)

    compute(1.0)
    with backend.count_kernels() as counter:
        compute(2.0)
    assert counter.launched >= 1 and counter.compiled == 0


def test_doctor_command(capsys):
    from sq_mitsuba.cli import main

    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert "variant" in out and "ok" in out


def test_a_variant_the_environment_forces_and_cannot_run_says_to_unset_it(tmp_path):
    """SQ_MITSUBA_VARIANT=cuda_ad_mono on a machine without a GPU: the message names the
    variable and what to do (it said to install libllvm19, which was there)."""
    import subprocess
    import sys

    env = {**os.environ, backend.VARIANT_ENV: "cuda_ad_mono"}
    env.pop("SQ_MITSUBA_TRACEBACK", None)
    done = subprocess.run([sys.executable, "-m", "sq_mitsuba", "doctor"], env=env,
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    if done.returncode == 0:
        pytest.skip("this machine runs cuda_ad_mono")
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        "sq-mitsuba doctor: error: Mitsuba variant 'cuda_ad_mono' (from SQ_MITSUBA_VARIANT) "
        "cannot run here (no CUDA driver or GPU?); unset SQ_MITSUBA_VARIANT to use the first "
        "that can (cuda_ad_mono, llvm_ad_mono)")


def test_a_variant_set_by_name_stays_and_the_integrators_follow_it(monkeypatch):
    """$SQ_MITSUBA_VARIANT chooses the first variant only: after a variant set by name
    (training asks for cuda_ad_mono; llvm_ad_rgb stands in here, no GPU), the plain
    mitsuba() every renderer calls keeps it, and the project's integrators, which Mitsuba
    registers per variant, are registered in it too."""
    from sq_mitsuba.render.silhouette.integrator import COVERAGE_PLUGIN, PLUGIN, register

    mi = backend.mitsuba()
    first = mi.variant()
    monkeypatch.setenv(backend.VARIANT_ENV, first)
    register()
    try:
        mi.set_variant("llvm_ad_rgb")
        assert backend.mitsuba().variant() == "llvm_ad_rgb"
        register()
        # "Plugin not found" when registered in the first variant only.
        mi.load_dict({"type": PLUGIN, "max_depth": 1})
        mi.load_dict({"type": COVERAGE_PLUGIN})
    finally:
        mi.set_variant(first)
    assert backend.mitsuba().variant() == first
