"""The training data: the dataset opened and checked, decoded once into caches, and served as
an endless stream of batches (:class:`~sq_mitsuba.training.batch.TrainingBatch`).

Convention: the training data are an endless stream of per-epoch permutations of the training
images (epoch e's permutation drawn from the seed and e); step s takes the next
``batch_size`` images of it, and an epoch is ceil(images / batch_size) steps. Under
``torchrun`` process r of N takes the r-th of N equal slices of each step's batch. Every
per-item random draw (points, augmentation) comes from (seed, step, position in the batch)
(:mod:`sq_mitsuba.training.random_streams`), so the stream can restart at any step.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.checks import value_checks
from sq_mitsuba.data.spe3r import MODELS, SAMPLES_FILE, Spe3rDataset
from sq_mitsuba.data.symmetry import model_symmetries, stack_symmetries
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.image_turns import check_rotation_exact
from sq_mitsuba.training.augment import (
    AugmentDraws,
    apply_augmentation,
    draw_augmentation,
    to_device,
)
from sq_mitsuba.training.batch import TrainingBatch
from sq_mitsuba.training.cache import (
    ImageCache,
    PointCache,
    decode_pixels,
    open_image_cache,
    open_point_cache,
    point_cache_ready,
)
from sq_mitsuba.training.config import TrainConfig
from sq_mitsuba.training.distributed import World, broadcast_object
from sq_mitsuba.training.part_targets import PartTargetError, load_part_targets
from sq_mitsuba.training.random_streams import STREAMS, seed_of
from sq_mitsuba.training.run.state import TrainError, TrainRun

__all__ = ["DataSources", "HostBatch", "TrainingData", "TrainingStream", "evenly",
           "open_datasets", "open_training_data", "run_cache_root", "symmetry_table",
           "warn_long_warmup"]


class TrainingStream:
    """Batches of the training stream from the caches (see the module docstring)."""

    def __init__(self, images: ImageCache, points: PointCache, keep: np.ndarray,
                 config: TrainConfig, camera: Camera, symmetries: Tensor) -> None:
        self.images, self.points = images, points
        self.keep = keep  # cache rows that train, (N,)
        self.config = config
        self.camera = camera
        self.symmetries = symmetries  # (models, S, 3, 3)
        self.batch_size = config.optim.batch_size
        self.steps_per_epoch = math.ceil(len(keep) / self.batch_size)
        self._order: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.keep)

    def _permutation(self, epoch: int) -> np.ndarray:
        if epoch not in self._order:
            rng = np.random.default_rng(seed_of(self.config.seed, STREAMS["order"], epoch))
            self._order = {epoch: rng.permutation(len(self.keep))}  # keep one epoch
        return self._order[epoch]

    def rows(self, step: int) -> np.ndarray:
        """Cache rows (batch_size,) of the global batch of ``step``."""
        n = len(self.keep)
        positions = step * self.batch_size + np.arange(self.batch_size)
        out = np.empty(self.batch_size, dtype=np.int64)
        for epoch in np.unique(positions // n):
            where = positions // n == epoch
            out[where] = self.keep[self._permutation(int(epoch))[positions[where] % n]]
        return out

    def host_batch(self, step: int, world: World, pin: bool = False) -> HostBatch:
        """The host's share of :meth:`batch`: this process's rows of step ``step``, their
        cached pixels and poses, their point draws and augmentation draws (each item's from its
        own generator, points first); what the prefetch workers prepare while earlier steps
        run (:class:`~sq_mitsuba.training.prefetch.BatchPrefetcher`).
        ``pin``: the tensors in pinned memory, for copies to a GPU that do not wait."""
        local = self.batch_size // world.size
        start = world.rank * local
        rows = self.rows(step)[start:start + local]
        raw = self.images.raw_batch(rows)
        cfg = self.config
        generators = [np.random.default_rng(seed_of(cfg.seed, STREAMS["item"], step, j))
                      for j in range(start, start + local)]
        surface, occupancy, labels, normals = [], [], [], []
        for k, model in enumerate(raw["model_index"].tolist()):
            s, o, lab, n = self.points.sample(model, generators[k], cfg.data.num_surface,
                                              cfg.data.num_occupancy)
            surface.append(s)
            normals.append(n)
            occupancy.append(o)
            labels.append(lab)
        raw.update(surface_points=torch.from_numpy(np.stack(surface)),
                   surface_normals=torch.from_numpy(np.stack(normals)),
                   occupancy_points=torch.from_numpy(np.stack(occupancy)),
                   occupancy_labels=torch.from_numpy(np.stack(labels)),
                   symmetries=self.symmetries[raw["model_index"]])
        draws = None
        if cfg.augment.enabled:  # the images' shape once decoded: (B, 1, S, S) float32
            shape = (local, 1, self.images.size, self.images.size)
            draws = draw_augmentation(cfg.augment, generators, shape, torch.float32)
        host = HostBatch(step, raw, draws)
        return host.pin_memory() if pin else host

    def device_batch(self, host: HostBatch, device: torch.device | str | None = None
                     ) -> TrainingBatch:
        """The :class:`TrainingBatch` of a :meth:`host_batch` on ``device`` (default the CPU):
        its pixels decoded and the batch augmented there with the host batch's draws."""
        device = torch.device("cpu" if device is None else device)
        moved = {name: to_device(value, device) for name, value in host.tensors.items()}
        image, mask = decode_pixels(moved.pop("image_u8"), moved.pop("mask_packed"),
                                    self.images.size)
        rotation, translation = moved["rotation"], moved["translation"]
        if host.augmentation is not None:
            with value_checks(False):  # checked where cached; a scan here would wait for a GPU
                image, mask, rotation, translation = apply_augmentation(
                    image, mask, rotation, translation, host.augmentation, self.camera)
        return TrainingBatch(
            image=image, mask=mask, rotation=rotation, translation=translation,
            model_index=moved["model_index"], surface_points=moved["surface_points"],
            occupancy_points=moved["occupancy_points"],
            occupancy_labels=moved["occupancy_labels"], symmetries=moved["symmetries"],
            surface_normals=moved["surface_normals"])

    def batch(self, step: int, world: World, device: torch.device | str | None = None
              ) -> TrainingBatch:
        """This process's slice of step ``step``'s batch, with points and augmentation, on
        ``device`` (default the CPU): :meth:`device_batch` of :meth:`host_batch`.

        The random draws are made on the host, item by item (each from its own generator, so
        the batch is the same on every device); the pixels travel as uint8 (images and
        bit-packed masks, in copies that do not wait on a GPU) and are decoded and augmented on
        ``device``. On the CPU the batch equals, bit for bit, one decoded and augmented there.
        """
        device = torch.device("cpu" if device is None else device)
        return self.device_batch(self.host_batch(step, world, pin=device.type == "cuda"),
                                 device)


