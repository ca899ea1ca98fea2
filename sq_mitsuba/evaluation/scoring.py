"""How the evaluation scores a prediction: every metric of B predicted assemblies and poses
against a dataset batch (:func:`score`), the uniform points that the 3D IoU needs per model
(:func:`volume_points`, :class:`ModelData`), and the trivial baseline's prediction
(:func:`baseline_prediction`).

Convention: poses map body to camera (``x_cam = R x_body + t``, OpenCV frame); the metrics
are those of :mod:`sq_mitsuba.geometry.metrics`, in float64.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.evaluation.split import collate, evenly
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.rotation import matrix_to_quaternion, mean_rotation
from sq_mitsuba.geometry.so3_grid import axis_turns, half_turns
from sq_mitsuba.inference.refine import raw_from_assembly

__all__ = ["METRICS", "ModelData", "baseline_prediction", "score",
           "volume_points"]

#: Metric columns of ``per_image.csv``, in order.
METRICS = ("chamfer_l1_paper", "chamfer_l1_occnet", "chamfer_l2", "iou_2d", "iou_3d",
           "rotation_error_deg", "rotation_error_sym_deg", "rotation_error_folded_deg",
           "translation_error_m", "translation_error_rel", "speed_score", "camera_chamfer",
           "rotation_error_axes_deg")


def score(assembly: Assembly, rotation: Tensor, translation: Tensor, batch: dict[str, Any],
          renderer: Any, symmetries: Sequence[Tensor], volume: Sequence[tuple[Tensor, Tensor]],
          level: int = 3) -> dict[str, Tensor]:
    """Every metric (B,) of B predictions against a dataset batch.

    Args:
        assembly: predicted assemblies, batch size B; rotation (B, 3, 3); translation (B, 3).
        batch: collated dataset items (``mask`` (B, 1, S, S), ``rotation``, ``translation``,
            ``quaternion``, ``surface_points`` (B, K, 3)).
        renderer: a SilhouetteRenderer for the S x S masks.
        symmetries: per item, the (S_i, 3, 3) body-frame symmetries of its model.
        volume: per item, uniform points (N_i, 3) around its model and their inside labels
            (N_i,) bool.
        level: icosphere level of the primitive meshes.
    """
    from sq_mitsuba.geometry.metrics import (
        camera_frame_chamfer,
        chamfer_l1,
        chamfer_l2,
        mask_iou,
        rotation_error_deg,
        speed_score,
        translation_error,
        volumetric_iou,
    )
    from sq_mitsuba.model.losses import counted_surface_samples

    rotation = rotation.detach().double()
    translation = translation.detach().double()
    gt_rotation = batch["rotation"].double()
    gt_translation = batch["translation"].double()
    size = rotation.shape[0]
    with torch.no_grad():
        assembly = Assembly(assembly.params.detach().double())
        # (B, M * V, 3), (B, M * V); an assembly whose every point is inside another keeps all.
        points, keep = counted_surface_samples(assembly, level)
        gt_points = batch["surface_points"].double()
        silhouettes = _silhouettes(assembly, rotation, translation, batch, renderer, level)
        volume_iou = torch.stack([
            volumetric_iou(assembly[i:i + 1].union_occupancy(pts.double()[None]),
                           labels[None])[0] for i, (pts, labels) in enumerate(volume)])
    symmetric = torch.stack([
        rotation_error_deg(rotation[i:i + 1], gt_rotation[i:i + 1], symmetries[i])[0]
        for i in range(size)])

    folded = rotation_error_deg(rotation, gt_rotation, half_turns())
    speed = speed_score(matrix_to_quaternion(rotation), batch["quaternion"].double(),
                        translation, gt_translation)
    return {
        "chamfer_l1_paper": chamfer_l1(points, gt_points, "paper", pred_mask=keep),
        "chamfer_l1_occnet": chamfer_l1(points, gt_points, "occnet", pred_mask=keep),
        "chamfer_l2": chamfer_l2(points, gt_points, pred_mask=keep),
        "iou_2d": mask_iou(silhouettes, batch["mask"][:, 0].double()),
        "iou_3d": volume_iou,
        "rotation_error_deg": rotation_error_deg(rotation, gt_rotation),
        "rotation_error_sym_deg": symmetric,
        "rotation_error_folded_deg": folded,
        "translation_error_m": translation_error(translation, gt_translation),
        "translation_error_rel": translation_error(translation, gt_translation, relative=True),
        "speed_score": speed.total,
        "camera_chamfer": camera_frame_chamfer(points, rotation, translation, gt_points,
                                               gt_rotation, gt_translation, pred_mask=keep),
        "rotation_error_axes_deg": rotation_error_deg(rotation, gt_rotation, axis_turns()),
    }


def image_seed(model: str, index: int) -> int:
    """The seed of the silhouette samples an image is scored with: CRC32 of
    ``<model>/<index>`` (the image itself, not its place in a run)."""
    return zlib.crc32(f"{model}/{int(index)}".encode())


def _silhouettes(assembly: Assembly, rotation: Tensor, translation: Tensor,
                 batch: dict[str, Any], renderer: Any, level: int) -> Tensor:
    """The silhouettes (B, S, S) the 2D IoU scores. Each image of a dataset batch (one that
    names its ``model`` and ``index``) renders with samples of its own
    (:func:`image_seed`), the same for every method: its score is then what it is alone,
    whatever batch, position or order of methods a run gives it (the renderer's running
    sequence moved one image's 2D IoU by up to 0.007 between ``eval --batch-size 1`` and 4).
    A batch without those names renders on the renderer's sequence."""
    from sq_mitsuba.render.silhouette.renderer import render_assembly

    models, indices = batch.get("model"), batch.get("index")
    if models is None or indices is None:
        return render_assembly(assembly, rotation, translation, renderer, level)
    silhouettes = []
    for k in range(rotation.shape[0]):
        renderer.reseed(image_seed(models[k], indices[k]))
        silhouettes.append(render_assembly(assembly[k:k + 1], rotation[k:k + 1],
                                           translation[k:k + 1], renderer, level))
    return torch.cat(silhouettes)


def volume_points(model_dir: Path, count: int) -> tuple[Tensor, Tensor]:
    """Up to ``count`` points uniform in the cube around a model (N, 3) float64 and whether
    each is inside (N,) bool: ``samples.npz``'s uniform points, or, without them (the SPE3R
    release), points uniform in the unit cube labelled by ray casting the mesh."""
    from sq_mitsuba.data.spe3r.layout import MODELS, SAMPLES_FILE, load_model, read_samples

    rng = np.random.default_rng(0)
    path = model_dir / MODELS / SAMPLES_FILE
    if path.is_file():  # read as every reader does: sizes from the headers, values checked
        samples = read_samples(path, ("uniform_points", "uniform_inside"))
        points = samples["uniform_points"].astype(np.float64)
        inside = samples["uniform_inside"].astype(bool)
        if len(points) > count:
            chosen = np.sort(rng.choice(len(points), count, replace=False))
            points, inside = points[chosen], inside[chosen]
    else:
        from sq_mitsuba.render.depth import RayCaster

        vertices, faces, _ = load_model(model_dir)
        centre = 0.5 * (vertices.min(0) + vertices.max(0))
        points = centre + rng.uniform(-0.5, 0.5, (count, 3))
        inside = np.asarray(RayCaster(vertices, faces).inside(points), dtype=bool)
    return torch.from_numpy(points), torch.from_numpy(inside)


class ModelData:
    """Per-model symmetries and volume points of a dataset, computed once each."""

    def __init__(self, dataset: Any, volume_count: int) -> None:
        self.dataset, self.volume_count = dataset, volume_count
        self.symmetries: dict[int, Tensor] = {}
        self.volumes: dict[int, tuple[Tensor, Tensor]] = {}

    def symmetry(self, model_index: int) -> Tensor:
        if model_index not in self.symmetries:
            from sq_mitsuba.data.symmetry import model_symmetries

            matrices = model_symmetries(self.dataset.root / self.dataset.models[model_index])
            self.symmetries[model_index] = torch.as_tensor(np.asarray(matrices),
                                                           dtype=torch.float64)
        return self.symmetries[model_index]

    def volume(self, model_index: int) -> tuple[Tensor, Tensor]:
        if model_index not in self.volumes:
            self.volumes[model_index] = volume_points(
                self.dataset.root / self.dataset.models[model_index], self.volume_count)
        return self.volumes[model_index]


def baseline_prediction(predictor: Any, data_root: Path, count: int,
                        batch_size: int = 32, split: str = "train", progress: bool = False
                        ) -> tuple[Tensor, Tensor, Tensor]:
    """The trivial baseline: mean raw output (1, M, 16) of the network over up to ``count``
    training images (spread evenly), with the mean rotation (1, 3, 3) and translation (1, 3)
    of their labels. ``split``: the split those images come from (``sq-mitsuba demo`` takes
    its own test images when the checkpoint stores no baseline). ``progress``: a bar over the
    images (seconds to tens of seconds before an evaluation's own bar).

    Convention: a network with existence probabilities is read with every primitive (one M
    for all images); the baseline keeps those whose mean probability reaches the predictor's
    ``min_existence`` (its most probable one always), the others replaced by invisible
    stand-ins (:mod:`sq_mitsuba.model.existence`), so it still holds M rows.

    Raises:
        ValueError: the split has no images.
    """
    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.inference.loading import with_fast_path
    from sq_mitsuba.model.existence import gathered_primitives, kept_primitives
    from sq_mitsuba.progress import progress_bar

    train = Spe3rDataset(data_root, split, image_size=predictor.image_size, num_surface=1,
                         num_occupancy=2)
    if len(train) == 0:
        raise ValueError(f"{data_root}: no images for the baseline (the {split!r} split "
                         "is empty); evaluate without it (--no-baseline)")
    camera = train.camera.rescaled(predictor.image_size, predictor.image_size)
    indices = evenly(len(train), count)
    threshold = predictor.min_existence
    every = with_fast_path(predictor, predictor.fast, min_existence=0.0)
    raws, existences, rotations, translations = [], [], [], []
    with progress_bar(total=len(indices), desc="baseline", unit="img", disable=not progress,
                      leave=False) as bar:
        for start in range(0, len(indices), batch_size):
            batch = collate([train[i] for i in indices[start:start + batch_size]])
            prediction = every.predict(batch["image"], camera)
            raws.append(raw_from_assembly(prediction.assembly).cpu())  # labels: CPU
            if prediction.existence is not None:
                existences.append(prediction.existence.cpu())
            rotations.append(batch["rotation"])
            translations.append(batch["translation"])
            bar.update(len(batch["rotation"]))
    raw = torch.cat(raws).double().mean(0, keepdim=True)
    if existences:
        rows = kept_primitives(torch.cat(existences).double().mean(0, keepdim=True), threshold,
                               width=raw.shape[1])
        raw = raw_from_assembly(Assembly(gathered_primitives(Assembly.from_raw(raw).params,
                                                             rows)))
    return (raw,
            mean_rotation(torch.cat(rotations))[None],
            torch.cat(translations).double().mean(0, keepdim=True))
