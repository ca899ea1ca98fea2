"""Training of :class:`~sq_mitsuba.learning.network.SuperquadricNet`: the loop, its log, its
checkpoints, and exact resumption.

:func:`train` runs one training job described by a :class:`TrainConfig` on an SPE3R-layout
dataset and writes into a run folder:

- ``config.json``: the resolved config (written once, when the run starts);
- ``log.csv``: one row per step: step, epoch, learning rate, total loss and each loss term (the
  mean over the global batch), gradient norm before clipping, images/s;
- ``val.csv``: one row per validation: mean Chamfer-L1 (the paper's convention, see
  :func:`chamfer_l1_paper`), 2D IoU (the predicted assembly's Mitsuba silhouette at the
  predicted pose against the mask) and rotation error in degrees, over a fixed subset;
- ``curves.png``: loss terms and validation metrics, refreshed at each validation;
- ``last.pt`` (the latest state) and ``best.pt`` (best validation ``validation.metric``);
- TensorBoard events in ``tensorboard/`` when the ``tensorboard`` package is importable;
- ``cache/``: the decoded training data (:mod:`sq_mitsuba.learning.cache`), unless
  ``data.cache_dir`` points elsewhere.

Checkpoints (written atomically by :func:`~sq_mitsuba.learning.checkpoint.write_checkpoint`)
hold the config, the model, optimiser and scheduler states, the RNG states (torch, numpy,
python), the data-order state, the dataset fingerprint and the git commit. ``resume=True``
continues from ``last.pt`` exactly: the data order and every per-item random draw are pure
functions of (seed, step, position in the batch), and the renderer's sample sequence restarts
from a seed of the step, so the steps after a resume repeat an uninterrupted run's.

Convention: on the CPU, the losses after a resume are bit-identical to an uninterrupted run's
(tested). That needs every float sum to run in a fixed order: Mitsuba's backward pass adds
vertex gradients atomically in thread order (6e-8 apart between two runs with 2 threads), and
training amplifies such differences (two runs differed by 1e-3 in the loss after 5 steps of
tiny.toml), so with ``reprojection.deterministic`` (the default) Dr.Jit renders on one thread
during training. The cores are used instead by ``reprojection.workers`` processes that share a
step's rendered items, each on one thread: an item's samples depend on (seed, step, item)
alone, so any number of workers gives the same losses bit for bit (tested), and a run may
resume with another. Torch's CPU kernels are deterministic at a fixed thread count; a resumed
run must use the same one.

Convention: the training data are an endless stream of per-epoch permutations of the training
images (epoch e's permutation drawn from the seed and e); step s takes the next
``batch_size`` images of it, and an epoch is ceil(images / batch_size) steps. Under
``torchrun`` (``WORLD_SIZE`` > 1) process r of N takes the r-th of N equal slices of each
step's batch and renders its own items; gradients are averaged by DistributedDataParallel
(gloo on the CPU, nccl on CUDA), and BatchNorm statistics are synchronised over the global
batch (torch's SyncBatchNorm on CUDA, :class:`CpuSyncBatchNorm` on the CPU), so N processes
follow the same trajectory as one process with the same global batch, up to float rounding
(other summation orders; tested: 3 steps agree to 1e-5) and the encoder's stochastic depth,
whose random draws are per process. The CUDA path (device ``cuda``, Mitsuba's ``cuda_ad_mono``
variant, nccl) is written but untested here, and not bit-reproducible.

Errors (one line, :class:`TrainError` or the dataset's ``DatasetError``, both ``ValueError``):
an unwritable run folder or a run folder that already holds a run (without ``resume``) before
any work starts; a corrupt or missing image while the cache is built (naming the file); a
checkpoint of another config or dataset on resume (naming the first difference); a loss or
gradient that is not finite (the step is not applied and the last checkpoint stays as it was).
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import random
import subprocess
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sq_mitsuba.checks import value_checks
from sq_mitsuba.config import to_dict
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.nearest import nearest_neighbours
from sq_mitsuba.geometry.rotation import rotation_angle
from sq_mitsuba.io import atomic_path, atomic_write_json, atomic_write_text
from sq_mitsuba.learning.augment import augment_batch, check_rotation_exact
from sq_mitsuba.learning.cache import (
    ImageCache,
    PointCache,
    dataset_fingerprint,
    manifest_hash,
    open_image_cache,
    open_point_cache,
)
from sq_mitsuba.learning.losses import (
    chamfer_loss,
    counted_surface_samples,
    occupancy_loss,
    oriented_chamfer_loss,
    overlap,
    pose_loss,
    reprojection_loss,
    taper_loss,
    total_loss,
)
from sq_mitsuba.learning.train_config import TrainConfig

__all__ = [
    "CpuSyncBatchNorm",
    "TrainError",
    "TrainResult",
    "chamfer_l1_paper",
    "cosine_lr_factor",
    "train",
]

LOG_FILE, VAL_FILE, CURVES_FILE = "log.csv", "val.csv", "curves.png"
LAST, BEST, CONFIG_FILE = "last.pt", "best.pt", "config.json"
CHECKPOINT_FORMAT, CHECKPOINT_VERSION = "sq_mitsuba.checkpoint", 1
#: Loss terms in log order (the fields of LossWeights).
TERMS = ("chamfer", "occupancy", "reprojection", "rotation", "translation", "overlap", "taper",
         "oriented_chamfer")
VAL_METRICS = ("chamfer_l1", "iou_2d", "rotation_error_deg")
#: Config fields that may differ between a checkpoint and the run that resumes it.
RESUME_FREE = frozenset({"data.cache_dir", "reprojection.workers"})
_HIGHER_IS_BETTER = {"chamfer_l1": False, "iou_2d": True, "rotation_error_deg": False}
_STREAMS = {"order": 1, "item": 2, "subset": 3, "render": 4, "torch": 5}


class TrainError(ValueError):
    """A training run that cannot start or go on; the message is one line."""


@dataclass
class TrainResult:
    """What :func:`train` did."""

    out_dir: Path
    steps: int
    "Optimiser steps completed in total (resumed runs count the earlier ones)."
    total_steps: int
    "Steps of the full schedule (epochs x steps per epoch)."
    last_checkpoint: Path | None
    best_checkpoint: Path | None
    losses: list[float] = field(default_factory=list)
    "Total loss of each step run by this call."
    validation: list[dict[str, float]] = field(default_factory=list)
    "Every validation of the run so far (resumed runs include the earlier ones)."
    images_per_second: float = float("nan")
    "Mean training throughput of this call (after its first step, which compiles kernels)."
    train_seconds: float = 0.0
    "Wall time of this call's steps (validation, checkpoints and set-up excluded)."


# ------------------------------------------------------------------------------ schedule


def cosine_lr_factor(step: int, total_steps: int, warmup_steps: int = 0,
                     min_ratio: float = 0.0) -> float:
    """Learning-rate multiplier of step ``step`` (0-based): linear warm-up over
    ``warmup_steps``, then a cosine from 1 down to ``min_ratio`` at the last step."""
    if warmup_steps > 0 and step < warmup_steps:
        return (step + 1) / warmup_steps
    span = max(1, total_steps - 1 - warmup_steps)
    progress = min(1.0, max(0.0, (step - warmup_steps) / span))
    return min_ratio + (1.0 - min_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


def _seed_of(*parts: int) -> int:
    """A 63-bit seed from integers (numpy's SeedSequence: well mixed, order sensitive)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1, np.uint64)[0]
               >> 1)


