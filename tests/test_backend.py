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


def test_unknown_variant_raises_one_clear_error():
    with pytest.raises(backend.BackendError, match="no Mitsuba variant"):
        backend.mitsuba("no_such_variant")


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
