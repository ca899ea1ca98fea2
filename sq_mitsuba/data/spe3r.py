"""Datasets in the SPE3R layout: render one with Mitsuba, read one (ours or SPE3R), check one.

Layout (DESIGN section 6)::

    <root>/camera.json                    SPEED-style intrinsics
    <root>/splits.csv                     "model,train" / "model,test", no header
    <root>/<model>/labels.json            [{filename, q_vbs2tango_true, r_Vo2To_vbs_true, ...}]
    <root>/<model>/images/<index>.png     8-bit grayscale (.jpg accepted on read)
    <root>/<model>/masks/<index>.png      binary mask of the target alone
    <root>/<model>/models/                model_normalized.obj (+ samples.npz, model_card.json)

Resuming: each image's label is first written to ``<model>/.progress/<index>.json``, after its
image and mask, so a label there means the image is complete. ``labels.json`` is assembled from
them once a model is done. Every file is written atomically, and every image has its own seed,
so a run killed at any point and restarted with the same command ends byte-identical to an
uninterrupted one.
"""

from __future__ import annotations

import csv
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from sq_mitsuba.camera import Camera
from sq_mitsuba.data.frames import SceneConfig, sample_frame
from sq_mitsuba.io import (
    atomic_path,
    atomic_write_json,
    atomic_write_text,
    read_json,
    save_figure,
)
from sq_mitsuba.rotation import quaternion_to_matrix

IMAGES, MASKS, MODELS, PROGRESS = "images", "masks", "models", ".progress"
MESH_FILE = "model_normalized.obj"
SAMPLES_FILE = "samples.npz"
#: SPE3R v1.1 validation images of each training model.
VALIDATION_INDICES = frozenset(range(400, 500)) | frozenset(range(900, 1000))


class DatasetError(ValueError):
    """A dataset or model folder that cannot be used; the message names the file."""


# ------------------------------------------------------------------------ small helpers


def read_splits(path: Path) -> dict[str, str]:
    """``splits.csv`` as {model: "train" | "test"}."""
    splits: dict[str, str] = {}
    with open(path, newline="", encoding="utf-8") as handle:
        for line_number, row in enumerate(csv.reader(handle), start=1):
            if not row:
                continue
            if len(row) != 2 or row[1].strip() not in ("train", "test"):
                raise DatasetError(f"{path}:{line_number}: expected 'model,train|test', "
                                   f"got {','.join(row)!r}")
            splits[row[0].strip()] = row[1].strip()
    return splits


def write_png(path: Path, array: np.ndarray) -> None:
    """8-bit grayscale PNG, written atomically (deterministic bytes for the same array)."""
    with atomic_path(path) as tmp:
        Image.fromarray(array, mode="L").save(tmp, format="PNG", optimize=False)


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
    from sq_mitsuba.render.preview import read_obj
    from sq_mitsuba.spacecraft.materials import MATERIALS

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
                face_material = samples["face_material"] if "face_material" in samples else None
        except Exception as error:  # numpy raises several kinds on corrupt archives
            raise DatasetError(f"{samples_path}: cannot read ({error})") from None
        if face_material is not None:
            if len(face_material) != len(faces):
                raise DatasetError(f"{samples_path}: face_material has {len(face_material)} "
                                   f"entries for {len(faces)} faces")
            tags = np.asarray(MATERIALS)[np.asarray(face_material, dtype=np.int64)]
    return vertices, faces, tags


# ------------------------------------------------------------------------ writer


@dataclass
class RenderOptions:
    """Options of ``sq-mitsuba dataset render``."""

    images_per_model: int = 1000
    seed: int = 0
    resolution: int = 256
    spp: int = 64
    exr: bool = False
    scene: SceneConfig = field(default_factory=SceneConfig.load)
    #: Intrinsics to render with (e.g. a SPEED camera.json), rescaled to ``resolution`` pixels
    #: wide; default: the project's default camera (DESIGN section 3).
    camera: Camera | None = None

    def dataset_camera(self) -> Camera:
        if self.camera is None:
            return Camera.default(self.resolution)
        if self.camera.width == self.resolution:
            return self.camera
        return self.camera.rescaled(self.resolution)

    def validate(self) -> None:
        if self.images_per_model < 1:
            raise ValueError(f"images_per_model: expected >= 1, got {self.images_per_model}")
        if self.resolution < 8:
            raise ValueError(f"resolution: expected >= 8, got {self.resolution}")
        if self.spp < 1:
            raise ValueError(f"spp: expected >= 1, got {self.spp}")