# ------------------------------------------------------------------------------ distributed


class CpuSyncBatchNorm(nn.BatchNorm2d):
    """BatchNorm2d whose training statistics span every process of a distributed run, on
    the CPU (torch's SyncBatchNorm needs a GPU).

    The per-channel sum, sum of squares and count are summed over processes with the
    autograd-aware ``torch.distributed.nn.functional.all_reduce``, whose backward sums the
    gradients likewise, so values and gradients equal those of BatchNorm over the global batch.
    Statistics are accumulated in float64. Outside a distributed run, or in eval mode, this is
    plain BatchNorm2d. The parameters and buffers are BatchNorm2d's (same state-dict keys).
    """

    def forward(self, x: Tensor) -> Tensor:
        import torch.distributed as dist

        if not (self.training and dist.is_available() and dist.is_initialized()):
            return super().forward(x)
        from torch.distributed.nn.functional import all_reduce

        channels = x.shape[1]
        dims = [0, *range(2, x.dim())]
        wide = x.to(torch.float64)
        count = wide.new_tensor([x.numel() / channels])
        packed = all_reduce(torch.cat([wide.sum(dims), (wide * wide).sum(dims), count]))
        total = packed[-1]
        mean = packed[:channels] / total
        var = (packed[channels:2 * channels] / total - mean * mean).clamp_min(0)
        if self.track_running_stats and self.running_mean is not None:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                momentum = (1.0 / float(self.num_batches_tracked) if self.momentum is None
                            else self.momentum)
                unbiased = var * total / (total - 1).clamp_min(1)
                self.running_mean.mul_(1 - momentum).add_(momentum * mean.to(x.dtype))
                self.running_var.mul_(1 - momentum).add_(momentum * unbiased.to(x.dtype))
        shape = [1, channels] + [1] * (x.dim() - 2)
        y = ((wide - mean.view(shape)) * torch.rsqrt(var.view(shape) + self.eps)).to(x.dtype)
        if self.affine:
            y = y * self.weight.view(shape) + self.bias.view(shape)
        return y


def _convert_cpu_sync_batchnorm(module: nn.Module) -> nn.Module:
    """Replace every BatchNorm2d of ``module`` by a :class:`CpuSyncBatchNorm` with its state."""
    for name, child in module.named_children():
        if isinstance(child, nn.BatchNorm2d) and not isinstance(child, CpuSyncBatchNorm):
            sync = CpuSyncBatchNorm(child.num_features, child.eps, child.momentum,
                                    child.affine, child.track_running_stats)
            sync.load_state_dict(child.state_dict())
            sync.train(child.training)
            setattr(module, name, sync)
        else:
            _convert_cpu_sync_batchnorm(child)
    return module


@dataclass(frozen=True)
class _World:
    rank: int = 0
    size: int = 1
    local_rank: int = 0
    owns_group: bool = False

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.size > 1


def _start_distributed(device: torch.device) -> _World:
    """Join the process group torchrun describes (``WORLD_SIZE`` > 1); else one process."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return _World()
    import torch.distributed as dist

    owns = False
    if not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(device)  # object collectives and barriers use this GPU
        # nccl takes CUDA tensors only; the loss means and flags are CPU tensors (gloo).
        dist.init_process_group(backend="cpu:gloo,cuda:nccl" if device.type == "cuda"
                                else "gloo")
        owns = True
    return _World(dist.get_rank(), dist.get_world_size(),
                  int(os.environ.get("LOCAL_RANK", "0")), owns)


def _all_mean(values: Tensor, world: _World) -> Tensor:
    if not world.distributed:
        return values
    import torch.distributed as dist

    values = values.clone()
    dist.all_reduce(values)
    return values / world.size


def _any(flag: bool, world: _World) -> bool:
    if not world.distributed:
        return flag
    import torch.distributed as dist

    value = torch.tensor([1.0 if flag else 0.0])
    dist.all_reduce(value, op=dist.ReduceOp.MAX)
    return bool(value.item() > 0)


def _barrier(world: _World) -> None:
    if world.distributed:
        import torch.distributed as dist

        dist.barrier()


# ------------------------------------------------------------------------------ run folder


def _check_out_dir(out_dir: Path, resume: bool) -> None:
    """A writable run folder; with ``resume`` it must hold last.pt, without it no run."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / ".write-test"
        atomic_write_text(probe, "ok\n")
        probe.unlink()
    except OSError as error:
        raise TrainError(f"{out_dir}: output folder is not writable "
                         f"({error.strerror or error})") from None
    if resume and not (out_dir / LAST).is_file():
        raise TrainError(f"{out_dir}: nothing to resume (no {LAST})")
    if not resume and any((out_dir / name).exists() for name in (LAST, LOG_FILE)):
        raise TrainError(f"{out_dir}: already holds a training run; resume it (--resume) or "
                         "choose another output folder")


