"""Evaluate a trained model on a dataset split: per-image metrics, tables, charts, figures.

:func:`evaluate` runs the network over the ``val`` or ``test`` split of an SPE3R-layout
dataset and scores every image with every metric of :mod:`sq_mitsuba.evaluation.metrics`, for
up to four methods:

- ``network``: the network's prediction;
- ``search``: the global pose search (:func:`sq_mitsuba.learning.search.search_poses`: the
  network's rotation (with ``search.candidates = "hypotheses"`` its top-K hypotheses too), or a
  uniform grid for a network without them, each times the four half turns, scored by Mitsuba
  silhouettes) against the mask read from the image, with the
  network's assembly (``refine``);
- ``refined``: that search followed by refinement of its best few
  (:func:`sq_mitsuba.learning.search.search_and_refine`) against the same mask; the mask is
  the network's mask head when it has one (``mask = "network"``), else the threshold
  segmentation of the image (:func:`sq_mitsuba.data.segmentation.segment_target`), named in
  the ``mask_source`` column; an image with nothing to segment (an eclipse, a black frame),
  or whose segmentation warns of a lit Earth merged with the target, keeps the network's
  prediction, with blank search columns;
- ``refined_gt``: search and refinement against the ground-truth mask, an upper bound
  (``refine`` and ``refine_ground_truth``);
- ``baseline``: a trivial floor, the mean training assembly (the mean of the network's raw
  outputs over training images, squashed) at the mean training pose (chordal mean rotation,
  mean translation of the training labels).

Files written to the output folder (each atomically):

- ``per_image.csv``: one row per image and method: every metric (:data:`METRICS`), the
  refinement's own IoUs where refined (:data:`EXTRAS`), and the label's lighting record
  (:data:`LIGHTING`: phase angle, Earth in view, eclipse, target visibility);
- ``per_model.csv`` / ``per_model.md``: mean, std and median per model and method;
- ``summary.csv`` / ``summary.md``: mean, std and median per method over the split;
- ``per_model.png``: bars with std error bars per model and method (as the paper's Fig. 10);
- ``qualitative.png``: input, reprojected silhouette, predicted assembly (one colour per
  primitive), its surface points and the ground-truth mesh (as the paper's Fig. 12);
- ``consistency.png``: several images of a model with their predicted assemblies in one fixed
  view of the body frame (as the paper's Fig. 11);
- ``mesh_ranking.csv`` (``mesh_ranking`` > 0): for that many network predictions, spread
  evenly, the rank of the image's own model among every model of the split by Chamfer-L1 to
  the prediction (:mod:`sq_mitsuba.evaluation.mesh_ranking`: is the shape read from the image?);
- ``eval.json``: settings, checkpoint, counts, symmetries per model, images/s, and the mesh
  ranking's medians.

Convention: 2D IoU compares the predicted assembly's silhouette at the *predicted* pose with
the ground-truth mask (for every method, the refined ones included), both at the network's
input resolution and thresholded at 0.5. Chamfer distances use the assembly's surface points
without those inside another primitive, against the model's surface samples, in the unit-size
body frame. 3D IoU uses points uniform in the cube around the model (``samples.npz``'s
``uniform_points``), so it estimates the volume IoU; balanced near-surface points would not.
"""

from __future__ import annotations

import csv
import io as _io
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.config import in_range, to_dict, validate
from sq_mitsuba.evaluation.methods import METHODS
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import matrix_to_quaternion
from sq_mitsuba.geometry.so3_grid import half_turns
from sq_mitsuba.io import atomic_write_json, atomic_write_text
from sq_mitsuba.learning.refine import RefineOptions, raw_from_assembly
from sq_mitsuba.learning.search import SEARCH_REFINEMENT, SearchOptions

#: Metric columns of ``per_image.csv``, in order.
METRICS = ("chamfer_l1_paper", "chamfer_l1_occnet", "chamfer_l2", "iou_2d", "iou_3d",
           "rotation_error_deg", "rotation_error_sym_deg", "rotation_error_folded_deg",
           "translation_error_m", "translation_error_rel", "speed_score", "camera_chamfer")
