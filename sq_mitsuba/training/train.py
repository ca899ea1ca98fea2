"""Training of :class:`~sq_mitsuba.model.network.SuperquadricNet`: :func:`train`, the loop.

:func:`train` runs one training job described by a :class:`TrainConfig` on an SPE3R-layout
dataset and writes into a run folder:

- ``config.json``: the resolved config (written once, when the run starts);
- ``log.csv``: one row per step: step, epoch, learning rate, total loss and each loss term (the
  mean over the global batch), gradient norm before clipping, images/s
  (:mod:`sq_mitsuba.training.run.log`);
- ``val.csv``: one row per validation: mean Chamfer-L1 (the paper's convention), 2D IoU (the
  predicted assembly's Mitsuba silhouette at the predicted pose against the mask) and rotation
  error in degrees, over a fixed subset (:mod:`sq_mitsuba.training.validation`);
- ``curves.png``: loss terms and validation metrics, refreshed at each validation;
- ``last.pt`` (the latest state) and ``best.pt`` (best validation ``validation.metric``;
  while no validation has run, a copy of ``last.pt``, said in :attr:`TrainResult.notes`, so
  ``RUN/best.pt`` exists whenever ``last.pt`` does, an interrupted run's too), written
  atomically (:mod:`sq_mitsuba.training.run.folder`);
- TensorBoard events in ``tensorboard/`` when the ``tensorboard`` package is importable;
- ``cache/``: the decoded training data (:mod:`sq_mitsuba.training.cache`), unless
  ``data.cache_dir`` points elsewhere.

The trainer's parts, each a module of :mod:`sq_mitsuba.training`: the data stream
(:mod:`~sq_mitsuba.training.data_stream`, batches typed by
:class:`~sq_mitsuba.training.batch.TrainingBatch`), the loss terms
(:mod:`~sq_mitsuba.training.loss_terms`), one step (:mod:`~sq_mitsuba.training.step`),
the schedule (:mod:`~sq_mitsuba.training.schedule`), random streams
(:mod:`~sq_mitsuba.training.random_streams`), distributed set-up
(:mod:`~sq_mitsuba.training.distributed`), the run folder and its records; they share one
:class:`~sq_mitsuba.training.run.state.TrainRun`.

``resume=True`` continues from ``last.pt`` exactly: the data order and every per-item random
draw are pure functions of (seed, step, position in the batch), and the renderer's sample
sequence restarts from a seed of the step, so the steps after a resume repeat an uninterrupted
run's (on the CPU bit for bit, tested; see :mod:`~sq_mitsuba.training.step`). Ctrl-C or
SIGTERM saves ``last.pt`` at the step it lands in and stops without validating (promptly), and
``resume`` first runs a validation that step was due: ``val.csv`` is an uninterrupted run's.

One run at a time per run folder: rank 0 holds :func:`sq_mitsuba.outputs.output_lock` on it
for the whole call, so a second run started into the same folder stops at once with one line
(``OutputBusyError``) and writes nothing; the lock dies with its process (``kill -9``
included), so a killed run never blocks the next. Reading the dataset changes nothing in it:
the models' symmetries are kept in the cache folder, not beside the models.

Errors (one line, :class:`TrainError` or the dataset's ``DatasetError``, both ``ValueError``),
all before any file is written unless said (a run folder this call created goes again): an
unwritable run folder or a run folder that already holds a run (without ``resume``), or that
another run is writing into; a dataset that does not open, whose images are not of
``camera.json``'s size, or whose ``samples.npz`` lacks an array or holds NaN (naming the file,
:meth:`Spe3rDataset.check <sq_mitsuba.data.spe3r.Spe3rDataset.check>`); a network that cannot
be built (``network.pretrained`` unreadable), is not of one input channel (the training data
are grey) or cannot feed a weighted loss term; a run on the CPU needing more memory than the
machine has (:func:`~sq_mitsuba.training.step.check_step_memory`); a corrupt
image while the cache is built (naming the file; the new run folder and cache are removed); a
checkpoint of another config or dataset on resume (naming the first difference); a loss or
gradient that is not finite (the step is not applied and the last checkpoint stays as it was).
Temporary files an earlier run left when killed mid-write are removed when the next starts.
"""

from __future__ import annotations

