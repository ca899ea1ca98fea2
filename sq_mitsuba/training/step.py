"""One training step, public: the network's forward pass, the weighted loss terms, the
backward pass and the optimiser's update (:func:`training_step`), and what it needs set up
(the renderer of the reprojection term, channels-last weights, Mitsuba's variant and threads).

The training loop (:mod:`sq_mitsuba.training.train`), ``sq-mitsuba bench train`` and any
experiment call these, so they time and run exactly what training runs.

Convention: on the CPU, a step's losses are bit-identical between runs (and so between a run
and its resumption). That needs every float sum to run in a fixed order: Mitsuba's backward
pass adds vertex gradients atomically in thread order, and training amplifies such
differences, so with ``reprojection.deterministic`` (the default) Dr.Jit renders on one thread
during training (:func:`mitsuba_for`). The cores are used instead by ``reprojection.workers``
processes that share a step's rendered items, each on one thread: an item's samples depend on
(seed, step, item) alone, so any number of workers gives the same losses bit for bit, and a run
may resume with another. Torch's CPU kernels are deterministic at a fixed thread count; a
resumed run must use the same one.

Convention: on a GPU, a step waits for the device once. The finite checks of the outputs, the
loss and the gradient norm, and the logged values (the loss, each term, the norm), are one
device reduction read back in one copy (:func:`training_step`), before the update; every other
part of the step (the batch's conversion and augmentation, the nearest-neighbour search of the
Chamfer term) is queued without waiting. On the CPU, where reading a value costs nothing, the
outputs are checked before the loss terms run (a KD-tree or the renderer never sees a NaN).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from sq_mitsuba.checks import value_checks
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.machine import LaunchRanks, available_memory, launch_ranks, too_much_memory
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer
from sq_mitsuba.render.silhouette.seeds import ITEM_SEED_STRIDE
from sq_mitsuba.training.batch import TrainingBatch
from sq_mitsuba.training.config import TrainConfig
from sq_mitsuba.training.distributed import World, any_rank
from sq_mitsuba.training.loss_terms import LossContext, compute_terms, total_loss
from sq_mitsuba.training.random_streams import STREAMS, seed_of
from sq_mitsuba.training.run.state import TrainError

__all__ = [
    "NotFiniteError",
    "StepMemory",
    "StepResult",
    "check_step_memory",
    "finite_flag",
    "forward_loss",
    "gradient_norm",
    "gradient_norm_tensor",
    "loss_context",
    "mitsuba_for",
    "outputs_finite",
    "render_workers",
    "reprojection_renderer",
    "step_memory",
    "to_channels_last",
    "training_step",
]


class NotFiniteError(TrainError):
    """A step whose loss or gradient is not finite (the update was not applied)."""

    def __init__(self, terms: dict[str, Tensor]) -> None:
        shown = ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in terms.items())
        super().__init__(f"the loss or its gradient is not finite "
                         f"({shown or 'non-finite network output'})")
        self.terms = terms


@dataclass
class StepResult:
    """What one :func:`training_step` did (this process's values)."""

    loss: Tensor
    "The weighted total, a detached scalar."
    terms: dict[str, Tensor]
    """Each term the loss weighs, unweighted (the value before its weight, as ``log.csv``
    holds it), detached scalars, in registry order."""
    grad_norm: float
    "The gradient's global L2 norm before clipping."
    values: dict[str, float] = dataclasses.field(default_factory=dict)
    """``loss`` and each term as floats (read back with the finite checks, in one copy):
    ``{"loss": ..., name: ...}``."""


def finite_flag(output: Any) -> Tensor:
    """Whether every floating tensor field of a network output is finite: a bool scalar on
    the output's device, one reduction, no synchronisation."""
    flags = [torch.isfinite(value).all() for item in dataclasses.fields(output)
             if isinstance(value := getattr(output, item.name), Tensor)
             and value.is_floating_point()]
    return torch.stack(flags).all() if flags else torch.tensor(True)


def outputs_finite(output: Any) -> bool:
    """Whether every floating tensor field of a network output is finite (one read)."""
    return bool(finite_flag(output))


def forward_loss(model: nn.Module, batch: TrainingBatch, k_matrix: Tensor,
                 context: LossContext) -> tuple[dict[str, Tensor], Tensor | None]:
    """The forward half of a training step: the network on ``batch.image`` and the weighted
    loss of its output (every term ``context.loss`` weighs, see
    :mod:`sq_mitsuba.training.loss_terms`).

    Args:
        model: the network (or its DistributedDataParallel wrapper), in training mode.
        batch: this process's batch, on the model's device.
        k_matrix: (3, 3) intrinsics at the network's input size.
        context: the loss's settings, renderer and subset generator for this step
            (:func:`loss_context`).

    Returns:
        (terms, loss): each term the loss weighs, unweighted, and their weighted sum
        (:func:`~sq_mitsuba.training.loss_terms.total_loss`), scalars; ({}, None) when the
        network's outputs are not finite.
    """
    output = model(batch.image, k_matrix)
    if not outputs_finite(output):
        return {}, None
    terms = compute_terms(output, batch,
                          dataclasses.replace(context, camera_matrix=k_matrix))
    return terms, total_loss(terms, context.loss)


def gradient_norm_tensor(model: nn.Module, grad_clip: float | None) -> Tensor:
    """Norm of the gradient of every parameter, before clipping it to ``grad_clip`` (None:
    no clipping): a scalar on the parameters' device, not read back (clipping does not wait
    for it)."""
    if grad_clip is not None:
        return nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
    return torch.linalg.vector_norm(torch.stack([
        p.grad.norm() for p in model.parameters() if p.grad is not None]))


def gradient_norm(model: nn.Module, grad_clip: float | None) -> float:
    """:func:`gradient_norm_tensor` read back as a float."""
    return float(gradient_norm_tensor(model, grad_clip))


def training_step(model: nn.Module, optimizer: torch.optim.Optimizer, batch: TrainingBatch,
                  k_matrix: Tensor, context: LossContext, grad_clip: float | None,
                  world: World | None = None) -> StepResult:
    """One optimiser step: :func:`forward_loss`, backward, gradient clipping, update.

    The inputs are checked once, where the data are cached; the per-call NaN scans of the
    geometry and loss functions are switched off here and replaced by one check of the outputs
    and one of the loss and of the gradient norm.

    On the CPU the outputs and the loss are checked before the backward pass; in a distributed
    run (``world``) every process agrees on them there (the gradient all-reduce would wait
    forever for a process that skipped it) and again on the norm after it. On any other device
    every process runs the loss and the backward pass whatever the outputs hold, and the
    outputs, the loss and the norm are checked together after it, with the logged values, in
    one read (see the module docstring).

    Raises:
        NotFiniteError: the loss or the gradient is not finite; the update was not applied.
    """
    world = World() if world is None else world
    if batch.image.device.type != "cpu":
        return _device_step(model, optimizer, batch, k_matrix, context, grad_clip, world)
    with value_checks(False):
        terms, loss = forward_loss(model, batch, k_matrix, context)
        finite = loss is not None and bool(torch.isfinite(loss))
    if any_rank(not finite, world):
        raise NotFiniteError(terms)
    assert loss is not None
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    norm = gradient_norm(model, grad_clip)
    if any_rank(not math.isfinite(norm), world):
        raise NotFiniteError({**terms, "gradient norm": torch.tensor(norm)})
    optimizer.step()
    detached = {k: v.detach() for k, v in terms.items()}
    # float32 -> float64 is exact: the values equal float() of each tensor.
    read = torch.stack([loss.detach(), *detached.values()]).to(torch.float64).tolist()
    return StepResult(loss.detach(), detached, norm, dict(zip(["loss", *detached], read,
                                                              strict=True)))


def _device_step(model: nn.Module, optimizer: torch.optim.Optimizer, batch: TrainingBatch,
                 k_matrix: Tensor, context: LossContext, grad_clip: float | None,
                 world: World) -> StepResult:
    """:func:`training_step` on a GPU: one read of the device per step (the finite checks
    and the logged values together), before the update."""
    with value_checks(False):
        output = model(batch.image, k_matrix)
        outputs_ok = finite_flag(output)
        terms = compute_terms(output, batch,
                          dataclasses.replace(context, camera_matrix=k_matrix))
        loss = total_loss(terms, context.loss)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    norm = gradient_norm_tensor(model, grad_clip)
    detached = {k: v.detach() for k, v in terms.items()}
    ok = outputs_ok & torch.isfinite(loss.detach()) & torch.isfinite(norm)
    read = torch.stack([ok.to(torch.float64), norm.detach().to(torch.float64),
                        *(v.to(torch.float64) for v in (loss.detach(), *detached.values()))]
                       ).tolist()  # the step's one synchronisation
    if any_rank(read[0] != 1.0, world):
        raise NotFiniteError({**detached, "gradient norm": torch.tensor(read[1])})
    optimizer.step()
    return StepResult(loss.detach(), detached, read[1],
                      dict(zip(["loss", *detached], read[2:], strict=True)))


def loss_context(config: TrainConfig, renderer: SilhouetteRenderer | None, step: int,
                 world: World | None = None, part_targets: Tensor | None = None) -> LossContext:
    """The loss context of step ``step``: the renderer restarted at the step's samples and the
    reprojection subset's generator seeded from the step (so a resumed step repeats);
    ``part_targets`` (models, M, 16) for the ``parts`` term."""
    world = World() if world is None else world
    generator = torch.Generator().manual_seed(
        seed_of(config.seed, STREAMS["subset"], step, world.rank))
    if renderer is not None:
        # Item j of this process is item rank * local + j of the global batch.
        local = config.optim.batch_size // world.size
        renderer.reseed(seed_of(config.seed, STREAMS["render"], step)
                        + ITEM_SEED_STRIDE * world.rank * local)
    return LossContext(config.loss, config.reprojection, renderer, generator,
                       part_targets=part_targets)


def to_channels_last(model: nn.Module) -> None:
    """Store ``model``'s 4-D weights channels-last and have it feed its encoder that way."""
    model.to(memory_format=torch.channels_last)
    if hasattr(model, "channels_last"):
        model.channels_last = True


def render_workers(requested: int | None, device: torch.device, processes: int = 1) -> int:
    """Worker processes for the reprojection renderer (see ``ReprojectionConfig.workers``).

    Args:
        requested: the config's value; None picks one per CPU core available to this process,
            divided among ``processes`` training processes (0 when that leaves one).
        device: the training device; CUDA renders in the training process (0).
        processes: training processes on this machine (torchrun's world size).
    """
    from sq_mitsuba.render.silhouette.workers import default_worker_count

    if device.type != "cpu":
        return 0
    return default_worker_count(processes) if requested is None else requested


# What training on the CPU holds in memory, measured 2026-12-02 (one step of
# train/configs/cpu.toml at 96 px input, the process tree's peak): batch 128 used 3.3 GB and
# batch 512 used 9.7 GB, so about 17 MB an image (the activations the backward pass keeps) over
# about 1.2 GB fixed (the interpreter, torch, Mitsuba, the network and its optimiser). An
# image's share grows with its pixels, (network.image_size / 96)^2. Those runs' trees held
# cpu.toml's default two reprojection workers too, so adding the workers' own cost below errs
# on the safe side.
STEP_MEMORY_IMAGE_SIZE = 96
STEP_BYTES_PER_IMAGE = 17_000_000
STEP_FIXED_BYTES = 1_200_000_000
#: A validation image at 96 px: forward only, nothing kept for a backward pass (measured
#: 2026-12-02, cpu.toml's network, batches of 64 and 256: 2.7 and 1.9 MB an image; rounded
#: up for its silhouette and points).
VALIDATION_BYTES_PER_IMAGE = 3_000_000
#: One reprojection worker process (measured 2026-12-02: 16 workers with tiny.toml, 18
#: processes in all, 5.4 GB).
RENDER_WORKER_BYTES = 300_000_000


@dataclass(frozen=True)
class StepMemory:
    """What a training step on the CPU would hold (bytes, the measured constants above), for
    the ``processes`` on this machine, against the ``memory`` this process may use."""

    memory: int
    fixed: float  # each process's fixed part and its reprojection workers
    step: float  # the step's images
    validation: float  # rank 0's validation batch
    workers: int
    processes: int
    scale: float  # an image's share against one of STEP_MEMORY_IMAGE_SIZE

    @property
    def need(self) -> int:
        return int(self.fixed + max(self.step, self.validation))


def step_memory(config: TrainConfig, device: torch.device,
                ranks: LaunchRanks | None = None) -> StepMemory | None:
    """The estimate :func:`check_step_memory` checks: for the ``ranks.local_size`` processes
    on this machine, each one's fixed part and reprojection workers, plus the larger of the
    step's images (``optim.batch_size`` split over ``ranks.size`` processes) and rank 0's
    validation batch. None on CUDA (the batch lives in GPU memory, which torch's own error
    reports) or where :func:`~sq_mitsuba.machine.available_memory` is unknown."""
    memory = available_memory()
    if device.type != "cpu" or memory is None:
        return None
    ranks = ranks or launch_ranks()
    processes, optim = ranks.local_size, config.optim
    workers = render_workers(config.reprojection.workers, device, processes) \
        if config.loss.weights.get("reprojection", 0.0) else 0
    scale = (config.network.image_size / STEP_MEMORY_IMAGE_SIZE) ** 2
    share = -(-optim.batch_size // ranks.size)  # each process's images of a step
    val_batch = min(config.validation.batch_size, config.validation.images) \
        if config.validation.every else 0
    return StepMemory(memory=memory,
                      fixed=processes * (STEP_FIXED_BYTES + workers * RENDER_WORKER_BYTES),
                      step=processes * share * STEP_BYTES_PER_IMAGE * scale,
                      validation=val_batch * VALIDATION_BYTES_PER_IMAGE * scale,
                      workers=workers, processes=processes, scale=scale)


def check_step_memory(config: TrainConfig, device: torch.device,
                      ranks: LaunchRanks | None = None) -> None:
    """Refuse (one-line :class:`TrainError` naming the ``--set`` keys to lower) a run on the
    CPU whose step, or validation batch, would need more memory than this machine has
    (:func:`step_memory`), so that it stops before the run folder is made instead of being
    killed at its first step."""
    ranks = ranks or launch_ranks()
    estimate = step_memory(config, device, ranks)
    if estimate is None or estimate.need <= estimate.memory:
        return
    optim, processes, scale = config.optim, estimate.processes, estimate.scale
    step, val, workers = estimate.step, estimate.validation, estimate.workers
    val_batch = min(config.validation.batch_size, config.validation.images)
    room = estimate.memory - estimate.fixed  # what the images may take (> 0: a batch helps)
    advice = []
    if 0 < room < step:
        most = int(room // (processes * STEP_BYTES_PER_IMAGE * scale)) * ranks.size
        advice.append("optim.batch_size" + (f" (at most {most} fits)" if most else ""))
    if 0 < room < val:
        most = int(room // (VALIDATION_BYTES_PER_IMAGE * scale))
        advice.append("validation.batch_size" + (f" (at most {most} fits)" if most else ""))
    if workers:
        advice.append(f"reprojection.workers (about {RENDER_WORKER_BYTES / 1e9:.1f} GB each)")
    what = (f"{'optim' if step >= val else 'validation'}.batch_size: "
            f"{optim.batch_size if step >= val else val_batch} images of "
            f"{config.network.image_size} px on the CPU"
            + (f" in {processes} processes" if processes > 1 else "")
            + (f" with {workers} reprojection worker(s)" if workers else "")
            + (" each" if workers and processes > 1 else ""))
    raise TrainError(too_much_memory(
        what, estimate.need, estimate.memory, "lower --set " + " or ".join(advice) if advice
        else f"each training process alone takes about {STEP_FIXED_BYTES / 1e9:.1f} GB"))


def reprojection_renderer(config: TrainConfig, dataset_camera: Camera, device: torch.device,
                          processes: int = 1) -> SilhouetteRenderer | None:
    """The reprojection term's renderer (``reprojection.resolution``, spp, workers), or None
    when the term is off."""
    if not config.loss.weights.get("reprojection", 0.0):
        return None
    rep = config.reprojection
    side = rep.resolution or config.network.image_size
    return SilhouetteRenderer(dataset_camera.rescaled(side, side), spp=rep.spp, sppp=rep.sppp,
                              workers=render_workers(rep.workers, device, processes))


@contextlib.contextmanager
def mitsuba_for(device: torch.device, deterministic: bool) -> Iterator[None]:
    """Mitsuba's variant for ``device``; on the CPU with ``deterministic``, one Dr.Jit thread
    inside the block (restored after), so that gradient sums do not depend on thread timing."""
    from sq_mitsuba.render.backend import mitsuba, one_thread

    mitsuba("cuda_ad_mono" if device.type == "cuda" else None)
    with one_thread(deterministic and device.type == "cpu"):
        yield
