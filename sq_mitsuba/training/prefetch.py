"""The next step's host work done while this step runs: a one-thread prefetch of the batches.

Why: a step's device work (a GPU's kernels, Mitsuba's launch) is queued and runs while the
host goes on, so the host's share of the next batch (cache rows, the per-item point draws,
pinned copies; about 50 ms for 256 images) can hide behind it instead of adding to it.

Convention: every batch is a pure function of its step (the draws come from (seed, step,
position), :mod:`~sq_mitsuba.training.random_streams`), so a prefetched batch equals the one
made on demand bit for bit, and a resumed run is unaffected. All host work runs on the one
worker thread, in step order, so the caches are never read by two threads at once.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from types import TracebackType

import torch

from sq_mitsuba.training.batch import TrainingBatch
from sq_mitsuba.training.data_stream import HostBatch, TrainingStream
from sq_mitsuba.training.distributed import World

__all__ = ["BatchPrefetcher", "prefetch_enabled"]


def prefetch_enabled(setting: bool | None, device: torch.device | str) -> bool:
    """``data.prefetch`` resolved: None means on where the step runs on a GPU (whose work is
    queued, so the host is free), off on the CPU (where the thread would take cores from the
    step itself)."""
    return torch.device(device).type == "cuda" if setting is None else bool(setting)


class BatchPrefetcher:
    """:meth:`TrainingStream.batch` with step s + 1's :meth:`~TrainingStream.host_batch`
    started on a worker thread as soon as step s's is handed out (``enabled``), up to
    ``end_step`` (exclusive). Disabled, it is the stream's own ``batch``. Close it (or use it
    as a context manager) to stop the thread."""

    def __init__(self, stream: TrainingStream, world: World, device: torch.device | str,
                 end_step: int, enabled: bool = True) -> None:
        self.stream, self.world = stream, world
        self.device = torch.device(device)
        self.end_step = end_step
        self.pin = self.device.type == "cuda"
        self._executor = ThreadPoolExecutor(1, "batch-prefetch") if enabled else None
        self._pending: Future[HostBatch] | None = None  # a host batch under way

    @property
    def enabled(self) -> bool:
        return self._executor is not None

    def batch(self, step: int) -> TrainingBatch:
        """Step ``step``'s batch on the device (the prefetched host share where it is the one
        asked for, else made now), the next step's host share started behind it."""
        if self._executor is None:
            return self.stream.batch(step, self.world, self.device)
        host = self._take(step)
        if step + 1 < self.end_step:
            self._pending = self._executor.submit(self.stream.host_batch, step + 1,
                                                  self.world, self.pin)
        return self.stream.device_batch(host, self.device)

    def _take(self, step: int) -> HostBatch:
        assert self._executor is not None
        pending, self._pending = self._pending, None
        if pending is not None:
            host = pending.result()  # also waits for a stale one: one reader at a time
            if host.step == step:
                return host
        return self._executor.submit(self.stream.host_batch, step, self.world,
                                     self.pin).result()

    def close(self) -> None:
        """Stop the worker (a prefetch under way is waited for, its batch dropped)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor, self._pending = None, None

    def __enter__(self) -> BatchPrefetcher:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()