import contextlib
import shutil
import time
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from sq_mitsuba.config import from_dict, to_dict
from sq_mitsuba.config import validate as validate_config
from sq_mitsuba.data.spe3r import DatasetError
from sq_mitsuba.io import atomic_write_json
from sq_mitsuba.machine import launch_ranks
from sq_mitsuba.model.network import SuperquadricNet
from sq_mitsuba.outputs import output_lock
from sq_mitsuba.progress import progress_bar
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer
from sq_mitsuba.training.cache import dataset_fingerprint
from sq_mitsuba.training.config import TrainConfig
from sq_mitsuba.training.data_stream import (
    DataSources,
    TrainingData,
    open_datasets,
    open_training_data,
    run_cache_root,
)
from sq_mitsuba.training.distributed import (
    all_mean,
    barrier,
    broadcast_object,
    start_distributed,
    unwrap,
    wrap_model,
)
from sq_mitsuba.training.loss_terms import LOSS_TERMS, LossTermError, check_terms, short_term_name
from sq_mitsuba.training.prefetch import BatchPrefetcher, prefetch_enabled
from sq_mitsuba.training.random_streams import rng_state, seed_globals, set_rng_state
from sq_mitsuba.training.run.folder import (
    BEST,
    CONFIG_FILE,
    CURVES_FILE,
    LAST,
    check_cache_dir,
    check_out_dir,
    check_resumable,
    copy_checkpoint,
    git_commit,
    load_initial_weights,
    not_finite_error,
    read_resumed,
    remove_stale_temporaries,
    save_checkpoint,
)
from sq_mitsuba.training.run.interrupt import StepInterrupt
from sq_mitsuba.training.run.log import RunLog, plot_curves
from sq_mitsuba.training.run.state import TrainError, TrainResult, TrainRun
from sq_mitsuba.training.schedule import cosine_lr_factor, make_optimizer
from sq_mitsuba.training.step import (
    NotFiniteError,
    check_step_memory,
    loss_context,
    mitsuba_for,
    reprojection_renderer,
    to_channels_last,
    training_step,
)
from sq_mitsuba.training.validation import improves, validate

__all__ = ["CURVES_FILE", "TrainError", "TrainResult", "cosine_lr_factor", "train"]


def train(config: TrainConfig | None, data_root: str | Path, out_dir: str | Path, *,
          resume: bool = False, max_steps: int | None = None, progress: bool = True,
          max_seconds: float | None = None) -> TrainResult:
    """Train (or resume) a run; see the module docstring for what it writes.

    Args:
        config: the run's config; None takes the checkpoint's when resuming, else the
            defaults. Resuming with a config that differs (other than in the fields of
            ``run.folder.RESUME_FREE``) is refused, naming the first differing field.
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
    data_root, out_dir = Path(data_root), Path(out_dir)
    if max_steps is not None and max_steps < 0:
        raise TrainError(f"max_steps: expected >= 0, got {max_steps}")
    if max_seconds is not None and not max_seconds > 0:
        raise TrainError(f"max_seconds: expected > 0, got {max_seconds}")
    main_process = launch_ranks().rank == 0
    created = not out_dir.exists()
    # One run at a time in a run folder: rank 0 holds its lock to the end (a second run, a
    # --resume too, stops with the lock's line before the folder's checks; the lock dies with
    # its process, kill -9 included): every check below sees the folder as no run changes it.
    with output_lock(out_dir, command="sq-mitsuba train") if main_process else \
            contextlib.nullcontext():
        return _train(config, data_root, out_dir, resume, max_steps, progress, max_seconds,
                      created, main_process)


def _train(config: TrainConfig | None, data_root: Path, out_dir: Path, resume: bool,
           max_steps: int | None, progress: bool, max_seconds: float | None, created: bool,
           main_process: bool) -> TrainResult:
    """:func:`train` under the run folder's lock (rank 0)."""
    # Checks before any work and before anything is written: the run folder (under the
    # lock), the checkpoint, the config and the memory it needs, the dataset.
    if main_process:
        check_out_dir(out_dir, resume)
    checkpoint = read_resumed(out_dir) if resume else None
    if config is None:
        config = TrainConfig() if checkpoint is None else from_dict(TrainConfig,
                                                                    checkpoint["config"])
    validate_config(config)
    if config.network.in_channels != 1:  # the caches decode and the stream serves grey images
        raise TrainError(f"network.in_channels: {config.network.in_channels}: training feeds "
                         "one-channel (grey) images only; expected 1")
    check_cache_dir(config.data.cache_dir, data_root)
    device = _device_of(config)
    check_step_memory(config, device)  # before the dataset is read and the run folder made
    # The fingerprint first: a point cache already built for it spares reading every model's
    # points again (open_datasets). A dataset it cannot be taken of gets open_datasets' error.
    try:
        fingerprint = dataset_fingerprint(data_root)
    except (OSError, DatasetError):
        fingerprint = None
    sources = open_datasets(config, data_root, run_cache_root(config, out_dir), fingerprint)
    if fingerprint is None:
        fingerprint = dataset_fingerprint(data_root)
    if checkpoint is not None:
        check_resumable(checkpoint, config, fingerprint, out_dir, data_root)
    world = start_distributed(device)
    run = TrainRun(config, data_root, out_dir, fingerprint, device, world, checkpoint,
                   max_steps, max_seconds, progress)
    try:  # the network first: a config it cannot train makes no folder
        model = _build_network(config, sources, checkpoint is not None, world.distributed)
        if world.main:
            out_dir.mkdir(parents=True, exist_ok=True)
            remove_stale_temporaries(out_dir)
        if config.optim.batch_size % world.size:
            raise TrainError(f"optim.batch_size: {config.optim.batch_size} does not split "
                             f"over {world.size} processes")
        with mitsuba_for(device, config.reprojection.deterministic):
            data = _open_data(run, sources, created)
            return _Loop(run, data, model, sources.part_targets).run()
    finally:
        if world.owns_group:
            import torch.distributed as dist

            dist.destroy_process_group()