def _git_commit() -> dict[str, Any]:
    """The source's git commit and whether the work tree differs from it (None outside git)."""
    root = Path(__file__).resolve().parents[2]
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                                text=True, timeout=10, check=True).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                                cwd=root, capture_output=True, text=True, timeout=10,
                                check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": commit, "dirty": bool(status.strip())}


def _flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(data, dict):
        out: dict[str, Any] = {}
        for key, value in data.items():
            out.update(_flatten(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: data}


def config_difference(old: dict[str, Any], new: dict[str, Any]) -> str | None:
    """The first field (dotted) where two ``to_dict`` configs differ, as ``field: a vs b``."""
    a, b = _flatten(old), _flatten(new)
    for key in sorted(set(a) | set(b)):
        if key in RESUME_FREE:
            continue
        if a.get(key, "<absent>") != b.get(key, "<absent>"):
            return (f"{key} = {a.get(key, '<absent>')!r} in the checkpoint, "
                    f"{b.get(key, '<absent>')!r} in this run")
    return None


# ------------------------------------------------------------------------------ data


class _TrainingData:
    """Batches of the training stream from the caches (see the module's data convention)."""

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
            rng = np.random.default_rng(_seed_of(self.config.seed, _STREAMS["order"], epoch))
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

    def batch(self, step: int, world: _World) -> dict[str, Any]:
        """This process's slice of step ``step``'s batch, with points and augmentation."""
        local = self.batch_size // world.size
        start = world.rank * local
        rows = self.rows(step)[start:start + local]
        batch: dict[str, Any] = self.images.batch(rows)
        cfg = self.config
        generators = [np.random.default_rng(_seed_of(cfg.seed, _STREAMS["item"], step, j))
                      for j in range(start, start + local)]
        surface, occupancy, labels = [], [], []
        for k, model in enumerate(batch["model_index"].tolist()):
            s, o, lab = self.points.sample(model, generators[k], cfg.data.num_surface,
                                           cfg.data.num_occupancy)
            surface.append(s)
            occupancy.append(o)
            labels.append(lab)
        batch["surface_points"] = torch.from_numpy(np.stack(surface))
        batch["occupancy_points"] = torch.from_numpy(np.stack(occupancy))
        batch["occupancy_labels"] = torch.from_numpy(np.stack(labels))
        batch["symmetries"] = self.symmetries[batch["model_index"]]
        if cfg.augment.enabled:
            image, mask, rotation, translation = augment_batch(
                batch["image"], batch["mask"], batch["rotation"], batch["translation"],
                cfg.augment, generators, self.camera)
            batch.update(image=image, mask=mask, rotation=rotation, translation=translation)
        return batch


def _symmetry_table(root: Path, models: Sequence[str]) -> Tensor:
    """(models, S, 3, 3) body-frame symmetries per model, padded with identities (identity
    alone where the symmetry module or a model's analysis is unavailable)."""
    try:
        from sq_mitsuba.data.symmetry import model_symmetries
    except ImportError:
        model_symmetries = None
    sets = []
    for model in models:
        matrices = torch.eye(3, dtype=torch.float32)[None]
        if model_symmetries is not None:
            with contextlib.suppress(OSError, ValueError):
                matrices = torch.as_tensor(np.asarray(model_symmetries(root / model)),
                                           dtype=torch.float32).reshape(-1, 3, 3)
        sets.append(matrices)
    width = max(len(s) for s in sets)
    table = torch.eye(3).repeat(len(sets), width, 1, 1)
    for i, matrices in enumerate(sets):
        table[i, :len(matrices)] = matrices
    return table


def _evenly(count: int, limit: int) -> list[int]:
    if limit >= count:
        return list(range(count))
    return sorted({int(i) for i in np.linspace(0, count - 1, limit).round()})


# ------------------------------------------------------------------------------ losses


def _loss_terms(output: Any, batch: dict[str, Any], config: TrainConfig, renderer: Any,
                reprojection_camera: Camera | None, generator: torch.Generator
                ) -> dict[str, Tensor]:
    """The loss terms with a non-zero weight, each a scalar (mean over the local batch)."""
    weights = config.loss.weights
    assembly = output.assembly
    terms: dict[str, Tensor] = {}
    if weights.chamfer or weights.oriented_chamfer:
        # One set of surface samples serves both Chamfer terms.
        points, keep = counted_surface_samples(assembly, config.loss.level)
        target = batch["surface_points"].to(points)
        if weights.chamfer:
            terms["chamfer"] = chamfer_loss(points, keep, target)
        if weights.oriented_chamfer:
            terms["oriented_chamfer"] = oriented_chamfer_loss(
                points, keep, output.rotation, target, batch["rotation"])
    if weights.occupancy or weights.overlap:
        points = batch["occupancy_points"].to(assembly.params)
        if weights.occupancy:
            terms["occupancy"] = occupancy_loss(assembly, points, batch["occupancy_labels"],
                                                config.loss.sharpness)
        if weights.overlap:
            terms["overlap"] = overlap(assembly.occupancy(points, config.loss.sharpness),
                                       config.loss.beta)
    if weights.reprojection:
        assert reprojection_camera is not None
        masks = batch["mask"][:, 0]
        size = (reprojection_camera.height, reprojection_camera.width)
        if tuple(masks.shape[-2:]) != size:
            masks = F.interpolate(masks[:, None], size=size, mode="area")[:, 0]
        # At most the process's batch: a smaller batch (tests, many processes) renders all.
        items = config.reprojection.items
        items = None if items is None or items >= len(masks) else items
        terms["reprojection"] = reprojection_loss(
            assembly, batch["rotation"].to(assembly.params), batch["translation"].to(
                assembly.params), masks, renderer, config.reprojection.level, items, generator)
    if weights.rotation or weights.translation:
        rotation, translation = pose_loss(output.rotation, output.translation,
                                          batch["rotation"].to(output.rotation),
                                          batch["translation"].to(output.translation),
                                          batch["symmetries"].to(output.rotation),
                                          config.loss.rotation_form, output.rotation_6d)
        terms["rotation"] = rotation.mean()
        terms["translation"] = translation.mean()
    if weights.taper:
        terms["taper"] = taper_loss(assembly)
    return terms


def _forward_loss(model: nn.Module, images: Tensor, k_matrix: Tensor, batch: dict[str, Any],
                  config: TrainConfig, renderer: Any, reprojection_camera: Camera | None,
                  generator: torch.Generator, device: torch.device
                  ) -> tuple[dict[str, Tensor], Tensor | None]:
    """The forward half of a training step: the network on ``images`` (B, C, S, S) and the
    weighted loss of its output on ``batch`` (the local batch, see ``_TrainingData.batch``).

    Returns:
        (terms, loss): the loss terms with a non-zero weight and their weighted sum, each a
        scalar; ({}, None) when the network's outputs are not finite.
    """
    output = model(images, k_matrix)
    if not (bool(torch.isfinite(output.raw).all()) and bool(
            torch.isfinite(output.translation).all()) and bool(
            torch.isfinite(output.rotation).all())):
        return {}, None
    batch = {k: v.to(device) if isinstance(v, Tensor) else v for k, v in batch.items()}
    terms = _loss_terms(output, batch, config, renderer, reprojection_camera, generator)
    return terms, total_loss(terms, config.loss.weights)


def _gradient_norm(model: nn.Module, grad_clip: float | None) -> float:
    """Norm of the gradient of every parameter, before clipping it to ``grad_clip`` (None:
    no clipping)."""
    if grad_clip is not None:
        return float(nn.utils.clip_grad_norm_(model.parameters(), grad_clip))
    return float(torch.linalg.vector_norm(torch.stack([
        p.grad.norm() for p in model.parameters() if p.grad is not None])))


# ------------------------------------------------------------------------------ validation


def chamfer_l1_paper(pred: Tensor, pred_keep: Tensor, gt: Tensor) -> Tensor:
    """Chamfer-L1 (B,) in the paper's convention: per point the L1 distance to its nearest
    neighbour under the L1 norm, averaged per direction, the two directions summed (as
    :func:`sq_mitsuba.evaluation.metrics.chamfer_l1` with ``"paper"``, which sits in a higher
    layer). pred (B, N, 3) with pred_keep (B, N) bool (an item keeping none keeps all);
    gt (B, K, 3)."""
    values = []
    pred_np = pred.detach().to("cpu", torch.float64).numpy()
    keep_np = pred_keep.detach().cpu().numpy()
    gt_np = gt.detach().to("cpu", torch.float64).numpy()
    for a, keep, b in zip(pred_np, keep_np, gt_np, strict=True):
        a = a[keep] if keep.any() else a
        forward = nearest_neighbours(a, b, p=1)[0]
        backward = nearest_neighbours(b, a, p=1)[0]
        values.append(forward.mean() + backward.mean())
    return torch.tensor(values, dtype=torch.float64)


def _validate(model: nn.Module, cache: ImageCache, points: PointCache, config: TrainConfig,
              camera: Camera, renderer: Any, device: torch.device) -> dict[str, float]:
    """Mean Chamfer-L1, 2D IoU and rotation error (deg) over the cached validation subset."""
    from sq_mitsuba.render.silhouette import mask_iou, render_assembly

    cfg = config.validation
    was_training = model.training
    model.eval()
    metrics: dict[str, list[Tensor]] = {name: [] for name in VAL_METRICS}
    k_matrix = camera.matrix(device=device)
    renderer.reseed(_seed_of(config.seed, _STREAMS["render"], 2**31))
    try:
        with torch.no_grad():
            for start in range(0, len(cache), cfg.batch_size):
                rows = np.arange(start, min(len(cache), start + cfg.batch_size))
                batch = cache.batch(rows)
                output = model(batch["image"].to(device), k_matrix)
                assembly = Assembly(output.assembly.params.detach().to("cpu", torch.float64))
                surface, inside_other = assembly.surface_points_with_mask(cfg.level)
                gt = []
                for row, model_index in zip(rows, batch["model_index"].tolist(), strict=True):
                    rng = np.random.default_rng(_seed_of(config.seed, 7, int(
                        cache.dataset_index[row])))
                    gt.append(points.sample(model_index, rng, config.data.num_surface, 2)[0])
                metrics["chamfer_l1"].append(chamfer_l1_paper(
                    surface.flatten(1, 2), ~inside_other.flatten(1, 2),
                    torch.from_numpy(np.stack(gt))))
                rotation = output.rotation.detach().to("cpu", torch.float64)
                translation = output.translation.detach().to("cpu", torch.float64)
                silhouettes = render_assembly(assembly, rotation, translation, renderer,
                                              cfg.level)
                metrics["iou_2d"].append(mask_iou(silhouettes, batch["mask"][:, 0].double()))
                metrics["rotation_error_deg"].append(torch.rad2deg(rotation_angle(
                    rotation, batch["rotation"].double())))
    finally:
        model.train(was_training)
    return {name: float(torch.cat(values).mean()) for name, values in metrics.items()}


# ------------------------------------------------------------------------------ logging


class _Log:
    """log.csv and val.csv (rank 0), truncated to the resumed step, plus TensorBoard."""

    def __init__(self, out_dir: Path, resume_step: int | None, tensorboard: bool = True
                 ) -> None:
        self.out_dir = out_dir
        self.log_path, self.val_path = out_dir / LOG_FILE, out_dir / VAL_FILE
        self.log_fields = ["step", "epoch", "lr", "loss", *TERMS, "grad_norm", "images_per_s"]
        self.val_fields = ["step", "epoch", *VAL_METRICS]
        self.rows: list[dict[str, float]] = []
        self.val_rows: list[dict[str, float]] = []
        if resume_step is not None:
            self.rows = self._read(self.log_path, resume_step)
            self.val_rows = self._read(self.val_path, resume_step)
        self._rewrite(self.log_path, self.log_fields, self.rows)
        self._rewrite(self.val_path, self.val_fields, self.val_rows)
        self._log = open(self.log_path, "a", newline="", encoding="utf-8")
        self._writer = csv.DictWriter(self._log, self.log_fields)
        self.tensorboard = None
        if tensorboard:
            with contextlib.suppress(ImportError):
                from torch.utils.tensorboard import SummaryWriter

                self.tensorboard = SummaryWriter(str(out_dir / "tensorboard"),
                                                 purge_step=resume_step)

    @staticmethod
    def _read(path: Path, upto: int) -> list[dict[str, float]]:
        """Complete rows of an earlier log up to step ``upto`` (a row cut by a kill is
        dropped, and so are steps after the checkpoint, which the resumed run repeats)."""
        if not path.is_file():
            return []
        rows = []
        with open(path, newline="", encoding="utf-8") as handle:
            for row in csv.DictReader(handle):
                if None in row or any(v is None for v in row.values()):
                    continue  # too many or too few fields: a line cut short
                try:
                    values = {k: float(v) for k, v in row.items() if v != ""}
                except ValueError:
                    continue
                if "step" in values and values["step"] <= upto:
                    rows.append(values)
        return rows

    @staticmethod
    def _rewrite(path: Path, fields: list[str], rows: list[dict[str, float]]) -> None:
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fields, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _fmt(row.get(k)) for k in fields})
        atomic_write_text(path, buffer.getvalue())

    def step(self, row: dict[str, float]) -> None:
        self.rows.append(row)
        self._writer.writerow({k: _fmt(row.get(k)) for k in self.log_fields})
        self._log.flush()
        if self.tensorboard is not None:
            step = int(row["step"])
            for key in ("loss", "lr", "images_per_s", *TERMS):
                if row.get(key) is not None:
                    self.tensorboard.add_scalar(f"train/{key}", row[key], step)

    def validation(self, row: dict[str, float]) -> None:
        self.val_rows.append(row)
        self._rewrite(self.val_path, self.val_fields, self.val_rows)
        if self.tensorboard is not None:
            for key in VAL_METRICS:
                self.tensorboard.add_scalar(f"val/{key}", row[key], int(row["step"]))

    def close(self) -> None:
        self._log.close()
        if self.tensorboard is not None:
            self.tensorboard.close()


