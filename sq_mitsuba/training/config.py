"""Configuration of ``sq-mitsuba train``: every default of a training run, in one place.

A :class:`TrainConfig` is a tree of frozen dataclasses in the project's configuration style
(:mod:`sq_mitsuba.config`): files in ``train/configs/`` are TOML tables of its fields, command
lines change fields with ``--set optim.lr=3e-4``, and a checkpoint records ``to_dict(config)``.

Files may start from another file with a top-level ``base = "a.toml"`` key (a path relative to
the file that names it): the base is read first (recursively, cycles refused) and the file's
own tables are merged over it key by key, so ``a_m6.toml`` can hold just ``base = "a.toml"``
and ``[network] num_primitives = 6``. :func:`load_train_config` resolves this; the result is
an ordinary, complete config.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from sq_mitsuba.config import (
    ConfigError,
    from_dict,
    in_range,
    non_negative,
    positive,
    read_mapping,
)
from sq_mitsuba.model.network import NetworkConfig
from sq_mitsuba.training.augment import AugmentConfig
from sq_mitsuba.training.loss_terms import LossConfig, ReprojectionConfig

__all__ = [
    "AugmentConfig",
    "DataConfig",
    "LossConfig",
    "OptimConfig",
    "ReprojectionConfig",
    "TrainConfig",
    "ValidationConfig",
    "load_train_config",
]

BASE_KEY = "base"
_MAX_BASE_DEPTH = 16


@dataclass(frozen=True)
class DataConfig:
    """What the shape losses compare against, and which images train.

    The input size S is ``network.image_size`` (one field, read by training and inference
    alike): images and masks are resized to S x S.
    """

    num_surface: int = in_range(1, 1_000_000, default=2500)
    "Ground-truth surface points per image for the Chamfer loss."
    num_occupancy: int = in_range(2, 1_000_000, default=10_000)
    "Labelled occupancy points per image (half inside, half outside where the model allows)."
    min_visibility: float = in_range(0, 1, default=0.0)
    """Train only on images whose label ``target_visibility`` (the target's mean grey level /
    255) is at least this: 0 keeps every image, 0.04 drops the dark ones (mean grey below
    10 / 255). Labels without the key (the SPE3R release) always count."""
    train_images: int | None = in_range(1, 100_000_000, default=None)
    """Train only on the first this many images of the train split (after the
    ``min_visibility`` filter), e.g. to study how results grow with the number of views;
    None: every image."""
    cache_dir: Path | None = None
    """Folder of the decoded training cache (shared between runs of the same dataset and
    size); None: ``RUN_DIR/cache``. Not compared when a run resumes."""
    prefetch: bool | None = None
    """Prepare the next steps' host share of the batch (cache rows, point and augmentation
    draws, pinned copies) while the step runs; the batches are the same either way. None: on
    where the step runs on a GPU, off on the CPU (the workers would take the step's cores).
    Not compared when a run resumes."""
    prefetch_workers: int = in_range(0, 64, default=2)
    """Processes that prepare the batches when ``prefetch`` is on, each two steps ahead; 0:
    one thread of the training process, one step ahead (its Python work then competes with
    the step's for the interpreter lock). Not compared when a run resumes."""


@dataclass(frozen=True)
class OptimConfig:
    """AdamW with a per-step cosine schedule and gradient clipping.

    Large batches: ``lr`` and ``warmup_images`` are given for ``reference_batch`` images per
    step, and ``lr_scaling`` says how they follow ``batch_size`` (:meth:`peak_lr`,
    :meth:`warmup_step_count`): a batch k times the reference takes k times fewer steps per
    epoch, so each step must move further ("linear": k lr, Goyal et al. 2017 for SGD; "sqrt":
    sqrt(k) lr, the rule that keeps Adam's update noise alike, Malladi et al. 2022; "adam_sde":
    that rule in full, Adam's moments also made to remember as many images as at the reference
    batch, each beta to 1 - k (1 - beta), and eps to eps / sqrt(k), :meth:`adam_betas`,
    :meth:`adam_eps`).
    """

    lr: float = positive(1e-4)
    """Peak learning rate at ``reference_batch`` images per step (the peak of this run:
    :meth:`peak_lr`)."""
    lr_scaling: Literal["none", "linear", "sqrt", "adam_sde"] = "none"
    """How the peak learning rate follows batch_size / reference_batch = k: none (lr as
    given), linear (k lr), sqrt (sqrt(k) lr) or adam_sde (sqrt(k) lr, and betas and eps
    rescaled: see the class)."""
    reference_batch: int = in_range(1, 1_000_000, default=32)
    "The batch size that lr (and warmup_images) are tuned for; read with lr_scaling."
    weight_decay: float = non_negative(1e-4)
    "AdamW's decoupled weight decay."
    eps: float = positive(1e-5)
    "AdamW's epsilon."
    betas: tuple[float, float] = (0.9, 0.999)
    "AdamW's moment decay rates."
    min_lr_ratio: float = in_range(0, 1, default=0.0)
    "The cosine schedule decays to lr * min_lr_ratio at the last step."
    warmup_steps: int = in_range(0, 1_000_000_000, default=0)
    """Steps W of linear warm-up, lr / W up to lr, before the cosine decay (unless
    warmup_images is set). A warm-up as long as the run (epochs x steps per epoch) is said in
    a warning: the learning rate would never reach lr."""
    warmup_images: int | None = in_range(0, 1_000_000_000, default=None)
    """Warm-up length in images seen instead of steps: ceil(warmup_images / batch_size)
    steps, so a larger batch warms up over the same data; None: warmup_steps."""
    grad_clip: float | None = positive(1.0)
    "Clip the gradient's global L2 norm to this; None: no clipping."
    batch_size: int = in_range(1, 4096, default=32)
    "Images per step over all processes (each of N processes takes batch_size / N)."
    epochs: int = in_range(1, 100_000, default=50)
    """Epochs of the schedule, an epoch being ceil(images / batch_size) steps of the data
    stream (:mod:`~sq_mitsuba.training.data_stream`): one pass over the training images when
    batch_size divides their number. Otherwise the stream runs on across epochs (an epoch's
    last batch is filled from the next permutation, nothing dropped or padded), so an epoch
    sees some images twice and, later, may miss some."""
    trainable: tuple[str, ...] = ()
    """Train only the parameters whose names start with one of these (e.g. ["mask_head."]
    with init_from: a new head on a trained network); the rest stay as they are, in eval
    mode. Empty: train everything."""

    def __post_init__(self) -> None:
        for index, beta in enumerate(self.betas):
            if not 0 <= beta < 1:
                raise ValueError(f"betas[{index}]: expected a value in [0, 1), got {beta}")
        ratio = self.batch_size / self.reference_batch
        for index, beta in enumerate(self.betas):
            if self.lr_scaling == "adam_sde" and ratio * (1 - beta) >= 1:
                raise ValueError(
                    f"betas[{index}]: {beta} cannot be rescaled to batch_size "
                    f"{self.batch_size} (lr_scaling adam_sde: 1 - k (1 - beta) must stay "
                    f"above 0, k = {ratio:g}); use a batch closer to reference_batch")

    def peak_lr(self) -> float:
        """The peak learning rate of this run: ``lr`` scaled by ``lr_scaling`` from
        ``reference_batch`` to ``batch_size`` (k = batch_size / reference_batch: lr, k lr or
        sqrt(k) lr)."""
        ratio = self.batch_size / self.reference_batch
        factor = {"none": 1.0, "linear": ratio, "sqrt": math.sqrt(ratio),
                  "adam_sde": math.sqrt(ratio)}[self.lr_scaling]
        return self.lr * factor

    def adam_betas(self) -> tuple[float, float]:
        """AdamW's betas of this run: ``betas``, or with ``lr_scaling = "adam_sde"`` each
        ``1 - k (1 - beta)`` (k = batch_size / reference_batch), so that the moments average
        over as many images as at the reference batch."""
        if self.lr_scaling != "adam_sde":
            return self.betas
        ratio = self.batch_size / self.reference_batch
        first, second = (1 - ratio * (1 - beta) for beta in self.betas)
        return first, second

    def adam_eps(self) -> float:
        """AdamW's eps of this run: ``eps``, or ``eps / sqrt(k)`` with ``adam_sde`` (the
        gradient's noise, which eps is compared with, shrinks by sqrt(k) in a k times larger
        batch)."""
        if self.lr_scaling != "adam_sde":
            return self.eps
        return self.eps / math.sqrt(self.batch_size / self.reference_batch)

    def warmup_step_count(self) -> int:
        """Steps of warm-up: ``ceil(warmup_images / batch_size)`` when ``warmup_images`` is
        set, else ``warmup_steps``."""
        if self.warmup_images is None:
            return self.warmup_steps
        return math.ceil(self.warmup_images / self.batch_size)


@dataclass(frozen=True)
class ValidationConfig:
    """Validation during training, on a fixed subset of the ``val`` split (skipped, and no
    best.pt written, when the dataset's val split is empty)."""

    every: int = non_negative(1)
    "Validate every this many epochs (and after the last); 0: never."
    images: int = in_range(1, 1_000_000, default=64)
    "Validation images, spread evenly over the val split."
    batch_size: int = in_range(1, 4096, default=32)
    "Images per validation batch."
    metric: Literal["chamfer_l1", "iou_2d", "rotation_error_deg", "mask_iou"] = "chamfer_l1"
    """The metric that picks best.pt (Chamfer and rotation error lower, the IoUs higher;
    mask_iou: the mask head's, for a network with one)."""
    level: int = in_range(0, 5, default=3)
    "Icosphere level of the primitive meshes for the validation silhouettes and points."
    spp: int = in_range(1, 1024, default=16)
    "Samples per pixel of the validation silhouettes."


@dataclass(frozen=True)
class TrainConfig:
    """A training run: data, network, losses, renderer, optimiser, augmentation, validation."""

    data: DataConfig = field(default_factory=DataConfig)
    "Input size, point counts, image filter and cache."
    network: NetworkConfig = field(default_factory=NetworkConfig)
    "The network (encoder and heads)."
    loss: LossConfig = field(default_factory=LossConfig)
    "Loss weights and shape-loss settings."
    reprojection: ReprojectionConfig = field(default_factory=ReprojectionConfig)
    "The reprojection term's renderer."
    optim: OptimConfig = field(default_factory=OptimConfig)
    "Optimiser, schedule and batch."
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    "Label-preserving augmentation (all off by default, as the paper)."
    validation: ValidationConfig = field(default_factory=ValidationConfig)
    "Validation during training."
    seed: int = in_range(0, 2**63 - 1, default=42)  # torch.manual_seed takes 64-bit seeds
    "Seeds the network's initialisation, the data order, point sampling and augmentation."
    device: Literal["auto", "cpu", "cuda"] = "auto"
    "Where to train: auto = CUDA when available (Mitsuba's cuda variant), else the CPU."
    channels_last: bool = True
    """Train with the encoder's weights and activations channels-last (NHWC): the same
    network up to float rounding, and on the CPU its depthwise convolutions run far faster this
    way (see eval/BENCHMARKS.md)."""
    checkpoint_every: int = non_negative(200)
    """Also write last.pt every this many steps (0: only at the end of each epoch, or of the run
    when ``checkpoint_each_epoch`` is off)."""
    checkpoint_each_epoch: bool = True
    """Write last.pt at the end of every epoch. Off: only every ``checkpoint_every`` steps and
    at the run's end, for runs of many tiny epochs (one fixed batch, a few models seen for many
    epochs) where writing the checkpoint would cost more than the step."""
    init_from: Path | None = None
    """Start from the weights of this checkpoint or exported model (after the seed's
    initialisation): layers it lacks keep their new weights; a layer of another shape, or one
    the network lacks, is refused, but for a network with existence probabilities (its
    primitive generators grow from a file with fewer) and a file's shape decoder of another
    kind (left out: the new decoder starts anew). None: start from the seed (and
    network.pretrained)."""


# ------------------------------------------------------------------------------- files


def _merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` merged into ``base``: tables key by key, anything else replaced."""
    merged = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = _merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def resolve_mapping(path: str | Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The table of a TOML config file with its ``base`` chain merged in (``base`` removed)."""
    path = Path(path)
    if path.suffix.lower() != ".toml":
        raise ConfigError(f"{path}: training configs are TOML files (.toml)")
    resolved = path.resolve()
    if resolved in _seen:
        chain = " -> ".join(p.name for p in (*_seen, resolved))
        raise ConfigError(f"{path}: base: the chain of bases loops ({chain})")
    if len(_seen) >= _MAX_BASE_DEPTH:
        raise ConfigError(f"{path}: base: more than {_MAX_BASE_DEPTH} levels of bases")
    data = dict(read_mapping(path))
    base = data.pop(BASE_KEY, None)
    if base is None:
        return data
    if not isinstance(base, str) or not base:
        raise ConfigError(f"{path}: base: expected a file name (string), got {base!r}")
    base_path = path.parent / base
    if not base_path.is_file():
        raise ConfigError(f"{path}: base: no such file: {base_path}")
    return _merge(resolve_mapping(base_path, (*_seen, resolved)), data)


def load_train_config(path: str | Path) -> TrainConfig:
    """A :class:`TrainConfig` from a TOML file (``base`` chains resolved), strictly checked.

    Errors are one-line :class:`~sq_mitsuba.config.ConfigError` s naming the file and the
    dotted field, e.g. ``a.toml: optim.lr: expected a value > 0, got -1``.
    """
    path = Path(path)
    repository = Path(__file__).resolve().parents[2]
    if not path.exists() and not path.is_absolute() and (repository / path).is_file():
        # A config named as from the repository's root, run from another folder.
        raise ConfigError(f"{path}: no such file here ({Path.cwd()}); the repository's is "
                          f"{repository / path}")
    data = resolve_mapping(path)
    try:
        return from_dict(TrainConfig, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
