"""Render a dataset in the SPE3R layout (see :mod:`.layout`) with Mitsuba's path tracer.

Manifest: ``dataset.json`` records how the dataset was made: the settings that decide its
pixels (seed, resolution, spp, exr, camera, the scene configuration with its
:func:`~sq_mitsuba.config.config_hash`), the tool version, ``images_per_model``, each model's
split and image count, and ``state`` ("rendering", or "complete" once every model is finished
or failed). It is written atomically before the first image. A run into a folder whose
manifest has other settings stops with a one-line :class:`DatasetError` naming them, before
touching any file; ``overwrite=True`` starts clean instead, deleting what
:data:`OVERWRITE_DELETES` names (only where ``dataset.json`` is a valid manifest: a folder
that is not empty and holds none is refused either way, nothing the tool did not write being
ever deleted or written into). A larger ``images_per_model`` grows a dataset: the new images
are exactly those an uninterrupted larger run writes (every image has its own seed); a
smaller one is an error.

Resuming: each image's label is first written to ``<model>/.progress/<index>.json``, after its
image and mask, so a label there means the image is complete. ``labels.json`` is assembled from
them once a model is done. Every file is written atomically, so a run killed at any point and
restarted with the same command ends byte-identical to an uninterrupted one (the EXR depth
``Z`` up to float32 rounding where Dr.Jit runs several threads: they add its samples in the
order they finish); stray temporary files of an image are deleted before it is rendered again.

Shards: ``shard="I/N"`` renders block I of N of the work, every (model, image index) pair of
the plan (models sorted by name, indices ascending) cut into N contiguous blocks of equal size
(within one image): a model is shared by at most a few shards, so few scenes are built twice.
Shards may run at the same time into one folder on a shared file system, and finish in any
order: a model's ``labels.json`` is assembled by whichever process finishes its last image, and
``splits.csv``, ``failures.json`` and the final manifest by whichever process, its own work
done, finds every model settled (complete or failed). The manifest holds no shard count, so N
shards leave exactly the files, byte for byte, of one unsharded run.

Failures: the library's models of the run's work are read before any file is written
(:func:`check_library_models`), so a missing or corrupt model file is a one-line error, not a
failure. A model that fails while rendering (a full disk, its files in the dataset damaged)
is recorded in ``.failures/<model>/<I>-of-<N>.json`` and skipped; the others go on. Once
every model is settled, failed models are listed with their reason in ``failures.json`` and
left out of ``splits.csv``. Running the same command (or shard) again retries them.

Splits: a model's split is its row in the library's ``splits.csv``; without that file, the
split its ``model_card.json`` records, else the one the dataset already has, else train (a
warning counts those).
"""

from __future__ import annotations

import contextlib
import dataclasses
import filecmp
import functools
import hashlib
import json
import os
import shutil
import tempfile
import unicodedata
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sq_mitsuba.config import validate
from sq_mitsuba.data.frames import sample_frame, sample_pass_frame
from sq_mitsuba.data.spe3r.layout import (
    EXR,
    FAILURE_MARKS,
    FAILURES,
    IMAGES,
    MANIFEST,
    MASKS,
    MESH_FILE,
    MODELS,
    PROGRESS,
    SAMPLES_FILE,
    DatasetError,
    check_model_folder,
    check_model_points,
    load_model,
    read_labels,
    read_manifest,
    read_splits,
    splits_text,
    write_exr,
    write_png,
    write_splits,
)
from sq_mitsuba.data.spe3r.manifest import (
    dataset_settings,
    manifest_plan,
    manifest_record,
    settings_differences,
)
from sq_mitsuba.data.spe3r.render_options import (
    RenderOptions,
    RenderSummary,
    check_disk_room,
    check_render_resources,
    parse_shard,
)
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.io import (
    OUTPUT_DEPTH,
    atomic_path,
    atomic_write_json,
    atomic_write_text,
    check_path_room,
    inside_folder,
    read_json,
)
from sq_mitsuba.outputs import LOCK_NAME, TEMPORARY_NAME, output_lock

#: What ``overwrite`` deletes from the output folder before rendering, and only from a folder
#: whose ``dataset.json`` is a valid manifest of this tool (nothing else there is touched):
#: these files, the ``.failures`` folder, the model folders that manifest lists, and the
#: temporary files of atomic writes (:data:`~sq_mitsuba.outputs.TEMPORARY_NAME`) at the top
#: level. An entry among them that is a link, or not of the kind the tool writes there, is
#: refused before anything is deleted.
OVERWRITE_DELETES = (MANIFEST, "camera.json", "splits.csv", FAILURES, "preview.png")
#: Entries of a dataset's model folder that the render writes into: a link there would lead
#: its writes out of the dataset.
_MODEL_SUBFOLDERS = (IMAGES, MASKS, EXR, PROGRESS, MODELS, "labels.json")

