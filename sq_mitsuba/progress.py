"""Progress bars that read well both on a terminal and in a log file.

On a terminal a tqdm bar redraws itself in place with carriage returns. Redirected to a file
(``nohup sq-mitsuba train ... > train.log``) the same bar was one endless line: a carriage
return per update, about 1.5 MB for the shipped recipe's 4,448 steps. Where the stream is not
a terminal, :func:`progress_bar` writes a whole line instead, at most every
:data:`LOG_INTERVAL_S` seconds however often the bar is redrawn (a step's loss on the bar
redraws it at every step), and the final state when the bar closes.
"""

from __future__ import annotations

import sys
import time
from typing import IO, Any

from tqdm import tqdm

__all__ = ["LOG_INTERVAL_S", "progress_bar"]

#: Seconds between two lines of a bar written to a file (a log, not a terminal).
LOG_INTERVAL_S = 30.0


class _Lines:
    """A text stream that turns tqdm's in-place redraws into whole lines."""

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream

    def write(self, text: str) -> int:
        line = text.replace("\r", "").strip("\n")
        if line.strip():
            self.stream.write(line + "\n")
        return len(text)

    def flush(self) -> None:
        self.stream.flush()


class _LogBar(tqdm):
    """A bar written to a log: every redraw, those that ``set_postfix`` and ``set_description``
    force included, at most every ``mininterval`` seconds; a transient bar (``leave=False``)
    starts silent (its first line after ``mininterval``), a kept one with its first state;
    the final state when it closes (tqdm's own, for a kept bar)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        # Set before tqdm's __init__, which draws the first state through refresh().
        self._last_line = -float("inf") if kwargs.get("leave", True) else time.monotonic()
        super().__init__(*args, **kwargs)

    def __del__(self) -> None:
        # Ctrl-C inside tqdm's __init__ leaves a bar without its state: nothing to close (its
        # close() would print "Exception ignored ... no attribute 'pos'" at exit).
        if hasattr(self, "pos"):
            super().__del__()

    def refresh(self, nolock: bool = False, lock_args: Any = None) -> None:
        now = time.monotonic()
        if now - self._last_line < self.mininterval:
            return
        self._last_line = now
        super().refresh(nolock=nolock, lock_args=lock_args)


def _is_terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def progress_bar(iterable: Any = None, **options: Any) -> tqdm:
    """``tqdm(iterable, **options)``; where its stream (``file``, default stderr) is not a
    terminal, one whole line at most every :data:`LOG_INTERVAL_S` seconds (unless
    ``mininterval`` is given), however often the bar is redrawn, and no carriage returns."""
    stream = options.get("file") or sys.stderr
    if not options.get("disable") and not _is_terminal(stream):
        options["file"] = _Lines(stream)
        options.setdefault("mininterval", LOG_INTERVAL_S)
        options.pop("dynamic_ncols", None)  # a file has no width to follow
        return _LogBar(iterable, **options)
    return tqdm(iterable, **options)
