"""Render a dataset in the SPE3R layout (see :mod:`.layout`) with Mitsuba's path tracer.

Resuming: each image's label is first written to ``<model>/.progress/<index>.json``, after its
image and mask, so a label there means the image is complete. ``labels.json`` is assembled from
them once a model is done. Every file is written atomically, and every image has its own seed,
so a run killed at any point and restarted with the same command ends byte-identical to an
uninterrupted one.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sq_mitsuba.data.frames import sample_frame
from sq_mitsuba.data.spe3r.layout import (
    IMAGES,
    MASKS,
    MESH_FILE,
    MODELS,
    PROGRESS,
    DatasetError,
    load_model,
    read_splits,
    write_exr,
    write_png,
)
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.io import atomic_path, atomic_write_json, atomic_write_text, read_json
from sq_mitsuba.render.scene_config import SceneConfig

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
    #: wide; default: :meth:`Camera.default` (SPEED's 35.45 deg horizontal field of view).
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
    from sq_mitsuba.data.spe3r.layout import write_splits

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