# ------------------------------------------------------------------------ writer


def find_models(models_dir: Path) -> list[str]:
    """Model folders (those holding ``models/model_normalized.obj``), sorted by name."""
    if not models_dir.is_dir():
        raise DatasetError(f"{models_dir}: not a folder")
    names = sorted(p.parent.parent.name for p in models_dir.glob(f"*/{MODELS}/{MESH_FILE}"))
    splits_path = models_dir / "splits.csv"
    if splits_path.is_file():
        # Models named in splits.csv whose files are missing still count, so they fail loudly.
        # (read_splits refuses a name that is not one plain folder name.)
        names = sorted(set(names) | set(read_splits(splits_path)))
    if not names:
        raise DatasetError(f"{models_dir}: no model folders (<model>/{MODELS}/{MESH_FILE})")
    for name in names:  # a folder's own name too: a control character, a leading '.'
        check_model_folder(models_dir, name)  # and no model read through a link
    # A model folder named as a dataset's own file would stand where that file is written.
    clash = [name for name in names if name in OVERWRITE_DELETES]
    if clash:
        raise DatasetError(f"{models_dir / clash[0]}: a model named as a dataset's own file "
                           f"({', '.join(OVERWRITE_DELETES)}); rename its folder (and its row "
                           "in splits.csv)")
    return names


def _normalisation_twins(folders: Sequence[str], rows: Iterable[str]) -> list[tuple[str, str]]:
    """(folder, row) pairs of the ``folders`` without a row in ``splits.csv`` whose name a
    row of ``rows`` spells in another Unicode normalisation form ('café' as one code point or
    as 'e' and a combining accent: a copy through macOS can turn one into the other). They
    are not matched (on most file systems they are two names, and both can be folders), only
    named, since they look the same in the message."""
    by_form = {unicodedata.normalize("NFC", row): row for row in rows}
    return [(folder, by_form[unicodedata.normalize("NFC", folder)]) for folder in folders
            if unicodedata.normalize("NFC", folder) in by_form]


def check_library_models(models_dir: Path, models: Sequence[str]) -> None:
    """Read each model of the library as :func:`render_model` will (its mesh and materials,
    its points), so that a missing or damaged model is a one-line :class:`DatasetError`
    before any work rather than a failed model after the others' images (the check ``study
    illumination`` makes of its models too). :func:`load_model` sizes ``samples.npz``'s
    arrays from their headers and names a file that is no archive as such."""
    for model in models:
        load_model(models_dir / model)
        check_model_points(models_dir / model)


def _card_split(models_dir: Path, model: str) -> str | None:
    """The split a model's ``model_card.json`` records (``models generate`` writes it), or
    None: no card, an unreadable one, or no split name in it."""
    try:
        card = read_json(models_dir / model / MODELS / "model_card.json")
    except (OSError, ValueError):
        return None
    split = card.get("split") if isinstance(card, dict) else None
    return split if split in ("train", "test") else None


def check_writable(out_dir: Path, models: Sequence[str] = ()) -> None:
    """Create ``out_dir`` and write a file there (a unique name: shards may check at once),
    once its path leaves room for the deepest file a render of ``models`` writes (a path near
    the file system's limit failed part-way, leaving a dataset marked "rendering")."""
    if out_dir.exists() and not out_dir.is_dir():
        raise DatasetError(f"{out_dir}: exists and is not a folder; give a folder to render into")
    # <model>/masks/.000000.XXXXXXXX.tmp.png, .failures/<model>/...: the model's name, 2 x.
    deepest = 2 * max((len(os.fsencode(model)) for model in models), default=0) + OUTPUT_DEPTH
    try:
        check_path_room(out_dir, deepest)
    except ValueError as error:
        raise DatasetError(str(error)) from None
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=".write-test.", dir=out_dir)
        os.close(fd)
        os.unlink(name)
    except OSError as error:
        raise DatasetError(f"{out_dir}: output folder is not writable ({error.strerror})") \
            from None


def label_entry(filename: str, frame: Any, result: Any) -> dict[str, Any]:
    """One image's label: the SPE3R pose keys, then the render record of ``result`` (a
    :class:`~sq_mitsuba.render.space.RenderedFrame`: ``exposure``, ``target_visibility`` = mean
    grey inside the mask in [0, 1], ``target_lit_fraction`` = share of mask pixels at or above
    10/255), then the lighting of ``frame`` (a :class:`~sq_mitsuba.render.scene_config.Frame`)."""
    return {
        "filename": filename,
        "q_vbs2tango_true": [round(v, 12) for v in frame.quaternion],
        "r_Vo2To_vbs_true": [round(v, 12) for v in frame.translation],
        **result.label_extras(),
        **frame.label_extras(),
    }


