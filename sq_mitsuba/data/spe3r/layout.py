"""The SPE3R dataset layout: paths, splits, labels and model files, shared by every role.

Layout (our datasets and the SPE3R release alike)::

    <root>/camera.json                    SPEED-style intrinsics
    <root>/splits.csv                     "model,train" / "model,test", no header (CSV)
    <root>/<model>/labels.json            [{filename, q_vbs2tango_true, r_Vo2To_vbs_true, ...}]
    <root>/<model>/images/<index>.png     8-bit grayscale (.jpg accepted on read)
    <root>/<model>/masks/<index>.png      binary mask of the target alone
    <root>/<model>/models/                model_normalized.obj (+ samples.npz, model_card.json)

Our datasets add their bookkeeping (see :mod:`.writer`)::

    <root>/dataset.json                   manifest: how the dataset was made, image counts
    <root>/failures.json                  {model: reason} of models left out of splits.csv
    <root>/.failures/<model>/<I>-of-<N>.json   why shard I of N failed a model (until it works)
    <root>/<model>/.progress/<index>.json      labels of finished images of an unfinished model

Splits: ``splits.csv`` names the train and test models; ``val`` holds images
[0.4 n, 0.5 n) and [0.9 n, n) of each training model with n its image count, exactly SPE3R's
400-499 and 900-999 at n = 1000 (:func:`is_validation`), ``train`` the rest of them.

Convention: a label's pose maps body to camera (OpenCV frame: x right, y down, z forward),
``x_cam = R x_body + t`` with R the Hamilton matrix of the scalar-first quaternion
``q_vbs2tango_true`` and t = ``r_Vo2To_vbs_true`` in metres. Extra keys (lighting record, seed)
are ignored by SPE3R readers.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from sq_mitsuba.inputs import open_image
from sq_mitsuba.io import atomic_path, atomic_write_text, read_json

IMAGES, MASKS, MODELS, PROGRESS = "images", "masks", "models", ".progress"
EXR = "exr"
MESH_FILE = "model_normalized.obj"
SAMPLES_FILE = "samples.npz"
MANIFEST = "dataset.json"
FAILURES = "failures.json"
FAILURE_MARKS = ".failures"
MANIFEST_FORMAT = "sq-mitsuba-dataset/1"
"""``format`` of the manifest; a reader refuses another one."""
#: Largest deviation of a label quaternion's norm from 1 that readers accept.
QUATERNION_NORM_TOLERANCE = 1e-3


class DatasetError(ValueError):
    """A dataset or model folder that cannot be used; the message names the file."""


def is_validation(index: int, count: int) -> bool:
    """Whether image ``index`` of a training model with ``count`` images is in ``val``.

    ``val`` = [0.4 n, 0.5 n) and [0.9 n, n) with n = ``count``, as real intervals (compared in
    integers, so there is no rounding): SPE3R's 400-499 and 900-999 at n = 1000, images 4 and 9
    at n = 10, 16-19 and 36-39 at n = 40. Every n >= 10 has at least two; smaller datasets may
    have none (n = 3 or 8: none).
    """
    return (4 * count <= 10 * index and 2 * index < count) or 9 * count <= 10 * index < 10 * count


def validation_indices(count: int) -> list[int]:
    """The ``val`` image indices of a training model with ``count`` images, sorted."""
    return [i for i in range(count) if is_validation(i, count)]


#: SPE3R v1.1 validation images of each training model (1000 images each).
VALIDATION_INDICES = frozenset(validation_indices(1000))


# ------------------------------------------------------------------------ model names


def model_name_problem(name: Any) -> str | None:
    """Why ``name`` is not a usable model name (None: it is one).

    A model name becomes a folder path (``root/<model>``, ``.failures/<model>``) in every
    reader and writer, and comes from files a library or dataset brings along (``splits.csv``,
    ``dataset.json``): only one plain path component is accepted, so that no name reaches
    outside its folder (an absolute name replaces the root in ``root / name``, ``..`` climbs
    out of it) or names a hidden entry of the tool's own (``.failures``, ``.progress``).
    """
    if not isinstance(name, str) or not name:
        return "empty"
    if name in (".", ".."):
        return "not a folder name"
    if name.startswith(("/", "\\")):
        return "an absolute path"
    if "/" in name or "\\" in name:
        return "contains a path separator"
    if name.startswith("."):
        return "starts with '.'"
    if any(ord(c) < 32 or 127 <= ord(c) < 160 for c in name):  # NUL, newline, escapes
        return "contains a control character"
    if name != name.strip():  # ' cube' and 'cube' look alike in every listing: a trap
        return "starts or ends with white space"
    try:  # a file system's non-UTF-8 byte comes as a surrogate escape: no file can hold it
        name.encode("utf-8")
    except UnicodeEncodeError:
        return "not valid UTF-8 (a raw byte of the file system's name)"
    return None


def check_model_name(name: Any, where: str) -> str:
    """``name`` where it is a plain model name (:func:`model_name_problem`), else a one-line
    :class:`DatasetError` beginning with ``where`` (the file, and its row)."""
    problem = model_name_problem(name)
    if problem is not None:
        shown = repr(name)  # quoted: a control character cannot break the line
        shown = shown if len(shown) <= 200 else shown[:197] + "..."
        raise DatasetError(f"{where}: model name {shown} is not a plain folder name "
                           f"({problem}); refused")
    return name


def check_model_folder(root: Path, model: str, inner: Iterable[str] = (MODELS,)) -> Path:
    """``root/model`` where it is no symbolic link and resolves to a folder inside ``root``
    (or does not exist yet), and where none of its entries ``inner`` is a symbolic link;
    else a one-line :class:`DatasetError`: through a link, a model's files would be read
    from, and a dataset's written to, another place than the folder given."""
    root = Path(root)
    folder = root / check_model_name(model, str(root))
    for path in (folder, *(folder / name for name in inner)):
        if path.is_symlink():
            target = os.readlink(path)  # quoted where it would break the line
            target = target if target.isprintable() else repr(target)
            raise DatasetError(f"{path}: a symbolic link (to {target}); "
                               f"a model's files are read and written inside {root} only, "
                               "not through links: refused")
    if folder.exists() and folder.resolve().parent != root.resolve():
        raise DatasetError(f"{folder}: resolves to {folder.resolve()}, outside {root}; refused")
    return folder


