"""Atomic file output: write to a temporary file beside the target, then rename.

A crash or kill at any moment leaves either the old file or the complete new one, never a
half-written file.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto ``path`` on success.

    The temporary name keeps the target's suffix, so writers that pick a format from the
    extension (trimesh, PIL, Mitsuba) still work. On an exception the temporary file is removed
    and the target is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}",
                                    dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        # mkstemp creates 0600 files; give the result the usual permissions (umask applied).
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def _umask() -> int:
    current = os.umask(0)
    os.umask(current)
    return current


def staging_folder(prefix: str, dir: str | Path) -> Path:
    """``tempfile.mkdtemp(prefix=prefix, dir=dir)`` with the permissions ``mkdir`` gives
    (0o777, umask applied): mkdtemp makes 0700 folders, and one renamed into place as a
    run's output would shut out other users (a web server showing a demo page)."""
    path = Path(tempfile.mkdtemp(prefix=prefix, dir=dir))
    os.chmod(path, 0o777 & ~_umask())
    return path


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (fsynced before the rename)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | Path, obj: Any, indent: int | None = 2) -> None:
    """Write ``obj`` as JSON to ``path`` atomically."""
    atomic_write_text(path, json.dumps(obj, indent=indent) + "\n")


def read_json(path: str | Path) -> Any:
    """Parse a JSON file; a malformed one raises a one-line ``ValueError`` naming it.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``"<path>: not valid JSON (<reason>, line <n>)"``, an empty file, or not a
            regular file.
    """
    path = Path(path)
    if path.exists() and not path.is_file():  # a device or pipe could block, or never end
        raise ValueError(f"{path}: not a regular file (a folder, device, pipe or socket)")
    try:
        text = path.read_text(encoding="utf-8")
        if not text.strip():  # json says "Expecting value": a file cut at its first write
            raise ValueError(f"{path}: an empty file, not JSON")
        return json.loads(text)
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not valid JSON ({error.msg}, line {error.lineno})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not valid JSON (not UTF-8 text)") from None
    except RecursionError:  # arrays or objects nested deeper than the parser's stack
        raise ValueError(f"{path}: not valid JSON here (nested too deeply)") from None