def _fmt(value: float | None) -> str:
    """Exact text of a logged number (repr round-trips floats); whole numbers as integers."""
    if value is None:
        return ""
    if isinstance(value, int) or (isinstance(value, float) and value.is_integer()
                                  and abs(value) < 2**53):
        return str(int(value))
    return repr(float(value))


def plot_curves(rows: Sequence[dict[str, float]], val_rows: Sequence[dict[str, float]],
                path: Path) -> Path:
    """``curves.png``: each loss term per step (log scale) and the validation metrics."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(12, 4))
    axes = figure.subplots(1, 1 + len(VAL_METRICS))
    steps = [r["step"] for r in rows]
    settled: list[float] = []  # values after the first steps, which set the y range
    skip = max(10, len(rows) // 50)
    for name in ("loss", *TERMS):
        values = [r.get(name) for r in rows]
        if any(v is not None and v > 0 for v in values):
            axes[0].plot(steps, [v if v is not None and v > 0 else np.nan for v in values],
                         label=name, linewidth=0.8)
            settled += [v for v in values[skip:] if v is not None and v > 0]
    axes[0].set_yscale("log")
    if settled:  # a regulariser starting near 0 (taper) would otherwise squash every curve
        low, high = np.percentile(settled, [0.5, 100.0])
        axes[0].set_ylim(0.5 * low, 2.0 * high)
    axes[0].set_xlabel("step")
    axes[0].set_title("training loss (global batch mean)")
    axes[0].legend(fontsize=7)
    for axis, name in zip(axes[1:], VAL_METRICS, strict=True):
        axis.plot([r["step"] for r in val_rows], [r[name] for r in val_rows], marker="o")
        axis.set_xlabel("step")
        axis.set_title(f"val {name}")
    figure.tight_layout()
    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=100, format="png")
    return path


# ------------------------------------------------------------------------------ checkpoints


def _rng_state() -> dict[str, Any]:
    # The legacy global numpy state: this module draws from its own Generators, but code it
    # calls may use the global one, so it is saved and restored too.
    np_state = np.random.get_state()  # noqa: NPY002
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"name": np_state[0], "keys": torch.from_numpy(np_state[1].astype(np.int64)),
                  "pos": int(np_state[2]), "has_gauss": int(np_state[3]),
                  "cached_gaussian": float(np_state[4])},
        "python": random.getstate(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    numpy = state["numpy"]
    legacy = (numpy["name"], numpy["keys"].numpy().astype(np.uint32), numpy["pos"],
              numpy["has_gauss"], numpy["cached_gaussian"])
    np.random.set_state(legacy)  # noqa: NPY002
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _to_channels_last(model: nn.Module) -> None:
    """Store ``model``'s 4-D weights channels-last and have it feed its encoder that way."""
    model.to(memory_format=torch.channels_last)
    if hasattr(model, "channels_last"):
        model.channels_last = True


