"""sq_mitsuba: single-image abstraction of spacecraft into superquadric assemblies.

Layers (dependencies point down only; see ``README.md``):

- geometry: :mod:`sq_mitsuba.superquadric`, :mod:`sq_mitsuba.rotation`,
  :mod:`sq_mitsuba.icosphere`, :mod:`sq_mitsuba.assembly` (pure torch / numpy)
- rendering: Mitsuba 3 and Dr.Jit, imported lazily
- data, learning, evaluation, cli

Importing this package never imports Mitsuba or Dr.Jit. It only points Dr.Jit at a usable
libLLVM (if one exists and the user has not chosen one), because Dr.Jit reads
``DRJIT_LIBLLVM_PATH`` once, when it first initialises.
"""

from sq_mitsuba.llvm import configure_llvm

__version__ = "0.1.0"

configure_llvm(required=False)

__all__ = ["__version__"]
