"""Choose and initialise the Mitsuba variant, once per process.

Order of preference: ``cuda_ad_mono`` when Dr.Jit's CUDA backend works, else ``llvm_ad_mono``
(which needs libLLVM >= 17, see :mod:`sq_mitsuba.llvm`). ``SQ_MITSUBA_VARIANT`` overrides the
choice. Dr.Jit's kernel cache goes to the project-local ``.drjit-cache`` unless the user set
``DRJIT_CACHE_DIR``, so compiled kernels survive between runs without touching ``~/.drjit``.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

from sq_mitsuba.llvm import configure_llvm

PREFERRED_VARIANTS = ("cuda_ad_mono", "llvm_ad_mono")
#: Mitsuba renders all samples of an image in one wavefront of at most 2^32 lanes; past that
#: it splits the render into passes, a path that took 24 GB for a 1024 px preview at 4096 spp.
#: Every renderer here refuses more samples per render, naming its options.
MAX_SAMPLES_PER_RENDER = 2**32 - 1
VARIANT_ENV = "SQ_MITSUBA_VARIANT"
CACHE_ENV = "DRJIT_CACHE_DIR"
PROJECT_ROOT = Path(__file__).resolve().parents[2]


class BackendError(RuntimeError):
    """No Mitsuba variant can run on this machine (what to install, not a bug: the CLI exits
    with its bad-input code)."""


def check_variant_name(name: str, where: str = VARIANT_ENV) -> str:
    """``name`` if it is one of :data:`PREFERRED_VARIANTS` (the tool renders with Dr.Jit's
    differentiable JIT variants only: a scalar or spectral one would fail deep in a render).

    Raises:
        ValueError: ``"<where>=<name>: not a variant sq-mitsuba renders with; ..."``.
    """
    if name not in PREFERRED_VARIANTS:
        raise ValueError(f"{where}={name!r}: not a variant sq-mitsuba renders with; use "
                         f"{' or '.join(PREFERRED_VARIANTS)}, or unset it to choose")
    return name


def check_variant_environment() -> None:
    """Refuse a misspelled or unusable ``$SQ_MITSUBA_VARIANT`` before any work (one line)."""
    requested = os.environ.get(VARIANT_ENV)
    if requested:
        check_variant_name(requested)


def _configure_cache() -> None:
    """Dr.Jit's compiled kernels in the checkout's ``.drjit-cache`` (kept with the project,
    shared by its processes); an installed package (no checkout above it: ``PROJECT_ROOT`` is
    site-packages) or a folder that cannot be made keeps Dr.Jit's own default."""
    if CACHE_ENV in os.environ or not (PROJECT_ROOT / "pyproject.toml").is_file():
        return
    cache = PROJECT_ROOT / ".drjit-cache"
    try:
        cache.mkdir(exist_ok=True)
    except OSError:  # a read-only checkout
        return
    os.environ[CACHE_ENV] = str(cache)


def _backend_works(variant: str) -> bool:
    import drjit as dr

    backend = dr.JitBackend.CUDA if variant.startswith("cuda") else dr.JitBackend.LLVM
    return bool(dr.has_backend(backend))


