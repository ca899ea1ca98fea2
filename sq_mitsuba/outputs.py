"""A command's output, all or nothing: one cleanup for every command that writes into ``--out``.

:func:`all_or_nothing` wraps the work of a command whose output is one folder (or one file):

- at start-up it deletes the stray temporary files of atomic writes
  (:func:`sq_mitsuba.io.atomic_path` names them ``.<stem>.<random>.tmp<suffix>``) that a run
  killed mid-write left at the top of the folder, so they do not outlive the next run;
- when the work fails (an exception other than the user's Ctrl-C), it deletes what the run
  added at the top of the folder, and the folder itself (and parents) when the run created
  them: a failed run leaves the folder as it found it, apart from files it replaced, which
  atomic writes replace whole or not at all. What the run added is known by name only: the
  command's outputs (``outputs``: patterns of the paths it writes) and the temporary files of
  atomic writes; anything else that appeared meanwhile (a file the user saved into the
  folder during the run) is someone else's and stays, with the folders holding it (said in
  one warning). A folder the run made goes only once it holds nothing else.

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
- Shared (``shared=True``): the shards of one ``dataset render`` write one folder together;
  each holds the lock shared, which refuses (and is refused by) an exclusive holder only. The
  last shared holder out deletes the lock file.
- Waiting (``wait=True``): a short section that processes sharing an output take in turn
  (the shards' check and write of one manifest) waits for the holder instead of refusing.
"""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import os
import re
import sys
import warnings
from collections.abc import Collection, Iterator, Sequence
from pathlib import Path
from typing import Any

__all__ = ["LOCK_NAME", "MAX_RECORD_BYTES", "TEMPORARY_NAME", "OutputBusyError",
           "all_or_nothing", "holds_lock", "interrupted", "is_output", "json_record",
           "lock_path", "output_lock", "refuse_present", "remove_stray_temporaries",
           "remove_unwritten"]

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


#: Largest file :func:`json_record` reads: the records commands write are a few kB.
MAX_RECORD_BYTES = 1 << 20


def json_record(path: str | Path) -> dict[str, Any]:
    """The JSON object in the plain file ``path`` (at most :data:`MAX_RECORD_BYTES`), else
    ``{}``: absent, a folder or link, too large, unreadable, not JSON, nested too deep, not an
    object. For telling a file a command of this tool wrote (by its keys) from one of the same
    name that someone else put there, before anything beside it is replaced or deleted."""
    import json

    path = Path(path)
    try:
        if path.is_symlink() or not path.is_file() or path.stat().st_size > MAX_RECORD_BYTES:
            return {}
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # RecursionError: arrays nested too deep
        return {}
    return record if isinstance(record, dict) else {}


def refuse_present(folder: Path, names: Sequence[str], why: str) -> None:
    """A one-line ``ValueError`` naming the first of ``names`` present in ``folder`` (a file,
    folder or link): ``<path>: <why>; move it or choose another --out``. For a run that would
    replace it but cannot tell it is its own (checked before any work)."""
    for name in names:
        path = folder / name
        if path.exists() or path.is_symlink():
            raise ValueError(f"{path}: {why}; move it or choose another --out")


def remove_unwritten(folder: Path, names: Sequence[str], written: Collection[Path]
                     ) -> list[Path]:
    """Delete the files of ``names`` in ``folder`` that this run did not write (``written``):
    an earlier run's of the same command that this one does not make again (figures after
    ``--no-figures``), so that the folder holds one run's outputs. Call it only where the
    folder holds an earlier run of the command (its own record there): a file of those names
    in any other folder is someone else's. Returns the files deleted."""
    kept = {Path(path).name for path in written}
    removed = []
    for name in names:
        path = folder / name
        if name not in kept and path.is_file() and not path.is_symlink():
            path.unlink()
            removed.append(path)
    return removed


def is_output(relative: str | Path, outputs: Collection[str] | None, folder: bool = False
              ) -> bool:
    """Whether the path ``relative`` (to the output folder) is one a command writing
    ``outputs`` may write: the patterns' parts are matched name by name (``fnmatch``: ``*``
    within one name), a part ``**`` matches everything below (``renders/**``); ``folder``: a
    folder on the way to such a path also matches. None: every path (a caller that owns every
    name in its folder)."""
    if outputs is None:
        return True
    parts = Path(relative).parts
    for pattern in outputs:
        wanted = tuple(part for part in pattern.split("/") if part)
        for k, part in enumerate(parts):
            if k >= len(wanted) or (wanted[k] != "**"
                                    and not fnmatch.fnmatchcase(part, wanted[k])):
                break
            if wanted[k] == "**":
                return True
        else:
            if len(parts) == len(wanted) or (folder and len(parts) < len(wanted)):
                return True
    return False


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
        text = path.read_text(encoding="utf-8", errors="replace").split()
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


#: Bytes of a shared holder's record (padded: each one's write replaces the whole record).
_RECORD_BYTES = 160


