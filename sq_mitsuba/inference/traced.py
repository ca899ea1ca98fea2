"""The traced fast path of prediction (``Predictor(fast=True, traced=True)``): a
BatchNorm-folded network traced and frozen by TorchScript, one trace per input shape (a trace
may fix the batch size), kept for reuse. Asked for, not the fast path's default: a trace
costs 0.7-0.8 s and saves a quarter of the network's time at batch 1 only (2026-11-30, the
shipped model, 2 cores, batch 1: 13.3 ms traced, 17.9 folded, 21.0 eager; at batch 7 46.9
traced against 45.5 folded; at batch 56, a pass's turned copies, 388 against 329 ms, its trace
made in 2.6 s).

Measured (`sq-mitsuba bench train`, batch 1, quiet 2-core EPYC): TorchScript's trace + freeze
of the folded network takes 6.2 ms at 96 px against 8.7 ms eager (the eager time is mostly
Python's per-module overhead at batch 1); ``optimize_for_inference`` was slower (11 ms), and
oneDNN graph fusion fails to compile this network.

Every path runs at most :data:`RUN_CHUNK` images at once (:func:`run_in_chunks`): the network's
activations take about 4.6 MB an image at 96 px, so 360 turned copies of 16 images (5,760
inputs) asked for 26 GB in one batch and were killed for memory instead of running.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import fields

import torch
from torch import Tensor

from sq_mitsuba.model.network import NetworkOutput

__all__ = ["RUN_CHUNK", "OutputTuple", "TracedNetwork", "run_in_chunks"]

RUN_CHUNK = 256
"""The most images the network reads in one call at prediction (about 1.2 GB of activations
at 96 px); a batch up to it runs whole, as before (its results round as one batch's)."""

# Traces kept (one per input shape seen, oldest dropped).
_TRACES_KEPT = 4
# Runs of a new trace before it is used (the profiling executor optimises on the second).
_TRACE_WARMUP_RUNS = 2


class TracedNetwork:
    """``network`` (a folded :class:`~sq_mitsuba.model.network.SuperquadricNet`) called
    through a TorchScript trace per input shape, dtype and device; the same outputs as the
    eager network up to float rounding."""

    def __init__(self, network: torch.nn.Module) -> None:
        self.network = network
        self._traced: dict[tuple, tuple[torch.nn.Module, tuple[str, ...]]] = {}

    def __call__(self, images: Tensor, matrix: Tensor) -> NetworkOutput:
        traced, names = self._traced_for(images, matrix)
        return NetworkOutput(**dict(zip(names, traced(images, matrix), strict=True)))

    def __len__(self) -> int:
        """Traces kept."""
        return len(self._traced)

    def _traced_for(self, images: Tensor,
                    matrix: Tensor) -> tuple[torch.nn.Module, tuple[str, ...]]:
        """The folded network traced and frozen for inputs like these (cached per shape, dtype
        and device: a trace may fix the batch size), and the names of the
        :class:`NetworkOutput` fields whose tensors it returns."""
        key = (tuple(images.shape), tuple(matrix.shape), images.dtype, images.device)
        cached = self._traced.get(key)
        if cached is None:
            import warnings

            module = OutputTuple(self.network).eval()
            with torch.no_grad():
                module(images, matrix)  # sets module.names
            # torch 2.13 (pinned) marks TorchScript deprecated; should a later torch drop it,
            # the eager folded network runs instead (the same outputs, ~2.5 ms slower).
            try:
                with torch.no_grad(), warnings.catch_warnings():
                    warnings.simplefilter("ignore", torch.jit.TracerWarning)
                    warnings.simplefilter("ignore", DeprecationWarning)
                    traced = torch.jit.freeze(torch.jit.trace(module, (images, matrix),
                                                              check_trace=False))
                    # TorchScript's profiling executor records shapes on the first run and
                    # builds the optimised graph on the second; run both here, so that the
                    # first prediction a caller times is the steady-state one.
                    for _ in range(_TRACE_WARMUP_RUNS):
                        traced(images, matrix)
            except Exception:  # any failure to trace leaves the eager network, never an error
                traced = module
            if len(self._traced) >= _TRACES_KEPT:
                self._traced.pop(next(iter(self._traced)))  # the oldest
            cached = self._traced[key] = (traced, module.names)
        return cached


class OutputTuple(torch.nn.Module):
    """``network``'s :class:`NetworkOutput` as a tuple of its tensors (TorchScript traces
    tuples, not dataclasses): the fields that are not None, in field order; ``names`` (set by
    the first call) says which."""

    def __init__(self, network: torch.nn.Module) -> None:
        super().__init__()
        self.network = network
        self.names: tuple[str, ...] = ()

    def forward(self, images: Tensor, matrix: Tensor) -> tuple[Tensor, ...]:
        out = self.network(images, matrix)
        present = [f.name for f in fields(out) if getattr(out, f.name) is not None]
        self.names = tuple(present)
        return tuple(getattr(out, name) for name in present)


def run_in_chunks(run: Callable[[Tensor, Tensor], NetworkOutput], images: Tensor,
                  matrix: Tensor, chunk: int = RUN_CHUNK) -> NetworkOutput:
    """``run(images, matrix)`` on ``chunk`` images at a time, the outputs joined along the
    batch as one call's would be (to float rounding: the convolutions round by batch size).

    Args:
        run: the network call, ``(B, C, S, S)`` images and a (3, 3) or (B, 3, 3) camera
            matrix to a :class:`~sq_mitsuba.model.network.NetworkOutput` of B items.
        images: (B, C, S, S); matrix: (3, 3), or (B, 3, 3) split with the images.
    """
    starts = range(0, images.shape[0], chunk)
    parts = [run(images[i:i + chunk], matrix if matrix.dim() == 2 else matrix[i:i + chunk])
             for i in starts]
    return NetworkOutput(**{field.name: None if getattr(parts[0], field.name) is None
                            else torch.cat([getattr(part, field.name) for part in parts])
                            for field in fields(NetworkOutput)})
