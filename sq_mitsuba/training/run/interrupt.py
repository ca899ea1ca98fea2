"""Ctrl-C during training: held until the step in progress is done, then saved.

An interrupt that lands inside a step (between the backward pass and the optimiser's update,
inside a render) leaves the network half updated: the run could only stop without saving,
losing every step since the last checkpoint (up to an epoch). Held for the step's few
seconds, it lets the loop write ``last.pt`` at a step boundary, from which ``--resume``
repeats the uninterrupted run exactly, and then stop. A distributed run keeps the plain
behaviour: its processes would have to agree on the step first.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["StepInterrupt"]


class StepInterrupt:
    """Whether Ctrl-C arrived during a step (:meth:`step`); ``pending`` once it has."""

    def __init__(self, processes: int = 1) -> None:
        self.enabled = processes == 1
        self.pending = False

    @contextmanager
    def step(self) -> Iterator[None]:
        """Run a step with Ctrl-C held back; an interrupt sets :attr:`pending` instead of
        raising (the caller saves, then raises ``KeyboardInterrupt``)."""
        if not self.enabled:
            yield
            return
        from sq_mitsuba.render.backend import interrupts_deferred

        try:
            with interrupts_deferred():
                yield
        except KeyboardInterrupt:
            self.pending = True