@dataclass
class RenderSummary:
    rendered: int = 0
    skipped: int = 0
    models_done: list[str] = field(default_factory=list)
    failures: dict[str, str] = field(default_factory=dict)


def find_models(models_dir: Path) -> list[str]:
    """Model folders (those holding ``models/model_normalized.obj``), sorted by name."""
    if not models_dir.is_dir():
        raise DatasetError(f"{models_dir}: not a folder")
    names = sorted(p.parent.parent.name for p in models_dir.glob(f"*/{MODELS}/{MESH_FILE}"))
    splits_path = models_dir / "splits.csv"
    if splits_path.is_file():
        # Models named in splits.csv whose files are missing still count, so they fail loudly.
        names = sorted(set(names) | set(read_splits(splits_path)))
    if not names:
        raise DatasetError(f"{models_dir}: no model folders (<model>/{MODELS}/{MESH_FILE})")
    return names


def check_writable(out_dir: Path) -> None:
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out_dir / ".write-test", "ok\n")
        (out_dir / ".write-test").unlink()
    except OSError as error:
        raise DatasetError(f"{out_dir}: output folder is not writable ({error.strerror})") \
            from None


def label_entry(filename: str, frame: Any, exposure: float) -> dict[str, Any]:
    return {
        "filename": filename,
        "q_vbs2tango_true": [round(v, 12) for v in frame.quaternion],
        "r_Vo2To_vbs_true": [round(v, 12) for v in frame.translation],
        "exposure": exposure,
        **frame.label_extras(),
    }


def _copy_model_files(source: Path, target: Path) -> None:
    target.mkdir(parents=True, exist_ok=True)
    for item in sorted(source.iterdir()):
        if item.is_file() and not item.name.startswith("."):
            destination = target / item.name
            if destination.exists() and destination.stat().st_size == item.stat().st_size \
                    and destination.read_bytes() == item.read_bytes():
                continue
            with atomic_path(destination) as tmp:
                shutil.copyfile(item, tmp)


def render_image(scene: Any, vertices: np.ndarray, options: RenderOptions, model: str,
                 index: int, model_out: Path) -> None:
    """Render image ``index`` of ``model`` with ``scene`` (a :class:`SpaceScene`) and write its
    image, mask (and EXR), then its progress label, all atomically."""
    name = f"{index:06d}"
    frame = sample_frame(vertices, scene.camera, options.scene, options.seed, model, index)
    result = scene.render(frame)
    write_png(model_out / IMAGES / f"{name}.png", result.image_8bit())
    write_png(model_out / MASKS / f"{name}.png", result.mask)
    if options.exr:
        write_exr(model_out / "exr" / f"{name}.exr",
                  {"Y": result.radiance, "Z": result.depth, "A": result.coverage})
    # The label is the commit marker: written last, it says the image is complete.
    atomic_write_json(model_out / PROGRESS / f"{name}.json",
                      label_entry(f"{name}.png", frame, result.exposure))