#: Metrics where higher is better (the others: lower is better).
HIGHER_IS_BETTER = ("iou_2d", "iou_3d")
#: Search and refinement columns: the search's best soft IoU at its resolution, the refinement's
#: IoU after it (refinement resolution), and the IoU of the image's mask against the ground
#: truth (``search`` and ``refined`` rows).
EXTRAS = ("search_score", "refine_iou_after", "segmentation_iou")
#: Mask sources named in the ``mask_source`` column.
MASK_SOURCES = ("network", "segmentation", "ground truth")
#: The label's lighting record (empty where the dataset has none, e.g. the SPE3R release).
LIGHTING = ("phase_angle_deg", "earth_in_view", "eclipse", "target_visibility")
#: Columns of ``per_image.csv``.
COLUMNS = ("model", "index", "filename", "method", *METRICS, *EXTRAS, "mask_source", *LIGHTING)
#: Metrics shown in the Markdown tables (every metric is in the CSV files).
SHOWN = ("chamfer_l1_paper", "chamfer_l1_occnet", "camera_chamfer", "iou_2d", "iou_3d",
         "rotation_error_deg", "rotation_error_sym_deg", "rotation_error_folded_deg",
         "translation_error_rel")
MESH_RANKING_FILE = "mesh_ranking.csv"
"""Per ranked image: its own model's rank among the split's meshes (``mesh_ranking`` > 0)."""
OUTPUT_FILES = ("per_image.csv", "per_model.csv", "per_model.md", "summary.csv", "summary.md",
                "per_model.png", "qualitative.png", "consistency.png", "eval.json")
"""What :func:`evaluate` writes (the PNGs unless ``figures`` is off)."""


@dataclass(frozen=True)
class EvalOptions:
    """Settings of ``sq-mitsuba eval``."""

    split: Literal["val", "test"] = "val"
    "Dataset split to evaluate: 'val' (held-out images of training models) or 'test' (new models)."
    limit: int | None = in_range(1, 10_000_000, default=None)
    "Evaluate at most this many images, spread evenly over the split (None: all)."
    batch_size: int = in_range(1, 1024, default=16)
    "Images per network batch (and per refinement batch)."
    refine: bool = False
    "Also search the pose and refine it at test time (rows search, refined, refined_gt)."
    mask: Literal["network", "segmentation"] = "network"
    "Mask read from the image: the network's mask head (segmentation for a model without one)."
    refine_ground_truth: bool = True
    "With refine, also search and refine against the ground-truth mask (an upper bound)."
    search: SearchOptions = field(default_factory=SearchOptions)
    "Global pose search settings."
    refinement: RefineOptions = field(default_factory=lambda: SEARCH_REFINEMENT)
    """Refinement after the search (by default the pose only, its rotation held near the
    search's: shape changes degraded Chamfer-L1; see learning.search.SEARCH_REFINEMENT)."""
    baseline: bool = True
    "Also score the trivial baseline (needs the dataset's train split)."
    baseline_images: int = in_range(1, 1_000_000, default=256)
    "Training images (spread evenly) whose mean prediction and mean pose make the baseline."
    level: int = in_range(0, 5, default=3)
    "Icosphere level of the primitive meshes for surface points and silhouettes (3: 642)."
    surface_points: int = in_range(1, 1_000_000, default=2500)
    "Ground-truth surface points per image for the Chamfer distances."
    volume_points: int = in_range(1, 1_000_000, default=100_000)
    "Uniform points per model for the 3D IoU (at most those of samples.npz)."
    silhouette_spp: int = in_range(1, 1024, default=32)
    "Samples per pixel of the silhouettes scored by the 2D IoU."
    fast: bool = True
    "Predict with the batch-norm-folded network (same output up to ~1e-5; faster on CPU)."
    figures: bool = True
    "Draw per_model.png, qualitative.png and consistency.png."
    mesh_ranking: int = in_range(0, 10_000_000, default=0)
    "Network predictions ranked by Chamfer-L1 against every model of the split (0: off)."
    qualitative: int = in_range(1, 64, default=6)
    "Rows (images, spread over the split) of the qualitative grid."
    consistency_models: int = in_range(1, 16, default=3)
    "Models shown in the consistency figure."
    consistency_views: int = in_range(1, 16, default=6)
    "Images per model in the consistency figure."
    figure_size: int = in_range(32, 1024, default=192)
    "Width in pixels of the ray-cast pictures in the figures."


