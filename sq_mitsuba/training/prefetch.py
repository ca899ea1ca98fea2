"""The next steps' host work done while this step runs: batches prefetched by worker processes
(or one thread).

Why: a step's device work (a GPU's kernels, Mitsuba's launch) is queued and runs while the
host goes on, so the host's share of the next batch (cache rows, the per-item point draws,
the augmentation's draws and sensor noise, pinned copies; about 60 ms for 256 images) can hide
behind it instead of adding to it. Most of that share is Python item by item, which holds the
interpreter lock: on one thread it took the lock from the step's own kernel launches and the
loop gained 1.25 x where the step allowed 1.9 x (H100, batch 256). Worker processes
(``data.prefetch_workers``, through :class:`torch.utils.data.DataLoader`) have their own
interpreters; their batches come back in shared memory and are pinned in the training process.

Convention: every batch is a pure function of its step (the draws come from (seed, step,
position), :mod:`~sq_mitsuba.training.random_streams`), so a prefetched batch equals the one
made on demand bit for bit, whichever worker made it, and a resumed run is unaffected. Workers
are forked: they read the caches the training process opened and never touch a GPU or Mitsuba.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from types import TracebackType

import torch
from torch.utils.data import DataLoader, Dataset

from sq_mitsuba.processes import ignore_group_signals
from sq_mitsuba.training.batch import TrainingBatch
from sq_mitsuba.training.data_stream import HostBatch, TrainingStream
from sq_mitsuba.training.distributed import World

__all__ = ["BatchPrefetcher", "prefetch_enabled"]


def prefetch_enabled(setting: bool | None, device: torch.device | str) -> bool:
    """``data.prefetch`` resolved: None means on where the step runs on a GPU (whose work is
    queued, so the host is free), off on the CPU (where the thread would take cores from the
    step itself)."""
    return torch.device(device).type == "cuda" if setting is None else bool(setting)


class _Failed:
    """An error a worker met making a batch, handed back as a value: the training process
    raises it as it is (a DataLoader would wrap it in the worker's traceback)."""

    def __init__(self, error: Exception) -> None:
        self.error = error


class _HostBatches(Dataset[HostBatch | _Failed]):
    """Step -> :meth:`TrainingStream.host_batch`, the item a DataLoader worker makes."""

    def __init__(self, stream: TrainingStream, world: World) -> None:
        self.stream, self.world = stream, world

    def __getitem__(self, step: int) -> HostBatch | _Failed:
        try:
            return self.stream.host_batch(step, self.world)
        except Exception as error:  # raised again in the training process, unwrapped
            return _Failed(error)


class BatchPrefetcher:
    """:meth:`TrainingStream.batch` with the next steps' :meth:`~TrainingStream.host_batch`
    made ahead (``enabled``), up to ``end_step`` (exclusive): by ``workers`` processes, each
    ``depth`` batches ahead, or with ``workers = 0`` on one thread, one batch ahead. Disabled,
    it is the stream's own ``batch``. Close it (or use it as a context manager) to stop the
    workers."""

    def __init__(self, stream: TrainingStream, world: World, device: torch.device | str,
                 end_step: int, enabled: bool = True, workers: int = 0, depth: int = 2
                 ) -> None:
        if workers < 0 or depth < 1:
            raise ValueError(f"workers {workers}, depth {depth}: expected >= 0 and >= 1")
        self.stream, self.world = stream, world
        self.device = torch.device(device)
        self.end_step = end_step
        self.pin = self.device.type == "cuda"
        self.workers, self.depth = (workers if enabled else 0), depth
        self._executor = (ThreadPoolExecutor(1, "batch-prefetch")
                          if enabled and workers == 0 else None)
        self._pending: Future[HostBatch] | None = None  # a host batch under way (thread)
        self._loader: Iterator[HostBatch | _Failed] | None = None  # workers' batches, in order
        self._next = -1  # the step the loader hands out next
        self._open = enabled

    @property
    def enabled(self) -> bool:
        return self._open

    def batch(self, step: int) -> TrainingBatch:
        """Step ``step``'s batch on the device (the prefetched host share where it is the one
        asked for, else made now), the next steps' host shares started behind it."""
        if not self._open:
            return self.stream.batch(step, self.world, self.device)
        host = self._from_workers(step) if self.workers else self._from_thread(step)
        return self.stream.device_batch(host, self.device)

    def _from_thread(self, step: int) -> HostBatch:
        assert self._executor is not None
        host = self._take(step)
        if step + 1 < self.end_step:
            self._pending = self._executor.submit(self.stream.host_batch, step + 1,
                                                  self.world, self.pin)
        return host

    def _take(self, step: int) -> HostBatch:
        assert self._executor is not None
        pending, self._pending = self._pending, None
        if pending is not None:
            host = pending.result()  # also waits for a stale one: one reader at a time
            if host.step == step:
                return host
        return self._executor.submit(self.stream.host_batch, step, self.world,
                                     self.pin).result()

    def _from_workers(self, step: int) -> HostBatch:
        if self._loader is None or step != self._next or step >= self.end_step:
            self._stop_loader()
            if step >= self.end_step:  # past the planned steps: made here
                return self.stream.host_batch(step, self.world, self.pin)
            self._loader = iter(DataLoader(
                _HostBatches(self.stream, self.world), batch_size=None,
                sampler=range(step, self.end_step), num_workers=self.workers,
                prefetch_factor=self.depth, pin_memory=self.pin,
                # Ctrl-C and SIGTERM to the group are the training's (it finishes its step,
                # saves and ends the loader).
                multiprocessing_context="fork", worker_init_fn=ignore_group_signals,
                # Its own generator: the loader's base seed would otherwise be a draw from
                # the global RNG (the encoder's stochastic depth), which a resume restores
                # before the loader is made again. The batches are seeded by step anyway.
                generator=torch.Generator().manual_seed(step)))
        host = next(self._loader)
        self._next = step + 1
        if isinstance(host, _Failed):
            self._stop_loader()
            raise host.error
        return host

    def _stop_loader(self) -> None:
        self._loader = None  # the last reference: the iterator stops its workers

    def close(self) -> None:
        """Stop the workers (a prefetch under way is waited for, its batch dropped)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor, self._pending = None, None
        self._stop_loader()
        self._open = False

    def __enter__(self) -> BatchPrefetcher:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()