#: Model files that decide the pixels; an existing dataset's copy must match the library's.
_PIXEL_FILES = (MESH_FILE, SAMPLES_FILE)


def _copy_model_files(source: Path, target: Path, has_images: bool = False) -> None:
    """Copy a model's files into the dataset; where the dataset already has images of the
    model, a mesh or samples file that differs from the library's is an error (those images
    were rendered from another model)."""
    target.mkdir(parents=True, exist_ok=True)
    for item in sorted(source.iterdir()):
        if item.is_file() and not item.name.startswith("."):
            destination = target / item.name
            if destination.exists() and filecmp.cmp(destination, item, shallow=False):
                continue
            if has_images and destination.exists() and item.name in _PIXEL_FILES:
                raise DatasetError(f"{destination}: differs from {item}, the model the "
                                   f"dataset's images of {target.parent.name} were rendered "
                                   f"from; render into another folder, or use --overwrite")
            with atomic_path(destination) as tmp:
                shutil.copyfile(item, tmp)


def _check_same_model(source: Path, target: Path) -> None:
    """A finished model of the dataset (``target``, its copied model files) against the
    library's (``source``): its images are of the library's model unless its mesh or samples
    differ (another library with a model of the same name, or a model generated again). The
    model cards compared first (a few hundred bytes): equal cards are the same model."""
    card = "model_card.json"
    if not source.is_dir() or ((source / card).is_file() and (target / card).is_file()
                               and filecmp.cmp(source / card, target / card, shallow=False)):
        return  # a model the library no longer has is kept as rendered
    for name in _PIXEL_FILES:
        mine, theirs = target / name, source / name
        if mine.is_file() and theirs.is_file() and not filecmp.cmp(mine, theirs, shallow=False):
            raise DatasetError(f"{mine}: differs from {theirs}, the model the dataset's images "
                               f"of {target.parent.name} were rendered from; render into "
                               "another folder, or use --overwrite")


def render_image(scene: Any, vertices: np.ndarray, options: RenderOptions, model: str,
                 index: int, model_out: Path) -> None:
    """Render image ``index`` of ``model`` with ``scene`` (a :class:`SpaceScene`) and write its
    image, mask (and EXR), then its progress label (with the image's exposure and the target's
    visibility, see :func:`label_entry`), all atomically."""
    name = f"{index:06d}"
    if options.pass_frames > 1:
        frame = sample_pass_frame(vertices, scene.camera, options.scene, options.seed, model,
                                  index, options.pass_frames)
    else:
        frame = sample_frame(vertices, scene.camera, options.scene, options.seed, model, index)
    result = scene.render(frame)
    write_png(model_out / IMAGES / f"{name}.png", result.image_8bit())
    write_png(model_out / MASKS / f"{name}.png", result.mask)
    if options.exr:
        write_exr(model_out / "exr" / f"{name}.exr",
                  {"Y": result.radiance, "Z": result.depth, "A": result.coverage})
    # The label is the commit marker: written last, it says the image is complete.
    label = label_entry(f"{name}.png", frame, result)
    if options.pass_frames > 1:
        label.update({"pass": index // options.pass_frames,
                      "frame_in_pass": index % options.pass_frames})
    atomic_write_json(model_out / PROGRESS / f"{name}.json", label)


# ------------------------------------------------------------------------ per model


def _name(index: int) -> str:
    return f"{index:06d}"


def _assembled(model_out: Path) -> list[Any]:
    """The model's ``labels.json`` entries ([] where there is none yet)."""
    path = model_out / "labels.json"
    if not path.is_file():
        return []
    return read_labels(path)


def _image_done(model_out: Path, index: int, assembled: list[Any], exr: bool) -> bool:
    """Image ``index`` is complete: its label (progress file, or assembled) and its files."""
    name = _name(index)
    if index >= len(assembled) and not (model_out / PROGRESS / f"{name}.json").is_file():
        return False
    pictures = [model_out / IMAGES / f"{name}.png", model_out / MASKS / f"{name}.png"]
    if exr and not (model_out / EXR / f"{name}.exr").is_file():
        return False
    return all(_png_complete(path) for path in pictures)


_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the IEND chunk every whole PNG ends with