# ------------------------------------------------------------------------ small helpers


def read_splits(path: Path) -> dict[str, str]:
    """``splits.csv`` as {model: "train" | "test"}; a model listed in both splits, or a model
    name that is not one plain folder name (:func:`model_name_problem`), is a one-line
    ``DatasetError`` naming the line (the later row would silently win; such a name would
    lead readers and writers outside the folder).

    Rows are CSV (:func:`splits_text`: a name holding a comma or a double quote is quoted),
    read strictly: a quote that CSV cannot place is refused, never read as another name.
    Files of older versions, written without quoting, read as before, and a row of theirs
    whose name holds commas (``twin, wing,train``: more than two fields, no quote) reads as
    that name, since their split never holds a comma. Names are not stripped (the folder
    `` cube`` is not ``cube``): a name with white space around it is refused, naming it.
    """
    splits: dict[str, str] = {}
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise DatasetError(f"{path}: not UTF-8 text ({error.reason} at byte {error.start})") \
            from None
    # Line by line (newline="": CSV's own line ends only): a name holds no line break, so
    # no quoted field spans two lines, and an unclosed quote is refused on its own line.
    for line_number, line in enumerate(io.StringIO(text, newline=""), start=1):
        try:
            row = next(csv.reader([line], strict=True), [])
        except csv.Error as error:
            shown = line.rstrip("\r\n")
            raise DatasetError(f"{path}:{line_number}: not a CSV row ({error}): "
                               f"{shown!r}; a name holding a comma "
                               "or a double quote is written in double quotes, any quote in "
                               "it doubled") from None
        if not row:
            continue
        if len(row) > 2 and '"' not in line:  # an older version's unquoted row
            row = [",".join(row[:-1]), row[-1]]
        if len(row) != 2 or row[1].strip() not in ("train", "test"):
            raise DatasetError(f"{path}:{line_number}: expected 'model,train|test', "
                               f"got {','.join(row)!r}")
        # A blank name is an empty one; any other keeps its spaces (refused below).
        model, split = row[0] if row[0].strip() else "", row[1].strip()
        check_model_name(model, f"{path}:{line_number}")
        if splits.get(model, split) != split:
            raise DatasetError(f"{path}:{line_number}: {model!r} is listed as "
                               f"{splits[model]} above and as {split} here")
        splits[model] = split
    return splits