@dataclass
class EvalResult:
    """What :func:`evaluate` did.

    Attributes:
        rows: one dict per image and method (the ``per_image.csv`` rows, values unformatted).
        summary: {method: {metric: (mean, std, median)}}.
        images: images evaluated; images_per_second: over the whole loop (network, refinement
            and scoring); network_ms_per_image: the network alone.
        out_dir: output folder; files: the files written.
    """

    rows: list[dict[str, Any]]
    summary: dict[str, dict[str, tuple[float, float, float]]]
    images: int
    images_per_second: float
    network_ms_per_image: float
    out_dir: Path
    files: list[Path]

    def describe(self) -> str:
        """A few lines: throughput and the network's main numbers."""
        lines = [f"evaluated {self.images} images: {self.images_per_second:.2f} images/s "
                 f"(network alone {self.network_ms_per_image:.1f} ms/image)"]
        for method, stats in self.summary.items():
            parts = [f"{m} {stats[m][0]:.3f}" for m in ("chamfer_l1_paper", "iou_2d",
                                                        "rotation_error_deg")]
            lines.append(f"  {method}: " + ", ".join(parts))
        lines.append(f"wrote {len(self.files)} files to {self.out_dir}")
        return "\n".join(lines)


# ------------------------------------------------------------------------------- scoring


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
    from sq_mitsuba.evaluation.metrics import (
        camera_frame_chamfer,
        chamfer_l1,
        chamfer_l2,
        mask_iou,
        rotation_error_deg,
        speed_score,
        translation_error,
        volumetric_iou,
    )
    from sq_mitsuba.learning.losses import counted_surface_samples
    from sq_mitsuba.render.silhouette import render_assembly

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
        silhouettes = render_assembly(assembly, rotation, translation, renderer, level)
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
    }


def mean_rotation(rotations: Tensor) -> Tensor:
    """Chordal L2 mean (3, 3) of rotations (N, 3, 3): the arithmetic mean projected onto SO(3)
    by SVD (the rotation nearest to it in the Frobenius norm)."""
    u, _, vh = torch.linalg.svd(rotations.double().mean(0))
    d = torch.sign(torch.linalg.det(u @ vh))
    return u @ torch.diag(torch.stack([torch.ones_like(d), torch.ones_like(d), d])) @ vh


# ------------------------------------------------------------------------------- tables


