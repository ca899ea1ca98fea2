"""A command's output, all or nothing: one cleanup for every command that writes into ``--out``.

:func:`all_or_nothing` wraps the work of a command whose output is one folder (or one file):

- at start-up it deletes the stray temporary files of atomic writes
  (:func:`sq_mitsuba.io.atomic_path` names them ``.<stem>.<random>.tmp<suffix>``) that a run
  killed mid-write left at the top of the folder, so they do not outlive the next run;
- when the work fails (an exception other than the user's Ctrl-C), it deletes what the run
  added at the top of the folder, and the folder itself (and parents) when the run created
  them: a failed run leaves the folder as it found it, apart from files it replaced, which
  atomic writes replace whole or not at all.

A run interrupted with Ctrl-C keeps what it wrote (``study illumination`` resumes its renders).
One folder takes one run at a time: a second run into it would see the first one's temporary
files as strays.
"""

from __future__ import annotations

import contextlib
import re
import shutil
from collections.abc import Iterator
from pathlib import Path

__all__ = ["TEMPORARY_NAME", "all_or_nothing", "remove_stray_temporaries"]

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


@contextlib.contextmanager
def all_or_nothing(out: str | Path | None, file: bool = False) -> Iterator[None]:
    """Run the block as a command writing into ``out`` (see the module docstring).

    Args:
        out: the output folder; None: no cleanup.
        file: ``out`` is one output file instead (its stray temporaries lie beside it).
    """
    if out is None:
        yield
        return
    out = Path(out)
    created = _first_missing(out)
    before = set(out.iterdir()) if out.is_dir() and not file else None
    if file:
        remove_stray_temporaries(out.parent, of=out.name)
    else:
        remove_stray_temporaries(out)
    try:
        yield
    except Exception:
        _remove_added(out, created, before)
        raise


def _remove_added(out: Path, created: Path | None, before: set[Path] | None) -> None:
    """Delete what a failed run added: ``created`` (the outermost folder it made, or the file
    ``out``) as a whole, or the entries of ``out`` not in ``before``."""
    if created is not None:
        _remove(created)
    elif before is not None and out.is_dir():
        for path in set(out.iterdir()) - before:
            _remove(path)


def _remove(path: Path) -> None:
    with contextlib.suppress(OSError):  # gone already, or never made (a file in the way)
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()