@dataclass
class HostBatch:
    """The host's share of one step's batch (:meth:`TrainingStream.host_batch`)."""

    step: int
    "The step it belongs to."
    tensors: dict[str, Tensor]
    """``image_u8``, ``mask_packed`` (see :meth:`ImageCache.raw_batch`), ``quaternion``,
    ``rotation``, ``translation``, ``model_index``, ``surface_points``, ``occupancy_points``,
    ``occupancy_labels`` and ``symmetries`` of :class:`TrainingBatch`, on the host."""
    augmentation: AugmentDraws | None
    """The augmentation's parameters and noise, drawn on the host from each item's generator
    after its point draws; None when the augmentation is off."""

    def pin_memory(self) -> HostBatch:
        """The same batch in pinned host memory, for copies to a GPU that do not wait (also
        what a DataLoader's pinning thread calls)."""
        return HostBatch(self.step, {name: value.pin_memory()
                                     for name, value in self.tensors.items()},
                         None if self.augmentation is None else self.augmentation.pinned())


#: From this many training models on, their symmetries are analysed in worker processes.
POOL_MODELS = 64


def symmetry_table(root: Path, models: Sequence[str], cache_dir: Path | None = None,
                   workers: int | None = None) -> Tensor:
    """(models, S, 3, 3) body-frame symmetries per model, padded with identities (identity
    alone where a model's analysis fails). The analysis of
    each model is kept in ``cache_dir`` (never in the dataset, which is only read).

    The analysis costs about 0.4 s per model on one core, minutes for a library of
    thousands, so it runs in ``workers`` processes (default: this process's cores where
    there are at least :data:`POOL_MODELS` models, else this process: starting the workers
    costs seconds); a model already on record in ``cache_dir`` is only read."""
    if workers is None:
        workers = _symmetry_workers(len(models))
    arguments = ([root / model for model in models], [cache_dir] * len(models))
    if workers > 1 and len(models) > 1:
        from sq_mitsuba.processes import worker_pool

        with worker_pool(workers) as pool:
            found = list(pool.map(_model_symmetries, *arguments, chunksize=8))
    else:
        found = list(map(_model_symmetries, *arguments))
    sets = [np.eye(3)[None] if matrices is None else np.asarray(matrices).reshape(-1, 3, 3)
            for matrices in found]
    return torch.from_numpy(stack_symmetries(sets)).to(torch.float32)