def save_figure(figure: Any, path: str | Path, dpi: int = 110) -> Path:
    """Write a matplotlib figure as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            figure.savefig(tmp, dpi=dpi, format="png")
    finally:
        plt.close(figure)
    return path


def check_output_folder(out: str | Path, files: Sequence[str | Path] = (),
                        keep: Sequence[str | Path] = (), shown: str | Path | None = None
                        ) -> Path:
    """``out`` as a Path, if it is (or can be created as) a writable folder that can take the
    run's ``files`` without losing one of its inputs.

    Probes by creating and removing a temporary file in ``out`` or its nearest existing
    ancestor: permission bits alone do not tell (root ignores them; read-only mounts).
    Creates nothing that stays.

    Args:
        out: the output folder.
        files: the files the run will write there (names, or paths, relative to ``out``):
            one that exists as a folder (or another non-file), or whose folder inside ``out``
            exists as a file, is refused now, not after the work.
        keep: the run's input files: one that ``files`` would overwrite is refused
            (:func:`check_inputs_kept`).
        shown: the output named in the messages as ``out <shown>: ...`` (default ``out``;
            :func:`check_output_file` names the file given, not its folder).

    Raises:
        ValueError: ``out`` or an ancestor is a file, the folder is not writable, an output
            is not a file, or an output is one of ``keep``.
    """
    if not str(out).strip():  # Path("") is the working folder: never what was meant
        raise ValueError("out: an empty path; give an output folder")
    out = Path(out)
    label = out if shown is None else shown
    if out.exists() and not out.is_dir():
        raise ValueError(f"out {label}: exists and is not a folder" if shown is None
                         else f"out {label}: {out} is a file, not a folder")
    existing = nearest_existing(out)
    if not existing.is_dir():
        raise ValueError(f"out {label}: {existing} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".sq-mitsuba-probe.", dir=existing)
    except OSError as error:
        raise ValueError(f"out {label}: cannot write in {existing} "
                         f"({error.strerror or type(error).__name__})") from None
    os.close(fd)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(probe)
    written = [out / name for name in files]
    _check_room(out, written, existing, label)
    check_inputs_kept([Path(path) for path in keep], written)
    for path in written:
        if path.exists() and not path.is_file():
            raise ValueError(f"{path}: an output of this run, but a folder (or another "
                             "non-file) is there; move it or write elsewhere (--out)")
        for folder in path.parents:  # a sub-folder of the run's (colmap/, say) taken by a file
            if folder == out or out not in folder.parents:
                break
            if folder.exists() and not folder.is_dir():
                raise ValueError(f"{folder}: the run writes {path.name} into this folder, but "
                                 "a file is there; move it or write elsewhere (--out)")
    return out


#: What an atomic write's temporary name adds to its target's (``.`` ``.XXXXXXXX`` ``.tmp``).
TEMPORARY_EXTRA = 14
#: Room kept below an output folder for what a run writes beside its named files (a journal
#: folder and its records, a staging name): ``.eval_partial/.batch_00001.XXXXXXXX.tmp.pt``.
OUTPUT_DEPTH = 64


def _limit(folder: Path, name: str, default: int) -> int:
    try:
        return int(os.pathconf(folder, name))
    except (OSError, ValueError):
        return default


def nearest_existing(path: Path) -> Path:
    """``path``, or its nearest ancestor that exists: where a folder to be made will be (its
    file system, its disk)."""
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_path_room(out: str | Path, below: int = OUTPUT_DEPTH, label: object = None) -> None:
    """Refuse, before the work, an output folder whose path leaves less than ``below`` bytes
    for what a run writes under it before the file system's path limit (4,096 bytes on
    Linux): such a run failed part-way, naming a temporary file, and left partial outputs.

    Raises:
        ValueError: ``out <label>: a path of N bytes, ...`` (``label`` default ``out``).
    """
    out = Path(out)
    path_max = _limit(nearest_existing(out), "PC_PATH_MAX", 4096)
    length = len(os.fsencode(os.path.abspath(out)))
    if length + below > path_max:
        raise ValueError(f"out {out if label is None else label}: a path of {length} bytes, "
                         f"too long for what the run writes below it (paths may have "
                         f"{path_max} bytes); choose a shorter one")


def _check_room(out: Path, written: Sequence[Path], existing: Path, label: object) -> None:
    """:func:`check_path_room` of ``out``, and each of ``written`` refused whose name leaves
    no room for its atomic write's temporary name (a legal name of 242-255 bytes failed
    part-way, naming the temporary file)."""
    check_path_room(out, OUTPUT_DEPTH, label)
    name_max = _limit(existing, "PC_NAME_MAX", 255)
    for path in written:
        name = len(os.fsencode(path.name))
        if name + TEMPORARY_EXTRA > name_max:
            raise ValueError(f"{path.name}: a name of {name} bytes, too long for its temporary "
                             f"file while it is written ({name_max} at most, less "
                             f"{TEMPORARY_EXTRA}); choose a shorter name")


def inside_folder(path: str | Path, folder: str | Path) -> bool:
    """Whether ``path`` is ``folder`` or lies inside it (both resolved: links followed)."""
    resolved, root = Path(path).resolve(), Path(folder).resolve()
    return resolved == root or root in resolved.parents


def check_output_file(out: str | Path) -> Path:
    """``out`` as a Path, if its folder is (or can be created as) a writable folder and
    ``out`` is not a folder: checked before the work, so that a run does not render everything
    and then fail naming the temporary file of its atomic write. The one-line ``ValueError``
    of :func:`check_output_folder`, naming ``out`` as given rather than its
    folder."""
    out = Path(out)
    check_output_folder(out.parent, [out.name], shown=out)
    return out


def check_inputs_kept(inputs: list[Path], outputs: list[Path]) -> None:
    """Refuse a run that would overwrite one of its own inputs with one of its outputs (an
    image named like another's overlay, say): one line naming the input.

    Raises:
        ValueError: ``"<input>: ... would overwrite it ..."``.
    """
    written = {os.path.realpath(path) for path in outputs}
    for path in inputs:
        if os.path.realpath(path) in written:
            raise ValueError(f"{path}: an output of this run would overwrite it; write "
                             "elsewhere (--out)")