def _png_complete(path: Path) -> bool:
    """Whether ``path`` is a file ending as a PNG does: a file deleted or cut short since it
    was written (the writes themselves are atomic) is rendered again; twelve bytes read."""
    try:
        with open(path, "rb") as file:
            file.seek(-len(_PNG_END), os.SEEK_END)
            return file.read() == _PNG_END
    except OSError:  # missing, or shorter than the chunk
        return False


def _remove_stray_temps(model_out: Path, index: int) -> None:
    """Delete temporary files of image ``index`` that a killed run left behind (atomic writes
    name them ``.<name>.<random>.tmp<suffix>``); the image is about to be rendered again."""
    for folder in (IMAGES, MASKS, EXR, PROGRESS):
        for stray in (model_out / folder).glob(f".{_name(index)}.*.tmp*"):
            stray.unlink(missing_ok=True)


def _remove_tree(path: Path) -> None:
    """Delete a folder that another process may be deleting at the same time."""
    shutil.rmtree(path, ignore_errors=True)
    if path.exists():
        shutil.rmtree(path)  # still there: a real problem, raise it


def _assemble(model_out: Path, count: int) -> bool:
    """Write ``labels.json`` once all ``count`` images of a model are done; True when it is
    complete. Safe against another process assembling the same model at the same time."""
    progress = model_out / PROGRESS
    assembled = _assembled(model_out)
    if len(assembled) == count:
        if progress.exists():
            _remove_tree(progress)
        return True
    labels = []
    for index in range(count):
        try:
            labels.append(read_json(progress / f"{_name(index)}.json"))
            continue
        except FileNotFoundError:
            pass
        if index < len(assembled):  # grown dataset: the first images are assembled already
            labels.append(assembled[index])
        else:  # not done yet, or another process assembled it and removed .progress
            return len(_assembled(model_out)) == count
    atomic_write_json(model_out / "labels.json", labels)
    _remove_tree(progress)
    return True


def render_model(models_dir: Path, out_dir: Path, model: str, camera: Camera,
                 options: RenderOptions, tick: Callable[[int], None] = lambda n: None,
                 indices: Sequence[int] | None = None) -> tuple[int, int]:
    """Render (or finish) images ``indices`` (default: all) of one model, then assemble its
    ``labels.json`` if every image of it is done; return (rendered, skipped)."""
    from sq_mitsuba.render.space import SpaceScene

    count = options.images_per_model
    indices = range(count) if indices is None else indices
    model_out = out_dir / model
    _clear_failure(out_dir, model, options.shard)
    try:
        assembled = _assembled(model_out)
    except DatasetError as error:  # damaged after the fact: the images can be rendered again
        raise DatasetError(f"{error}; delete {model_out} and run again to render the model "
                           "anew (the same settings give the same images)") from None
    if len(assembled) > count:
        raise DatasetError(f"{model_out / 'labels.json'}: {len(assembled)} labels, more than "
                           f"images_per_model {count}")
    todo = [i for i in indices if not _image_done(model_out, i, assembled, options.exr)]
    if len(assembled) == count and not todo:
        tick(len(indices))
        _assemble(model_out, count)  # removes a .progress left by a concurrent assembly
        _clear_failures(out_dir, model)
        return 0, len(indices)
    skipped = len(indices) - len(todo)
    tick(skipped)
    if todo:
        vertices, faces, tags = load_model(models_dir / model)
        check_model_points(models_dir / model)  # a NaN point would pass on to every reader
        has_images = bool(assembled) or any((model_out / PROGRESS).glob("*.json"))
        _copy_model_files(models_dir / model / MODELS, model_out / MODELS, has_images)
        (model_out / PROGRESS).mkdir(parents=True, exist_ok=True)
        scene = SpaceScene(vertices, faces, tags, camera, options.scene, spp=options.spp,
                           dataset_seed=options.seed, with_depth=options.exr)
        for index in todo:
            _remove_stray_temps(model_out, index)
            render_image(scene, vertices, options, model, index, model_out)
            tick(1)
    if _assemble(model_out, count):
        _clear_failures(out_dir, model)
    return len(todo), skipped


# ------------------------------------------------------------------------ failures


def _failure_path(out_dir: Path, model: str, shard: str) -> Path:
    index, count = parse_shard(shard)
    return out_dir / FAILURE_MARKS / model / f"{index}-of-{count}.json"


def _record_failure(out_dir: Path, model: str, shard: str, reason: str) -> None:
    atomic_write_json(_failure_path(out_dir, model, shard),
                      {"model": model, "shard": shard, "reason": reason})


def _clear_failure(out_dir: Path, model: str, shard: str) -> None:
    """This shard retries ``model``: its own record of an earlier failure goes."""
    _failure_path(out_dir, model, shard).unlink(missing_ok=True)


