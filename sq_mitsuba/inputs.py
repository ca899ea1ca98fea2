"""Input files checked one way for every command: images, torch files, cameras, tables.

Each reader here is the one path its kind of file takes, whichever command reads it, and each
failure is one line that names the file (and where in it): a ``FileNotFoundError`` for a
missing file, a ``ValueError`` otherwise, raised before any work that depends on the file.

- **Images** (:func:`open_image`): decoded completely (a truncated file is an error, not a
  grey tail), at least :data:`MIN_IMAGE_SIDE` pixels on each side (the smallest resolution a
  dataset renders at, and the smallest a silhouette can be fitted at) and at most
  :data:`MAX_IMAGE_PIXELS` pixels; PIL's decompression-bomb warning, which that bound
  replaces, is not printed.
- **Torch files** (:func:`load_torch_file`): read with ``weights_only=True`` on the CPU, so a
  file cannot run code; a random, damaged or hostile file is one line saying so, without
  torch's advice to load it unsafely, and torch's warnings about the pickle are not printed.
  :func:`check_finite_tensors` refuses weights holding NaN or infinities (a diverged run).
- **Cameras** (:func:`check_camera_intrinsics`): a camera description (SPEED's
  ``camera.json``: ``Nu``, ``Nv``, ``cameraMatrix``) must describe images of at least
  :data:`MIN_IMAGE_SIDE` pixels, and its matrix must fit them: the principal point within a
  quarter of the image size of its centre, and a field of view from
  :data:`MIN_FIELD_OF_VIEW_DEG` to under :data:`MAX_FIELD_OF_VIEW_DEG` across either axis. A
  matrix written for another image size (or a focal length in another unit) fails one of
  these, instead of giving poses that are silently wrong
  (:func:`sq_mitsuba.inference.images.check_camera` holds a Camera object given in code to
  the same rules).
- **Tables** (:func:`read_csv_table`, :func:`finite_number`): CSV files with the columns a
  reader needs, every row complete (a truncated file is an error), numbers finite.
- **Quaternion lists** (:func:`check_quaternions`): a parsed JSON list of one rotation per item,
  each ``[w, x, y, z]`` of finite numbers and unit length (within :data:`UNIT_TOLERANCE`;
  normalised), exactly as many as the items they go with.

This module imports nothing of the project; torch, PIL and numpy are imported when used.
"""

from __future__ import annotations

import csv
import math
import os
import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = [
    "MAX_FIELD_OF_VIEW_DEG",
    "MAX_IMAGE_PIXELS",
    "MIN_FIELD_OF_VIEW_DEG",
    "MIN_IMAGE_SIDE",
    "check_camera_intrinsics",
    "check_finite_tensors",
    "check_image_size",
    "check_quaternions",
    "check_unique_stems",
    "field_of_view_deg",
    "finite_number",
    "image_header",
    "load_torch_file",
    "one_line",
    "open_image",
    "principal_point_off_centre",
    "read_csv_table",
]

MIN_IMAGE_SIDE = 8
"""Smallest width and height of an image, and of the images a camera describes (pixels)."""
MAX_IMAGE_PIXELS = 2**27
"""Largest image, in pixels (134 megapixels, e.g. 11,585 x 11,585; PIL warns from 89)."""
MAX_FIELD_OF_VIEW_DEG = 160.0
"""Widest field of view a camera description may give across either image axis (degrees)."""
MIN_FIELD_OF_VIEW_DEG = 1e-3
"""Narrowest (degrees; a telescope's is about 0.1): a focal length beyond it puts the target so
far away that its distance is no longer a finite float32 (poses came back infinite)."""
UNIT_TOLERANCE = 1e-3
"""How far from 1 a quaternion's length may be (rounding in a file written by hand or in
single precision); it is normalised."""
_MAX_REASON = 160


def _label(what: str, path: Path) -> str:
    return f"{what} {path}" if what else str(path)


def one_line(error: BaseException) -> str:
    """An error's message as one short line for ours: whitespace collapsed; a message longer
    than 160 characters cut to its first sentence (torch's run on for pages), then to 160
    with "..."; the error's type where it says nothing."""
    text = " ".join(str(error).split()) or type(error).__name__
    if len(text) > _MAX_REASON:
        text = text.split(". ")[0].rstrip(".")
    return text if len(text) <= _MAX_REASON else text[: _MAX_REASON - 3] + "..."


# ----------------------------------------------------------------------------- images


