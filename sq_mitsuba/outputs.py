"""A command's output, all or nothing: one cleanup for every command that writes into ``--out``.

:func:`all_or_nothing` wraps the work of a command whose output is one folder (or one file):

- at start-up it deletes the stray temporary files of atomic writes
  (:func:`sq_mitsuba.io.atomic_path` names them ``.<stem>.<random>.tmp<suffix>``) that a run
  killed mid-write left at the top of the folder, so they do not outlive the next run;
- when the work fails (an exception other than the user's Ctrl-C), it deletes what the run
  added at the top of the folder, and the folder itself (and parents) when the run created
  them: a failed run leaves the folder as it found it, apart from files it replaced, which
  atomic writes replace whole or not at all.

A run interrupted with Ctrl-C keeps what it wrote (``study illumination`` resumes its renders),
also where the interrupt comes out of Dr.Jit as a ``RuntimeError`` caused by it
(:func:`interrupted`); the CLI handles SIGTERM as Ctrl-C. A run that fails by no fault of its
input (out of memory, a disk error, a bug: anything but a ``ValueError``, the project's bad
input) still keeps the entries named ``keep``: the journals of finished work a rerun takes up
(``eval``'s ``.eval_partial``, a study's renders), which would otherwise go with hours of work
in them. Bad input leaves nothing, as before any work.

One output takes one run at a time (a second run into it would see the first one's temporary
files as strays, and the two would mix their files): :func:`output_lock` holds an exclusive
lock on the output for the length of a run, and :func:`all_or_nothing` takes it first, so
every command that writes its ``--out`` through it refuses to start while another process
writes there.

The lock (:func:`output_lock`): ``fcntl.flock`` on a lock file, :data:`LOCK_NAME` inside the
output folder (``.<name>.sq-mitsuba.lock`` beside an output file), created with the folder
when needed and holding the holder's process id and command (for the message only).

- Taken without waiting: a run that finds the output locked stops at once with one line
  (:class:`OutputBusyError`, a ``ValueError``: exit code 2) naming the output and the process
  that holds it, before any work.
- Released on any exit: the lock file is deleted when the block ends (success, error, Ctrl-C),
  and folders the lock created are removed again when they are still empty.
- Stale locks cannot block: the kernel drops a ``flock`` when its process dies, however it
  dies (``kill -9`` included), so a lock file a killed run left behind is simply taken over.
  No process id is ever compared.
- Re-entrant within one process (a command that locks its output and then calls a library
  function that locks the same output); another process is always refused.
- Where the lock file cannot be created (a file in the way, a folder that cannot be written),
  the block runs unlocked: the command then stops with its own one-line error about the
  output.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import sys
from collections.abc import Collection, Iterator
from pathlib import Path

__all__ = ["LOCK_NAME", "TEMPORARY_NAME", "OutputBusyError", "all_or_nothing", "holds_lock",
           "interrupted", "lock_path", "output_lock", "remove_stray_temporaries"]

#: The lock file of :func:`output_lock` inside an output folder.
LOCK_NAME = ".sq-mitsuba.lock"

#: The name of a temporary file of :func:`sq_mitsuba.io.atomic_path`: ``.<stem>.`` then
#: ``tempfile``'s eight random characters, then ``.tmp<suffix>``.
TEMPORARY_NAME = re.compile(r"\..*\.[a-z0-9_]{8}\.tmp(\.[^/]*)?")


def remove_stray_temporaries(folder: str | Path, of: str | None = None) -> list[Path]:
    """Delete the temporary files of atomic writes at the top of ``folder`` (only those of
    the file named ``of``, when given); returns them."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = []
    for path in sorted(folder.iterdir()):
        if not TEMPORARY_NAME.fullmatch(path.name) or not path.is_file() or path.is_symlink():
            continue
        if of is not None and not (path.name.startswith(f".{Path(of).stem}.")
                                   and path.name.endswith(f".tmp{Path(of).suffix}")):
            continue
        path.unlink(missing_ok=True)
        removed.append(path)
    return removed


def _first_missing(path: Path) -> Path | None:
    """The outermost folder of ``path``'s chain (``path`` included) that does not exist."""
    missing = None
    for candidate in (path, *path.parents):
        if candidate.exists() or candidate.is_symlink():
            break
        missing = candidate
    return missing


# ----------------------------------------------------------------------------- the lock


class OutputBusyError(ValueError):
    """Another process holds the lock on the output: one line naming the output and it."""


#: Locks this process holds: lock file -> (open descriptor, depth).
_HELD: dict[Path, list[int]] = {}


def holds_lock(out: str | Path, file: bool = False) -> bool:
    """Whether this process holds the lock on ``out`` (inside :func:`output_lock`; False where
    that lock ran unlocked, no lock file being possible there)."""
    return lock_path(out, file).resolve() in _HELD


def lock_path(out: str | Path, file: bool = False) -> Path:
    """The lock file of the output ``out``: ``out/.sq-mitsuba.lock`` for a folder,
    ``.<name>.sq-mitsuba.lock`` beside it for a file (``file``)."""
    out = Path(out)
    return out.parent / f".{out.name}{LOCK_NAME}" if file else out / LOCK_NAME


def _holder(path: Path) -> str:
    """Who holds the lock file ``path``, from what it records (for the message)."""
    try:
        text = path.read_text(encoding="utf-8").split()
    except OSError:
        text = []
    if text and text[0].isdigit():
        command = " ".join(text[1:])
        return f"process {text[0]}" + (f", {command}" if command else "")
    return "another process"


def _command_name() -> str:
    name = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python"
    if name in ("__main__.py", "-m", "-c"):  # python -m sq_mitsuba
        name = "sq-mitsuba"
    words = [name, *(w for w in sys.argv[1:3] if not w.startswith("-"))]
    return " ".join(words)[:120]


