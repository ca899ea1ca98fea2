"""Locate a libLLVM that Dr.Jit's LLVM backend can use.

Dr.Jit 1.5 emits NaN-propagating ``fmaximum``, which libLLVM 15 (Debian 12's default) cannot
select; libLLVM >= 17 works. Dr.Jit reads ``DRJIT_LIBLLVM_PATH`` only before it first
initialises, so :func:`configure_llvm` must run before ``import drjit``; ``import sq_mitsuba``
does that.
"""

from __future__ import annotations

import glob
import os
import re
import sys
from pathlib import Path

MIN_LLVM_MAJOR = 17
ENV_VAR = "DRJIT_LIBLLVM_PATH"

_SEARCH_GLOBS = (
    "/usr/lib/*/libLLVM*.so*",
    "/usr/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm*/lib/libLLVM*.dylib",
    "/usr/local/opt/llvm*/lib/libLLVM*.dylib",
)
# libLLVM-19.so, libLLVM-19.so.1, libLLVM.so.19.1, libLLVM-19.1.7.so, llvm-19/lib/libLLVM.so
_VERSION_PATTERNS = (
    re.compile(r"libLLVM-(\d+)"),
    re.compile(r"libLLVM\.so\.(\d+)"),
    re.compile(r"llvm-?(\d+)"),
)


class LLVMNotFoundError(RuntimeError):
    """No libLLVM >= 17 on this machine."""


def llvm_major_version(path: str | Path) -> int | None:
    """Major LLVM version encoded in a library path, or None if it carries none."""
    text = str(path)
    for pattern in _VERSION_PATTERNS:
        match = pattern.search(text)
        if match:
            return int(match.group(1))
    return None


def find_libllvm(min_major: int = MIN_LLVM_MAJOR) -> Path | None:
    """Newest libLLVM with major version >= ``min_major`` among the usual system paths."""
    candidates: list[tuple[int, Path]] = []
    for pattern in _SEARCH_GLOBS:
        for name in glob.glob(pattern):
            major = llvm_major_version(name)
            if major is not None and major >= min_major and os.path.isfile(name):
                candidates.append((major, Path(name)))
    if not candidates:
        return None
    # Prefer the newest major; among equals the shortest name (the unversioned symlink).
    candidates.sort(key=lambda c: (-c[0], len(str(c[1]))))
    return candidates[0][1]


def configure_llvm(required: bool = True) -> Path | None:
    """Point ``DRJIT_LIBLLVM_PATH`` at a usable libLLVM unless the user already chose one.

    Returns the library in use. With ``required=True`` a missing library raises
    :class:`LLVMNotFoundError` with a one-line fix.
    """
    chosen = os.environ.get(ENV_VAR)
    if chosen:
        return Path(chosen)
    if "drjit" in sys.modules:
        # Too late to choose: Dr.Jit already read the environment.
        return None
    found = find_libllvm()
    if found is not None:
        os.environ[ENV_VAR] = str(found)
        return found
    if required:
        raise LLVMNotFoundError(
            f"no libLLVM >= {MIN_LLVM_MAJOR} found (Dr.Jit's LLVM backend needs it): "
            f"run `make setup` or `apt-get install libllvm19`, or set {ENV_VAR}"
        )
    return None
