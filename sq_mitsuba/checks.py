"""Input checks shared by the public functions: one-line ``ValueError`` naming the argument.

Shape and dtype checks always run. Value checks (the NaN / infinity scan of
:func:`check_tensor`) read the whole tensor and, on a GPU, force a synchronisation, so hot
loops can switch them off: for the whole process with the environment variable
``SQ_MITSUBA_CHECKS=0`` (read once, when this module is imported; ``0``, ``false``, ``no`` and
``off`` switch them off), or for a block with ``with value_checks(False): ...``.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import warnings
from collections.abc import Iterator, Sequence

import torch

CHECKS_ENV = "SQ_MITSUBA_CHECKS"
"""Environment variable that switches value checks off (``0``) or on (``1``, the default)."""
_OFF_WORDS = frozenset({"0", "false", "no", "off"})
_ON_WORDS = frozenset({"", "1", "true", "yes", "on"})


def _checks_from_environment() -> bool:
    """Whether value checks are on, from :data:`CHECKS_ENV` (unset: on)."""
    word = os.environ.get(CHECKS_ENV, "1").strip().lower()
    if word in _OFF_WORDS:
        return False
    if word not in _ON_WORDS:
        warnings.warn(f"{CHECKS_ENV}={word!r} is not one of 0/1/false/true/no/yes/off/on; "
                      "value checks stay on", stacklevel=2)
    return True


_CHECKS_AT_IMPORT = _checks_from_environment()
# Convention: a context variable, not a plain global, so that value_checks(False) in one
# thread (or asyncio task) does not switch the checks off in another.
_VALUE_CHECKS: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "sq_mitsuba_value_checks", default=_CHECKS_AT_IMPORT)


def value_checks_enabled() -> bool:
    """Whether :func:`check_tensor` scans values for NaN and infinities here and now."""
    return _VALUE_CHECKS.get()


@contextlib.contextmanager
def value_checks(enabled: bool) -> Iterator[None]:
    """Switch value checks on or off inside a ``with`` block (restored on exit, nestable).

    Shape and dtype checks are unaffected.
    """
    token = _VALUE_CHECKS.set(bool(enabled))
    try:
        yield
    finally:
        _VALUE_CHECKS.reset(token)


def check_tensor(
    name: str,
    value: object,
    trailing: Sequence[int | None] = (),
    *,
    min_dims: int | None = None,
    floating: bool = True,
    finite: bool = True,
) -> torch.Tensor:
    """Check that ``value`` is a tensor ending in dims ``trailing`` (None = any size).

    Args:
        name: argument name used in the error message.
        value: the object to check.
        trailing: required sizes of the last ``len(trailing)`` dims.
        min_dims: minimum number of dims (default ``len(trailing)``).
        floating: require a floating-point dtype.
        finite: require no NaN or infinity (a value check: skipped while
            :func:`value_checks_enabled` is false).

    Returns:
        ``value``, unchanged.

    Raises:
        ValueError: naming ``name`` and what is wrong.
    """
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(value).__name__}")
    if value.is_meta:  # its value checks failed inside torch ("Tensor.item() ... meta")
        raise ValueError(f"{name}: a meta tensor (a shape without values); give its values")
    needed = len(trailing) if min_dims is None else min_dims
    # A dimension of any size is N (then M, ...): "(..., N, 3)", points of 3 coordinates.
    sizes = iter("NMKL")
    want = "(..., " + ", ".join(next(sizes, "any") if t is None else str(t)
                                for t in trailing) + ")"
    if value.dim() < needed or any(
        t is not None and value.shape[value.dim() - len(trailing) + i] != t
        for i, t in enumerate(trailing)
    ):
        raise ValueError(f"{name}: expected shape {want}, got {tuple(value.shape)}")
    if floating and not value.is_floating_point():
        raise ValueError(f"{name}: expected a floating-point dtype, got {value.dtype}")
    if (finite and value.is_floating_point() and _VALUE_CHECKS.get()
            and not bool(torch.isfinite(value).all())):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return value


def check_nonzero(name: str, value: torch.Tensor) -> torch.Tensor:
    """Check that no vector ``value[..., :]`` is zero: a quaternion to normalise, a true
    translation to divide by. A value check, skipped while :func:`value_checks_enabled` is
    false.

    Raises:
        ValueError: naming ``name`` and the first zero vector's index.
    """
    if _VALUE_CHECKS.get():
        zero = (value == 0).all(-1)
        if bool(zero.any()):
            index = tuple(int(i) for i in torch.nonzero(zero)[0])
            where = f" at {index[0] if len(index) == 1 else index}" if index else ""
            raise ValueError(f"{name}: zero vector{where} (a quaternion or distance of 0 "
                             "has no direction or scale)")
    return value


def check_broadcast(**tensors: torch.Tensor) -> torch.Size:
    """Broadcast shape of the batch dims (all but the last) of the named tensors."""
    try:
        return torch.broadcast_shapes(*(t.shape[:-1] for t in tensors.values()))
    except RuntimeError:
        shapes = ", ".join(f"{k}={tuple(v.shape)}" for k, v in tensors.items())
        raise ValueError(f"batch dims do not broadcast: {shapes}") from None


def check_same_shape(**tensors: torch.Tensor) -> torch.Size:
    """The common shape of the named tensors (a prediction and its truth, item by item);
    ``ValueError`` naming them if they differ, where broadcasting would score every pair."""
    shapes = {tuple(t.shape) for t in tensors.values()}
    if len(shapes) != 1:
        listing = ", ".join(f"{k}={tuple(v.shape)}" for k, v in tensors.items())
        raise ValueError(f"{', '.join(tensors)}: expected the same shape, got {listing}")
    return next(iter(tensors.values())).shape


def check_same_dtype(**tensors: torch.Tensor) -> torch.dtype:
    """The common dtype of the named tensors; ``ValueError`` if they differ."""
    dtypes = {t.dtype for t in tensors.values()}
    if len(dtypes) != 1:
        listing = ", ".join(f"{k}={v.dtype}" for k, v in tensors.items())
        raise ValueError(f"mixed dtypes: {listing}")
    return dtypes.pop()


ORTHONORMAL_TOLERANCE = 1e-3
"""Largest ``|R^T R - I|`` entry accepted of a rotation matrix (float32 rotations pass easily)."""


def check_rotations(name: str, rotations: torch.Tensor) -> None:
    """``ValueError`` naming ``name`` unless ``rotations`` (..., 3, 3) are finite rotation
    matrices (orthonormal within :data:`ORTHONORMAL_TOLERANCE`, determinant +1). The values
    are a value check (:func:`value_checks_enabled`); the shape is always checked."""
    check_tensor(name, rotations, (3, 3), min_dims=3)
    if not value_checks_enabled():
        return
    if not bool(torch.isfinite(rotations).all()):
        raise ValueError(f"{name}: contains NaN or infinite values")
    matrices = rotations.detach().double()
    gram = matrices.transpose(-1, -2) @ matrices
    error = float((gram - torch.eye(3, dtype=torch.float64, device=gram.device)).abs().amax()) \
        if gram.numel() else 0.0
    if error > ORTHONORMAL_TOLERANCE:
        raise ValueError(f"{name}: not rotation matrices (|R^T R - I| up to {error:.2g}, "
                         f"tolerance {ORTHONORMAL_TOLERANCE:g})")
    if bool((torch.linalg.det(matrices) <= 0).any()):
        raise ValueError(f"{name}: not rotation matrices (a reflection among them: "
                         "determinant -1)")


def check_switch(name: str, value: object) -> bool:
    """``value`` as a bool (numpy's as Python's), else a one-line ``ValueError`` naming
    ``name``: a string or a number is no switch (``'yes'`` was taken as true, ``0.0`` as
    false)."""
    value = python_scalar(value)
    if not isinstance(value, bool):
        raise ValueError(f"{name}: expected True or False, got {value!r}")
    return value


def check_int(name: str, value: object, low: int | None = 1, high: int | None = None) -> int:
    """``value`` as a Python int (numpy's as Python's) in ``[low, high]`` (``None``: no
    bound), else a one-line ``ValueError`` naming ``name``: a bool is no count (``True`` was
    read as 1), nor is a float, even ``3.0``."""
    value = python_scalar(value)
    if (isinstance(value, bool) or not isinstance(value, int)
            or (low is not None and value < low) or (high is not None and value > high)):
        if low is not None and high is not None:
            expected = f"an integer in [{low}, {high}]"
        elif low == 1:
            expected = "a positive integer"
        elif low is not None:
            expected = f"an integer >= {low}"
        elif high is not None:
            expected = f"an integer <= {high}"
        else:
            expected = "an integer"
        raise ValueError(f"{name}: expected {expected}, got {value!r}")
    return value


def python_scalar(value: object) -> object:
    """A numpy integer or bool as Python's (``np.int64(8)`` -> 8, ``np.True_`` -> True), for
    counts and switches a user computed with numpy; anything else as it is (to be checked)."""
    import numpy as np

    if isinstance(value, np.integer | np.bool_):
        return value.item()
    return value