def _clear_failures(out_dir: Path, model: str) -> None:
    """``model`` is complete: every shard's failure record of it goes."""
    folder = out_dir / FAILURE_MARKS / model
    if folder.exists():
        _remove_tree(folder)
    try:
        (out_dir / FAILURE_MARKS).rmdir()  # only when empty
    except OSError:
        pass


def recorded_failures(out_dir: Path) -> dict[str, str]:
    """{model: reason} of every failure record (the lowest-numbered shard's reason)."""
    failures: dict[str, str] = {}
    root = Path(out_dir) / FAILURE_MARKS
    if not root.is_dir():
        return failures
    for folder in sorted(root.iterdir()):
        for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
            try:
                record = read_json(path)
                failures[folder.name] = str(record["reason"])
                break
            except (OSError, ValueError, KeyError, TypeError):
                continue  # vanished or half-read: another process is clearing it
    return failures


def _shown(name: str) -> str:
    """A file name for a one-line message (quoted where it holds a line break or the like)."""
    return name if name.isprintable() else repr(name)


def _foreign_entries(out_dir: Path) -> list[str]:
    """What ``out_dir`` holds (folders with a trailing '/'), leaving out the temporary files
    of atomic writes (:data:`TEMPORARY_NAME`, e.g. of a ``dataset.json`` a killed run was
    writing), those of :func:`check_writable` and an output lock: an output folder without a
    manifest must hold nothing else to be rendered into."""
    if not out_dir.is_dir():
        return []
    return [_shown(p.name) + ("/" if p.is_dir() and not p.is_symlink() else "")
            for p in sorted(out_dir.iterdir())
            if not (p.is_file() and (TEMPORARY_NAME.fullmatch(p.name) or p.name.endswith(LOCK_NAME)
                                     or p.name.startswith(".write-test.")))]


def _overwrite_targets(out_dir: Path, manifest: dict[str, Any]) -> list[Path]:
    """What ``overwrite`` deletes from ``out_dir``, whose valid ``manifest`` lists its models
    (see :data:`OVERWRITE_DELETES`), every entry checked first to be of the kind the tool
    writes there: a link or a file of another kind is a one-line :class:`DatasetError`
    before anything is deleted (not a half-cleared folder)."""
    targets: list[Path] = []
    folders = [out_dir / FAILURE_MARKS, *(out_dir / model for model in sorted(manifest["models"]))]
    for path, kind in [*((out_dir / name, "file") for name in OVERWRITE_DELETES),
                       *((folder, "folder") for folder in folders)]:
        if not path.exists() and not path.is_symlink():
            continue
        if path.is_symlink() or not (path.is_file() if kind == "file" else path.is_dir()):
            what = "a symbolic link" if path.is_symlink() else \
                f"not a {kind} ({'a folder' if path.is_dir() else 'another kind of file'})"
            raise DatasetError(f"{path}: {what} where this tool writes a {kind}, so not the "
                               "tool's to delete; nothing was changed (--overwrite): move it "
                               "away, or choose another --out")
        targets.append(path)
    targets += [path for path in sorted(out_dir.iterdir()) if TEMPORARY_NAME.fullmatch(path.name)
                and path.is_file() and not path.is_symlink()]
    return targets


def _clear_dataset(targets: Sequence[Path]) -> None:
    """Delete ``targets`` (:func:`_overwrite_targets`, checked): ``--overwrite``."""
    for path in targets:
        if path.is_dir() and not path.is_symlink():
            _remove_tree(path)
        else:
            path.unlink(missing_ok=True)


def _write_json_if_changed(path: Path, obj: Any) -> None:
    """:func:`atomic_write_json`, skipped where the file already holds these bytes."""
    text = json.dumps(obj, indent=2) + "\n"
    try:
        if path.read_text(encoding="utf-8") == text:
            return
    except (OSError, UnicodeDecodeError):
        pass
    atomic_write_text(path, text)