def splits_text(rows: Iterable[tuple[str, str]]) -> str:
    """The text of a ``splits.csv`` of ``rows`` (``model,train|test``, no header): CSV, so a
    name holding a comma or a double quote is quoted and reads back as itself
    (:func:`read_splits`); plain names give the bytes of older versions (``name,split``)."""
    buffer = io.StringIO()
    csv.writer(buffer, lineterminator="\n").writerows(rows)
    return buffer.getvalue()


def write_splits(out_root: str | Path, rows: Iterable[tuple[str, str]]) -> Path:
    """Write ``splits.csv`` (:func:`splits_text` of ``rows``) atomically; a name that
    :func:`read_splits` would refuse is a one-line :class:`DatasetError` before writing."""
    path = Path(out_root) / "splits.csv"
    rows = list(rows)
    for name, _ in rows:
        check_model_name(name, str(path))
    atomic_write_text(path, splits_text(rows))
    return path


def write_png(path: Path, array: np.ndarray) -> None:
    """8-bit grayscale PNG, written atomically (deterministic bytes for the same array)."""
    with atomic_path(path) as tmp:
        Image.fromarray(array, mode="L").save(tmp, format="PNG", optimize=False)


def check_outside_datasets(out: Path, data_root: Path | None, command: str) -> None:
    """Refuse an output ``out`` (a file or folder to write) inside ``data_root`` or inside any
    dataset folder (one holding a ``dataset.json`` manifest): it would become part of a
    dataset, which ``command`` only reads (as ``eval`` and ``train`` refuse their outputs
    there, and ``dataset check`` would then flag it).

    Raises:
        ValueError: ``out <out>: inside the dataset folder <folder> ...``.
    """
    from sq_mitsuba.io import inside_folder

    folders = [] if data_root is None or not inside_folder(out, data_root) else [data_root]
    resolved = Path(out).resolve()  # links followed, as inside_folder does; out itself too
    folders += [folder for folder in (resolved, *resolved.parents)
                if (folder / MANIFEST).is_file()]
    if folders:
        raise ValueError(f"out {out}: inside the dataset folder {folders[0]}, which {command} "
                         "only reads; write outside it")


def write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    """Float32 channels (H, W) into one OpenEXR file, atomically."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    data = {name: np.ascontiguousarray(array, dtype=np.float32)
            for name, array in channels.items()}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, data) as exr:
            exr.write(str(tmp))


def load_model(model_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertices (V, 3), faces (F, 3) and per-face material tags (F,) or None of a model.

    The OBJ is read in file order (trimesh regroups the faces of multi-material OBJs, which
    would detach them from the per-face tags of ``samples.npz``).
    """
    from sq_mitsuba.data.mesh_io import (
        NOT_AN_NPZ,
        NpzArrayTooLarge,
        check_face_material,
        check_npz_array,
        read_obj,
    )
    from sq_mitsuba.render.materials import MATERIALS

    mesh_path = model_dir / MODELS / MESH_FILE
    if not mesh_path.is_file():
        raise DatasetError(f"{mesh_path}: missing")
    try:
        vertices, faces, _ = read_obj(mesh_path)
    except (OSError, ValueError, IndexError) as error:
        raise DatasetError(f"{mesh_path}: cannot read mesh ({error})") from None
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(vertices) < 4 or len(faces) < 4 or not np.isfinite(vertices).all() or \
            faces.min() < 0 or faces.max() >= len(vertices):
        raise DatasetError(f"{mesh_path}: not a usable mesh ({len(vertices)} vertices, "
                           f"{len(faces)} faces)")
    tags = None
    samples_path = model_dir / MODELS / SAMPLES_FILE
    if samples_path.is_file():
        try:
            with np.load(samples_path) as samples:
                face_material = None
                if "face_material" in samples:  # one tag per face: no more read than that
                    check_npz_array(samples, "face_material", samples_path, len(faces))
                    face_material = samples["face_material"]
        except NpzArrayTooLarge as error:
            raise DatasetError(str(error)) from None
        except Exception:  # numpy raises several kinds on corrupt archives, and for a file
            # that is no archive advises loading it "unsafely": not repeated here
            raise DatasetError(f"{samples_path}: {NOT_AN_NPZ}") from None
        if face_material is not None:
            try:
                indices = check_face_material(face_material, len(faces), samples_path,
                                              mesh_path)
            except ValueError as error:
                raise DatasetError(str(error)) from None
            tags = np.asarray(MATERIALS)[indices]
    return vertices, faces, tags



