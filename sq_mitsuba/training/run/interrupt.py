"""Ctrl-C or SIGTERM during training: held until the step in progress is done, then saved.

An interrupt that lands inside a step (between the backward pass and the optimiser's update,
inside a render) leaves the network half updated: the run could only stop without saving,
losing every step since the last checkpoint (up to an epoch). Held for the step's few
seconds, it lets the loop write ``last.pt`` at a step boundary, from which ``--resume``
repeats the uninterrupted run exactly, and then stop (a validation that step was due is left
to ``--resume``, which runs it first).

Held, for the whole loop: SIGINT (Ctrl-C) and SIGTERM (``kill``, ``timeout``, a scheduler
such as SLURM at the end of a job's time, which waits some seconds before killing; torchrun,
which passes the signal it gets on to every process and kills them 30 s later). In a
distributed run every process must stop at the same step, or the others would wait for it in
the next collective for ever: after each step the processes agree (one all-reduce of a flag)
that one of them was interrupted, and all of them save that step and stop.

Convention: in a run of one process a second Ctrl-C stops at once (``KeyboardInterrupt``
where the loop is, the steps since the last checkpoint lost), for a user who will not wait
for a long step or a validation. In a distributed run every signal after the first stays
held: the processes must stop at one step, and one acting alone on a second signal would
leave the others waiting in a collective (torchrun starts them in their own session and
passes its own signals on; it kills them 30 s after the first).
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = ["HELD_SIGNALS", "StepInterrupt"]

HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""The signals a step holds back."""


class StepInterrupt:
    """SIGINT and SIGTERM held back from construction to :meth:`close` (the training loop):
    one that arrives sets :attr:`pending` (the signal's number) instead of acting, and the
    loop, after the step in progress (:meth:`step`), saves and raises ``KeyboardInterrupt``.
    Where the handler in place ignores a signal it is left alone; off the main thread (which
    alone receives signals) nothing is held.

    Between steps too (the log, the bar, a checkpoint, a validation, which then runs to its
    end): the loop is cut only where its state is whole. Later signals are held as well, but
    for a second Ctrl-C in a run of one process, which raises ``KeyboardInterrupt`` at once:
    files being written are left as they were (every write goes through a temporary file).

    Args:
        world: the run's :class:`~sq_mitsuba.training.distributed.World` (None: one process).
        last: the run's ``last.pt``, named by the second Ctrl-C's message (None: not named).
    """

    def __init__(self, world: Any = None, last: Path | None = None) -> None:
        self.world = world
        self.last = last
        self.pending: int | None = None
        self._agreed = False
        self._previous: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for number in HELD_SIGNALS:
                previous = signal.getsignal(number)
                if previous is not signal.SIG_IGN and previous is not None:
                    self._previous[number] = signal.signal(number, self._hold)

    @contextmanager
    def step(self) -> Iterator[None]:
        """Run a step; in a distributed run, every process then learns whether any of them
        was interrupted (one all-reduce of a flag), so that all stop at this step."""
        yield
        if self.world is not None and self.world.distributed:
            from sq_mitsuba.training.distributed import any_rank

            self._agreed = any_rank(self.pending is not None, self.world)

    @property
    def stop(self) -> bool:
        """Whether the loop stops after this step: an interrupt held, in a distributed run the
        one every process agreed on after the step (a signal that lands later, during a
        validation or a save, waits for the next step's agreement: acted on by one process
        alone, it would leave the others waiting in a collective)."""
        if self.world is not None and self.world.distributed:
            return self._agreed
        return self.pending is not None

    def close(self) -> None:
        """Put the handlers back (idempotent)."""
        for number, previous in self._previous.items():
            signal.signal(number, previous)
        self._previous = {}

    @property
    def _alone(self) -> bool:
        return self.world is None or not self.world.distributed

    def _hold(self, number: int, frame: object) -> None:
        if self.pending is None:
            self.pending = number
            if self.world is None or self.world.main:
                name = "Ctrl-C" if number == signal.SIGINT else signal.Signals(number).name
                now = "Ctrl-C again" if number == signal.SIGINT else "Ctrl-C"
                again = f" ({now}: stop at once, without saving)" if self._alone else ""
                print(f"{name}: the step in progress finishes, last.pt is written at it, then "
                      f"the run stops{again}", file=sys.stderr, flush=True)
        elif number == signal.SIGINT and self._alone:
            self.close()
            if self.last is None:
                kept = "the last checkpoint written is kept"
            elif self.last.is_file():
                kept = f"{self.last} holds the last checkpoint written"
            else:
                kept = f"no {self.last.name} was written yet: nothing to resume"
            print(f"Ctrl-C again: stopped at once; {kept}", file=sys.stderr, flush=True)
            raise KeyboardInterrupt
