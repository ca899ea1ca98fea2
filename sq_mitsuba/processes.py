"""Worker processes that stop with their parent: the one pool every ``--workers`` option uses.

Ctrl-C in a terminal sends SIGINT to every process of the foreground group, the workers of a
:class:`~concurrent.futures.ProcessPoolExecutor` included. Each then raised
``KeyboardInterrupt`` wherever it was (inside the pool's own queue handling, mid-pipe), and
the parent, leaving the pool's ``with`` block, waited for them for ever; a worker inside a
Mitsuba render fares worse: the integrator's own SIGINT handler cancels the render and hands
back the part done, as if it were the image. Ignoring SIGINT in the workers does not help
(the integrator installs its handler over the ignoring one for each render), so each worker
starts a process group of its own, which a terminal's Ctrl-C does not reach: the parent alone
is interrupted, and it ends the workers itself (their unfinished work is unfinished work:
every caller writes its outputs atomically, and a rerun takes up where it stopped).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

__all__ = ["ignore_group_signals", "process_alive", "worker_pool"]


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (another user's counts: it cannot be
    signalled, but it is there). Decides whether a dead run's temporary folder may go."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def ignore_group_signals(*_: object) -> None:
    """Ignore Ctrl-C and SIGTERM in a helper process whose parent acts on them: a terminal,
    ``timeout``, torchrun and SLURM signal the whole process group, and the parent finishes its
    work with the helpers' help, then ends them; a helper the signal stopped would fail that
    work, or print a traceback of its own. (Any arguments are ignored: it serves as a
    DataLoader's ``worker_init_fn``.)"""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _own_group_start(initializer: Callable[..., Any] | None, arguments: tuple[Any, ...]
                     ) -> None:
    """A worker's start: a process group of its own (its parent stops it), then the caller's
    initializer."""
    os.setpgrp()
    if initializer is not None:
        initializer(*arguments)


def _end_workers(pool: ProcessPoolExecutor) -> None:
    """Cancel what has not started and end the workers now, without waiting for their jobs."""
    # The executor keeps no public handle on its processes; an executor without them (a
    # future Python) falls back to waiting, as a plain pool does.
    processes = list((getattr(pool, "_processes", None) or {}).values())
    manager = getattr(pool, "_executor_manager_thread", None)  # shutdown drops the handle
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(timeout=10)
        if process.is_alive():
            process.kill()
    # The executor's own thread, seeing its workers gone, closes its pipes: let it finish
    # here, not race the interpreter's exit, which wakes it through a pipe it may have just
    # closed ("Exception ignored ... Bad file descriptor" after a Ctrl-C, now and then).
    if manager is not None and manager.is_alive():
        manager.join(timeout=5)


@contextmanager
def worker_pool(workers: int, initializer: Callable[..., Any] | None = None,
                initargs: tuple[Any, ...] = ()) -> Iterator[ProcessPoolExecutor]:
    """A pool of ``workers`` spawned processes (spawn, not fork: the parent may hold threads,
    torch's or tqdm's, that fork would copy mid-state), each in a process group of its own, out
    of a terminal's Ctrl-C (see the module docstring). Leaving the block
    normally waits for the jobs, as a plain pool does; leaving it by an exception (Ctrl-C,
    SIGTERM handled as one, a failed job) ends the workers at once.

    Args:
        workers: processes, >= 1.
        initializer: run in each worker at its start, with ``initargs`` (picklable).
    """
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_own_group_start, initargs=(initializer, initargs))
    try:
        yield pool
    except BaseException:
        _end_workers(pool)
        raise
    pool.shutdown(wait=True)