def _symmetry_workers(models: int, processes: int = 1) -> int:
    """Processes for :func:`symmetry_table`: this process's cores shared by ``processes``
    (the training processes of a run), or one for fewer than :data:`POOL_MODELS` models."""
    if models < POOL_MODELS:
        return 1
    return max(1, len(os.sched_getaffinity(0)) // processes)


def _model_symmetries(model_dir: Path, cache_dir: Path | None) -> np.ndarray | None:
    """One model's symmetries (S, 3, 3), or None where they cannot be analysed (a worker's
    job of :func:`symmetry_table`)."""
    try:
        return np.asarray(model_symmetries(model_dir, cache_dir=cache_dir))
    except (OSError, ValueError):
        return None


def evenly(count: int, limit: int) -> list[int]:
    """At most ``limit`` indices of ``range(count)`` spread evenly, first and last included."""
    if limit >= count:
        return list(range(count))
    return sorted({int(i) for i in np.linspace(0, count - 1, limit).round()})


@dataclass
class DataSources:
    """The dataset's splits, opened and checked but not yet decoded (no file written)."""

    train_set: Spe3rDataset
    val_set: Spe3rDataset
    val_indices: list[int]
    "The val images that validate (spread evenly; empty when validation is off)."
    part_targets: Tensor | None = None
    """(train models, M, 16) their fitted assemblies' raw parameters when the ``parts`` loss
    term is weighted (:mod:`sq_mitsuba.training.part_targets`), else None."""


def run_cache_root(config: TrainConfig, out_dir: Path) -> Path:
    """Where a run's caches live: ``data.cache_dir``, else ``<out>/cache``."""
    return config.data.cache_dir or out_dir / "cache"


def open_datasets(config: TrainConfig, data_root: Path, cache_root: Path | None = None,
                  fingerprint: str | None = None) -> DataSources:
    """The train and val splits of ``data_root`` at the network's input size; one-line errors
    for a missing folder or an empty train split (the dataset's own for bad labels).

    The models' point files are checked unless ``cache_root`` already holds the point cache
    of this split for ``fingerprint`` (checked when it was built; training reads that): a
    library of thousands takes a minute to read again at every start and resume."""
    if not data_root.is_dir():
        raise TrainError(f"{data_root}: " + ("not a folder (a dataset is a folder)"
                                              if data_root.exists() else
                                              "dataset folder not found"))
    size = config.network.image_size
    train_set = Spe3rDataset(data_root, "train", image_size=size, num_surface=1,
                             num_occupancy=2, seed=config.seed)
    if len(train_set) == 0:
        raise TrainError(f"{data_root}: the train split has no images (splits.csv marks no "
                         "training model; imported models are test unless imported with "
                         "--split train)")
    images = min(len(train_set), config.data.train_images or len(train_set))
    if config.optim.batch_size > images:
        import warnings

        warnings.warn(f"optim.batch_size: {config.optim.batch_size} is more than the {images} "
                      "training images: each step repeats them (and holds them all in memory "
                      "as many times)", stacklevel=2)
    # Images of camera.json's size, readable finite points: refused here, before any work,
    # not at the cache build or a step later (the val split holds the same models).
    cached = cache_root is not None and fingerprint is not None and \
        point_cache_ready(train_set.root, train_set.models, cache_root, fingerprint)
    train_set.check(points=not cached)
    val_set = Spe3rDataset(data_root, "val", image_size=size, num_surface=1, num_occupancy=2,
                           seed=config.seed)
    val_indices = evenly(len(val_set), config.validation.images) if config.validation.every \
        else []
    if config.augment.enabled and config.augment.rotation:
        check_rotation_exact(train_set.camera.rescaled(size, size))
    if config.augment.enabled and config.augment.blur and \
            math.ceil(3 * config.augment.blur_sigma[1]) >= size:  # the kernel's reach, 3 sigma
        raise TrainError(f"augment.blur_sigma: {config.augment.blur_sigma[1]:g} px reaches past "
                         f"the {size} px network input; at most {(size - 1) / 3:.3g} px")
    part_targets = None
    if config.loss.weights.get("parts", 0.0) > 0:
        try:
            part_targets = load_part_targets(data_root, train_set.models,
                                             config.network.num_primitives)
        except PartTargetError as error:
            raise TrainError(f"loss.weights.parts: {error}") from None
    return DataSources(train_set, val_set, val_indices, part_targets)


@dataclass
class TrainingData:
    """Everything the loop reads of the data."""

    stream: TrainingStream
    points: PointCache
    "Surface and occupancy points of every training model."
    val_images: ImageCache | None
    "The validation images (rank 0, when validation is on and the val split has images)."
    validating: bool
    "Whether validations run (on rank 0; the other ranks receive the metrics)."
    dataset_camera: Camera
    "The dataset's camera (what checkpoints record)."
    camera: Camera
    "The camera at the network's input size."


def _build_caches(run: TrainRun, sources: DataSources, cache_root: Path) -> None:
    """Decode the splits into the caches (rank 0), removing a cache folder this call created
    when decoding fails (a corrupt image), so that nothing half-built stays behind."""
    created = not cache_root.exists()
    try:
        open_point_cache(sources.train_set, cache_root, run.fingerprint, run.progress)
        open_image_cache(sources.train_set, "train", cache_root, run.fingerprint,
                         progress=run.progress)
        if sources.val_indices:
            open_image_cache(sources.val_set, "val", cache_root, run.fingerprint,
                             sources.val_indices, progress=run.progress)
    except BaseException:
        if created:
            shutil.rmtree(cache_root, ignore_errors=True)
        raise


def _check_normals(points: PointCache, data_root: Path) -> None:
    """Refuse (one line), before the first step, training the surface-normal term on a model
    whose samples hold no normals (read as zeros: the term would be 0 for its images, with
    no gradient); the point cache that carries the normals is built by then."""
    offsets = points.surface_offsets
    for index, model in enumerate(points.models):
        # A model's normals are all there or all zeros (usable_normals): its first few tell,
        # not a read of the whole memory-mapped file (gigabytes for a large library).
        first = offsets[index]
        if not np.any(points.normals[first:min(first + 16, offsets[index + 1])]):
            samples = data_root / model / MODELS / SAMPLES_FILE
            raise TrainError(f"loss.weights.surface_normal: {samples} holds no surface normals "
                             "(an older library's); make the model again (sq-mitsuba models "
                             "generate) or weigh the term 0")


def open_training_data(run: TrainRun, sources: DataSources) -> TrainingData:
    """The caches of ``sources`` (rank 0 builds them, the others wait and open them) and the
    stream of training batches over them."""
    cfg = run.config
    cache_root = run_cache_root(cfg, run.out_dir)
    error = None
    if run.world.main:
        try:
            _build_caches(run, sources, cache_root)
        except ValueError as exc:
            error = str(exc)
    error = broadcast_object(error, run.world)
    if error is not None:
        raise TrainError(error)
    train_set = sources.train_set
    points = open_point_cache(train_set, cache_root, run.fingerprint)
    if cfg.loss.weights.get("surface_normal", 0.0) > 0:
        _check_normals(points, run.data_root)
    images = open_image_cache(train_set, "train", cache_root, run.fingerprint)
    # Validation runs on rank 0 only; the others receive its metrics.
    val_images = (open_image_cache(sources.val_set, "val", cache_root, run.fingerprint,
                                   sources.val_indices)
                  if sources.val_indices and run.world.main else None)
    keep = np.arange(len(images))
    if cfg.data.min_visibility > 0:
        visible = np.isnan(images.visibility) | (images.visibility >= cfg.data.min_visibility)
        keep = keep[visible]
        if len(keep) == 0:
            raise TrainError(f"data.min_visibility: no training image has target_visibility >= "
                             f"{cfg.data.min_visibility}")
    if cfg.data.train_images is not None:
        keep = keep[:cfg.data.train_images]
    size = cfg.network.image_size
    camera = train_set.camera.rescaled(size, size)
    stream = TrainingStream(images, points, keep, cfg, camera,
                            symmetry_table(run.data_root, train_set.models,
                                           Path(cache_root) / "symmetries",
                                           workers=_symmetry_workers(len(train_set.models),
                                                                     run.world.local_size)))
    if run.world.main and run.checkpoint is None:  # said once, when the run starts
        warn_long_warmup(cfg, stream.steps_per_epoch)
    return TrainingData(stream, points, val_images, bool(sources.val_indices), train_set.camera,
                        camera)


def warn_long_warmup(config: TrainConfig, steps_per_epoch: int) -> None:
    """Warn (one line, naming the field) when the warm-up lasts at least the whole run: the
    learning rate then never passes its warm-up, and one far longer leaves it near 0, the run
    learning nothing. A warning, not an error: a warm-up-only run may be meant."""
    optim = config.optim
    warmup, total = optim.warmup_step_count(), optim.epochs * steps_per_epoch
    if warmup < total:
        return
    import warnings

    name = "optim.warmup_steps" if optim.warmup_images is None else "optim.warmup_images"
    warnings.warn(f"{name}: a warm-up of {warmup} steps is at least the run's {total} steps "
                  f"({optim.epochs} epoch(s) of {steps_per_epoch}): the learning rate rises "
                  f"only to {optim.peak_lr() * total / warmup:.3g} at the last step, of its "
                  f"peak {optim.peak_lr():.3g}", stacklevel=2)