def check_image_size(width: int, height: int, where: str) -> None:
    """Refuse a ``width`` x ``height`` image outside [:data:`MIN_IMAGE_SIDE`, ...] per side or
    above :data:`MAX_IMAGE_PIXELS` pixels; ``where`` starts the message."""
    if width < MIN_IMAGE_SIDE or height < MIN_IMAGE_SIDE:
        raise ValueError(f"{where}: {width} x {height} px is below the smallest image size, "
                         f"{MIN_IMAGE_SIDE} x {MIN_IMAGE_SIDE} px")
    if width * height > MAX_IMAGE_PIXELS:
        raise ValueError(f"{where}: {width} x {height} px is above the largest image size, "
                         f"{MAX_IMAGE_PIXELS:,} pixels")


@contextmanager
def image_header(path: str | os.PathLike[str]) -> Iterator[Any]:
    """The PIL image at ``path`` opened lazily, for its header (size, mode, frames), without
    PIL's decompression-bomb warning: the size bound of :func:`check_image_size` says it in
    one line where the image is read. PIL's own errors pass through."""
    from PIL import Image

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        with Image.open(path) as image:
            yield image


def open_image(path: str | os.PathLike[str], what: str = "image", verify: bool = False) -> Any:
    """The image at ``path`` as a PIL image, decoded completely and of a size within bounds.

    Args:
        path: the file.
        what: the word that names it in messages (``"image"``, ``"mask"``; ``""``: the path
            alone).
        verify: also check every chunk's checksum (PNG) first.

    Raises:
        FileNotFoundError: ``<what> <path>: no such file``.
        ValueError: ``<what> <path>: ...``: not a regular file, not an image, corrupt or
            truncated, or of a size :func:`check_image_size` refuses.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    where = _label(what, path)
    if not path.is_file():
        if path.exists():  # a device, a pipe, a socket: reading it could block or never end
            raise ValueError(f"{where}: not a regular file (a device, pipe or socket)")
        raise FileNotFoundError(f"{where}: no such file")
    try:
        with warnings.catch_warnings():
            # The size bound below replaces PIL's warning (it would print for large images).
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            if verify:
                with Image.open(path) as image:
                    image.verify()
            with Image.open(path) as image:
                check_image_size(image.width, image.height, where)
                image.load()
                return image.copy()
    except UnidentifiedImageError:
        raise ValueError(f"{where}: not an image (no format PIL reads)") from None
    except Image.DecompressionBombError as error:
        # PIL's own text names its limit, not this one: only its count of pixels is kept.
        import re

        found = re.search(r"\((\d+) pixels\)", str(error))
        size = f"{int(found.group(1)):,} pixels, " if found else ""
        raise ValueError(f"{where}: {size}above the largest image size, {MAX_IMAGE_PIXELS:,} "
                         "pixels") from None
    except (OSError, SyntaxError, EOFError) as error:
        # PIL reports damaged data as OSError ("image file is truncated"), SyntaxError (bad
        # chunk headers) or EOFError.
        raise ValueError(f"{where}: cannot read image (corrupt or truncated: "
                         f"{one_line(error)})") from None


# ----------------------------------------------------------------------------- torch files


def _torch_reason(error: BaseException) -> str:
    """The cause of a failed ``torch.load``, without torch's advice to load unsafely."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    if lines and lines[0].startswith("Weights only load failed"):
        boilerplate = ("Weights only load failed", "Please file an issue",
                       "Check the documentation")
        detail = [line.removeprefix("WeightsUnpickler error:").strip() for line in lines[1:]
                  if not line.startswith(boilerplate)]
        detail = [line for line in detail if line and "weights_only" not in line]
        cause = detail[0] if detail else "an object other than tensors and plain values"
        return (f"refused by the safe loader, which reads tensors and plain values only: "
                f"{one_line(cause)}")
    if (lines and ("PytorchStreamReader" in lines[0] or "miniz" in lines[0])) or (
            isinstance(error, OSError) and error.errno == 22):  # EINVAL
        # torch's zip reader: "failed finding central directory. This is an internal miniz
        # error. If you are seeing this error...", or a seek past the end ("[Errno 22]
        # Invalid argument"): the file is cut short or damaged.
        return "corrupt or truncated: not a valid .pt file"
    text = f"{type(error).__name__}: {lines[0]}" if lines else type(error).__name__
    return one_line(text) if "weights_only" not in text else type(error).__name__


