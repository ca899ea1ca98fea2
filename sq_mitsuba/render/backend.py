"""Choose and initialise the Mitsuba variant, once per process.

Order of preference: ``cuda_ad_mono`` when Dr.Jit's CUDA backend works, else ``llvm_ad_mono``
(which needs libLLVM >= 17, see :mod:`sq_mitsuba.llvm`). ``SQ_MITSUBA_VARIANT`` overrides the
choice. Dr.Jit's kernel cache goes to the project-local ``.drjit-cache`` unless the user set
``DRJIT_CACHE_DIR``, so compiled kernels survive between runs without touching ``~/.drjit``.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

from sq_mitsuba.llvm import configure_llvm

PREFERRED_VARIANTS = ("cuda_ad_mono", "llvm_ad_mono")
VARIANT_ENV = "SQ_MITSUBA_VARIANT"
CACHE_ENV = "DRJIT_CACHE_DIR"
PROJECT_ROOT = Path(__file__).resolve().parents[2]


class BackendError(RuntimeError):
    """No Mitsuba variant can run on this machine."""


def _configure_cache() -> None:
    if CACHE_ENV not in os.environ:
        cache = PROJECT_ROOT / ".drjit-cache"
        cache.mkdir(exist_ok=True)
        os.environ[CACHE_ENV] = str(cache)


def _backend_works(variant: str) -> bool:
    import drjit as dr

    backend = dr.JitBackend.CUDA if variant.startswith("cuda") else dr.JitBackend.LLVM
    return bool(dr.has_backend(backend))


def mitsuba(variant: str | None = None) -> ModuleType:
    """The ``mitsuba`` module with a working variant set (idempotent).

    Args:
        variant: force a variant (e.g. ``"llvm_ad_mono"``); default: ``$SQ_MITSUBA_VARIANT`` or
            the first of :data:`PREFERRED_VARIANTS` whose backend works.

    Raises:
        BackendError: no variant can run (one line saying what to install).
    """
    _configure_cache()
    requested = variant or os.environ.get(VARIANT_ENV)
    if requested is None or requested.startswith("llvm"):
        configure_llvm(required=requested is not None)
    import mitsuba as mi

    current = mi.variant()
    if current is not None and (requested is None or current == requested):
        return mi
    candidates = [requested] if requested else list(PREFERRED_VARIANTS)
    for name in candidates:
        if name not in mi.variants():
            continue
        if name.startswith("llvm"):
            configure_llvm(required=True)
        if _backend_works(name):
            mi.set_variant(name)
            return mi
    raise BackendError(
        f"no Mitsuba variant can run (tried {', '.join(candidates)}): install libllvm19 "
        "(`make setup`) for the CPU, or a CUDA driver for the GPU"
    )


def active_variant() -> str | None:
    """The variant set in this process, or None (does not import Mitsuba)."""
    import sys

    mi = sys.modules.get("mitsuba")
    return None if mi is None else mi.variant()


class KernelCounter:
    """Kernels Dr.Jit launched inside a :func:`count_kernels` block.

    ``compiled`` counts kernels that were neither in the in-memory nor on the on-disk cache
    (fresh LLVM/CUDA compilations: the costly re-tracing the renderer must avoid once warm);
    ``loaded`` those found in the on-disk cache; ``launched`` all launches.
    """

    def __init__(self) -> None:
        self.launched = 0
        self.compiled = 0
        self.loaded = 0

    def __repr__(self) -> str:
        return (f"KernelCounter(launched={self.launched}, compiled={self.compiled}, "
                f"loaded={self.loaded})")


@contextlib.contextmanager
def count_kernels() -> Iterator[KernelCounter]:
    """Count Dr.Jit kernel launches and compilations in a ``with`` block (Dr.Jit's kernel
    history, switched on only for the block so that it does not grow without bound)."""
    mitsuba()
    import drjit as dr

    counter = KernelCounter()
    previous = dr.flag(dr.JitFlag.KernelHistory)
    dr.eval()
    dr.kernel_history()  # drop entries recorded before the block
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        yield counter
    finally:
        dr.eval()
        for entry in dr.kernel_history():
            counter.launched += 1
            if entry.get("type") != dr.KernelType.JIT:
                continue  # memcpy, reductions...: no code generated
            if entry.get("cache_disk", False):
                counter.loaded += 1
            elif not entry.get("cache_hit", False):
                counter.compiled += 1
        dr.set_flag(dr.JitFlag.KernelHistory, previous)


def describe() -> dict[str, str]:
    """Versions, variant, LLVM and device of the active backend (for ``sq-mitsuba doctor``)."""
    mi = mitsuba()
    import drjit as dr

    info = {
        "mitsuba": mi.__version__,
        "drjit": dr.__version__,
        "variant": mi.variant(),
        "kernel cache": os.environ.get(CACHE_ENV, "~/.drjit"),
    }
    if mi.variant().startswith("llvm"):
        version = dr.detail.llvm_version()
        info["llvm"] = ".".join(str(v) for v in version) if version else "unknown"
        info["libllvm"] = os.environ.get("DRJIT_LIBLLVM_PATH", "(Dr.Jit default search)")
        info["device"] = f"CPU, {dr.thread_count()} Dr.Jit threads"
    else:
        info["device"] = "CUDA GPU"
        with contextlib.suppress(Exception):
            import torch

            if torch.cuda.is_available():
                info["device"] = f"CUDA GPU {torch.cuda.get_device_name()}"
    return info
