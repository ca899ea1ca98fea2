"""The worker pool every ``--workers`` option uses: Ctrl-C stops the command at once, its
workers with it, whether the signal reaches the parent alone (``kill -INT``, a scheduler) or
the whole foreground group (Ctrl-C in a terminal). Run in a child process, as a user's
command would be."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

SCRIPT = textwrap.dedent("""
    import os, signal, sys, time
    from sq_mitsuba.processes import worker_pool

    if __name__ == "__main__":
        # A command started from a terminal has Python's Ctrl-C handler; one started by a
        # process that ignores SIGINT (a pytest-xdist worker, a shell's background job)
        # inherits the ignoring, so the script installs the handler a terminal's would get.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            with worker_pool(2) as pool:
                workers = list(pool.map(_pid, range(8)))
                jobs = [pool.submit(_watch, sys.argv[1], k) for k in range(2)]
                print(" ".join(map(str, sorted(set(workers)))), flush=True)
                for job in jobs:
                    job.result()
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr, flush=True)
            sys.exit(130)
""")


HELPERS = textwrap.dedent("""
    def _pid(_):
        import os, time
        time.sleep(0.05)
        return os.getpid()

    def _watch(folder, k):
        # A job that sets its own SIGINT handler, as Mitsuba's integrator does for each render
        # (it cancels the render): the terminal's Ctrl-C must not reach it.
        import signal, time
        from pathlib import Path
        signal.signal(signal.SIGINT, lambda *_: Path(folder, f"interrupted_{k}").touch())
        time.sleep(60)
""")


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs Linux /proc")
@pytest.mark.parametrize("to_group", [False, True], ids=["parent", "group"])
def test_an_interrupt_ends_the_pool_and_its_workers_at_once(tmp_path, to_group):
    script = tmp_path / "pool_script.py"
    script.write_text(HELPERS + SCRIPT)
    child = subprocess.Popen([sys.executable, str(script), str(tmp_path)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, start_new_session=True,
                             cwd=Path(__file__).resolve().parents[1])
    try:
        workers = [int(pid) for pid in child.stdout.readline().split()]
        assert workers and all(_alive(pid) for pid in workers)
        time.sleep(0.3)  # the two 60 s jobs are running
        (os.killpg if to_group else os.kill)(child.pid, signal.SIGINT)
        _, err = child.communicate(timeout=20)  # a plain pool waited 60 s for its jobs
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
    assert child.returncode == 130
    assert err.strip() == "interrupted"  # no worker's traceback
    assert not list(tmp_path.glob("interrupted_*"))  # no job saw the signal
    deadline = time.time() + 10
    while any(_alive(pid) for pid in workers) and time.time() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in workers)