def render_model(models_dir: Path, out_dir: Path, model: str, camera: Camera,
                 options: RenderOptions, tick: Callable[[int], None] = lambda n: None,
                 ) -> tuple[int, int]:
    """Render (or finish) one model's images, masks and labels; return (rendered, skipped)."""
    from sq_mitsuba.render.space import SpaceScene

    model_out = out_dir / model
    progress = model_out / PROGRESS
    labels_path = model_out / "labels.json"
    if labels_path.is_file() and not progress.exists() and \
            len(read_json(labels_path)) == options.images_per_model:
        tick(options.images_per_model)
        return 0, options.images_per_model
    vertices, faces, tags = load_model(models_dir / model)
    _copy_model_files(models_dir / model / MODELS, model_out / MODELS)
    progress.mkdir(parents=True, exist_ok=True)
    scene = None
    rendered = skipped = 0
    for index in range(options.images_per_model):
        name = f"{index:06d}"
        label_path = progress / f"{name}.json"
        if label_path.is_file() and (model_out / IMAGES / f"{name}.png").is_file() and \
                (model_out / MASKS / f"{name}.png").is_file():
            skipped += 1
            tick(1)
            continue
        if scene is None:
            scene = SpaceScene(vertices, faces, tags, camera, options.scene, spp=options.spp,
                               dataset_seed=options.seed, with_depth=options.exr)
        render_image(scene, vertices, options, model, index, model_out)
        rendered += 1
        tick(1)
    labels = [read_json(progress / f"{i:06d}.json") for i in range(options.images_per_model)]
    atomic_write_json(labels_path, labels)
    shutil.rmtree(progress)
    return rendered, skipped


def _start_worker(threads: int) -> None:
    import drjit as dr

    from sq_mitsuba.render.backend import mitsuba

    mitsuba()
    dr.set_thread_count(threads)


def render_dataset(models_dir: str | Path, out_dir: str | Path, options: RenderOptions,
                   progress: bool = True, workers: int = 1) -> RenderSummary:
    """Render every model of ``models_dir`` into ``out_dir`` in the SPE3R layout.

    A model that fails (missing or corrupt files, a full disk) is reported and skipped; the
    others go on. Calling again with the same arguments resumes where a run stopped. With
    ``workers > 1`` models render in parallel processes sharing the cores (each worker's
    images are identical to a single-process run: every image has its own seed).
    """
    from tqdm import tqdm

    options.validate()
    if workers < 1:
        raise ValueError(f"workers: expected >= 1, got {workers}")
    models_dir, out_dir = Path(models_dir), Path(out_dir)
    models = find_models(models_dir)
    check_writable(out_dir)
    camera = options.dataset_camera()
    atomic_write_json(out_dir / "camera.json", camera.to_speed_dict())
    from sq_mitsuba.data.library import write_splits

    splits_path = models_dir / "splits.csv"
    splits = read_splits(splits_path) if splits_path.is_file() else {}
    write_splits(out_dir, ((m, splits.get(m, "train")) for m in models))
    summary = RenderSummary()
    total = len(models) * options.images_per_model
    with tqdm(total=total, unit="img", disable=not progress, dynamic_ncols=True) as bar:

        def record(model: str, outcome: tuple[int, int] | BaseException) -> None:
            if isinstance(outcome, BaseException):
                summary.failures[model] = str(outcome)
                bar.write(f"failed: {model}: {outcome}")
                return
            summary.rendered += outcome[0]
            summary.skipped += outcome[1]
            summary.models_done.append(model)

        if workers == 1:
            for model in models:
                bar.set_description(model)
                try:
                    outcome = render_model(models_dir, out_dir, model, camera, options,
                                           tick=bar.update)
                except (DatasetError, OSError, ValueError) as error:
                    outcome = error
                record(model, outcome)
        else:
            import multiprocessing
            import os
            from concurrent.futures import ProcessPoolExecutor, as_completed

            threads = max(1, (os.cpu_count() or 1) // workers)
            with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                     initializer=_start_worker, initargs=(threads,)) as pool:
                jobs = {pool.submit(render_model, models_dir, out_dir, m, camera, options): m
                        for m in models}
                for job in as_completed(jobs):
                    try:
                        outcome = job.result()
                    except (DatasetError, OSError, ValueError) as error:
                        outcome = error
                    record(jobs[job], outcome)
                    bar.update(options.images_per_model)
    summary.models_done.sort()
    return summary


