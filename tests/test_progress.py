"""Progress bars on a terminal and in a log file (sq_mitsuba.progress)."""

from __future__ import annotations

import io
import os
import pty
import select

from sq_mitsuba.progress import LOG_INTERVAL_S, progress_bar


def test_a_bar_into_a_file_writes_whole_lines_and_its_end():
    log = io.StringIO()
    for _ in progress_bar(range(500), desc="work", unit="step", file=log, mininterval=0):
        pass
    text = log.getvalue()
    assert "\r" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert all(line.startswith("work:") for line in lines), lines[:3]
    assert "500/500" in lines[-1]
    # The default interval: a fast loop writes its start and its end, not 500 lines.
    log = io.StringIO()
    with progress_bar(total=500, desc="work", file=log) as bar:
        for _ in range(500):
            bar.update(1)
    lines = log.getvalue().splitlines()
    assert LOG_INTERVAL_S >= 10 and 1 <= len(lines) <= 3 and "500/500" in lines[-1], lines
    # leave=False clears its line on a terminal: nothing left in a log but whole lines.
    log = io.StringIO()
    for _ in progress_bar(range(3), desc="cache", file=log, leave=False, mininterval=0):
        pass
    assert all(line.startswith("cache:") for line in log.getvalue().splitlines())


def test_a_bar_redrawn_at_every_step_still_writes_a_line_per_interval():
    """A training loop shows its loss at every step (set_postfix, set_description: each
    forces a redraw): into a log that is still the start and the end, not a line a step; a
    transient bar (leave=False, as bench's) that ends within the interval writes nothing."""
    log = io.StringIO()
    with progress_bar(total=500, desc="train", file=log) as bar:
        for step in range(500):
            bar.set_postfix(loss=f"{1 / (step + 1):.4g}")
            bar.set_description(f"train {step}")
            bar.update(1)
    lines = log.getvalue().splitlines()
    assert 1 <= len(lines) <= 3 and "500/500" in lines[-1], lines[:5]
    log = io.StringIO()
    with progress_bar(total=4, desc="bench", file=log, leave=False) as bar:
        for _ in range(4):
            bar.update(1)
    assert log.getvalue().strip() == ""


def test_a_bar_on_a_terminal_redraws_in_place():
    leader, follower = pty.openpty()
    with os.fdopen(follower, "w") as terminal:
        for _ in progress_bar(range(3), desc="work", file=terminal, mininterval=0):
            pass
        terminal.flush()
        # The pty hands the bar's writes over in pieces: read until nothing more comes (one
        # read could return the first redraw alone).
        chunks = []
        while select.select([leader], [], [], 0.5)[0]:
            chunks.append(os.read(leader, 4096))
        shown = b"".join(chunks).decode()
    os.close(leader)
    assert "\r" in shown and "3/3" in shown


def test_a_disabled_bar_writes_nothing():
    log = io.StringIO()
    for _ in progress_bar(range(3), file=log, disable=True):
        pass
    assert log.getvalue() == ""


def test_a_command_logged_to_a_file_writes_lines(tmp_path, capfd):
    """A command's bar with stderr redirected (here to pytest's capture file, as to a log)."""
    from sq_mitsuba.cli import main

    assert main(["models", "generate", "--count", "2", "--seed", "3", "--points", "2000",
                 "--out", str(tmp_path / "library")]) == 0
    err = capfd.readouterr().err
    assert "\r" not in err
    assert "2/2" in [line for line in err.splitlines() if line.startswith("models:")][-1]
    # models preview (silent before: a third of a second a model).
    assert main(["models", "preview", str(tmp_path / "library"), "--size", "32", "--spp",
                 "4"]) == 0
    err = capfd.readouterr().err
    assert "\r" not in err
    assert "2/2" in [line for line in err.splitlines() if line.startswith("preview:")][-1]