def find_image(root: Path, model: str, folder: str, filename: str) -> Path:
    """The file of a label's image or mask, ``root/model/folder/filename``, or the same stem
    as .png, .jpg or .jpeg where that is the file there (SPE3R's labels name .jpg images while
    its masks are .png); the path as named when none exists (its reader says "missing")."""
    path = root / model / folder / filename
    if not path.is_file():
        for suffix in (".png", ".jpg", ".jpeg"):
            if path.with_suffix(suffix).is_file():
                return path.with_suffix(suffix)
    return path


def read_image(path: Path, verify: bool = False) -> Image.Image:
    """The image at ``path`` decoded completely (a truncated file is an error, not a grey
    tail); ``verify`` also checks every chunk's checksum (PNG). One-line DatasetError naming
    the file otherwise (read by :func:`sq_mitsuba.inputs.open_image`, as every image is)."""
    try:
        return open_image(path, "", verify=verify)
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing") from None
    except ValueError as error:
        raise DatasetError(str(error)) from None


def read_gray(path: Path) -> np.ndarray:
    """An 8-bit grayscale image (H, W) uint8, decoded completely (see :func:`read_image`); a
    float image with pixels not finite is refused (converting would hide them)."""
    image = read_image(path)
    if image.mode == "F":
        bad = int((~np.isfinite(np.asarray(image))).sum())
        if bad:
            raise DatasetError(f"{path}: {bad} pixel(s) not finite (NaN or infinite)")
    return np.asarray(image if image.mode == "L" else image.convert("L"))


def resize(array: np.ndarray, size: int, resample: int) -> np.ndarray:
    """``array`` (H, W) resized to (size, size) with PIL's ``resample`` filter."""
    if array.shape == (size, size):
        return array
    return np.asarray(Image.fromarray(array).resize((size, size), resample))


_resize = resize  # former private name


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def label_problem(label: Any) -> str | None:
    """What is wrong with one ``labels.json`` entry (None: usable).

    Checks the keys every reader needs: ``filename`` (a plain file name),
    ``q_vbs2tango_true`` (4 finite numbers of norm 1 within
    :data:`QUATERNION_NORM_TOLERANCE`) and ``r_Vo2To_vbs_true`` (3 finite numbers, z > 0: the
    target in front of the camera).
    """
    if not isinstance(label, dict):
        return f"expected an object, got {_short(label)}"
    filename = label.get("filename")
    if not isinstance(filename, str) or not filename or "/" in filename or \
            "\\" in filename or filename in (".", ".."):
        return f"filename: expected a file name, got {_short(filename)}"
    for key, length in (("q_vbs2tango_true", 4), ("r_Vo2To_vbs_true", 3)):
        value = label.get(key)
        if not isinstance(value, list) or len(value) != length or not all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in value):
            return f"{key}: expected a list of {length} numbers, got {_short(value)}"
        if not all(math.isfinite(v) for v in value):
            return f"{key}: not finite ({_short(value)})"
    norm = math.sqrt(sum(v * v for v in label["q_vbs2tango_true"]))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        return f"q_vbs2tango_true: not a unit quaternion (norm {norm:.6g})"
    if label["r_Vo2To_vbs_true"][2] <= 0:
        return (f"r_Vo2To_vbs_true: the target is not in front of the camera "
                f"(z = {label['r_Vo2To_vbs_true'][2]:g})")
    return None


def read_labels(path: Path) -> list[Any]:
    """A ``labels.json`` as a list (entries unchecked: see :func:`label_problem`); a missing,
    malformed or non-list file is a one-line DatasetError naming it."""
    try:
        labels = read_json(path)
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing") from None
    except (OSError, ValueError) as error:
        raise DatasetError(str(error) if str(path) in str(error) else f"{path}: {error}") \
            from None
    if not isinstance(labels, list):
        raise DatasetError(f"{path}: expected a list of labels, got {type(labels).__name__}")
    return labels


def read_manifest(root: Path) -> dict[str, Any] | None:
    """``root/dataset.json`` (None where there is none: the SPE3R release, or a dataset of an
    older version). A malformed one is a one-line DatasetError naming it."""
    path = Path(root) / MANIFEST
    try:
        manifest = read_json(path)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as error:
        raise DatasetError(str(error) if str(path) in str(error) else f"{path}: {error}") \
            from None
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        found = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise DatasetError(f"{path}: not a dataset manifest of this version (format "
                           f"{_short(found)}, expected {MANIFEST_FORMAT!r})")
    for key, kind in (("settings", dict), ("images_per_model", int), ("models", dict)):
        if not isinstance(manifest.get(key), kind):
            raise DatasetError(f"{path}: {key}: expected {kind.__name__}, got "
                               f"{_short(manifest.get(key))}")
    for model, entry in manifest["models"].items():
        check_model_name(model, f"{path}: models")
        if not isinstance(entry, dict):
            raise DatasetError(f"{path}: models.{model}: expected an object, got "
                               f"{_short(entry)}")
    where = _not_finite(manifest["settings"], "settings")  # Python's json reads NaN
    if where is not None:
        raise DatasetError(f"{path}: {where}: not a finite number")
    return manifest