def preview_dataset(root: str | Path, out: str | Path, count: int = 16,
                    axis_length: float = 0.3) -> Path:
    """Contact sheet PNG: images with the mask outline and the pose's body axes drawn.

    The body axes x, y, z (red, green, blue, ``axis_length`` metres) are projected with the
    label pose and ``camera.json``; they start at the model origin (its centre of mass).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    root = Path(root)
    if count < 1:
        raise ValueError(f"count: expected >= 1, got {count}")
    camera = Camera.load(root / "camera.json")
    chosen: list[tuple[str, dict[str, Any]]] = []
    labels = {}
    for model in dataset_models(root):
        path = root / model / "labels.json"
        if path.is_file():
            labels[model] = read_json(path)
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
        image = _read_gray(root / model / IMAGES / label["filename"])
        mask = _read_gray(root / model / MASKS / label["filename"]) >= 128
        axis.imshow(image, cmap="gray", vmin=0, vmax=255)
        axis.contour(mask, levels=[0.5], colors=["#ffcc00"], linewidths=0.6)
        rotation = quaternion_to_matrix(torch.tensor(label["q_vbs2tango_true"],
                                                     dtype=torch.float64))
        origin = torch.tensor(label["r_Vo2To_vbs_true"], dtype=torch.float64)
        ends = origin + axis_length * rotation.T  # rows: camera-frame tips of body x, y, z
        pixels = camera.project(torch.cat([origin[None], ends]).float()).numpy()
        for tip, colour in zip(pixels[1:], ("r", "g", "b"), strict=True):
            axis.plot([pixels[0, 0], tip[0]], [pixels[0, 1], tip[1]], colour, linewidth=1.2)
        phase = label.get("phase_angle_deg")
        subtitle = f"phase {phase:.0f} deg" if phase is not None else ""
        axis.set_title(f"{model} {label['filename']}\n{subtitle}", fontsize=7)
        axis.set_xlim(0, camera.width)
        axis.set_ylim(camera.height, 0)
    figure.tight_layout()
    return save_figure(figure, out)


# ------------------------------------------------------------------------ reader


def _read_gray(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as image:
            return np.asarray(image.convert("L"))
    except (OSError, ValueError) as error:
        raise DatasetError(f"{path}: cannot read image ({error})") from None


def _resize(array: np.ndarray, size: int, resample: int) -> np.ndarray:
    if array.shape == (size, size):
        return array
    return np.asarray(Image.fromarray(array).resize((size, size), resample))


class Spe3rDataset(torch.utils.data.Dataset):
    """A torch Dataset over an SPE3R-layout folder (ours, or the SPE3R release).

    Each item is a dict: ``image`` (1, S, S) float in [0, 1]; ``mask`` (1, S, S) float in
    {0, 1}; ``quaternion`` (4,), ``rotation`` (3, 3) and ``translation`` (3,), the pose body ->
    camera; ``camera`` (3, 3) intrinsics for S x S pixels; ``model`` (str) and ``model_index``;
    ``surface_points`` (num_surface, 3); ``occupancy_points`` (num_occupancy, 3) with
    ``occupancy_labels`` (num_occupancy,), half inside and half outside where the model has
    enough of each; ``index`` of the image within its model.

    Args:
        root: dataset folder.
        split: "train", "val" (images 400-499 and 900-999 of the train models) or "test".
        image_size: S, the side images and masks are resized to (default 128).
        num_surface, num_occupancy: points per item (2,500 and 10,000 by default).
        seed: makes the point subsets reproducible (item i uses seed + i).
    """

    def __init__(self, root: str | Path, split: str = "train", image_size: int = 128,
                 num_surface: int = 2500, num_occupancy: int = 10_000, seed: int = 0):
        if split not in ("train", "val", "test"):
            raise ValueError(f"split: expected 'train', 'val' or 'test', got {split!r}")
        self.root = Path(root)
        for required in ("camera.json", "splits.csv"):
            if not (self.root / required).is_file():
                raise DatasetError(f"{self.root / required}: missing")
        self.camera = Camera.load(self.root / "camera.json")
        self.image_size, self.seed = image_size, seed
        self.num_surface, self.num_occupancy = num_surface, num_occupancy
        splits = read_splits(self.root / "splits.csv")
        wanted = "test" if split == "test" else "train"
        self.models = sorted(m for m, s in splits.items() if s == wanted)
        self.items: list[tuple[int, int, dict[str, Any]]] = []
        for model_index, model in enumerate(self.models):
            labels_path = self.root / model / "labels.json"
            try:
                labels = read_json(labels_path)
            except FileNotFoundError:
                raise DatasetError(f"{labels_path}: missing") from None
            except ValueError as error:
                raise DatasetError(str(error)) from None
            for index, label in enumerate(labels):
                in_val = index in VALIDATION_INDICES
                if split == "test" or (split == "val") == in_val:
                    self.items.append((model_index, index, label))
        self._points: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.items)

    def _image_path(self, model: str, folder: str, filename: str) -> Path:
        path = self.root / model / folder / filename
        if path.is_file():
            return path
        for suffix in (".png", ".jpg", ".jpeg"):
            candidate = path.with_suffix(suffix)
            if candidate.is_file():
                return candidate
        raise DatasetError(f"{path}: missing")

    def model_points(self, model_index: int) -> dict[str, np.ndarray]:
        """Surface and labelled occupancy points of a model (from samples.npz, or the mesh)."""
        if model_index not in self._points:
            self._points[model_index] = _model_points(self.root / self.models[model_index])
        return self._points[model_index]

    def __getitem__(self, item: int) -> dict[str, Any]:
        model_index, index, label = self.items[item]
        model = self.models[model_index]
        size = self.image_size
        image = _resize(_read_gray(self._image_path(model, IMAGES, label["filename"])), size,
                        Image.BILINEAR)
        mask = _resize(_read_gray(self._image_path(model, MASKS, label["filename"])), size,
                       Image.NEAREST)
        quaternion = torch.tensor(label["q_vbs2tango_true"], dtype=torch.float32)
        camera = self.camera.rescaled(size, size)
        points = self.model_points(model_index)
        rng = np.random.default_rng(self.seed + item)
        surface = points["surface"][rng.choice(len(points["surface"]), self.num_surface,
                                               replace=len(points["surface"]) < self.num_surface)]
        occupancy, labels = _balanced_occupancy(points["points"], points["inside"],
                                                self.num_occupancy, rng)
        return {
            "image": torch.from_numpy(image.astype(np.float32) / 255.0)[None],
            "mask": torch.from_numpy((mask >= 128).astype(np.float32))[None],
            "quaternion": quaternion,
            "rotation": quaternion_to_matrix(quaternion),
            "translation": torch.tensor(label["r_Vo2To_vbs_true"], dtype=torch.float32),
            "camera": camera.matrix(),
            "model": model,
            "model_index": model_index,
            "index": index,
            "surface_points": torch.from_numpy(surface.astype(np.float32)),
            "occupancy_points": torch.from_numpy(occupancy.astype(np.float32)),
            "occupancy_labels": torch.from_numpy(labels.astype(np.float32)),
        }


def _balanced_occupancy(points: np.ndarray, inside: np.ndarray, count: int,
                        rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    inside_idx, outside_idx = np.flatnonzero(inside), np.flatnonzero(~inside)
    want_in = min(count // 2, len(inside_idx))
    want_out = count - want_in
    chosen = np.concatenate([
        rng.choice(inside_idx, want_in, replace=False) if want_in else np.empty(0, int),
        rng.choice(outside_idx, want_out, replace=len(outside_idx) < want_out),
    ])
    return points[chosen], inside[chosen]


def _model_points(model_dir: Path) -> dict[str, np.ndarray]:
    samples_path = model_dir / MODELS / SAMPLES_FILE
    if samples_path.is_file():
        with np.load(samples_path) as samples:
            return {
                "surface": samples["surface_points"],
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
    surface, _ = trimesh.sample.sample_surface(mesh, 100_000, seed=0)
    uniform = rng.uniform(-0.5, 0.5, (50_000, 3))
    near = surface[:50_000] + rng.normal(scale=0.01, size=(50_000, 3))
    points = np.concatenate([uniform, near])
    inside = RayCaster(vertices, faces).inside(points)
    return {"surface": np.asarray(surface), "points": points, "inside": np.asarray(inside)}


# ------------------------------------------------------------------------ check


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
                mask = _read_gray(root / model / MASKS / label["filename"]) >= 128
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


def dataset_models(root: Path) -> list[str]:
    """The models named in ``root/splits.csv``, sorted."""
    return sorted(read_splits(root / "splits.csv"))
