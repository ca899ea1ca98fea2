"""Contact sheet of a model library: every model rendered by :mod:`sq_mitsuba.render.preview`."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sq_mitsuba.data.mesh_io import read_obj
from sq_mitsuba.io import atomic_path
from sq_mitsuba.render.preview import render_model


def library_models(root: str | Path) -> list[Path]:
    """``<root>/<model>/models/model_normalized.obj`` files, sorted by model name."""
    return sorted(Path(root).glob("*/models/model_normalized.obj"))


def contact_sheet(root: str | Path, out: str | Path, tile: int = 160, spp: int = 64,
                  columns: int | None = None, limit: int | None = None) -> int:
    """Render the models of a library into one labelled PNG grid; return the model count.

    Args:
        root: library root holding ``<model>/models/model_normalized.obj``.
        out: PNG path (written atomically).
        tile: tile side in pixels.
        spp: samples per pixel.
        columns: tiles per row (default: a square-ish grid).
        limit: render only the first ``limit`` models by name (default all).
    """
    from PIL import Image, ImageDraw

    if limit is not None and limit < 1:
        raise ValueError(f"limit: expected >= 1, got {limit}")
    files = library_models(root)[:limit]
    if not files:
        raise ValueError(f"{root}: no <model>/models/model_normalized.obj found")
    columns = columns or math.ceil(math.sqrt(len(files)))
    rows = math.ceil(len(files) / columns)
    label_h = 14
    sheet = Image.new("L", (columns * tile, rows * (tile + label_h)), color=0)
    draw = ImageDraw.Draw(sheet)
    for k, obj in enumerate(files):
        vertices, faces, tags = read_obj(obj)
        image = render_model(vertices, faces, tags, tile, spp)
        x, y = (k % columns) * tile, (k // columns) * (tile + label_h)
        sheet.paste(Image.fromarray((image * 255 + 0.5).astype(np.uint8), "L"), (x, y))
        draw.text((x + 3, y + tile + 1), obj.parent.parent.name[:28], fill=220)
    with atomic_path(out) as tmp:
        sheet.save(tmp)
    return len(files)
