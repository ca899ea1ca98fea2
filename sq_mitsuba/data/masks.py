"""Binary masks and SPE3R-style pose labels read from files, checked before any work starts.

Masks: one image per view, the object bright on a dark background. Binary single-channel
images (8-bit gray, 1-bit) are read as they are; anything else is converted first, then
thresholded at half its range (see :func:`read_mask`). Every error is one line naming the file
(and the entry, for labels).

Labels: an SPE3R ``labels.json``, a list of ``{"filename": ..., "q_vbs2tango_true": [w, x, y,
z], "r_Vo2To_vbs_true": [x, y, z]}``; the pose maps body to camera (OpenCV frame):
``x_cam = R(q) x_body + r``. A mask takes the entry whose filename has the same stem
(``img000001.png`` <- ``img000001.jpg``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.inputs import image_header, open_image
from sq_mitsuba.io import read_json

QUATERNION_KEY = "q_vbs2tango_true"
#: Largest difference of a label quaternion's norm from 1 (as the dataset's labels): beyond
#: it, the label is not a rotation (a typo, another convention), and is refused.
QUATERNION_NORM_TOLERANCE = 1e-3
TRANSLATION_KEY = "r_Vo2To_vbs_true"

#: Largest value of each PIL mode read as one gray channel (the threshold is half of it).
_GRAY_RANGE = {"1": 1.0, "L": 255.0, "I;16": 65535.0, "I;16B": 65535.0, "I;16L": 65535.0,
               "I;16N": 65535.0, "I": 65535.0, "F": 1.0}


def _gray(image: Any, path: Path, what: str) -> tuple[np.ndarray, float]:
    """One gray channel (H, W) float64 of a PIL image and the largest value of its range.

    Convention: colour images become luminance (ITU-R 601, PIL's ``convert("L")``); alpha, where
    present, multiplies it (composited on black: transparent pixels are background); 16-bit
    and 32-bit integer images are taken as 16-bit (range 0..65535), float images as 0..1.
    """
    mode = image.mode
    if mode in _GRAY_RANGE:
        return np.asarray(image, dtype=np.float64), _GRAY_RANGE[mode]
    if mode in ("LA", "La", "RGBA", "RGBa", "PA") or (mode == "P" and "transparency" in image.info):
        rgba = image.convert("RGBA")
        gray = np.asarray(rgba.convert("L"), dtype=np.float64)
        alpha = np.asarray(rgba.getchannel("A"), dtype=np.float64) / 255.0
        return gray * alpha, 255.0
    try:
        return np.asarray(image.convert("L"), dtype=np.float64), 255.0
    except (ValueError, OSError) as error:
        raise ValueError(f"{what} {path}: cannot convert PIL mode {mode!r} to gray "
                         f"({_one_line(error)})") from None


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__


def check_not_folder(path: str | Path, what: str, hint: str = "") -> None:
    """A one-line ``IsADirectoryError`` (``<what> <path>: is a folder, not a file``, then
    `` (<hint>)`` where given) when ``path`` is a folder: given where a file is expected, it
    is not "no such file"."""
    if Path(path).is_dir():
        raise IsADirectoryError(f"{what} {path}: is a folder, not a file"
                                + (f" ({hint})" if hint else ""))


def read_gray_image(path: str | Path, what: str = "image", warn: bool = True) -> np.ndarray:
    """One image (H, W) as float64 in [0, 1], converted as the module docstring says: colour
    images become luminance, alpha composites on black, 16-bit images keep their range.
    ``warn``: say where the pixels are not what a viewer shows (an EXIF orientation, 12-bit
    data in a 16-bit file); False where the file was read and checked before.

    Raises:
        FileNotFoundError: ``path`` does not exist; IsADirectoryError: it is a folder.
        ValueError: not an image, a corrupt or truncated one, one of several frames (an
            animated GIF, a multi-page TIFF: which frame is meant is not guessed), one with
            pixels not finite (a float image), or one outside the size bounds of
            :func:`sq_mitsuba.inputs.open_image` (at least 8 x 8 px); one line naming
            ``what`` and ``path``.
    """
    path = Path(path)
    check_not_folder(path, what)
    image = open_image(path, what)
    with image_header(path) as opened:
        frames = getattr(opened, "n_frames", 1)
    if frames > 1:
        raise ValueError(f"{what} {path}: holds {frames} frames (an animation or a multi-page "
                         "file); save the one frame to use as an image of its own")
    gray, top = _gray(image, path, what)
    if gray.ndim != 2:
        raise ValueError(f"{what} {path}: expected one image channel, got shape {gray.shape}")
    if not np.isfinite(gray).all():  # a float image (TIFF) can hold them; clipping would hide
        bad = int((~np.isfinite(gray)).sum())
        raise ValueError(f"{what} {path}: {bad} pixel(s) not finite (NaN or infinite)")
    if warn:
        _warn_of_surprises(image, gray, top, path, what)
    return np.clip(gray / top, 0.0, 1.0)


#: EXIF orientations (tag 274) other than 1, as a viewer turns the stored pixels to show them.
_EXIF_TURNS = {2: "mirrored", 3: "turned 180 deg", 4: "flipped", 5: "mirrored and turned",
               6: "turned 90 deg clockwise", 7: "flipped and turned", 8: "turned 90 deg "
               "counter-clockwise"}


def _warn_of_surprises(image: Any, gray: np.ndarray, top: float, path: Path, what: str) -> None:
    """One-line warnings where the pixels read are not what a viewer shows of the file.

    Convention: an EXIF orientation is not applied (the pixels are read as stored, so that a
    camera calibrated on the sensor's raster is the image's camera); a 16-bit image is read on
    its whole range, so one holding 12- or 10-bit data is read 16 or 64 times too dark."""
    try:
        orientation = image.getexif().get(274)
    except Exception:  # an unreadable EXIF block is no orientation
        orientation = None
    if orientation in _EXIF_TURNS:
        warnings.warn(f"{what} {path}: its EXIF orientation ({_EXIF_TURNS[orientation]}) is not "
                      f"applied: read as stored, {gray.shape[1]} x {gray.shape[0]} px, the "
                      "poses are in that raster's camera frame (save it upright, without the "
                      "tag, to read it as a viewer shows it)", stacklevel=3)
    brightest = float(gray.max()) if gray.size else 0.0
    if top == 65535.0 and 0.0 < brightest <= 4095.0:
        warnings.warn(f"{what} {path}: a 16-bit image whose brightest pixel is "
                      f"{brightest:.0f} of 65535, read on the 16-bit range: if it holds 12-, "
                      "10- or 8-bit data, scale it to 16 bits first", stacklevel=3)


def read_mask(path: str | Path, warn: bool = True) -> np.ndarray:
    """One mask (H, W) bool: object where the gray value exceeds half the format's range.

    Conversion: RGB and palette images become gray (luminance); RGBA/LA are composited on
    black first; 16-bit images keep their range. Object = gray > 127.5 for 8-bit images (> 127),
    > 32767.5 for 16-bit, > 0.5 for float images.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: not an image, a corrupt or truncated one, an empty (all background) mask
            or a full one (no background: an outline cannot be fitted to it, and it is most
            often a mask with black and white swapped); one line naming ``path``.
    """
    mask = read_gray_image(path, "mask", warn) > 0.5
    if not mask.any():
        raise ValueError(f"mask {path}: empty (no pixel above half range: all background)")
    if mask.all():
        raise ValueError(f"mask {path}: full (every pixel above half range: no background to "
                         "fit an outline against; black and white swapped?)")
    border = np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]])
    if warn and border.mean() > 0.9:  # a target filling the frame's edge all round is rare
        warnings.warn(f"mask {path}: {border.mean():.0%} of its border is target (black and "
                      "white swapped? the target is white on black)", stacklevel=2)
    return mask


def read_masks(paths: Sequence[str | Path]) -> Tensor:
    """Masks (V, H, W) bool of ``paths``, all of one size (see :func:`read_mask`).

    Raises:
        ValueError: no paths, a bad mask (see :func:`read_mask`), or two sizes (naming both
            files and their sizes, width x height).
    """
    if len(paths) == 0:
        raise ValueError("masks: no mask files given")
    masks = []
    first: tuple[Path, tuple[int, ...]] | None = None
    for path in paths:
        mask = read_mask(path)
        if first is None:
            first = (Path(path), mask.shape)
        elif mask.shape != first[1]:
            raise ValueError(f"masks: {first[0]} is {first[1][1]} x {first[1][0]} pixels but "
                             f"{path} is {mask.shape[1]} x {mask.shape[0]} (width x height); "
                             "all masks must have one size")
        masks.append(mask)
    return torch.from_numpy(np.stack(masks))


def _numbers(entry: dict[str, Any], key: str, count: int, where: str) -> list[float]:
    """``entry[key]`` as ``count`` finite floats, or a one-line ``ValueError`` at ``where``."""
    if key not in entry:
        raise ValueError(f"{where}: no {key!r}")
    value = entry[key]
    if (not isinstance(value, list | tuple) or len(value) != count
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)):
        shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
        noun = "quaternion" if count == 4 else "translation"
        raise ValueError(f"{where}: {key} must be a list of {count} numbers (the {noun}), "
                         f"got {shown}")
    numbers = [float(v) for v in value]
    if not all(math.isfinite(v) for v in numbers):
        raise ValueError(f"{where}: {key} holds NaN or infinity: {numbers}")
    return numbers


def read_label_poses(labels_path: str | Path, names: Sequence[str | Path]
                     ) -> tuple[Tensor, Tensor]:
    """Poses of the images ``names`` from an SPE3R-style ``labels.json``, matched by file stem.

    Args:
        labels_path: the labels file (a JSON list of entries, see the module docstring).
        names: image file names or paths (only their stems matter), one per view.

    Returns:
        (quaternions (V, 4), translations (V, 3)) float64, body to camera; quaternions are
        scalar-first, unit within :data:`QUATERNION_NORM_TOLERANCE`, and returned as stored
        (not normalised).

    Raises:
        FileNotFoundError: no ``labels_path``.
        ValueError: malformed JSON, an entry without ``filename``, two entries with one stem,
            no entry for a name, or an entry whose quaternion is not 4 finite numbers of norm
            1 or whose translation is not 3 finite numbers with z > 0 (the target in front of
            the camera); one line naming the file and the entry (index and filename).
    """
    labels_path = Path(labels_path)
    check_not_folder(labels_path, "labels")
    if not labels_path.is_file():
        raise FileNotFoundError(f"labels {labels_path}: no such file")
    labels = read_json(labels_path)
    if not isinstance(labels, list):
        raise ValueError(f"labels {labels_path}: expected a JSON list of entries, got "
                         f"{type(labels).__name__}")
    by_stem: dict[str, tuple[int, dict[str, Any]]] = {}
    for index, entry in enumerate(labels):
        if not isinstance(entry, dict) or not isinstance(entry.get("filename"), str):
            raise ValueError(f"labels {labels_path}: entry {index} has no 'filename' string")
        stem = Path(entry["filename"]).stem
        if stem in by_stem:
            raise ValueError(f"labels {labels_path}: entries {by_stem[stem][0]} and {index} "
                             f"both have the stem {stem!r}")
        by_stem[stem] = (index, entry)
    quaternions, translations = [], []
    for name in names:
        stem = Path(name).stem
        if stem not in by_stem:
            raise ValueError(f"labels {labels_path}: no label with the stem of "
                             f"{Path(name).name!r}")
        index, entry = by_stem[stem]
        where = f"labels {labels_path}: entry {index} ({entry['filename']!r})"
        q = _numbers(entry, QUATERNION_KEY, 4, where)
        norm = math.hypot(*q)
        if norm < 1e-8:
            raise ValueError(f"{where}: {QUATERNION_KEY} has zero norm")
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise ValueError(f"{where}: {QUATERNION_KEY} has norm {norm:.6g}, not 1 (within "
                             f"{QUATERNION_NORM_TOLERANCE:g}): not a rotation quaternion")
        translation = _numbers(entry, TRANSLATION_KEY, 3, where)
        if not translation[2] > 0:  # as the dataset reader refuses it
            raise ValueError(f"{where}: {TRANSLATION_KEY}: the target is not in front of the "
                             f"camera (z = {translation[2]:g})")
        quaternions.append(q)
        translations.append(translation)
    return (torch.tensor(quaternions, dtype=torch.float64),
            torch.tensor(translations, dtype=torch.float64))
