"""Check a dataset: files, labels, and masks against the mesh rendered at each label's pose."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from sq_mitsuba.data.spe3r.layout import MASKS, dataset_models, load_model, read_gray
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import quaternion_to_matrix
from sq_mitsuba.io import read_json


@dataclass
class CheckReport:
    models: int = 0
    images: int = 0
    iou: list[float] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        lines = [f"{self.models} models, {self.images} labelled images"]
        if self.iou:
            values = np.asarray(self.iou)
            lines.append(f"label/mask IoU over {len(values)} images: min {values.min():.4f}, "
                         f"mean {values.mean():.4f}")
        lines += [f"problem: {p}" for p in self.problems] or ["no problems found"]
        return "\n".join(lines)


def check_dataset(root: str | Path, per_model: int | None = 20, min_iou: float = 0.99,
                  spp: int = 256, progress: bool = True) -> CheckReport:
    """Validate a dataset: files, labels, and that masks match the mesh rendered at the label.

    Renders each model's ``model_normalized.obj`` at the label pose with
    :class:`~sq_mitsuba.render.silhouette.SilhouetteRenderer` (an independent renderer from
    the one that wrote the masks) for up to ``per_model`` images per model (None: all), and
    reports images whose IoU with the stored mask is below ``min_iou``.
    """
    from tqdm import tqdm

    from sq_mitsuba.render.silhouette import SilhouetteRenderer

    root = Path(root)
    report = CheckReport()
    try:
        camera = Camera.load(root / "camera.json")
        models = dataset_models(root)
    except (OSError, ValueError) as error:
        report.problems.append(str(error))
        return report
    renderer = SilhouetteRenderer(camera, spp=spp)
    for model in tqdm(models, disable=not progress, desc="check"):
        report.models += 1
        labels_path = root / model / "labels.json"
        try:
            labels = read_json(labels_path)
            vertices, faces, _ = load_model(root / model)
        except (OSError, ValueError) as error:
            report.problems.append(f"{model}: {error}")
            continue
        report.images += len(labels)
        chosen = labels if per_model is None else labels[:: max(1, len(labels) // per_model)]
        vertices_t = torch.tensor(vertices, dtype=torch.float32)
        faces_t = torch.tensor(faces, dtype=torch.int64)
        for label in chosen:
            try:
                mask = read_gray(root / model / MASKS / label["filename"]) >= 128
                rotation = quaternion_to_matrix(torch.tensor(label["q_vbs2tango_true"],
                                                             dtype=torch.float32))
                translation = torch.tensor(label["r_Vo2To_vbs_true"], dtype=torch.float32)
            except (KeyError, TypeError, ValueError) as error:
                report.problems.append(f"{model}/{label.get('filename', '?')}: {error}")
                continue
            if mask.shape != (camera.height, camera.width):
                report.problems.append(f"{model}/{label['filename']}: mask is {mask.shape}, "
                                       f"camera is {camera.height} x {camera.width}")
                continue
            with torch.no_grad():
                posed = vertices_t @ rotation.T + translation
                coverage = renderer.render(posed[None], faces_t)[0].numpy()
            rendered = coverage >= 0.5
            union = np.logical_or(rendered, mask).sum()
            iou = float(np.logical_and(rendered, mask).sum() / max(union, 1))
            report.iou.append(iou)
            if iou < min_iou:
                report.problems.append(f"{model}/{label['filename']}: label/mask IoU "
                                       f"{iou:.4f} < {min_iou}")
    return report

