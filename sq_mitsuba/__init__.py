"""sq_mitsuba: single-image abstraction of spacecraft into superquadric assemblies.

Layers, one folder each, lowest first (a module imports only its own layer and those below;
``tests/test_layers.py`` enforces it): the shared utilities at the top level (``checks``,
``config``, ``inputs``, ``io``, ``llvm``, ``machine``, ``outputs``, ``processes``,
``progress``), then ``geometry``, ``render``, ``data``, ``model`` (the network), ``training``
and ``inference`` side by side (neither imports the other), ``evaluation`` (the protocol),
``apps`` (predict, demo, export, fit), ``bench`` (benchmarks) and ``cli``.

Importing this package never imports Mitsuba or Dr.Jit. It only points Dr.Jit at a usable
libLLVM (if one exists and the user has not chosen one), because Dr.Jit reads
``DRJIT_LIBLLVM_PATH`` once, when it first initialises.

``sq_mitsuba.load_model(path=None)`` (:func:`sq_mitsuba.inference.loading.load_model`) gives
a ready :class:`~sq_mitsuba.inference.predictor.Predictor`; it is imported lazily, on first
access. ``load_model().predict(images, refine=True)`` runs the whole shipped path.
"""

from sq_mitsuba.llvm import configure_llvm
from sq_mitsuba.version import __version__

configure_llvm(required=False)

__all__ = ["__version__", "load_model"]


def __getattr__(name: str) -> object:
    """``sq_mitsuba.load_model``, imported on first use so that ``import sq_mitsuba`` stays
    light (no torch network code, no Mitsuba)."""
    if name == "load_model":
        from sq_mitsuba.inference.loading import load_model

        return load_model
    raise AttributeError(f"module 'sq_mitsuba' has no attribute {name!r}")