def _acquire(path: Path, out: Path, command: str | None) -> int:
    """Open and ``flock`` the lock file ``path`` without waiting; its descriptor."""
    import fcntl

    for _ in range(100):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except FileNotFoundError:  # a failed run's cleanup removed the folder: make it again
            path.parent.mkdir(parents=True, exist_ok=True)
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            os.close(fd)
            if error.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            where = "folder" if path.parent == out else "file"
            raise OutputBusyError(
                f"{out}: another run is writing into this {where} ({_holder(path)}); wait "
                f"for it to finish, or choose another output") from None
        # The holder before us may have deleted the file between our open and our lock:
        # then we hold a lock on a file no one else can find; start again.
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    else:
        raise OSError(errno.EAGAIN, "the lock file keeps disappearing", str(path))
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()} {command or _command_name()}\n".encode())
    return fd


@contextlib.contextmanager
def output_lock(out: str | Path, file: bool = False, command: str | None = None
                ) -> Iterator[Path]:
    """Hold the lock on the output ``out`` for the block (see the module docstring).

    Args:
        out: the output folder (created, with its parents, when missing), or with ``file``
            the output file (its folder is created).
        file: ``out`` is one file.
        command: what runs, for the message another run prints (default: the command line's
            first words).

    Yields:
        The output folder (``out``, or its parent with ``file``).

    Raises:
        OutputBusyError: another process holds the lock (a ``ValueError``, one line); raised
            before anything is created or changed except folders a concurrent run also made.
    """
    out = Path(out)
    folder = out.parent if file else out
    path = lock_path(out, file)
    key = path.resolve()
    if key in _HELD:  # this process holds it already: re-entrant
        _HELD[key][1] += 1
        try:
            yield folder
        finally:
            _HELD[key][1] -= 1
        return
    created = _first_missing(folder)
    fd = None
    try:
        if not (folder.exists() and not folder.is_dir()):
            folder.mkdir(parents=True, exist_ok=True)
            fd = _acquire(path, out, command)
    except OutputBusyError:
        _remove_empty(created, folder)
        raise
    except OSError:  # no lock file can be made here: the command reports its own error
        pass
    if fd is None:  # runs unlocked (see the module docstring)
        _remove_empty(created, folder)
        yield folder
        return
    _HELD[key] = [fd, 1]
    try:
        yield folder
    finally:
        del _HELD[key]
        with contextlib.suppress(OSError):  # gone already (the folder removed by a cleanup)
            if os.path.samestat(os.fstat(fd), os.stat(path)):
                path.unlink()
        os.close(fd)  # releases the lock
        _remove_empty(created, folder)


def _remove_empty(created: Path | None, folder: Path) -> None:
    """Remove ``folder`` and its parents up to ``created`` while they are empty."""
    if created is None:
        return
    for candidate in (folder, *folder.parents):
        try:
            candidate.rmdir()
        except OSError:  # not empty (another run's, or output written), or gone
            return
        if candidate == created:
            return


# ----------------------------------------------------------------------------- all or nothing


@contextlib.contextmanager
def all_or_nothing(out: str | Path | None, file: bool = False, lock: bool = True,
                   command: str | None = None, keep: Collection[str] = ()) -> Iterator[None]:
    """Run the block as a command writing into ``out`` (see the module docstring).

    Args:
        out: the output folder; None: no cleanup.
        file: ``out`` is one output file instead (its stray temporaries lie beside it).
        lock: hold :func:`output_lock` on ``out`` for the block, taken first (another run
            into ``out`` is refused with :class:`OutputBusyError` before anything else).
        command: the command, for the message another run prints.
        keep: names of entries at the top of ``out`` a run that failed other than by bad
            input (a ``ValueError``) keeps (finished work a rerun resumes); the folder then
            stays too.
    """
    if out is None:
        yield
        return
    out = Path(out)
    created = _first_missing(out)  # before the lock makes the folder
    with output_lock(out, file, command) if lock else contextlib.nullcontext():
        before = set(out.iterdir()) if out.is_dir() and not file else None
        if file:
            remove_stray_temporaries(out.parent, of=out.name)
        else:
            remove_stray_temporaries(out)
        try:
            yield
        except Exception as error:
            if not interrupted(error):  # Ctrl-C inside Dr.Jit comes as a RuntimeError
                _remove_added(out, created, before,
                              set() if isinstance(error, ValueError) else set(keep))
            raise


def interrupted(error: BaseException) -> bool:
    """Whether ``error`` is a Ctrl-C in disguise: a ``KeyboardInterrupt`` in its chain of causes
    and contexts. Raised inside Dr.Jit or Mitsuba (Python code run from C++), one comes out as
    a ``RuntimeError`` caused by it (``drjit.switch(): encountered an exception``, or
    ``@drjit.syntax`` "could not be compiled" followed by a page of generated code), and an
    error raised while handling it carries it as context."""
    seen: set[int] = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return True
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return False


def _remove_added(out: Path, created: Path | None, before: set[Path] | None,
                  keep: set[str]) -> None:
    """Delete what a failed run added: ``created`` (the outermost folder it made, or the file
    ``out``) as a whole, or the entries of ``out`` not in ``before``; entries named in
    ``keep`` stay, with the folders above them."""
    kept = bool(keep) and out.is_dir() and any((out / name).exists() for name in keep)
    if created is not None and not kept:
        _remove(created)
    elif out.is_dir() and (created is not None or before is not None):
        for path in set(out.iterdir()) - (before if created is None else set()):
            if path.name not in keep:
                _remove(path)


def _remove(path: Path) -> None:
    with contextlib.suppress(OSError):  # gone already, or never made (a file in the way)
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()