def _build_network(config: TrainConfig, sources: DataSources, resuming: bool, distributed: bool
                   ) -> nn.Module:
    """The network from the seed (every process alike) and ``init_from`` (not when resuming),
    after checking that it builds (``network.pretrained`` loads) and feeds every loss term."""
    torch.manual_seed(config.seed)
    try:
        model = SuperquadricNet(config.network)
    except ValueError as error:
        raise TrainError(" ".join(str(error).split())) from None
    except Exception as error:  # a hostile or foreign file: torch's long advice is not ours
        raise TrainError(f"network.pretrained: {config.network.pretrained}: cannot be loaded "
                         f"as a weights file ({type(error).__name__})") from None
    if config.validation.metric == "mask_iou" and model.mask_head is None:
        raise TrainError("validation.metric: 'mask_iou' needs a mask head (network.mask_head)")
    if config.init_from is not None and not resuming:  # the start may be gone by now
        load_initial_weights(model, config.init_from)
    try:
        model.freeze_except(config.optim.trainable)
    except ValueError as error:
        raise TrainError(f"optim.{error}") from None
    size = config.network.image_size
    matrix = sources.train_set.camera.rescaled(size, size).matrix()
    model.eval()  # no statistics updated, no random draw
    with torch.set_grad_enabled(distributed):  # a distributed run's check follows gradients
        probe = model(torch.zeros(1, config.network.in_channels, size, size), matrix)
    try:
        check_terms(config.loss, probe, model if distributed else None)
    except LossTermError as error:
        raise TrainError(str(error)) from None
    return model.train()


def _open_data(run: TrainRun, sources: DataSources, created: bool) -> TrainingData:
    """The caches and the stream; a run folder this call created goes again when they fail."""
    try:
        return open_training_data(run, sources)
    except BaseException:
        if created and run.world.main and not (run.out_dir / LAST).exists():
            shutil.rmtree(run.out_dir, ignore_errors=True)
        raise