def summarise(rows: Sequence[dict[str, Any]], keys: Sequence[str] = ("method",),
              metrics: Sequence[str] = METRICS
              ) -> dict[tuple, dict[str, tuple[float, float, float]]]:
    """Mean, std (population) and median of every metric per group of ``keys``; values that
    are missing or not finite are left out (NaN where none is left)."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(tuple(row[k] for k in keys), []).append(row)
    out = {}
    for group, members in groups.items():
        stats = {}
        for metric in metrics:
            values = np.array([as_number(m.get(metric)) for m in members], dtype=np.float64)
            values = values[np.isfinite(values)]
            stats[metric] = ((float(values.mean()), float(values.std()), float(np.median(values)))
                             if len(values) else (math.nan, math.nan, math.nan))
        out[group] = stats
    return out


def as_number(value: Any) -> float:
    """``float(value)``, or NaN for a value that is not a number (a blank CSV cell, None)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def csv_text(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """CSV (comma, ``\\n`` line ends) of a header and rows."""
    buffer = _io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def format_stats(mean: float, std: float, median: float | None = None) -> str:
    """``mean ± std`` (and ``(median)``) with three decimals."""
    text = f"{mean:.3f} ± {std:.3f}"
    return text if median is None else f"{text} ({median:.3f})"


def write_tables(rows: Sequence[dict[str, Any]], out_dir: Path) -> dict[str, Any]:
    """per_image.csv, per_model.{csv,md}, summary.{csv,md}; returns the per-method summary
    {method: {metric: (mean, std, median)}}."""
    out_dir = Path(out_dir)
    atomic_write_text(out_dir / "per_image.csv",
                      csv_text(COLUMNS, [[r.get(c, "") for c in COLUMNS] for r in rows]))
    by_method = summarise(rows)
    counts = {method: sum(1 for r in rows if r["method"] == method) for (method,) in by_method}
    summary_rows = [[method, metric, *stats[metric], counts[method]]
                    for (method,), stats in by_method.items() for metric in METRICS]
    atomic_write_text(out_dir / "summary.csv", csv_text(
        ["method", "metric", "mean", "std", "median", "images"], summary_rows))
    md_rows = [[method, counts[method], *(format_stats(*stats[m]) for m in SHOWN)]
               for (method,), stats in by_method.items()]
    atomic_write_text(out_dir / "summary.md", (
        "Mean ± std (median) per method; every metric is in summary.csv.\n\n"
        + markdown_table(["method", "images", *SHOWN], md_rows)
        + "\nChamfer-L1 'paper': L1 nearest neighbours, the two directions summed (the "
        "convention of the paper's tables); 'occnet': L2 nearest neighbours, directions "
        "averaged; camera_chamfer: occnet Chamfer of the posed clouds over the true distance. "
        "Rotation errors in degrees ('sym': the least over the model's symmetries).\n"))
    by_model = summarise(rows, ("model", "method"))
    model_counts = {key: sum(1 for r in rows if (r["model"], r["method"]) == key)
                    for key in by_model}
    model_rows = [[model, method, metric, *stats[metric], model_counts[(model, method)]]
                  for (model, method), stats in sorted(by_model.items()) for metric in METRICS]
    atomic_write_text(out_dir / "per_model.csv", csv_text(
        ["model", "method", "metric", "mean", "std", "median", "images"], model_rows))
    md = [[model, method, model_counts[(model, method)],
           *(format_stats(*stats[m]) for m in SHOWN)]
          for (model, method), stats in sorted(by_model.items())]
    atomic_write_text(out_dir / "per_model.md",
                      "Mean ± std (median) per model and method.\n\n"
                      + markdown_table(["model", "method", "images", *SHOWN], md))
    return {method: stats for (method,), stats in by_method.items()}


# ------------------------------------------------------------------------------- data


def collate(items: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Dataset items -> one batch: tensors stacked, other values in lists."""
    out: dict[str, Any] = {}
    for key in items[0]:
        values = [item[key] for item in items]
        out[key] = torch.stack(values) if isinstance(values[0], Tensor) else values
    return out


def evenly(count: int, limit: int | None) -> list[int]:
    """``limit`` indices spread evenly over ``range(count)`` (all when None or larger)."""
    if limit is None or limit >= count:
        return list(range(count))
    return sorted({int(i) for i in np.linspace(0, count - 1, limit).round()})


def label_record(label: dict[str, Any]) -> dict[str, Any]:
    """The filename and lighting record (:data:`LIGHTING`) of one label ("" where absent)."""
    return {"filename": label.get("filename", ""),
            **{key: label.get(key, "") for key in LIGHTING}}


def volume_points(model_dir: Path, count: int) -> tuple[Tensor, Tensor]:
    """Up to ``count`` points uniform in the cube around a model (N, 3) float64 and whether
    each is inside (N,) bool: ``samples.npz``'s uniform points, or, without them (the SPE3R
    release), points uniform in the unit cube labelled by ray casting the mesh."""
    from sq_mitsuba.data.spe3r.layout import MODELS, SAMPLES_FILE, DatasetError, load_model

    rng = np.random.default_rng(0)
    path = model_dir / MODELS / SAMPLES_FILE
    if path.is_file():
        try:
            with np.load(path) as samples:
                points = np.asarray(samples["uniform_points"], dtype=np.float64)
                inside = np.asarray(samples["uniform_inside"], dtype=bool)
        except Exception as error:  # numpy raises several kinds on corrupt archives
            raise DatasetError(f"{path}: cannot read uniform_points ({error})") from None
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


class _ModelData:
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


# ------------------------------------------------------------------------------- methods


def baseline_prediction(predictor: Any, data_root: Path, count: int,
                        batch_size: int = 32, split: str = "train"
                        ) -> tuple[Tensor, Tensor, Tensor]:
    """The trivial baseline: mean raw output (1, M, 16) of the network over up to ``count``
    training images (spread evenly), with the mean rotation (1, 3, 3) and translation (1, 3)
    of their labels. ``split``: the split those images come from (``sq-mitsuba demo`` takes
    its own test images when the checkpoint stores no baseline).

    Raises:
        ValueError: the split has no images.
    """
    from sq_mitsuba.data.spe3r import Spe3rDataset

    train = Spe3rDataset(data_root, split, image_size=predictor.image_size, num_surface=1,
                         num_occupancy=2)
    if len(train) == 0:
        raise ValueError(f"{data_root}: no images for the baseline (the {split!r} split "
                         "is empty); evaluate without it (--no-baseline)")
    camera = train.camera.rescaled(predictor.image_size, predictor.image_size)
    indices = evenly(len(train), count)
    raws, rotations, translations = [], [], []
    for start in range(0, len(indices), batch_size):
        batch = collate([train[i] for i in indices[start:start + batch_size]])
        raws.append(raw_from_assembly(predictor.predict(batch["image"], camera).assembly))
        rotations.append(batch["rotation"])
        translations.append(batch["translation"])
    return (torch.cat(raws).double().mean(0, keepdim=True),
            mean_rotation(torch.cat(rotations))[None],
            torch.cat(translations).double().mean(0, keepdim=True))


@dataclass
class _Searched:
    """Search and search + refinement of a batch (items not searched keep the network's
    prediction, with NaN scores)."""

    search: tuple[Assembly, Tensor, Tensor]
    refined: tuple[Assembly, Tensor, Tensor]
    search_score: Tensor
    refine_iou: Tensor
    search_seconds: float
    seconds: float


def search_start(predictor: Any, images: Tensor, camera: Camera, prediction: Any,
                 turns: int) -> Any:
    """The prediction the pose search starts from: ``prediction`` (``predictor``'s for
    ``images``) itself, or (``turns`` > 1, for a predictor that can turn these images) the
    same read again from ``turns`` in-plane turns of ``images`` (:meth:`Predictor.read_turns`:
    the rotation and hypotheses from the copies' product, the assembly, position and mask as
    their means; the unturned pass is not run again)."""
    can_turn = getattr(predictor, "can_turn", None)
    if turns <= 1 or can_turn is None or not can_turn(camera):
        return prediction
    return predictor.read_turns(images, prediction, turns, camera)


def search_where(prediction: Any, masks: Tensor, usable: Tensor, camera: Camera,
                 search: SearchOptions, refinement: RefineOptions) -> _Searched:
    """:func:`~sq_mitsuba.learning.search.search_and_refine` of the items where ``usable``
    (B,) against ``masks`` (B, S, S), with the prediction's rotation hypotheses when it has
    them (a uniform grid otherwise)."""
    from sq_mitsuba.learning.search import search_and_refine

    params = prediction.assembly.params.detach().clone().double()
    rotation = prediction.rotation.detach().clone().double()
    translation = prediction.translation.detach().clone().double()
    hypotheses = getattr(prediction, "rotation_hypotheses", None)
    score_nan = torch.full((len(rotation),), math.nan, dtype=torch.float64)
    refine_iou = score_nan.clone()
    search_rotation, search_translation = rotation.clone(), translation.clone()
    refined_params = params.clone()
    refined_rotation, refined_translation = rotation.clone(), translation.clone()
    chosen = torch.nonzero(usable).flatten()
    search_seconds = seconds = 0.0
    if len(chosen):
        result = search_and_refine(
            Assembly(params[chosen]), rotation[chosen], translation[chosen], masks[chosen],
            camera, None if hypotheses is None else hypotheses[chosen], search, refinement)
        search_rotation[chosen] = result.search_rotation.double()
        search_translation[chosen] = result.search_translation.double()
        score_nan[chosen] = result.search.score.double()
        refined_params[chosen] = result.assembly.params.detach().double()
        refined_rotation[chosen] = result.rotation.double()
        refined_translation[chosen] = result.translation.double()
        refine_iou[chosen] = result.iou.double()
        search_seconds, seconds = result.search_seconds, result.total_seconds
    return _Searched((Assembly(params), search_rotation, search_translation),
                     (Assembly(refined_params), refined_rotation, refined_translation),
                     score_nan, refine_iou, search_seconds, seconds)


def image_masks(prediction: Any, images: Tensor, source: str) -> tuple[Tensor, Tensor, str]:
    """The masks (B, S, S) bool read from the images, which are usable (B,), and their source
    (:data:`MASK_SOURCES`): the prediction's mask head when ``source`` is "network" and it has
    one, else the threshold segmentation of ``images`` (B, 1, S, S)."""
    mask = getattr(prediction, "mask", None)
    if source == "network" and mask is not None:
        masks = mask.detach().cpu() > 0.5
        return masks, masks.flatten(1).any(dim=1), "network"
    masks, usable = _segmented(images)
    return masks, usable, "segmentation"


def _segmented(images: Tensor) -> tuple[Tensor, Tensor]:
    """Masks (B, S, S) bool segmented from images (B, 1, S, S), and which are usable (B,):
    segmented, and without the segmentation's warning (a lit Earth merged with the target: in
    the illumination study, fitting such masks lowered the 2D IoU from 0.32 to 0.21)."""
    from sq_mitsuba.data.segmentation import segment_target

    masks, usable = [], []
    for image in images[:, 0].double().numpy():
        try:
            segmentation = segment_target(image)
            masks.append(torch.from_numpy(segmentation.mask))
            usable.append(segmentation.warning is None)
        except ValueError:  # nothing bright (an eclipse, a black frame): no target to refine to
            masks.append(torch.zeros(image.shape, dtype=torch.bool))
            usable.append(False)
    return torch.stack(masks), torch.tensor(usable)


# ------------------------------------------------------------------------------- driver


def with_fast_path(predictor: Any, fast: bool) -> Any:
    """``predictor``, or, when ``fast`` and it has none, a copy predicting with the
    BatchNorm-folded network (folding takes about a second: done once the inputs are
    checked)."""
    from sq_mitsuba.learning.inference import Predictor

    if not fast or predictor.fast:
        return predictor
    folded = Predictor(predictor.model, predictor.camera, fast=True)
    folded.source = predictor.source
    return folded


def check_predictor(predictor: Any) -> None:
    """Refuse a network that cannot read SPE3R-layout images (grey, one channel)."""
    channels = predictor.model.config.in_channels
    if channels != 1:
        source = getattr(predictor, "source", None) or "model"
        raise ValueError(f"{source}: the network takes {channels}-channel images; datasets in "
                         "the SPE3R layout are grey (1 channel)")


def open_split(data_root: str | Path, split: str, options: EvalOptions, image_size: int) -> Any:
    """The :class:`Spe3rDataset` of ``split``; a one-line error when it is missing or empty."""
    from sq_mitsuba.data.spe3r import Spe3rDataset

    dataset = Spe3rDataset(data_root, split, image_size=image_size,
                           num_surface=options.surface_points, num_occupancy=2)
    if len(dataset) == 0:
        where = "test models" if split == "test" else "training models (whose held-out " \
            "images make 'val')"
        skipped = f"; left out: {', '.join(dataset.skipped)}" if dataset.skipped else ""
        raise ValueError(f"{data_root}: the {split!r} split is empty (splits.csv lists no "
                         f"{where}{skipped})")
    return dataset


def evaluate(predictor: Any, data_root: str | Path, out_dir: str | Path,
             options: EvalOptions | None = None, progress: bool = True,
             label: str | None = None) -> EvalResult:
    """Evaluate ``predictor`` (a :class:`sq_mitsuba.learning.inference.Predictor`) on a
    dataset split and write the files listed in the module docstring.

    Every input is checked before the work starts: the network's input channels, the dataset
    and split (not empty), the train split when the baseline is on, and the output folder.

    Args:
        label: the run's name in ``eval.json`` (the report's row label; default: the
            checkpoint's folder name).
    """
    from tqdm import tqdm

    from sq_mitsuba.evaluation.metrics import mask_iou
    from sq_mitsuba.io import check_output_folder
    from sq_mitsuba.render.silhouette import SilhouetteRenderer

    options = options or EvalOptions()
    validate(options)
    check_predictor(predictor)
    data_root, out_dir = Path(data_root), Path(out_dir)
    check_output_folder(out_dir)
    image_size = predictor.image_size
    dataset = open_split(data_root, options.split, options, image_size)
    camera = dataset.camera.rescaled(image_size, image_size)
    predictor = with_fast_path(predictor, options.fast)
    started = time.perf_counter()
    baseline = None
    if options.baseline:
        base_raw, base_rotation, base_translation = baseline_prediction(
            predictor, data_root, options.baseline_images, options.batch_size)
        baseline = (Assembly.from_raw(base_raw), base_rotation, base_translation)
    out_dir.mkdir(parents=True, exist_ok=True)
    renderer = SilhouetteRenderer(camera, spp=options.silhouette_spp)
    models = _ModelData(dataset, options.volume_points)
    indices = evenly(len(dataset), options.limit)
    wanted = {indices[k] for k in evenly(len(indices), options.qualitative)}
    ranked = ({indices[k] for k in evenly(len(indices), options.mesh_ranking)}
              if options.mesh_ranking and len(dataset.models) >= 2 else set())
    to_rank: list[tuple[int, int, str, Assembly]] = []  # item, model index, model, assembly
    rows: list[dict[str, Any]] = []
    examples: list[dict[str, Any]] = []
    network_seconds = search_seconds = refine_seconds = 0.0
    loop_started = time.perf_counter()
    with tqdm(total=len(indices), unit="img", disable=not progress, dynamic_ncols=True,
              desc=f"eval {options.split}") as bar:
        for start in range(0, len(indices), options.batch_size):
            chunk = indices[start:start + options.batch_size]
            batch = collate([dataset[i] for i in chunk])
            size = len(chunk)
            tick = time.perf_counter()
            prediction = predictor.predict(batch["image"], camera)
            network_seconds += time.perf_counter() - tick
            model_indices = [int(m) for m in batch["model_index"]]
            symmetries = [models.symmetry(m) for m in model_indices]
            volumes = [models.volume(m) for m in model_indices]
            candidates: dict[str, tuple[Assembly, Tensor, Tensor]] = {
                "network": (prediction.assembly, prediction.rotation, prediction.translation)}
            extras: dict[str, dict[str, Tensor]] = {}
            sources: dict[str, str] = {}
            if options.refine:
                gt_masks = batch["mask"][:, 0] > 0.5
                tick = time.perf_counter()
                start = search_start(predictor, batch["image"], camera, prediction,
                                     options.search.turns)
                turned_seconds = time.perf_counter() - tick  # the search's start: its cost
                masks, usable, mask_source = image_masks(start, batch["image"], options.mask)
                searched = search_where(start, masks, usable, camera, options.search,
                                        options.refinement)
                search_seconds += turned_seconds + searched.search_seconds
                refine_seconds += turned_seconds + searched.seconds
                mask_iou_gt = mask_iou(masks.double(), gt_masks.double())
                candidates["search"] = searched.search
                candidates["refined"] = searched.refined
                for method in ("search", "refined"):
                    extras[method] = {"search_score": searched.search_score,
                                      "refine_iou_after": searched.refine_iou,
                                      "segmentation_iou": mask_iou_gt}
                    sources[method] = mask_source
                if options.refine_ground_truth:
                    upper = search_where(start, gt_masks, torch.ones(size, dtype=torch.bool),
                                         camera, options.search, options.refinement)
                    candidates["refined_gt"] = upper.refined
                    extras["refined_gt"] = {"search_score": upper.search_score,
                                            "refine_iou_after": upper.refine_iou}
                    sources["refined_gt"] = "ground truth"
            if baseline is not None:
                candidates["baseline"] = (Assembly(baseline[0].params.expand(size, -1, -1)),
                                          baseline[1].expand(size, -1, -1),
                                          baseline[2].expand(size, -1))
            for method, (assembly, rotation, translation) in candidates.items():
                metrics = score(assembly, rotation, translation, batch, renderer, symmetries,
                                volumes, options.level)
                metrics.update(extras.get(method, {}))
                for k, item in enumerate(chunk):
                    row = {"model": batch["model"][k], "index": int(batch["index"][k]),
                           "method": method, "mask_source": sources.get(method, ""),
                           **label_record(dataset.items[item][2])}
                    row.update({name: float(value[k]) for name, value in metrics.items()})
                    for name in EXTRAS:  # NaN: not searched (no target segmented) -> blank
                        if name in row and not math.isfinite(row[name]):
                            row[name] = ""
                    rows.append(row)
            for k, item in enumerate(chunk):
                if item in ranked:
                    to_rank.append((int(batch["index"][k]), model_indices[k], batch["model"][k],
                                    Assembly(prediction.assembly.params[k:k + 1].detach())))
                if item in wanted:
                    example = {"image": batch["image"][k, 0], "mask": batch["mask"][k, 0],
                               "model": batch["model"][k], "index": int(batch["index"][k]),
                               "gt_rotation": batch["rotation"][k],
                               "gt_translation": batch["translation"][k]}
                    for method, (assembly, rotation, translation) in candidates.items():
                        example[method] = (assembly[k], rotation[k].detach(),
                                           translation[k].detach())
                    examples.append(example)
            bar.update(size)
            bar.set_postfix(img_s=f"{bar.n / (time.perf_counter() - loop_started):.2f}")
    loop_seconds = time.perf_counter() - loop_started
    summary = write_tables(rows, out_dir)
    files = [out_dir / name for name in OUTPUT_FILES[:5]]
    ranking = None
    if to_rank:
        from sq_mitsuba.evaluation.mesh_ranking import write_mesh_ranking

        ranking = write_mesh_ranking(dataset, to_rank, out_dir / MESH_RANKING_FILE,
                                     options.surface_points, options.level, progress)
        files.append(out_dir / MESH_RANKING_FILE)
    if options.figures:
        from sq_mitsuba.evaluation.figures import (
            plot_consistency,
            plot_per_model,
            plot_qualitative,
        )

        figure_camera = dataset.camera.rescaled(options.figure_size, options.figure_size)
        files.append(plot_per_model(rows, out_dir / "per_model.png"))
        files.append(plot_qualitative(examples, dataset, camera, figure_camera, renderer,
                                      out_dir / "qualitative.png", options.level))
        by_model: dict[int, list[int]] = {}
        for item in indices:
            by_model.setdefault(dataset.items[item][0], []).append(item)
        shown = [by_model[m] for m in sorted(by_model)]
        shown = [shown[k] for k in evenly(len(shown), options.consistency_models)]
        views = [[group[k] for k in evenly(len(group), options.consistency_views)]
                 for group in shown]
        files.append(plot_consistency(dataset, views, predictor, camera, figure_camera,
                                      out_dir / "consistency.png", options.level))
    images = len(indices)
    images_per_second = images / loop_seconds
    atomic_write_json(out_dir / "eval.json", {
        "data": str(data_root), "split": options.split, "images": images,
        "models": sorted({r["model"] for r in rows}),
        "methods": [m for m in METHODS if any(r["method"] == m for r in rows)],
        "label": label if label is not None else _default_label(predictor),
        "checkpoint": str(getattr(predictor, "source", None) or ""),
        "num_primitives": predictor.num_primitives, "image_size": image_size,
        "options": to_dict(options),
        "symmetries": {dataset.models[m]: len(s) for m, s in sorted(models.symmetries.items())},
        "images_per_second": round(images_per_second, 4),
        "network_ms_per_image": round(1000 * network_seconds / images, 3),
        "search_ms_per_image": round(1000 * search_seconds / images, 3),
        "search_refine_ms_per_image": round(1000 * refine_seconds / images, 3),
        "mesh_ranking": ranking,
        "loop_seconds": round(loop_seconds, 3),
        "wall_seconds": round(time.perf_counter() - started, 3),
    })
    files.append(out_dir / "eval.json")
    return EvalResult(rows, summary, images, images_per_second,
                      1000 * network_seconds / images, out_dir, files)


def _default_label(predictor: Any) -> str:
    """The checkpoint's folder name (a training run's output folder), or its file stem."""
    source = getattr(predictor, "source", None)
    if not source:
        return "model"
    source = Path(source)
    from sq_mitsuba.learning.checkpoint import SHIPPED_MODEL

    if source == SHIPPED_MODEL:
        return "shipped"
    return source.parent.name or source.stem


def evaluate_checkpoint(checkpoint: str | Path | None, data_root: str | Path,
                        out_dir: str | Path, options: EvalOptions | None = None,
                        progress: bool = True, label: str | None = None) -> EvalResult:
    """:func:`evaluate` the model of a checkpoint file (None: the model shipped with the
    package; a clear error when there is none)."""
    from sq_mitsuba.learning.checkpoint import load_model

    options = options or EvalOptions()
    validate(options)
    predictor = load_model(checkpoint)  # evaluate folds it once the inputs are checked
    return evaluate(predictor, data_root, out_dir, options, progress=progress, label=label)