def _file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def finalize_dataset(out_dir: Path, options: RenderOptions, camera: Camera,
                     plan: dict[str, str]) -> tuple[bool, dict[str, str]]:
    """Once every model of ``plan`` is settled (complete, or failed in some shard), write
    ``splits.csv`` (complete models only), ``failures.json`` (or remove a stale one) and the
    final manifest. Returns (complete, failures). Its files are a function of the folder's
    content alone, so processes finishing at once write the same bytes."""
    count = options.images_per_model
    marks = recorded_failures(out_dir)
    counts: dict[str, int] = {}
    hashes: dict[str, str] = {}
    settled = True
    for model in sorted(plan):
        try:
            labels = _assembled(out_dir / model)
        except DatasetError as error:
            marks.setdefault(model, str(error))
            labels = []
        counts[model] = len(labels)
        if len(labels) == count:
            hashes[model] = _file_sha256(out_dir / model / "labels.json")
        elif model not in marks:
            settled = False
    failures = {m: marks[m] for m in sorted(plan) if counts[m] != count and m in marks}
    if not settled:
        return False, failures
    rows = [(m, plan[m]) for m in sorted(plan) if counts[m] == count]
    splits_path = out_dir / "splits.csv"  # compared as write_splits would write it
    if not splits_path.is_file() or \
            splits_path.read_text(encoding="utf-8") != splits_text(rows):
        write_splits(out_dir, rows)
    if failures:
        _write_json_if_changed(out_dir / FAILURES, failures)
    else:
        (out_dir / FAILURES).unlink(missing_ok=True)
    _write_json_if_changed(out_dir / MANIFEST,
                           manifest_record(options, camera, plan, counts, "complete", hashes))
    return True, failures


def _shard_work(models: Sequence[str], count: int, shard: str) -> dict[str, range]:
    """Image indices per model of block I of N of all (model, index) pairs, in order."""
    index, shards = parse_shard(shard)
    total = len(models) * count
    start, stop = index * total // shards, (index + 1) * total // shards
    work = {}
    for position, model in enumerate(models):
        low, high = max(start, position * count), min(stop, (position + 1) * count)
        if low < high:
            work[model] = range(low - position * count, high - position * count)
    return work


# ------------------------------------------------------------------------ dataset


#: A worker's queue of images done, to its parent (:func:`_render_in_workers`).
_worker_ticks: Any = None


def _start_worker(threads: int, ticks: Any = None) -> None:
    import drjit as dr

    from sq_mitsuba.render.backend import mitsuba

    global _worker_ticks
    _worker_ticks = ticks
    mitsuba()
    dr.set_thread_count(threads)


def _tick_parent(model: str, count: int) -> None:
    """A worker's ``tick``: ``count`` images of ``model`` done, told to the parent."""
    if _worker_ticks is not None and count:
        _worker_ticks.put((model, count))