def _device_of(config: TrainConfig) -> torch.device:
    if config.device == "cuda" or (config.device == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise TrainError("device: 'cuda' asked for, but torch sees no CUDA device")
        local = launch_ranks().local_rank  # given its GPU alone, cuda:0
        return torch.device("cuda", local if torch.cuda.device_count() > 1 else 0)
    return torch.device("cpu")


class _Loop:
    """The loop of one :func:`train` call: model, optimiser and schedule, renderers, log."""

    def __init__(self, run: TrainRun, data: TrainingData, network: nn.Module,
                 part_targets: Tensor | None = None) -> None:
        cfg, world, checkpoint = run.config, run.world, run.checkpoint
        self.run_state, self.data = run, data
        self.part_targets = part_targets
        self.steps_per_epoch = data.stream.steps_per_epoch
        self.total_steps = cfg.optim.epochs * self.steps_per_epoch
        if checkpoint is not None:
            network.load_state_dict(checkpoint["model"])
        network.to(run.device).train()
        if cfg.channels_last:
            to_channels_last(network)
        self.model = wrap_model(network, run.device, world)
        self.optimizer, self.scheduler = make_optimizer(self.model, cfg.optim, self.total_steps)
        self.best: dict[str, Any] | None = None
        self.history: list[dict[str, float]] = []
        if checkpoint is not None:
            self.optimizer.load_state_dict(checkpoint["optimizer"])
            self.scheduler.load_state_dict(checkpoint["scheduler"])
            self.best = checkpoint.get("best")
            self.history = list(checkpoint.get("validation", []))
            rng = checkpoint["rng"]
            ranks = rng.get("ranks")
            set_rng_state(ranks[world.rank] if ranks and len(ranks) == world.size else rng)
        else:
            seed_globals(cfg.seed, world.rank)
        self.validation_due = checkpoint is not None and self._validation_skipped(run.start_step)
        self.renderer = reprojection_renderer(cfg, data.dataset_camera, run.device,
                                              world.local_size)
        self.val_renderer = (SilhouetteRenderer(data.camera, spp=cfg.validation.spp)
                             if data.val_images is not None and world.main else None)
        self.log: RunLog | None = None
        if world.main:
            if checkpoint is None:
                atomic_write_json(run.out_dir / CONFIG_FILE, to_dict(cfg))
            # A val.csv row of a due validation is one a killed resume wrote: it runs again.
            self.log = RunLog(run.out_dir, run.start_step if checkpoint is not None else None,
                              val_upto=run.start_step - 1 if self.validation_due else None)
        self.git = git_commit()
        self.k_matrix = data.camera.matrix(device=run.device)
        self.prefetcher: BatchPrefetcher | None = None

    # ------------------------------------------------------------------ checkpoints

    def save(self, name: str, step: int) -> None:
        """Write ``name`` (last.pt or best.pt) after ``step`` steps (rank 0; every process
        contributes its RNG state)."""
        run = self.run_state
        rng = rng_state()
        if run.world.distributed:
            import torch.distributed as dist

            states: list[Any] = [None] * run.world.size
            dist.all_gather_object(states, rng)
            rng = {**rng, "ranks": states}
        if not run.world.main:
            return
        save_checkpoint(run.out_dir / name, run, step, model=self.model,
                        optimizer=self.optimizer, scheduler=self.scheduler,
                        steps_per_epoch=self.steps_per_epoch, total_steps=self.total_steps,
                        train_images=len(self.data.stream), rng=rng, best=self.best,
                        validation=self.history,
                        camera=self.data.dataset_camera.to_speed_dict(), git=self.git)

    # ------------------------------------------------------------------ the loop

    def run(self) -> TrainResult:
        run, cfg = self.run_state, self.run_state.config
        out_dir, world = run.out_dir, run.world
        start_step = run.start_step
        result = TrainResult(out_dir, start_step, self.total_steps,
                             out_dir / LAST if run.checkpoint is not None else None,
                             out_dir / BEST if (out_dir / BEST).is_file() else None,
                             validation=self.history)
        end_step = self.total_steps if run.max_steps is None else min(self.total_steps,
                                                                     run.max_steps)
        self.prefetcher = BatchPrefetcher(self.data.stream, world, run.device, end_step,
                                          prefetch_enabled(cfg.data.prefetch, run.device),
                                          cfg.data.prefetch_workers)
        bar = None
        if run.progress and world.main:
            bar = progress_bar(total=end_step, initial=start_step, unit="step", desc="train",
                               dynamic_ncols=True)
        timed_images, timed_seconds = 0, 0.0
        stop_at = None if run.max_seconds is None else time.perf_counter() + run.max_seconds
        interrupt = StepInterrupt(world, out_dir / LAST)  # Ctrl-C, SIGTERM: saved at a step
        try:
            if self.validation_due:
                self._validate(start_step, result)
                self.save(LAST, start_step)  # which now records that validation
                barrier(world)
                if interrupt.stop:  # held during the validation: stop before the next step
                    raise KeyboardInterrupt
            for step in range(start_step, end_step):
                with interrupt.step():
                    row, seconds = self._step(step)
                result.train_seconds += seconds
                if step > start_step:  # the first step compiles kernels and fills caches
                    timed_images += cfg.optim.batch_size
                    timed_seconds += seconds
                done = step + 1
                result.steps = done
                result.losses.append(row["loss"])
                if self.log is not None:
                    self.log.step(row)
                if bar is not None:
                    shown = {short_term_name(n): f"{row[n]:.3g}" for n in LOSS_TERMS if n in row}
                    bar.set_postfix(loss=f"{row['loss']:.4g}", **shown,
                                    img_s=f"{row['images_per_s']:.1f}")
                    bar.update(1)
                epoch_end = done % self.steps_per_epoch == 0
                if epoch_end and self._validates(done) and not interrupt.stop:
                    self._validate(done, result)
                # Every process stops at the same step (rank 0's clock decides).
                out_of_time = stop_at is not None and done < end_step and bool(
                    broadcast_object(time.perf_counter() >= stop_at, world))
                # Read once: a signal landing between the save and the stop would otherwise
                # end the run without saving the step it lands after (it waits for the next).
                stopping = interrupt.stop
                if done == end_step or out_of_time or stopping or (
                        epoch_end and cfg.checkpoint_each_epoch) or (
                        cfg.checkpoint_every and done % cfg.checkpoint_every == 0):
                    self.save(LAST, done)
                    result.last_checkpoint = out_dir / LAST
                    barrier(world)
                if out_of_time:
                    break
                if stopping:
                    if self.best is None:
                        self._best_is_last(result)
                    raise KeyboardInterrupt
        finally:
            self._close(bar, interrupt)
        # A best.pt missing beside last.pt (a run killed before copying it) is made here too.
        if self.best is None and result.last_checkpoint is not None and (
                result.steps > start_step or not (out_dir / BEST).is_file()):
            self._best_is_last(result)
            result.notes.append(f"no validation has run yet: {BEST} holds the last state "
                                f"(step {result.steps})")
        result.validation = self.history
        if timed_seconds > 0:
            result.images_per_second = timed_images / timed_seconds
        return result

    def _step(self, step: int) -> tuple[dict[str, float], float]:
        """Run step ``step``; its log row and its wall time."""
        run, cfg = self.run_state, self.run_state.config
        tick = time.perf_counter()
        batch = self.prefetcher.batch(step)
        context = loss_context(cfg, self.renderer, step, run.world, self.part_targets)
        try:
            outcome = training_step(self.model, self.optimizer, batch, self.k_matrix, context,
                                    cfg.optim.grad_clip, run.world)
        except NotFiniteError as error:
            raise not_finite_error(step, error.terms, run.out_dir) from None
        lr = self.optimizer.param_groups[0]["lr"]
        self.scheduler.step()
        names = list(outcome.terms)
        # The step read these back with its finite checks (one copy; no more waits here).
        values = all_mean(torch.tensor([outcome.values["loss"]]
                                       + [outcome.values[t] for t in names],
                                       dtype=torch.float64), run.world)
        seconds = time.perf_counter() - tick
        row = {"step": step + 1, "epoch": step // self.steps_per_epoch, "lr": lr,
               "loss": float(values[0]), "grad_norm": outcome.grad_norm,
               "images_per_s": cfg.optim.batch_size / seconds}
        row.update({name: float(values[i + 1]) for i, name in enumerate(names)})
        return row, seconds

    def _best_is_last(self, result: TrainResult) -> None:
        """best.pt := last.pt (just written) while no validation has run (stopped before the
        first, validation off, an empty val split): the latest state, copied, not re-saved."""
        out_dir = self.run_state.out_dir
        if self.run_state.world.main:
            copy_checkpoint(out_dir / LAST, out_dir / BEST)
        result.best_checkpoint = out_dir / BEST

    def _validation_skipped(self, done: int) -> bool:
        """Whether the checkpoint after ``done`` steps lacks the validation due there: an
        interrupt saves the epoch's last step without it; nothing else does."""
        return (done > 0 and done % self.steps_per_epoch == 0 and self._validates(done)
                and all(int(entry["step"]) != done for entry in self.history))

    def _validates(self, done: int) -> bool:
        cfg = self.run_state.config.validation
        epoch = (done - 1) // self.steps_per_epoch
        return bool(cfg.every and self.data.validating and (
            (epoch + 1) % cfg.every == 0 or done == self.total_steps))

    def _validate(self, done: int, result: TrainResult) -> None:
        run, cfg = self.run_state, self.run_state.config
        metrics = None
        if run.world.main:
            assert self.data.val_images is not None and self.val_renderer is not None
            metrics = validate(unwrap(self.model), self.data.val_images, self.data.points, cfg,
                               self.data.camera, self.val_renderer, run.device)
        metrics = broadcast_object(metrics, run.world)
        entry = {"step": done, "epoch": (done - 1) // self.steps_per_epoch, **metrics}
        self.history.append(entry)
        if self.log is not None:
            self.log.validation(entry)
            plot_curves(self.log.rows, self.log.val_rows, run.out_dir / CURVES_FILE)
        name = cfg.validation.metric
        if improves(name, metrics[name], self.best):
            self.best = {"metric": name, "value": metrics[name], "step": done}
            self.save(BEST, done)
            result.best_checkpoint = run.out_dir / BEST

    def _close(self, bar: Any, interrupt: StepInterrupt | None = None) -> None:
        for part in (interrupt, bar, self.prefetcher, self.renderer):
            if part is not None:
                part.close()
        log, out_dir = self.log, self.run_state.out_dir
        if log is not None:
            if log.rows and not (out_dir / CURVES_FILE).is_file():
                with contextlib.suppress(Exception):
                    plot_curves(log.rows, log.val_rows, out_dir / CURVES_FILE)
            log.close()

