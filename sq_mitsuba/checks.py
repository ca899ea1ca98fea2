"""Input checks shared by the public functions: one-line ``ValueError`` naming the argument."""

from __future__ import annotations

from collections.abc import Sequence

import torch


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
        finite: require no NaN or infinity.

    Returns:
        ``value``, unchanged.

    Raises:
        ValueError: naming ``name`` and what is wrong.
    """
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(value).__name__}")
    needed = len(trailing) if min_dims is None else min_dims
    want = "(..., " + ", ".join("*" if t is None else str(t) for t in trailing) + ")"
    if value.dim() < needed or any(
        t is not None and value.shape[value.dim() - len(trailing) + i] != t
        for i, t in enumerate(trailing)
    ):
        raise ValueError(f"{name}: expected shape {want}, got {tuple(value.shape)}")
    if floating and not value.is_floating_point():
        raise ValueError(f"{name}: expected a floating-point dtype, got {value.dtype}")
    if finite and value.is_floating_point() and not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return value


def check_broadcast(**tensors: torch.Tensor) -> torch.Size:
    """Broadcast shape of the batch dims (all but the last) of the named tensors."""
    try:
        return torch.broadcast_shapes(*(t.shape[:-1] for t in tensors.values()))
    except RuntimeError:
        shapes = ", ".join(f"{k}={tuple(v.shape)}" for k, v in tensors.items())
        raise ValueError(f"batch dims do not broadcast: {shapes}") from None


def check_same_dtype(**tensors: torch.Tensor) -> torch.dtype:
    """The common dtype of the named tensors; ``ValueError`` if they differ."""
    dtypes = {t.dtype for t in tensors.values()}
    if len(dtypes) != 1:
        listing = ", ".join(f"{k}={v.dtype}" for k, v in tensors.items())
        raise ValueError(f"mixed dtypes: {listing}")
    return dtypes.pop()