def _acquire(path: Path, out: Path, command: str | None, shared: bool = False,
             wait: bool = False) -> int:
    """Open and ``flock`` the lock file ``path`` (exclusive, or ``shared``; without waiting
    unless ``wait``); its descriptor."""
    import fcntl

    mode = (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | (0 if wait else fcntl.LOCK_NB)
    for _ in range(100):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except FileNotFoundError:  # a failed run's cleanup removed the folder: make it again
            path.parent.mkdir(parents=True, exist_ok=True)
            continue
        try:
            fcntl.flock(fd, mode)
        except OSError as error:
            os.close(fd)
            if error.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            where = "folder" if path.parent == out or out.is_dir() else "file"
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
    # A file name that is no UTF-8 (bytes the file system holds) reaches argv as surrogates.
    record = f"{os.getpid()} {command or _command_name()}\n".encode(errors="backslashreplace")
    if shared:  # beside other holders: one write of the whole record, never a truncation
        os.pwrite(fd, record.ljust(_RECORD_BYTES)[:_RECORD_BYTES], 0)
    else:
        os.ftruncate(fd, 0)
        os.write(fd, record)
    return fd


def _release(fd: int, path: Path, shared: bool) -> None:
    """Unlock and close ``fd``, deleting the lock file where no other process holds it: an
    exclusive holder's always; a shared holder's when it can take the lock alone (the last
    one out), else the file stays for the others."""
    import fcntl

    alone = True
    if shared:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            alone = False
    if alone:
        with contextlib.suppress(OSError):  # gone already (the folder removed by a cleanup)
            if os.path.samestat(os.fstat(fd), os.stat(path)):
                path.unlink()
    os.close(fd)  # releases the lock


@contextlib.contextmanager
def output_lock(out: str | Path, file: bool = False, command: str | None = None,
                shared: bool = False, wait: bool = False) -> Iterator[Path]:
    """Hold the lock on the output ``out`` for the block (see the module docstring).

    Args:
        out: the output folder (created, with its parents, when missing), or with ``file``
            the output file (its folder is created).
        file: ``out`` is one file.
        command: what runs, for the message another run prints (default: the command line's
            first words).
        shared: hold it beside other shared holders (the shards of one render), refusing
            only an exclusive holder and refused by one.
        wait: wait for the lock instead of refusing (a short section several processes take
            in turn, such as a manifest's check and write).

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
            fd = _acquire(path, out, command, shared, wait)
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
        _release(fd, path, shared)
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
                   command: str | None = None, keep: Collection[str] = (),
                   outputs: Collection[str] | None = None) -> Iterator[None]:
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
        outputs: the paths the command writes in ``out``, as patterns (:func:`is_output`):
            a failed run deletes only the files it added that match them (and temporary
            files), and the folders it made once empty. None: every entry it added (for a
            caller that owns every name in ``out``).
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
                              set() if isinstance(error, ValueError) else set(keep),
                              outputs, file)
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
                  keep: set[str], outputs: Collection[str] | None, file: bool) -> None:
    """Delete what a failed run added: the entries of ``out`` not in ``before`` (all of them
    where the run made ``out``: ``created``, the outermost folder it made, or the file
    ``out``) that it could have written (:func:`_remove_own`), then the folders it made while
    they are empty; entries named in ``keep`` stay, with the folders above them. What stays
    that the run did not write is said in one warning."""
    if file:  # one output file: it, and its temporaries, if the run made it
        if created is not None:
            with contextlib.suppress(OSError):
                if out.is_file() or out.is_symlink():
                    out.unlink()
            remove_stray_temporaries(out.parent, of=out.name)
            _remove_empty(None if created == out else created, out.parent)
        return
    if not out.is_dir() or (created is None and before is None):
        return
    left: list[Path] = []
    try:
        added = sorted(set(out.iterdir()) - (before if created is None else set()))
    except OSError:  # unreadable now: nothing is removed (the run's own error is said)
        return
    for path in added:
        if path.name not in keep and path.name != LOCK_NAME:  # the lock: output_lock's
            left += _remove_own(path, out, outputs)
    if left:
        warnings.warn(f"{out}: the failed run left {len(left)} entr"
                      f"{'y' if len(left) == 1 else 'ies'} it did not write ({left[0]}"
                      f"{', ...' if len(left) > 1 else ''}), and the folders holding them",
                      stacklevel=4)
    _remove_empty(created, out)


def _remove_own(path: Path, out: Path, outputs: Collection[str] | None) -> list[Path]:
    """Delete ``path`` (new in ``out``) where the run could have written it: a file (or link)
    matching ``outputs`` or a temporary file's name; a folder on the way to such files
    (``outputs``), emptied so and then removed when nothing else is left in it. Never a
    folder's contents wholesale. Returns what it left: the entries the run did not write."""
    relative = path.relative_to(out)
    if path.is_dir() and not path.is_symlink():
        try:
            children = sorted(path.iterdir()) if is_output(relative, outputs, True) else None
        except OSError:  # unreadable: left as it is (the run's own error is the one to say)
            children = None
        if children is None:
            return [path]
        left = [entry for child in children for entry in _remove_own(child, out, outputs)]
        if not left:
            with contextlib.suppress(OSError):  # something appeared meanwhile: it stays
                path.rmdir()
        return left
    if (is_output(relative, outputs) or TEMPORARY_NAME.fullmatch(path.name)
            or path.name.endswith(LOCK_NAME)):  # a nested run's lock (a study's evals)
        with contextlib.suppress(OSError):  # gone already
            path.unlink()
        return []
    return [path]
