"""Contact sheet of a dataset: images with the mask outline and the label's body axes."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sq_mitsuba.config import in_range, validate
from sq_mitsuba.data.spe3r.check import check_dataset_root
from sq_mitsuba.data.spe3r.layout import (
    IMAGES,
    MASKS,
    DatasetError,
    dataset_models,
    find_image,
    label_problem,
    read_gray,
    read_labels,
)
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import quaternion_to_matrix
from sq_mitsuba.io import check_output_file, save_figure


@dataclass(frozen=True)
class PreviewOptions:
    """Options of ``sq-mitsuba dataset preview`` (checked when built)."""

    count: int = in_range(1, 1024, default=16)
    """Images on the sheet (spread over the models, first images first)."""
    axis_length: float = in_range(0, 100, default=0.3, low_inclusive=False)
    """Length in metres of the drawn body axes (models are 1 m long)."""

    def __post_init__(self) -> None:
        validate(self)


def default_preview_path(root: str | Path) -> Path:
    """Where ``dataset preview ROOT`` writes without ``--out``: ``<ROOT>_preview.png`` beside
    the dataset folder (not inside it: reading a dataset leaves it as it was)."""
    root = Path(root)
    if not root.name or root.name == "..":
        root = root.resolve()
    return root.parent / f"{root.name}_preview.png"


def preview_dataset(root: str | Path, out: str | Path | None = None,
                    options: PreviewOptions | None = None, *, count: int | None = None,
                    axis_length: float | None = None) -> Path:
    """Contact sheet PNG (default :func:`default_preview_path`, beside the dataset folder:
    reading a dataset never changes it): images with the mask outline and the pose's body
    axes drawn. ``count`` and ``axis_length`` override ``options``' fields.

    The body axes x, y, z (red, green, blue, ``axis_length`` metres) are projected with the
    label pose and ``camera.json``; they start at the model origin (its centre of mass).
    """
    options = options or PreviewOptions()
    overrides = {k: v for k, v in (("count", count), ("axis_length", axis_length))
                 if v is not None}
    options = PreviewOptions(**{"count": options.count, "axis_length": options.axis_length,
                                **overrides})
    count, axis_length = options.count, options.axis_length
    root = Path(root)
    out = Path(out) if out is not None else default_preview_path(root)
    if out.suffix.lower() != ".png":  # never a file whose name says another format
        raise DatasetError(f"out {out}: a preview is written as PNG; name it .png")
    check_dataset_root(root)  # a missing folder is named as such, not as its camera.json
    check_output_file(out)  # before the sheet is drawn: not an error naming a temporary file
    for required in ("camera.json", "splits.csv"):
        if not (root / required).is_file():
            raise DatasetError(f"{root / required}: missing")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    camera = Camera.load(root / "camera.json")
    chosen: list[tuple[str, dict[str, Any]]] = []
    labels = {}
    for model in dataset_models(root):
        path = root / model / "labels.json"
        if path.is_file():  # entries `dataset check` would report are left out
            labels[model] = [e for e in read_labels(path) if label_problem(e) is None]
    if not labels:
        raise DatasetError(f"{root}: no labelled models to preview")
    depth = 0
    while len(chosen) < count and any(depth < len(v) for v in labels.values()):
        for model, entries in labels.items():
            if depth < len(entries) and len(chosen) < count:
                chosen.append((model, entries[depth]))
        depth += 1
    columns = min(4, len(chosen))
    rows = -(-len(chosen) // columns)
    figure, axes = plt.subplots(rows, columns, figsize=(3 * columns, 3.2 * rows), squeeze=False)
    for axis in axes.flat:
        axis.axis("off")
    for axis, (model, label) in zip(axes.flat, chosen, strict=False):
        image = read_gray(find_image(root, model, IMAGES, label["filename"]))
        mask = read_gray(find_image(root, model, MASKS, label["filename"])) >= 128
        # Pixel (i, j) covers [j, j+1) x [i, i+1) (docs/conventions.md), as Camera.project
        # places points: imshow's default would put its centre at (j, i), half a pixel off.
        height, width = image.shape
        axis.imshow(image, cmap="gray", vmin=0, vmax=255, extent=(0, width, height, 0))
        axis.contour(np.arange(width) + 0.5, np.arange(height) + 0.5, mask, levels=[0.5],
                     colors=["#ffcc00"], linewidths=0.6)
        rotation = quaternion_to_matrix(torch.tensor(label["q_vbs2tango_true"],
                                                     dtype=torch.float64))
        origin = torch.tensor(label["r_Vo2To_vbs_true"], dtype=torch.float64)
        ends = origin + axis_length * rotation.T  # rows: camera-frame tips of body x, y, z
        pixels = camera.project(torch.cat([origin[None], ends]).float()).numpy()
        for tip, colour in zip(pixels[1:], ("r", "g", "b"), strict=True):
            axis.plot([pixels[0, 0], tip[0]], [pixels[0, 1], tip[1]], colour, linewidth=1.2)
        phase = label.get("phase_angle_deg")
        subtitle = f"phase {phase:.0f} deg" if phase is not None else ""
        # Drawn as written: a '$' in a model or file name is not mathtext ('cube $^$' failed
        # the sheet; 'twin $x_1$' came out as a formula).
        axis.set_title(f"{model} {label['filename']}\n{subtitle}", fontsize=7, parse_math=False)
        axis.set_xlim(0, camera.width)
        axis.set_ylim(camera.height, 0)
    figure.tight_layout()
    return save_figure(figure, out)

