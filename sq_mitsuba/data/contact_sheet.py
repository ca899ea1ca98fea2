"""Contact sheet of a model library: every model rendered by :mod:`sq_mitsuba.render.preview`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sq_mitsuba.config import in_range, validate
from sq_mitsuba.data.mesh_io import SAMPLES_FILE, read_npz, read_tagged_obj
from sq_mitsuba.io import atomic_path, check_output_file
from sq_mitsuba.render.backend import MAX_SAMPLES_PER_RENDER

LABEL_HEIGHT = 14
"""Pixels under each tile for the model's name."""
MAX_SHEET_PIXELS = 2**28
"""Largest sheet (268 megapixels, as many bytes in 8-bit grey): PIL's safe size and memory."""


@dataclass(frozen=True)
class ContactSheetOptions:
    """How ``sq-mitsuba models preview`` renders a library."""

    out: Path | None = None
    "Image to write, PNG, JPEG, TIFF or BMP by its suffix; None means ROOT/contact_sheet.png."
    size: int = in_range(16, 1024, default=160)
    "Tile side in pixels."
    spp: int = in_range(1, 4096, default=64)
    "Samples per pixel."
    columns: int | None = in_range(1, 256, default=None)
    "Tiles per row; None means a square-ish grid."
    limit: int | None = in_range(1, 100_000, default=None)
    "Render only the first LIMIT models by name; None means all."

    def __post_init__(self) -> None:
        if self.out is not None:
            image_format(self.out)
        if self.size * self.size * self.spp > MAX_SAMPLES_PER_RENDER:
            raise ValueError(f"spp: {self.spp} at a tile of {self.size} x {self.size} px is "
                             f"{self.size * self.size * self.spp:,} samples per render, more "
                             "than Mitsuba's 2^32 (a render split in passes that took 24 GB); "
                             "lower --spp or --size")


#: Image formats of a contact sheet, by the suffix of its path (lower case).
FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".tif": "TIFF", ".tiff": "TIFF",
           ".bmp": "BMP"}


def image_format(path: str | Path) -> str:
    """PIL's format name for an image written to ``path``, from its suffix; ``ValueError``
    (``out: ...``) for a suffix that names none of :data:`FORMATS`, so that a sheet is never
    written in a format its name does not say."""
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        shown = f"suffix {Path(path).suffix!r}" if suffix else "no suffix"
        raise ValueError(f"out: {str(path)!r} has {shown}; expected an image file name ending "
                         f"in {', '.join(FORMATS)}")
    return FORMATS[suffix]


@dataclass(frozen=True)
class ContactSheet:
    """A written contact sheet."""

    path: Path
    """The image."""
    models: int
    """How many models it shows."""


def library_models(root: str | Path) -> list[Path]:
    """``<root>/<model>/models/model_normalized.obj`` files, sorted by model name."""
    return sorted(Path(root).glob("*/models/model_normalized.obj"))


def _check_samples(path: Path) -> None:
    """``ValueError`` (one line, :func:`~sq_mitsuba.data.mesh_io.read_npz`'s) unless ``path``
    is absent or an ``.npz`` archive whose ``face_material`` (if any) numpy reads."""
    if path.is_file():
        read_npz(path, ["face_material"])


def contact_sheet(root: str | Path, options: ContactSheetOptions | None = None,
                  progress: bool = False) -> ContactSheet:
    """Render the models of a library into one labelled grid image (written atomically, in
    the format its suffix names: PNG, JPEG, TIFF or BMP).

    Each model is drawn with its per-face materials (from ``samples.npz`` beside the OBJ, see
    :func:`sq_mitsuba.data.mesh_io.read_tagged_obj`). Options and the sheet's size are checked
    before anything is rendered.

    Args:
        root: library root holding ``<model>/models/model_normalized.obj``.
        options: tile size, samples per pixel, grid and output path.
        progress: show a progress bar over the models.
    """
    from PIL import Image, ImageDraw

    # Deferred: the renderer pulls in Mitsuba and torch, which option parsing does not need.
    from sq_mitsuba.progress import progress_bar
    from sq_mitsuba.render.preview import render_model

    options = options or ContactSheetOptions()
    validate(options)
    root = Path(root)
    out = options.out or root / "contact_sheet.png"
    fmt = image_format(out)
    files = library_models(root)[:options.limit]
    if not files:
        raise ValueError(f"{root}: no <model>/models/model_normalized.obj found")
    tile = options.size
    columns = options.columns or math.ceil(math.sqrt(len(files)))
    rows = math.ceil(len(files) / columns)
    width, height = columns * tile, rows * (tile + LABEL_HEIGHT)
    if width * height > MAX_SHEET_PIXELS:
        raise ValueError(f"size: {len(files)} models of {tile} px in {columns} columns make a "
                         f"{width} x {height} sheet, over {MAX_SHEET_PIXELS // 2**20} "
                         "megapixels; lower the size or set a limit")
    for obj in files:  # before any render: an archive numpy cannot read stops the sheet
        _check_samples(obj.parent / SAMPLES_FILE)
    check_output_file(out)  # before any render too: not an error naming a temporary file
    sheet = Image.new("L", (width, height), color=0)
    draw = ImageDraw.Draw(sheet)
    for k, obj in enumerate(progress_bar(files, desc="preview", unit="model",
                                         disable=not progress)):
        mesh = read_tagged_obj(obj)
        image = render_model(mesh.vertices, mesh.faces, mesh.face_material, tile, options.spp)
        x, y = (k % columns) * tile, (k // columns) * (tile + LABEL_HEIGHT)
        sheet.paste(Image.fromarray((image * 255 + 0.5).astype(np.uint8), "L"), (x, y))
        draw.text((x + 3, y + tile + 1), obj.parent.parent.name[:28], fill=220)
    with atomic_path(out) as tmp:
        sheet.save(tmp, format=fmt)
    return ContactSheet(Path(out), len(files))