_deferring = False
"""Whether an :func:`interrupts_deferred` block is running (inner blocks then do nothing)."""


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) back while the block runs; act on it when the block ends.

    Dr.Jit and Mitsuba run Python code from C++: module initialisation (``import drjit``,
    ``import mitsuba``), ``@dr.syntax`` functions compiled when Mitsuba's AD integrators are
    imported, the callables of ``dr.switch`` and symbolic loops while a render is traced, Python
    plugins built by ``load_dict``. A ``KeyboardInterrupt`` raised in there does not come out
    as one: it comes out as a ``RuntimeError`` (``drjit.switch(): encountered an exception``,
    or ``@drjit.syntax`` "could not be compiled", with a page of generated code), as an
    ``ImportError`` / ``NameError`` / ``SystemError`` of a half-initialised extension, or as a
    C++ ``terminate`` that aborts the process. Inside this block Ctrl-C only sets a flag; at
    its end the previous handler runs (Python's raises ``KeyboardInterrupt`` there, in Python
    code), so an interruption waits for the Dr.Jit call in progress (one render) and is then
    a plain ``KeyboardInterrupt``.

    Only in the main thread (the only one that receives Python's signals) and only when the
    handler in place is a Python one; nested blocks defer to the outermost.
    """
    global _deferring
    previous = (signal.getsignal(signal.SIGINT)
                if not _deferring and threading.current_thread() is threading.main_thread()
                else None)
    if previous is None or previous is signal.SIG_IGN:
        yield
        return
    received: list[int] = []

    def hold(signum: int, frame: object) -> None:
        received.append(signum)

    signal.signal(signal.SIGINT, hold)
    _deferring = True
    try:
        yield
    finally:
        _deferring = False
        signal.signal(signal.SIGINT, previous)
        if received:
            if callable(previous):
                # Each one (a handler may count them: training's stops at once on the second);
                # Python's own raises KeyboardInterrupt at the first.
                for signum in received:
                    previous(signum, None)
            else:  # SIG_DFL: end as the signal would have
                signal.raise_signal(signal.SIGINT)


@contextlib.contextmanager
def one_thread(enabled: bool = True) -> Iterator[None]:
    """Dr.Jit on one thread inside the block (restored after), where ``enabled``.

    Convention: with several threads Dr.Jit sums gradients with atomic float32 additions whose
    order follows the threads' timing, so two runs with the same seed part in the last bits
    after the first backward pass and drift from there; on one thread they are bit-identical.
    The variant is left as it is (only set up, by :func:`mitsuba`, where Dr.Jit is not yet).
    """
    if "drjit" not in sys.modules:
        mitsuba()
    import drjit as dr

    previous = dr.thread_count()
    if enabled:
        dr.set_thread_count(1)
    try:
        yield
    finally:
        if dr.thread_count() != previous:
            dr.set_thread_count(previous)


def mitsuba(variant: str | None = None) -> ModuleType:
    """The ``mitsuba`` module with a working variant set (idempotent: without ``variant``,
    the variant already set stays; ``$SQ_MITSUBA_VARIANT`` chooses only the first).

    Importing Mitsuba and Dr.Jit and setting the variant hold Ctrl-C back until done (see
    :func:`interrupts_deferred`): interrupted half-way, their extensions fail in ways that are
    not a ``KeyboardInterrupt``.

    Args:
        variant: force a variant (e.g. ``"llvm_ad_mono"``); default: ``$SQ_MITSUBA_VARIANT`` or
            the first of :data:`PREFERRED_VARIANTS` whose backend works.

    Raises:
        ValueError: ``variant`` or ``$SQ_MITSUBA_VARIANT`` is not one of
            :data:`PREFERRED_VARIANTS`.
        BackendError: no variant can run (one line saying what to install).
    """
    if variant is not None:
        check_variant_name(variant, "variant")
    check_variant_environment()
    mi = sys.modules.get("mitsuba")
    current = mi.variant() if mi is not None and hasattr(mi, "variant") else None
    # Set up already (the common case): nothing to hold back. A call that names no variant
    # keeps the one set, which may be another than $SQ_MITSUBA_VARIANT's: training asks for
    # cuda_ad_mono by name, and its renderers' plain calls must not switch back.
    if current is not None and variant in (None, current):
        return mi
    with interrupts_deferred():
        return _set_up(variant)


def _set_up(variant: str | None) -> ModuleType:
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
    if variant is None and requested:  # the environment chose it: that is what to change
        raise BackendError(
            f"Mitsuba variant {requested!r} (from {VARIANT_ENV}) cannot run here"
            + (" (no CUDA driver or GPU?)" if requested.startswith("cuda") else
               " (libLLVM missing? `make setup` installs libllvm19)"
               if requested.startswith("llvm") else "")
            + f"; unset {VARIANT_ENV} to use the first that can ({', '.join(PREFERRED_VARIANTS)})")
    raise BackendError(
        f"no Mitsuba variant can run (tried {', '.join(candidates)}): install libllvm19 "
        "(`make setup`) for the CPU, or a CUDA driver for the GPU"
    )


def active_variant() -> str | None:
    """The variant set in this process, or None (does not import Mitsuba)."""
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
