"""sq_mitsuba: single-image abstraction of spacecraft into superquadric assemblies.

Layers, one folder each, lowest first (a module imports only its own layer and those below;
``tests/test_layers.py`` enforces it): the shared utilities at the top level (``checks``,
``config``, ``io``, ``llvm``), then ``geometry``, ``render``, ``data``, ``learning``,
``evaluation`` and ``cli``.

Importing this package never imports Mitsuba or Dr.Jit. It only points Dr.Jit at a usable
libLLVM (if one exists and the user has not chosen one), because Dr.Jit reads
``DRJIT_LIBLLVM_PATH`` once, when it first initialises.
"""

from sq_mitsuba.llvm import configure_llvm

__version__ = "0.1.0"

configure_llvm(required=False)

__all__ = ["__version__"]