def _unwrap(model: nn.Module) -> nn.Module:
    return model.module if hasattr(model, "module") else model


def _state_dict(model: nn.Module) -> dict[str, Tensor]:
    return {k: v.detach().cpu().clone() for k, v in _unwrap(model).state_dict().items()}


# ------------------------------------------------------------------------------ the loop


def _device_of(config: TrainConfig) -> torch.device:
    if config.device == "cuda" or (config.device == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise TrainError("device: 'cuda' asked for, but torch sees no CUDA device")
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return torch.device("cpu")


def render_workers(requested: int | None, device: torch.device, processes: int = 1) -> int:
    """Worker processes for the reprojection renderer (see ``ReprojectionConfig.workers``).

    Args:
        requested: the config's value; None picks one per CPU core available to this process,
            divided among ``processes`` training processes (0 when that leaves one).
        device: the training device; CUDA renders in the training process (0).
        processes: training processes on this machine (torchrun's world size).
    """
    from sq_mitsuba.render.silhouette_workers import default_worker_count

    if device.type != "cpu":
        return 0
    return default_worker_count(processes) if requested is None else requested


@contextlib.contextmanager
def _mitsuba_for(device: torch.device, deterministic: bool) -> Iterator[None]:
    """Mitsuba's variant for ``device``; on the CPU with ``deterministic``, one Dr.Jit thread
    inside the block (restored after), so that gradient sums do not depend on thread timing."""
    from sq_mitsuba.render.backend import mitsuba

    mitsuba("cuda_ad_mono" if device.type == "cuda" else None)
    import drjit as dr

    previous = dr.thread_count()
    if deterministic and device.type == "cpu":
        dr.set_thread_count(1)
    try:
        yield
    finally:
        if dr.thread_count() != previous:
            dr.set_thread_count(previous)


def train(config: TrainConfig | None, data_root: str | Path, out_dir: str | Path, *,
          resume: bool = False, max_steps: int | None = None, progress: bool = True,
          max_seconds: float | None = None) -> TrainResult:
    """Train (or resume) a run; see the module docstring for what it writes.

    Args:
        config: the run's config; None takes the checkpoint's when resuming, else the
            defaults. Resuming with a config that differs (other than in ``data.cache_dir``
            and ``reprojection.workers``) is refused, naming the first differing field.
        data_root: SPE3R-layout dataset (``train`` split for training, ``val`` for validation).
        out_dir: run folder (created; must not hold a run unless ``resume``).
        resume: continue from ``out_dir/last.pt``.
        max_steps: stop after this many steps in total (the schedule still spans every epoch;
            a later ``resume`` continues); None: run to the end.
        progress: show a progress bar (rank 0).
        max_seconds: stop after the first step that ends this many seconds (wall clock,
            validations and checkpoints included) after the first step started, writing
            ``last.pt`` (a later ``resume`` continues); None: no time limit.

    Returns:
        A :class:`TrainResult`.

    Raises:
        TrainError, DatasetError (both ``ValueError``): see the module docstring.
    """
    from sq_mitsuba.config import validate
    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.learning.checkpoint import read_checkpoint
    from sq_mitsuba.learning.network import SuperquadricNet

    data_root, out_dir = Path(data_root), Path(out_dir)
    if max_steps is not None and max_steps < 0:
        raise TrainError(f"max_steps: expected >= 0, got {max_steps}")
    if max_seconds is not None and not max_seconds > 0:
        raise TrainError(f"max_seconds: expected > 0, got {max_seconds}")
    env_rank = int(os.environ.get("RANK", "0"))
    # Checks before any work: the run folder (rank 0 writes), the dataset's presence.
    if env_rank == 0:
        _check_out_dir(out_dir, resume)
    if not data_root.is_dir():
        raise TrainError(f"{data_root}: dataset folder not found")
    checkpoint = None
    if resume:
        try:
            checkpoint = read_checkpoint(out_dir / LAST)
        except (OSError, ValueError, RuntimeError) as error:
            raise TrainError(f"{out_dir / LAST}: cannot read checkpoint ({error})") from None
        if config is None:
            from sq_mitsuba.config import from_dict

            config = from_dict(TrainConfig, checkpoint["config"])
    config = TrainConfig() if config is None else config
    validate(config)
    fingerprint = dataset_fingerprint(data_root)
    if checkpoint is not None:
        difference = config_difference(checkpoint["config"], to_dict(config))
        if difference is not None:
            raise TrainError(f"{out_dir / LAST}: the checkpoint is of another config: "
                             f"{difference}")
        recorded = checkpoint.get("dataset", {}).get("fingerprint")
        if recorded != fingerprint:
            raise TrainError(f"{out_dir / LAST}: the checkpoint was trained on another dataset "
                             f"({checkpoint.get('dataset', {}).get('root')}, fingerprint "
                             f"{str(recorded)[:12]}), {data_root} has {fingerprint[:12]}")
    device = _device_of(config)
    world = _start_distributed(device)
    try:
        return _run(config, data_root, out_dir, checkpoint, fingerprint, device, world,
                    max_steps, progress, Spe3rDataset, SuperquadricNet, max_seconds)
    finally:
        if world.owns_group:
            import torch.distributed as dist

            dist.destroy_process_group()


def _run(config: TrainConfig, data_root: Path, out_dir: Path, checkpoint: dict[str, Any] | None,
         fingerprint: str, device: torch.device, world: _World, max_steps: int | None,
         progress: bool, dataset_class: Any, network_class: Any,
         max_seconds: float | None = None) -> TrainResult:
    cfg = config
    if cfg.optim.batch_size % world.size:
        raise TrainError(f"optim.batch_size: {cfg.optim.batch_size} does not split over "
                         f"{world.size} processes")
    size = cfg.network.image_size
    with _mitsuba_for(device, cfg.reprojection.deterministic):
        return _train_loop(cfg, data_root, out_dir, checkpoint, fingerprint, device, world,
                           max_steps, progress, dataset_class, network_class, size,
                           max_seconds)


def _train_loop(cfg: TrainConfig, data_root: Path, out_dir: Path,
                checkpoint: dict[str, Any] | None, fingerprint: str, device: torch.device,
                world: _World, max_steps: int | None, progress: bool, dataset_class: Any,
                network_class: Any, size: int, max_seconds: float | None = None
                ) -> TrainResult:
    from sq_mitsuba.learning.checkpoint import write_checkpoint
    from sq_mitsuba.render.silhouette import SilhouetteRenderer

    # --- data: decoded once into the cache (rank 0 builds, the others wait and open it)
    cache_root = cfg.data.cache_dir or out_dir / "cache"
    train_set = dataset_class(data_root, "train", image_size=size, num_surface=1,
                              num_occupancy=2, seed=cfg.seed)
    if len(train_set) == 0:
        raise TrainError(f"{data_root}: the train split has no images")
    val_set = dataset_class(data_root, "val", image_size=size, num_surface=1, num_occupancy=2,
                            seed=cfg.seed)
    val_indices = _evenly(len(val_set), cfg.validation.images) if cfg.validation.every else []
    error = None
    if world.main:
        try:
            open_point_cache(train_set, cache_root, fingerprint, progress)
            open_image_cache(train_set, "train", cache_root, fingerprint, progress=progress)
            if val_indices:
                open_image_cache(val_set, "val", cache_root, fingerprint, val_indices,
                                 progress=progress)
        except ValueError as exc:
            error = str(exc)
    error = _broadcast_object(error, world)
    if error is not None:
        raise TrainError(error)
    points = open_point_cache(train_set, cache_root, fingerprint)
    images = open_image_cache(train_set, "train", cache_root, fingerprint)
    val_indices_present = bool(val_indices)
    # Validation runs on rank 0 only; the others receive its metrics.
    val_images = (open_image_cache(val_set, "val", cache_root, fingerprint, val_indices)
                  if val_indices and world.main else None)
    keep = np.arange(len(images))
    if cfg.data.min_visibility > 0:
        visible = np.isnan(images.visibility) | (images.visibility >= cfg.data.min_visibility)
        keep = keep[visible]
        if len(keep) == 0:
            raise TrainError(f"data.min_visibility: no training image has target_visibility >= "
                             f"{cfg.data.min_visibility}")
    dataset_camera = train_set.camera
    camera = dataset_camera.rescaled(size, size)
    if cfg.augment.enabled and cfg.augment.rotation:
        check_rotation_exact(camera)
    data = _TrainingData(images, points, keep, cfg, camera,
                         _symmetry_table(data_root, train_set.models))
    steps_per_epoch = data.steps_per_epoch
    total_steps = cfg.optim.epochs * steps_per_epoch

    # --- model, optimiser, schedule
    torch.manual_seed(cfg.seed)
    model = network_class(cfg.network)
    if checkpoint is not None:
        model.load_state_dict(checkpoint["model"])
    model.to(device).train()
    if cfg.channels_last:
        _to_channels_last(model)
    if world.distributed:
        if device.type == "cuda":
            model = nn.SyncBatchNorm.convert_sync_batchnorm(model)
        else:
            model = _convert_cpu_sync_batchnorm(model)
        model = nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None,
            broadcast_buffers=False, find_unused_parameters=True)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.optim.lr, betas=cfg.optim.betas,
                                  eps=cfg.optim.eps, weight_decay=cfg.optim.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: cosine_lr_factor(s, total_steps, cfg.optim.warmup_steps,
                                              cfg.optim.min_lr_ratio))
    start_step, best, history = 0, None, []
    if checkpoint is not None:
        optimizer.load_state_dict(checkpoint["optimizer"])
        scheduler.load_state_dict(checkpoint["scheduler"])
        start_step = int(checkpoint["step"])
        best = checkpoint.get("best")
        history = list(checkpoint.get("validation", []))
        rng = checkpoint["rng"]
        ranks = rng.get("ranks")
        _set_rng_state(ranks[world.rank] if ranks and len(ranks) == world.size else rng)
    else:
        torch.manual_seed(_seed_of(cfg.seed, _STREAMS["torch"], world.rank))

    # --- renderers
    renderer = reprojection_camera = None
    if cfg.loss.weights.reprojection:
        reprojection_camera = train_set.camera.rescaled(cfg.reprojection.resolution or size,
                                                        cfg.reprojection.resolution or size)
        renderer = SilhouetteRenderer(reprojection_camera, spp=cfg.reprojection.spp,
                                      sppp=cfg.reprojection.sppp,
                                      workers=render_workers(cfg.reprojection.workers, device,
                                                             world.size))
    val_renderer = (SilhouetteRenderer(camera, spp=cfg.validation.spp)
                    if val_images is not None and world.main else None)

    log = None
    if world.main:
        if checkpoint is None:
            atomic_write_json(out_dir / CONFIG_FILE, to_dict(cfg))
        log = _Log(out_dir, start_step if checkpoint is not None else None)
    git = _git_commit()
    k_matrix = camera.matrix(device=device)
    result = TrainResult(out_dir, start_step, total_steps,
                         out_dir / LAST if checkpoint is not None else None,
                         out_dir / BEST if (out_dir / BEST).is_file() else None,
                         validation=history)
    end_step = total_steps if max_steps is None else min(total_steps, max_steps)
    local = cfg.optim.batch_size // world.size

    def save(path: Path, step: int) -> None:
        rng = _rng_state()
        if world.distributed:
            import torch.distributed as dist

            states: list[Any] = [None] * world.size
            dist.all_gather_object(states, rng)
            rng = {**rng, "ranks": states}
        if not world.main:
            return
        write_checkpoint(path, {
            "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
            "config": to_dict(cfg), "model": _state_dict(model),
            "camera": dataset_camera.to_speed_dict(),
            "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
            "step": step, "epoch": step // steps_per_epoch, "total_steps": total_steps,
            "steps_per_epoch": steps_per_epoch, "rng": rng,
            "data_order": {"scheme": "epoch-permutations", "seed": cfg.seed, "step": step,
                           "images_seen": step * cfg.optim.batch_size,
                           "epoch": step * cfg.optim.batch_size // len(data),
                           "offset": step * cfg.optim.batch_size % len(data),
                           "train_images": len(data)},
            "dataset": {"root": str(data_root), "fingerprint": fingerprint,
                        "manifest_sha256": manifest_hash(data_root),
                        "train_images": len(data)},
            "git": git, "best": best, "validation": history, "world_size": world.size,
        })

    bar = None
    if progress and world.main:
        from tqdm import tqdm

        bar = tqdm(total=end_step, initial=start_step, unit="step", desc="train",
                   dynamic_ncols=True)
    timed_images, timed_seconds = 0, 0.0
    stop_at = None if max_seconds is None else time.perf_counter() + max_seconds
    try:
        for step in range(start_step, end_step):
            tick = time.perf_counter()
            batch = data.batch(step, world)
            images_in = batch["image"].to(device)
            generator = torch.Generator().manual_seed(
                _seed_of(cfg.seed, _STREAMS["subset"], step, world.rank))
            if renderer is not None:
                # Item j of this process is item rank * local + j of the global batch.
                renderer.reseed(_seed_of(cfg.seed, _STREAMS["render"], step)
                                + 7919 * world.rank * local)
            # The inputs are checked once, in the cache; the per-call NaN scans of the
            # geometry and loss functions are switched off here and replaced by one check of
            # the outputs and one of the loss, which stop the run with a clear message.
            with value_checks(False):
                terms, loss = _forward_loss(model, images_in, k_matrix, batch, cfg, renderer,
                                            reprojection_camera, generator, device)
                finite = loss is not None and bool(torch.isfinite(loss))
            # Every process agrees before the backward pass (whose gradient all-reduce would
            # wait forever for a process that skipped it) and again after it.
            if _any(not finite, world):
                raise _not_finite(step, terms, out_dir)
            assert loss is not None
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = _gradient_norm(model, cfg.optim.grad_clip)
            if _any(not math.isfinite(grad_norm), world):
                raise _not_finite(step, {**terms, "gradient norm": torch.tensor(grad_norm)},
                                  out_dir)
            optimizer.step()
            lr = optimizer.param_groups[0]["lr"]
            scheduler.step()
            values = torch.tensor([float(loss.detach())]
                                  + [float(terms[t].detach()) if t in terms else 0.0
                                     for t in TERMS], dtype=torch.float64)
            values = _all_mean(values, world)
            seconds = time.perf_counter() - tick
            rate = cfg.optim.batch_size / seconds
            result.train_seconds += seconds
            if step > start_step:  # the first step compiles kernels and fills caches
                timed_images += cfg.optim.batch_size
                timed_seconds += seconds
            done = step + 1
            result.steps = done
            result.losses.append(float(values[0]))
            row = {"step": done, "epoch": step // steps_per_epoch, "lr": lr,
                   "loss": float(values[0]), "grad_norm": grad_norm, "images_per_s": rate}
            for index, name in enumerate(TERMS):
                if name in terms:
                    row[name] = float(values[index + 1])
            if log is not None:
                log.step(row)
            if bar is not None:
                shown = {name[:5]: f"{row[name]:.3g}" for name in TERMS if name in row}
                bar.set_postfix(loss=f"{row['loss']:.4g}", **shown, img_s=f"{rate:.1f}")
                bar.update(1)

            epoch_end = done % steps_per_epoch == 0
            epoch = (done - 1) // steps_per_epoch
            if epoch_end and cfg.validation.every and val_indices_present and (
                    (epoch + 1) % cfg.validation.every == 0 or done == total_steps):
                metrics = None
                if world.main:
                    assert val_images is not None and log is not None
                    metrics = _validate(_unwrap(model), val_images, points, cfg, camera,
                                        val_renderer, device)
                metrics = _broadcast_object(metrics, world)
                entry = {"step": done, "epoch": epoch, **metrics}
                history.append(entry)
                if log is not None:
                    log.validation(entry)
                    plot_curves(log.rows, log.val_rows, out_dir / CURVES_FILE)
                name = cfg.validation.metric
                if best is None or (metrics[name] > best["value"] if _HIGHER_IS_BETTER[name]
                                    else metrics[name] < best["value"]):
                    best = {"metric": name, "value": metrics[name], "step": done}
                    save(out_dir / BEST, done)
                    result.best_checkpoint = out_dir / BEST
            # Every process stops at the same step (rank 0's clock decides).
            out_of_time = stop_at is not None and done < end_step and bool(
                _broadcast_object(time.perf_counter() >= stop_at, world))
            if epoch_end or done == end_step or out_of_time or (
                    cfg.checkpoint_every and done % cfg.checkpoint_every == 0):
                save(out_dir / LAST, done)
                result.last_checkpoint = out_dir / LAST
                _barrier(world)
            if out_of_time:
                break
    finally:
        if bar is not None:
            bar.close()
        if renderer is not None:
            renderer.close()
        if log is not None:
            if log.rows and not (out_dir / CURVES_FILE).is_file():
                with contextlib.suppress(Exception):
                    plot_curves(log.rows, log.val_rows, out_dir / CURVES_FILE)
            log.close()
    result.validation = history
    if timed_seconds > 0:
        result.images_per_second = timed_images / timed_seconds
    return result


def _broadcast_object(value: Any, world: _World) -> Any:
    """Rank 0's ``value`` on every rank."""
    if not world.distributed:
        return value
    import torch.distributed as dist

    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def _not_finite(step: int, terms: dict[str, Tensor], out_dir: Path) -> TrainError:
    """The error that stops a run at a step whose loss or gradient is not finite."""
    shown = ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in terms.items())
    last = out_dir / LAST
    kept = (f"the last checkpoint, {last} (step {_checkpoint_step(last)}), is intact"
            if last.is_file() else "no checkpoint was written yet")
    return TrainError(f"step {step + 1}: the loss or its gradient is not finite "
                      f"({shown or 'non-finite network output'}); stopped without applying "
                      f"the step; {kept}")


def _checkpoint_step(path: Path) -> int | str:
    from sq_mitsuba.learning.checkpoint import read_checkpoint

    try:
        return int(read_checkpoint(path)["step"])
    except Exception:  # only for a message
        return "?"

