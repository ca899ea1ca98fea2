"""Worker processes that share the items of a fused silhouette loss across CPU cores.

One Mitsuba render of a 128 x 128 silhouette and its backward pass keep one core busy for
tens of milliseconds, and most of it (the BVH rebuild, the Python-side tracing of the
projective integrator) does not speed up with more Dr.Jit threads. Several threads also sum
vertex gradients in a varying order, so training would no longer repeat exactly. Separate
processes, each rendering whole items on one Dr.Jit thread, use every core and keep results
exact: an item's samples depend on ``(seed, call, item)`` alone, so the pooled loss, coverage
and gradients equal a one-process, one-thread render bit for bit.

Convention: workers are plain subprocesses (``python -m
sq_mitsuba.render.silhouette.worker_process``, which holds their side)
talking over a socket pair with :mod:`multiprocessing.connection` framing, not a
``multiprocessing`` pool, so that no caller needs an ``if __name__ == "__main__"`` guard. Each
request carries a contiguous chunk of the batch; replies come back in order. A worker that
dies is reported with its exit code; the pool then refuses further work, and the renderer
that owns it closes it (its next call starts a new one).
"""

from __future__ import annotations

import contextlib
import os
import pickle
import socket
import subprocess
import sys
import weakref
from collections.abc import Callable
from dataclasses import asdict
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.checks import check_int
from sq_mitsuba.geometry.camera import Camera

WORKER_MODULE = "sq_mitsuba.render.silhouette.worker_process"
"""What each worker process runs (named, not imported: it imports the renderer)."""
_STARTUP_TIMEOUT_S = 300.0  # importing torch and Mitsuba, compiling kernels on a cold cache


def default_worker_count(processes: int = 1) -> int:
    """Workers worth starting: one per CPU core available to this process, shared among
    ``processes`` processes that render side by side (torchrun's), or 0 when that leaves one
    (a single worker only adds the cost of talking to it)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    share = cores // max(processes, 1)
    return share if share > 1 else 0


class WorkerError(RuntimeError):
    """A worker process failed or died."""


def _shutdown(connections: list[Connection], processes: list[subprocess.Popen]) -> None:
    for connection in connections:
        try:
            connection.send(None)
            connection.close()
        except OSError:
            pass
    for process in processes:
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()


class SilhouetteWorkers:
    """``count`` processes, each holding its own :class:`SilhouetteRenderer` of ``camera``.

    Args:
        camera, spp, sppp, integrator: the renderer's settings (every worker renders alike).
        count: number of processes (>= 1).
    """

    def __init__(self, camera: Camera, spp: int, sppp: int, integrator: str,
                 count: int) -> None:
        count = check_int("count", count)
        from sq_mitsuba.render.backend import mitsuba

        variant = mitsuba().variant()
        self._connections: list[Connection] = []
        self._processes: list[subprocess.Popen] = []
        settings = {"camera": asdict(camera), "spp": spp, "sppp": sppp,
                    "integrator": integrator, "variant": variant}
        # The workers import this very copy of the package, wherever the parent found it.
        package_root = str(Path(__file__).resolve().parents[3])
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            [package_root, *filter(None, [os.environ.get("PYTHONPATH")])])}
        for _ in range(count):
            ours, theirs = socket.socketpair()
            process = subprocess.Popen(
                [sys.executable, "-m", WORKER_MODULE, str(theirs.fileno())],
                pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL, env=env)
            theirs.close()
            connection = Connection(ours.detach())
            connection.send(settings)
            self._connections.append(connection)
            self._processes.append(process)
        self._finalizer = weakref.finalize(self, _shutdown, self._connections, self._processes)
        self._broken: str | None = None
        for index in range(count):
            self._receive(index, timeout=_STARTUP_TIMEOUT_S)  # "ready", or the startup error

    @property
    def count(self) -> int:
        return len(self._processes)

    def close(self) -> None:
        """Stop the workers (idempotent)."""
        self._finalizer()

    def _died(self, index: int, error: Exception) -> WorkerError:
        """Mark the pool broken by worker ``index``'s death; the error to raise."""
        process = self._processes[index]
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=5)
        self._broken = f"silhouette worker {index} (pid {process.pid}) exited (code " \
                       f"{process.returncode})"
        return WorkerError(self._broken)

    def _send(self, index: int, message: Any) -> None:
        try:
            self._connections[index].send(message)
        except OSError as error:
            raise self._died(index, error) from error

    def _receive(self, index: int, timeout: float | None = None) -> Any:
        connection = self._connections[index]
        try:
            if timeout is not None and not connection.poll(timeout):
                raise WorkerError(f"silhouette worker {index}: no answer within {timeout:.0f} s")
            status, payload = connection.recv()
        except (EOFError, OSError) as error:
            raise self._died(index, error) from error
        if status != "ok":
            raise WorkerError(f"silhouette worker {index}: {payload}")
        return payload

    def target_loss(self, seed: int, call: int, vertices: Tensor, faces: np.ndarray,
                    targets: Tensor, loss: Callable[[Tensor, Tensor], Tensor],
                    requires_grad: bool) -> tuple[Tensor, Tensor, Tensor]:
        """``SilhouetteRenderer.target_loss_items`` over the whole batch, shared out.

        Args:
            seed, call: the calling renderer's seed and call number.
            vertices: (B, V, 3) camera-frame vertices.
            faces: (F, 3) uint32 faces.
            targets: (B, H, W) float32 targets.
            loss: a module-level function (coverage (H, W), target (H, W)) -> scalar; the
                workers import it by name.
            requires_grad: also compute the vertex gradients.

        Returns:
            losses (B,) float64, coverage (B, H, W) float32, gradients (B, V, 3) float32.
        """
        if self._broken is not None:
            raise WorkerError(f"{self._broken}; close this pool and start a new one")
        try:
            pickle.dumps(loss)
        except (pickle.PicklingError, AttributeError, TypeError) as error:
            raise ValueError(f"loss: worker processes need a module-level function, got "
                             f"{loss!r} ({error})") from None
        array = np.ascontiguousarray(vertices.detach().to("cpu", torch.float32).numpy())
        target = np.ascontiguousarray(targets.numpy())
        chunks = [chunk for chunk in np.array_split(np.arange(array.shape[0]), self.count)
                  if chunk.size]
        for index, chunk in enumerate(chunks):
            first, last = int(chunk[0]), int(chunk[-1]) + 1
            self._send(index, (seed, call, first, array[first:last], faces, target[first:last],
                               loss, requires_grad))
        replies = [self._receive(index) for index in range(len(chunks))]
        losses, coverage, grad = (np.concatenate(part) for part in zip(*replies, strict=True))
        return torch.from_numpy(losses), torch.from_numpy(coverage), torch.from_numpy(grad)