def load_torch_file(path: str | os.PathLike[str], what: str) -> Any:
    """``torch.load(path, map_location="cpu", weights_only=True)`` with one-line errors.

    Args:
        what: what the file should be (``"checkpoint"``, ``"ImageNet weights"``), for messages.

    Raises:
        FileNotFoundError: ``<what>: no such file <path>``.
        ValueError: ``<path>: not a readable <what> (<cause>)``: a folder, an empty, random,
            damaged or hostile file (one that would run code when unpickled).
    """
    import torch

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what}: no such file {path}")
    if not path.is_file():
        raise ValueError(f"{path}: is not a file (expected {what})")
    try:
        with warnings.catch_warnings():
            # torch warns about pickle protocols of raw pickles before refusing them.
            warnings.simplefilter("ignore")
            return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for damaged files; report one line
        reason = _torch_reason(error)
        if not reason.startswith("refused by the safe loader"):  # a pickle it refused
            reason = _foreign_file(path) or reason
        raise ValueError(f"{path}: not a readable {what} ({reason})") from None


def _foreign_file(path: Path) -> str | None:
    """Why ``path`` is no torch file at all, from its first bytes (a torch file is a zip
    archive, ``PK``, or a legacy pickle, ``0x80``), or None where it could be one: torch's own
    error for a text file is a pickle opcode's ``KeyError: 101``."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(8)
    except OSError:
        return None
    if not head:
        return "an empty file"
    if head.startswith((b"PK", b"\x80")):
        return None
    return f"not a torch file: it starts with {head!r}"


def check_finite_tensors(tensors: Mapping[str, Any], where: str) -> None:
    """Refuse floating-point tensors of ``tensors`` holding NaN or infinities (weights of a run
    that diverged); ``where`` (the file) starts the one-line message, which names the first
    such tensor."""
    import torch

    bad = [key for key, value in tensors.items()
           if isinstance(value, torch.Tensor) and value.is_floating_point()
           and not bool(torch.isfinite(value).all())]
    if bad:
        raise ValueError(f"{where}: {len(bad)} weight tensor(s) hold NaN or infinite values "
                         f"(first: {bad[0]}); the training that wrote it diverged, so use an "
                         "earlier checkpoint")


# ----------------------------------------------------------------------------- cameras


def check_camera_intrinsics(width: int, height: int, fx: float, fy: float, cx: float,
                            cy: float, where: str) -> None:
    """Refuse a camera description whose matrix does not fit its image size (see the module
    docstring); ``where`` (the file) starts the one-line message."""
    if width < MIN_IMAGE_SIDE or height < MIN_IMAGE_SIDE:
        raise ValueError(f"{where}: Nu x Nv = {width} x {height} px is below the smallest "
                         f"image size, {MIN_IMAGE_SIDE} x {MIN_IMAGE_SIDE} px")
    if principal_point_off_centre(width, height, cx, cy):
        raise ValueError(f"{where}: the principal point ({cx:g}, {cy:g}) of cameraMatrix is "
                         f"far from the centre ({width / 2:g}, {height / 2:g}) of the Nu x Nv "
                         f"= {width} x {height} px image (a matrix for another image size?)")
    for axis, size, focal, centre in (("x", width, fx, cx), ("y", height, fy, cy)):
        fov = field_of_view_deg(size, focal, centre)
        if fov >= MAX_FIELD_OF_VIEW_DEG:
            raise ValueError(f"{where}: cameraMatrix gives a {fov:.1f} deg field of view "
                             f"across {axis} over the Nu x Nv = {width} x {height} px image, "
                             f"more than the {MAX_FIELD_OF_VIEW_DEG:g} deg a camera may have "
                             "(a matrix for another image size?)")
        if fov < MIN_FIELD_OF_VIEW_DEG:
            raise ValueError(f"{where}: cameraMatrix gives a {fov:.3g} deg field of view "
                             f"across {axis} over the Nu x Nv = {width} x {height} px image, "
                             f"less than the {MIN_FIELD_OF_VIEW_DEG:g} deg a camera may have "
                             "(a focal length in the wrong unit?)")


def principal_point_off_centre(width: int, height: int, cx: float, cy: float) -> bool:
    """Whether the principal point lies a quarter of the image or more from its centre: the
    intrinsics of another image size, for every camera this project reads."""
    return abs(cx - width / 2) >= width / 4 or abs(cy - height / 2) >= height / 4


def field_of_view_deg(size: int, focal: float, centre: float) -> float:
    """The field of view (degrees) across ``size`` pixels of focal length ``focal`` and
    principal point ``centre`` (pixels) along that axis."""
    return math.degrees(math.atan(centre / focal) + math.atan((size - centre) / focal))


# ----------------------------------------------------------------------------- tables


def finite_number(value: Any, where: str, text: bool = True) -> float:
    """``value`` as a finite float; ``where`` starts the one-line message otherwise. ``text``
    False refuses a number written as text (``"0.5"``: a JSON file's numbers are numbers, a
    CSV file's are text)."""
    if not text and isinstance(value, str):
        raise ValueError(f"{where}: expected a number, got the text {value!r:.{_MAX_REASON}}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(number):
        raise ValueError(f"{where}: expected a finite number, got {value!r}")
    return number


def read_csv_table(path: str | os.PathLike[str], columns: Sequence[str]) -> list[dict[str, str]]:
    """The rows of a CSV file with a header row that holds ``columns``: at least one row, every
    row with a value in every header column (a file cut short ends in a short row).

    Raises:
        FileNotFoundError: ``<path>: missing``.
        ValueError: ``<path>: ...``: empty, no header, a missing column, no rows, or a short
            or overlong row (naming its line).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing")
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            header = reader.fieldnames
            if not header:
                raise ValueError(f"{path}: empty (no header row)")
            missing = [c for c in columns if c not in header]
            if missing:
                raise ValueError(f"{path}: no column {missing[0]!r} (header: "
                                 f"{', '.join(header)})")
            rows = []
            for row in reader:
                if None in row or any(row[c] is None for c in header):
                    count = sum(1 for c in header if row[c] is not None) + len(row.get(None, []))
                    raise ValueError(f"{path}: line {reader.line_num} has {count} values for "
                                     f"{len(header)} columns (cut short?)")
                rows.append(row)
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: not UTF-8 text (byte {error.start})") from None
    except csv.Error as error:
        raise ValueError(f"{path}: malformed CSV ({one_line(error)})") from None
    if not rows:
        raise ValueError(f"{path}: no rows below the header")
    return rows


# ----------------------------------------------------------------------------- quaternions


def check_quaternions(data: Any, count: int, what: str, where: str) -> list[list[float]]:
    """The ``count`` unit quaternions ``[w, x, y, z]`` a parsed JSON value lists, normalised.

    Args:
        data: the value (e.g. :func:`sq_mitsuba.io.read_json` of a file): a list of ``count``
            lists of 4 numbers.
        count: how many it must hold (one per item it goes with).
        what: what the items are, for the message (e.g. ``"image"``).
        where: where the value came from (a file's path), the message's start.

    Raises:
        ValueError: ``<where>: ...``: not a list of ``count``, or an entry (named by its
            index) that is not 4 finite numbers of length 1 (within :data:`UNIT_TOLERANCE`).
    """
    if not isinstance(data, list):
        raise ValueError(f"{where}: expected a list of quaternions [w, x, y, z], got a "
                         f"{type(data).__name__}")
    if len(data) != count:
        raise ValueError(f"{where}: {len(data)} quaternion{'' if len(data) == 1 else 's'} for "
                         f"{count} {what}{'' if count == 1 else 's'} (one per "
                         f"{what}, in their order)")
    quaternions = []
    for index, entry in enumerate(data):
        named = f"{where}: quaternion {index}"
        if not isinstance(entry, list) or len(entry) != 4:
            raise ValueError(f"{named}: expected [w, x, y, z], got {entry!r:.{_MAX_REASON}}")
        numbers = [finite_number(value, named, text=False) for value in entry]
        length = math.sqrt(sum(v * v for v in numbers))
        if abs(length - 1.0) > UNIT_TOLERANCE:
            raise ValueError(f"{named}: expected unit length, got {length:.6g}")
        quaternions.append([v / length for v in numbers])
    return quaternions


def _same_file(a: Path, b: Path) -> bool:
    """Whether two paths name one file (a path typed twice, or a link to it)."""
    try:
        return a.samefile(b)
    except OSError:
        return a == b


def check_unique_stems(paths: Sequence[Path], what: str, consequence: str) -> None:
    """One-line ``ValueError`` when two of ``paths`` share a file stem (the name without its
    suffix: ``a.png`` and ``a.jpg``), naming ``what`` and both files, then ``consequence``
    (what the stem decides: the outputs' names, the pose a mask takes)."""
    import unicodedata

    first: dict[str, Path] = {}
    for path in paths:
        # Stems that differ only in case or Unicode form ('A' and 'a') name one output file
        # on macOS's and Windows' file systems: one stem here, wherever the outputs go.
        key = unicodedata.normalize("NFC", path.stem).casefold()
        if key in first and _same_file(first[key], path):
            raise ValueError(f"{what}: {path} given twice")
        if key in first:
            other = first[key].stem
            stems = (f"one file stem {path.stem!r}" if other == path.stem else
                     f"file stems {other!r} and {path.stem!r} alike but for case or Unicode "
                     "form (one name on macOS's and Windows' file systems)")
            raise ValueError(f"{what} {first[key]} and {path}: {stems}, {consequence}")
        first[key] = path