def _render_in_workers(models_dir: Path, out_dir: Path, camera: Camera, options: RenderOptions,
                       work: dict[str, list[int]], bar: Any,
                       record: Callable[[str, Any], None]) -> None:
    """Render ``work`` ({model: image indices}) in ``options.workers`` processes, one model a
    job, the bar moving by image (each worker tells its parent every image it finishes) rather
    than by model (minutes apart with a thousand images a model)."""
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, wait

    from sq_mitsuba.processes import worker_pool

    threads = max(1, (os.cpu_count() or 1) // options.workers)
    ticks = multiprocessing.get_context("spawn").SimpleQueue()
    shown = dict.fromkeys(work, 0)  # images of each model on the bar

    def drain() -> None:
        while not ticks.empty():
            model, count = ticks.get()
            count = min(count, len(work[model]) - shown[model])  # a late tick: never past
            shown[model] += count
            bar.update(count)

    with contextlib.closing(ticks), worker_pool(options.workers, _start_worker,
                                                (threads, ticks)) as pool:
        jobs = {pool.submit(render_model, models_dir, out_dir, model, camera, options,
                            tick=functools.partial(_tick_parent, model), indices=indices): model
                for model, indices in work.items()}
        running = set(jobs)
        while running:
            finished, running = wait(running, timeout=0.5, return_when=FIRST_COMPLETED)
            drain()
            for job in finished:
                model = jobs[job]
                try:
                    outcome = job.result()
                except (DatasetError, OSError, ValueError) as error:
                    outcome = error
                record(model, outcome)
                bar.update(len(work[model]) - shown[model])  # a failed model's rest too
                shown[model] = len(work[model])


def _existing_manifest(out_dir: Path, overwrite: bool) -> dict[str, Any] | None:
    """The output folder's manifest (None: none there); a malformed one, or one of another
    tool or version, is a one-line error: its folder is neither rendered into nor, with
    ``overwrite``, cleared (only a dataset of this tool is)."""
    if not out_dir.is_dir():
        return None
    try:
        return read_manifest(out_dir)
    except DatasetError as error:
        if overwrite:
            raise DatasetError(f"{error}; --overwrite clears only a dataset of this tool, so "
                               "nothing was changed: choose another --out") from None
        raise


def prepare_dataset(models_dir: Path, out_dir: Path, options: RenderOptions
                    ) -> tuple[Camera, dict[str, str]]:
    """Every check before work, then the manifest and ``camera.json``: returns the camera and
    the plan {model: split}. Raises ``DatasetError`` having touched no file where the folder
    holds a dataset of other settings (unless ``options.overwrite``)."""
    camera = options.dataset_camera()
    check_render_resources(camera, options)
    if options.images_per_model % options.pass_frames:  # a short last pass: refused by passes
        whole = options.pass_frames * max(1, options.images_per_model // options.pass_frames)
        raise DatasetError(f"pass_frames (--pass-frames) {options.pass_frames} does not divide "
                           f"images_per_model (--images-per-model) {options.images_per_model}: "
                           f"the last pass would be short; give a multiple, e.g. {whole}")
    found = find_models(models_dir)
    check_disk_room(out_dir, camera, options.images_per_model * len(found)
                    // options.shard_count)
    if inside_folder(out_dir, models_dir):  # inside: a folder the library reads as a model
        where = "the model library" if out_dir.resolve() == models_dir.resolve() else \
            f"inside the model library {models_dir}"
        raise DatasetError(f"{out_dir}: the output folder is {where}; render into another "
                           "folder")
    library_splits = read_splits(models_dir / "splits.csv") \
        if (models_dir / "splits.csv").is_file() else {}
    unlisted = [model for model in found if model not in library_splits] if library_splits \
        else []
    if unlisted:  # a split is not guessed: a held-out model would silently train
        twins = _normalisation_twins(unlisted, library_splits)
        hint = (f"folder {twins[0][0]!a} and row {twins[0][1]!a} look alike but "
                "differ in Unicode normalisation (NFC vs NFD: other code points for the same "
                "letters); rename the folder or rewrite the row so that the two match") \
            if twins else ("an interrupted `models generate`? run it again to finish the "
                           "library; else add their rows, model,train or model,test")
        raise DatasetError(f"{models_dir / 'splits.csv'}: no row for {len(unlisted)} model "
                           f"folder(s) ({', '.join(unlisted[:3])}"
                           f"{', ...' if len(unlisted) > 3 else ''}), so their split is not "
                           f"known ({hint})")
    manifest = _existing_manifest(out_dir, options.overwrite)
    if manifest is None:  # only a new or empty folder is rendered into (or cleared) then
        held = _foreign_entries(out_dir)
        # Another shard may have started this dataset since: its manifest comes first.
        manifest = _existing_manifest(out_dir, options.overwrite) if held else None
        if held and manifest is None:
            shown = ", ".join(held[:3]) + (", ..." if len(held) > 3 else "")
            raise DatasetError(f"{out_dir}: not empty ({shown}) and holds no {MANIFEST} of "
                               "this tool, so nothing there is known to be its own; nothing "
                               "was changed: choose another --out (a new or empty folder)")
    settings = dataset_settings(options, camera)
    if manifest is not None and not options.overwrite:
        differences = settings_differences(manifest, settings, options.scene)
        if differences:
            raise DatasetError(f"{out_dir / MANIFEST}: this dataset was rendered with other "
                               f"settings: {'; '.join(differences)}; nothing was changed "
                               f"(use --overwrite to start over, or another --out)")
        if options.images_per_model < manifest["images_per_model"]:
            raise DatasetError(f"{out_dir / MANIFEST}: images_per_model "
                               f"{options.images_per_model} is below the dataset's "
                               f"{manifest['images_per_model']}; a dataset grows but does not "
                               f"shrink (use --overwrite to start over, or another --out)")
    old_models = sorted(manifest["models"]) if manifest is not None else []
    for model in sorted(set(found) | set(old_models)):  # what the run writes into
        folder = check_model_folder(out_dir, model, _MODEL_SUBFOLDERS)
        if model not in old_models and (folder.exists() or folder.is_symlink()) and \
                model not in (_existing_manifest(out_dir, False) or {"models": {}})["models"]:
            # (read again: another shard may have started the dataset since)
            raise DatasetError(f"{folder}: exists, but {MANIFEST} does not list the model, so "
                               "the folder is not this tool's; nothing was changed: move it "
                               "away, or choose another --out")
    # Everything --overwrite deletes, checked now: refused whole, never half-cleared.
    doomed = _overwrite_targets(out_dir, manifest) if options.overwrite and \
        manifest is not None else []
    if not options.overwrite:  # images of another model under one name: before any work
        for model in sorted(set(found) & set(old_models)):
            _check_same_model(models_dir / model / MODELS, out_dir / model / MODELS)
    # The library models of this shard's work read now: a broken one stops the run here.
    kept = [] if options.overwrite else old_models
    work = _shard_work(sorted(set(found) | set(kept)), options.images_per_model, options.shard)
    check_library_models(models_dir, [model for model in work if model in found])
    check_writable(out_dir, work)
    if options.overwrite:
        _clear_dataset(doomed)
        manifest, old_models = None, []
    plan, guessed = {}, []
    for model in sorted(set(found) | set(old_models)):
        old_split = manifest["models"][model].get("split") if manifest is not None and \
            model in manifest["models"] else None
        # Without the library's splits.csv, the model's card says (a test model must not
        # train); then the split the dataset already has; train only where nothing says.
        split = library_splits.get(model) or \
            (_card_split(models_dir, model) if model in found else None) or old_split
        if split is None:
            guessed.append(model)
        plan[model] = split or "train"
    if guessed:
        warnings.warn(f"{models_dir}: no splits.csv and no split in the model card of "
                      f"{len(guessed)} model(s) ({', '.join(guessed[:3])}"
                      f"{', ...' if len(guessed) > 3 else ''}): rendered as train models",
                      stacklevel=3)
    fresh = manifest_record(options, camera, plan, {}, "rendering")
    if manifest is None or manifest_plan(manifest) != manifest_plan(fresh):
        counts = {}
        for model in plan:
            try:
                counts[model] = len(_assembled(out_dir / model))
            except DatasetError:
                counts[model] = 0
        atomic_write_json(out_dir / MANIFEST,
                          manifest_record(options, camera, plan, counts, "rendering"))
    _write_json_if_changed(out_dir / "camera.json", camera.to_speed_dict())
    return camera, plan


def render_dataset(models_dir: str | Path, out_dir: str | Path,
                   options: RenderOptions | None = None, progress: bool = True,
                   workers: int | None = None) -> RenderSummary:
    """Render every model of ``models_dir`` into ``out_dir`` in the SPE3R layout.

    See the module docstring for the manifest, resuming, growing, shards and failures. A
    model that fails is reported and skipped; the others go on. ``workers`` (default
    ``options.workers``) processes render models in parallel, sharing the cores (each
    worker's images are identical to a single-process run: every image has its own seed).
    Bad options and folders are ``ValueError`` s raised before any file is written; a folder
    another render writes into (without shards, or a shard beside a render without) is
    refused in one line, before any work.
    """
    options = options if options is not None else RenderOptions()
    if workers is not None:
        options = dataclasses.replace(options, workers=workers)
    validate(options)
    models_dir, out_dir = Path(models_dir), Path(out_dir)
    # One run at a time per folder, but the shards of one render together: a render without
    # shards (or one that overwrites) holds the folder alone, a shard shares it with shards.
    # The manifest's check and write are one shard's at a time: two shards of other settings
    # started together each found no manifest and mixed their images in one dataset.
    with output_lock(out_dir, shared=options.shard_count > 1, command="dataset render"):
        with output_lock(out_dir / MANIFEST, file=True, wait=True):
            camera, plan = prepare_dataset(models_dir, out_dir, options)
        return _render_planned(models_dir, out_dir, options, camera, plan, progress)


def _render_planned(models_dir: Path, out_dir: Path, options: RenderOptions, camera: Camera,
                    plan: dict[str, str], progress: bool) -> RenderSummary:
    """:func:`render_dataset` once the folder is prepared: this shard's images, then the
    dataset's bookkeeping (the manifest's lock held for it)."""
    from sq_mitsuba.progress import progress_bar

    work = _shard_work(sorted(plan), options.images_per_model, options.shard)
    summary = RenderSummary(shard=options.shard)
    total = sum(len(indices) for indices in work.values())
    with progress_bar(total=total, unit="img", disable=not progress, dynamic_ncols=True) as bar:

        def record(model: str, outcome: tuple[int, int] | BaseException) -> None:
            if isinstance(outcome, BaseException):
                reason = str(outcome) or type(outcome).__name__
                summary.failures[model] = reason
                _record_failure(out_dir, model, options.shard, reason)
                bar.write(f"failed: {model}: {reason}")
                return
            summary.rendered += outcome[0]
            summary.skipped += outcome[1]
            summary.models_done.append(model)

        if options.workers == 1 or len(work) <= 1:
            for model, indices in work.items():
                bar.set_description(model)
                try:
                    outcome = render_model(models_dir, out_dir, model, camera, options,
                                           tick=bar.update, indices=indices)
                except (DatasetError, OSError, ValueError) as error:
                    outcome = error
                record(model, outcome)
        else:
            _render_in_workers(models_dir, out_dir, camera, options, work, bar, record)
    summary.models_done.sort()
    with output_lock(out_dir / MANIFEST, file=True, wait=True):
        summary.complete, failures = finalize_dataset(out_dir, options, camera, plan)
    # Failures of other shards (and of earlier runs not retried here) count too.
    summary.failures = dict(sorted({**failures, **summary.failures}.items()))
    return summary