def _not_finite(value: Any, where: str) -> str | None:
    """The dotted place of the first NaN or infinity in parsed JSON ``value``, or None."""
    if isinstance(value, float) and not math.isfinite(value):
        return where
    items = value.items() if isinstance(value, dict) else \
        enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        found = _not_finite(item, f"{where}.{key}")
        if found is not None:
            return found
    return None


def is_model_library(root: Path) -> bool:
    """Whether ``root`` is a model library rather than a dataset: no ``camera.json`` and no
    dataset manifest, but model folders with their cards (what ``models generate`` writes)."""
    return not (root / "camera.json").exists() and not (root / "dataset.json").exists() \
        and any(root.glob("*/models/model_card.json"))


def balanced_occupancy(points: np.ndarray, inside: np.ndarray, count: int,
                        rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    inside_idx, outside_idx = np.flatnonzero(inside), np.flatnonzero(~inside)
    want_in = min(count // 2, len(inside_idx))
    want_out = count - want_in
    chosen = np.concatenate([
        rng.choice(inside_idx, want_in, replace=False) if want_in else np.empty(0, int),
        rng.choice(outside_idx, want_out, replace=len(outside_idx) < want_out),
    ])
    return points[chosen], inside[chosen]


#: The point sets of ``samples.npz`` that training and evaluation read: name -> the array's
#: kind ("points": (N, 3) finite numbers; "inside": (N,) flags of the points set named).
SAMPLE_ARRAYS: dict[str, str] = {
    "surface_points": "points",
    "uniform_points": "points",
    "uniform_inside": "uniform_points",
    "near_points": "points",
    "near_inside": "near_points",
}


def read_samples(path: Path, keys: Iterable[str] = tuple(SAMPLE_ARRAYS),
                 optional: Iterable[str] = ()) -> dict[str, np.ndarray]:
    """The arrays ``keys`` (of :data:`SAMPLE_ARRAYS`) of a model's ``samples.npz``, checked.

    Point sets must be (N, 3) with N >= 1 and hold finite numbers only; inside flags must have
    one entry per point of their set (read along where not asked for). Every failure is a
    one-line :class:`DatasetError` naming the file and the array: an unreadable archive, a
    missing array (the message lists those it holds), a wrong shape, NaN or infinite values.
    The arrays named in ``optional`` come along, unchecked, where the file holds them (read in
    the same pass over the archive; the caller decides what a bad one means).
    """
    path = Path(path)
    wanted = list(dict.fromkeys(keys))
    for key in list(wanted):
        kind = SAMPLE_ARRAYS.get(key)
        if kind is None:
            raise ValueError(f"keys: {key!r} is not one of {', '.join(SAMPLE_ARRAYS)}")
        if kind != "points" and kind not in wanted:
            wanted.append(kind)
    if not path.is_file():
        raise DatasetError(f"{path}: missing")
    from sq_mitsuba.data.mesh_io import (
        MAX_NPZ_VALUES,
        MAX_SAMPLE_POINTS,
        NOT_AN_NPZ,
        NpzArrayTooLarge,
        check_npz_array,
    )

    arrays: dict[str, np.ndarray] = {}
    try:
        with np.load(path) as samples:
            missing = [key for key in wanted if key not in samples.files]
            if missing:
                held = ", ".join(samples.files) or "no arrays"
                raise DatasetError(f"{path}: no array {missing[0]!r} (needed for the model's "
                                   f"points; the file holds {held})")
            extra_keys = [key for key in optional if key in samples.files and key not in wanted]
            # Sizes from the headers first: a small archive can expand to gigabytes.
            for key in [*wanted, *extra_keys]:
                flags = SAMPLE_ARRAYS.get(key, "points") != "points"
                check_npz_array(samples, key, path,
                                MAX_SAMPLE_POINTS if flags else MAX_NPZ_VALUES)
            for key in wanted:
                arrays[key] = np.asarray(samples[key])
            extra = {key: np.asarray(samples[key]) for key in extra_keys}
    except DatasetError:
        raise
    except NpzArrayTooLarge as error:
        raise DatasetError(str(error)) from None
    except Exception:  # numpy raises several kinds (see load_model)
        raise DatasetError(f"{path}: {NOT_AN_NPZ}") from None
    for key in wanted:
        array, kind = arrays[key], SAMPLE_ARRAYS[key]
        if kind == "points":
            if array.ndim != 2 or array.shape[1:] != (3,) or len(array) == 0 or \
                    not np.issubdtype(array.dtype, np.number):
                raise DatasetError(f"{path}: {key}: expected (N, 3) numbers with N >= 1, got "
                                   f"shape {array.shape} of {array.dtype}")
            finite = np.isfinite(array).all(axis=1)
            if not finite.all():
                raise DatasetError(f"{path}: {key}: {int((~finite).sum())} of {len(array)} "
                                   "points hold NaN or infinite values")
        elif array.shape != (len(arrays[kind]),):
            raise DatasetError(f"{path}: {key}: expected one flag per point of {kind} "
                               f"({len(arrays[kind])}), got shape {array.shape}")
    return {**{key: arrays[key] for key in wanted}, **extra}


def check_model_points(model_dir: Path, keys: Iterable[str] = tuple(SAMPLE_ARRAYS)) -> None:
    """Refuse, before any work, a model whose points cannot be read: a ``samples.npz`` that
    :func:`read_samples` refuses, or, without one, a missing mesh (what the points are then
    sampled from). One-line :class:`DatasetError` naming the file."""
    samples_path = model_dir / MODELS / SAMPLES_FILE
    if samples_path.is_file():
        read_samples(samples_path, keys)
        return
    mesh_path = model_dir / MODELS / MESH_FILE
    if not mesh_path.is_file():
        raise DatasetError(f"{mesh_path}: missing (and no {SAMPLES_FILE} beside it to read "
                           "the model's points from)")


def usable_normals(normals: np.ndarray | None, count: int) -> np.ndarray:
    """(count, 3) the unit outward normals of a ``samples.npz``'s ``count`` surface points as
    read (its ``surface_normals``, None where it holds none: an older release), or zeros where
    there are none or they come in another shape or with non-finite values: normals are an
    optional training target, not a reason to refuse a model."""
    if normals is None or normals.shape != (count, 3) or not np.isfinite(normals).all():
        return np.zeros((count, 3), np.float32)
    return normals


def model_points(model_dir: Path) -> dict[str, np.ndarray]:
    """Surface points (``surface``) with their unit outward normals (``normals``, zero where a
    ``samples.npz`` of an older release holds none) and labelled occupancy points of a model:
    ``samples.npz`` (checked by :func:`read_samples`), or, without one (the SPE3R release),
    samples of its mesh."""
    samples_path = model_dir / MODELS / SAMPLES_FILE
    if samples_path.is_file():
        samples = read_samples(samples_path, optional=("surface_normals",))
        surface = samples["surface_points"]
        return {
            "surface": surface,
            "normals": usable_normals(samples.get("surface_normals"), len(surface)),
            "points": np.concatenate([samples["uniform_points"], samples["near_points"]]),
            "inside": np.concatenate([samples["uniform_inside"],
                                      samples["near_inside"]]).astype(bool),
        }
    # SPE3R release or imported data without our samples: sample the mesh once.
    import trimesh

    from sq_mitsuba.render.depth import RayCaster

    vertices, faces, _ = load_model(model_dir)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    rng = np.random.default_rng(0)
    surface, faces_hit = trimesh.sample.sample_surface(mesh, 100_000, seed=0)
    # The cube around the mesh's box, not the origin (its centre of mass: a long boom on one
    # side would reach out of a cube about it), and as large as the mesh (a release mesh
    # need not be of unit size).
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    side = float((high - low).max())
    uniform = (low + high) / 2 + side * rng.uniform(-0.5, 0.5, (50_000, 3))
    near = surface[:50_000] + rng.normal(scale=0.01 * side, size=(50_000, 3))
    points = np.concatenate([uniform, near])
    inside = RayCaster(vertices, faces).inside(points)
    return {"surface": np.asarray(surface), "normals": np.asarray(mesh.face_normals[faces_hit]),
            "points": points, "inside": np.asarray(inside)}


def dataset_models(root: Path) -> list[str]:
    """The models named in ``root/splits.csv``, sorted."""
    return sorted(read_splits(root / "splits.csv"))
