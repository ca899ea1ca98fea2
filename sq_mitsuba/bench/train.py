"""``sq-mitsuba bench train``: training throughput and inference latency.

The headline (first rows; on any ``--device``, at batch 32 and ``--batch``): the shipped
recipe's (``train/configs/shipped.toml``) network alone (forward, backward, AdamW on one fixed
batch on the device) against its full training step (the batch made as the data stream makes
it, then :func:`~sq_mitsuba.training.step.training_step`), alternating, and the ratio of their
images/s: what the rest of the step costs beside the network. On a GPU, or with
``--step-only``, the suite stops there (report ``train-step``, its own section of
eval/BENCHMARKS.md); the rest measures the CPU recipes:

Training (batch 32, each config at its own input size): ``train/configs/a.toml`` (the paper's
settings: 128 px, Chamfer on level-3 primitives, every item rendered at 128 px) and
``train/configs/cpu.toml`` (this project's CPU recipe: 96 px input, reprojection on 8 of 32
items at 64 px). The step is the training loop's own
(:func:`~sq_mitsuba.training.step.training_step`: forward, loss terms, backward,
gradient clipping, AdamW step, one Dr.Jit thread per process and the config's render workers)
on synthetic in-memory batches of the right shapes, so no dataset is needed:

- images: Mitsuba silhouettes of random M = 5 assemblies at random poses, drawn once, with a
  random grey level and noise; masks: those silhouettes;
- ground truth: per item ``data.num_surface`` surface points drawn from the level-4 surface
  samples of its assembly, and ``data.num_occupancy`` occupancy points half inside, half
  outside, drawn from 20,000 uniform points of a box labelled by the assembly's
  inside-outside function, as the training data's point cache draws them; then the config's
  augmentation.

A second, decomposed pass over the same step times its parts: data (point draws and
augmentation), encoder (network forward, then backward from the output gradients), each
weighted loss term of the registry (:data:`~sq_mitsuba.training.loss_terms.LOSS_TERMS`; its
forward + backward to the network outputs), and the update (gradient clipping, AdamW).

Inference (128 px): :class:`~sq_mitsuba.inference.predictor.Predictor` at batch 1 and 32,
eager (``fast=False``), the fast path (``fast=True``; on one intra-op thread too) and the fast
path traced (``traced=True``), and the
shipped model (its own input size) on the same images.

The learning curves (``sq-mitsuba bench curves``) are in :mod:`sq_mitsuba.bench.curves`.
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sq_mitsuba.bench import BenchOptions, Report, Timing, load_average
from sq_mitsuba.training.batch import TrainingBatch

BATCH = 32
INPUT = 128
CONFIG_DIR = Path(__file__).resolve().parents[2] / "train" / "configs"
#: Training throughput targets (images/s) of the configs measured.
TARGETS = {"a": 20.0, "cpu": 40.0}
INFERENCE_TARGET_S = 0.005
REPROJECTION_TARGET_S = 0.010
#: The config of the headline ratio (full step / network alone): the shipped recipe.
RATIO_CONFIG = "shipped"
#: Parts of the decomposed step besides the loss terms (which the registry names).
STEP_PARTS = ("data", "encoder", "update")
_DEPTH = 2.0  # camera distance (m) of the synthetic poses: a unit-size model fills the frame


def load_config(name: str) -> Any:
    """``train/configs/<name>.toml`` as a TrainConfig (bases resolved)."""
    from sq_mitsuba.training.config import load_train_config

    return load_train_config(CONFIG_DIR / f"{name}.toml")


# ------------------------------------------------------------------------------ synthetic data


class SyntheticData:
    """In-memory batches of the training loop's shapes (see the module docstring).

    Args:
        config: the TrainConfig whose sizes, point counts and augmentation the batches follow.
        batch: items per batch.
        models: distinct random assemblies the items cycle through.
        seed: of every random draw.
    """

    def __init__(self, config: Any, batch: int = BATCH, models: int = 4, seed: int = 0,
                 device: torch.device | None = None) -> None:
        from sq_mitsuba.geometry.assembly import Assembly
        from sq_mitsuba.geometry.camera import Camera
        from sq_mitsuba.geometry.rotation import random_rotations
        from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

        self.config = config
        size = config.network.image_size
        self.camera = Camera.default(size)
        generator = torch.Generator().manual_seed(seed)
        truth = Assembly.from_raw(torch.randn(models, 5, 16, generator=generator) * 0.7)
        with torch.no_grad():
            self.surface = truth.surface_points(4).flatten(1, 2).numpy()  # (models, 12810, 3)
            box = torch.rand(models, 20_000, 3, generator=generator) * 1.4 - 0.7
            inside = truth.inside_outside(box).amin(dim=1) < 1.0
        self.box, self.inside = box.numpy(), inside.numpy()
        self.model_index = torch.arange(batch) % models
        self.rotation = random_rotations(batch, generator=generator)
        self.translation = torch.zeros(batch, 3)
        self.translation[:, 2] = _DEPTH
        renderer = SilhouetteRenderer(self.camera, spp=4)
        where = torch.device("cpu") if device is None else device  # Mitsuba's variant's
        with torch.no_grad():
            masks = render_assembly(Assembly(truth.params[self.model_index].to(where)),
                                    self.rotation.to(where), self.translation.to(where),
                                    renderer, 2).cpu()
        self.mask = (masks > 0.5).float()[:, None]
        grey = 0.3 + 0.6 * torch.rand(batch, 1, 1, 1, generator=generator)
        noise = 0.03 * torch.randn(self.mask.shape, generator=generator)
        self.image = (self.mask * grey + noise).clamp(0, 1)

    def host_batch(self, step: int, pin: bool = False) -> dict[str, Any]:
        """Step ``step``'s host share, as the data stream's: every item's point draws and
        augmentation draws (points first, from the item's own generator); ``pin``: in pinned
        memory. What the training loop's prefetch prepares while a step runs."""
        from sq_mitsuba.training.augment import draw_augmentation

        cfg = self.config
        generators = [np.random.default_rng([7, step, j]) for j in range(len(self.image))]
        surface, points, labels = [], [], []
        for j, model in enumerate(self.model_index.tolist()):
            rng = generators[j]
            surface.append(self.surface[model][rng.choice(len(self.surface[model]),
                                                          cfg.data.num_surface)])
            inside = np.flatnonzero(self.inside[model])
            outside = np.flatnonzero(~self.inside[model])
            want_in = min(cfg.data.num_occupancy // 2, len(inside))
            rows = np.concatenate([rng.choice(inside, want_in, replace=False),
                                   rng.choice(outside, cfg.data.num_occupancy - want_in,
                                              replace=len(outside) < cfg.data.num_occupancy)])
            points.append(self.box[model][rows])
            labels.append(np.concatenate([np.ones(want_in, np.float32),
                                          np.zeros(len(rows) - want_in, np.float32)]))
        host: dict[str, Any] = {
            "image": self.image, "mask": self.mask, "rotation": self.rotation,
            "translation": self.translation, "model_index": self.model_index,
            "surface_points": torch.from_numpy(np.stack(surface)),
            "occupancy_points": torch.from_numpy(np.stack(points)),
            "occupancy_labels": torch.from_numpy(np.stack(labels))}
        if pin:
            host = {name: value.pin_memory() for name, value in host.items()}
        draws = None
        if cfg.augment.enabled:
            draws = draw_augmentation(cfg.augment, generators, tuple(self.image.shape),
                                      self.image.dtype)
            draws = draws.pinned() if pin else draws
        host["augmentation"] = draws
        return host

    def device_batch(self, host: dict[str, Any], device: torch.device | None = None
                     ) -> TrainingBatch:
        """A :meth:`host_batch` on ``device`` (default the CPU), augmented there."""
        from sq_mitsuba.training.augment import apply_augmentation, to_device

        device = torch.device("cpu") if device is None else device
        moved = {name: to_device(value, device) for name, value in host.items()
                 if name != "augmentation"}
        image, mask, rotation, translation = (
            moved[name] for name in ("image", "mask", "rotation", "translation"))
        if host["augmentation"] is not None:
            image, mask, rotation, translation = apply_augmentation(
                image, mask, rotation, translation, host["augmentation"], self.camera)
        return TrainingBatch(
            image=image, mask=mask, rotation=rotation, translation=translation,
            model_index=moved["model_index"], surface_points=moved["surface_points"],
            occupancy_points=moved["occupancy_points"],
            occupancy_labels=moved["occupancy_labels"],
            symmetries=torch.eye(3, device=device).expand(len(self.image), 1, 3, 3))

    def batch(self, step: int, device: torch.device | None = None) -> TrainingBatch:
        """Step ``step``'s batch, as the training loop's data stream makes them: the draws on
        the host, the pixels copied to ``device`` (default the CPU) and augmented there."""
        device = torch.device("cpu") if device is None else device
        return self.device_batch(self.host_batch(step, pin=device.type == "cuda"), device)


# ------------------------------------------------------------------------------ training step


class StepBench:
    """One config's network, optimiser and renderer, as the training loop builds them, on
    :class:`SyntheticData` of ``batch`` items, on ``device`` (default the CPU; Mitsuba's
    variant for it set by the caller, :func:`~sq_mitsuba.training.step.mitsuba_for`)."""

    def __init__(self, config: Any, batch: int = BATCH, device: torch.device | None = None
                 ) -> None:
        from sq_mitsuba.model.network import SuperquadricNet
        from sq_mitsuba.training.schedule import make_optimizer
        from sq_mitsuba.training.step import reprojection_renderer, to_channels_last

        self.config = config
        self.device = torch.device("cpu") if device is None else device
        self.data = SyntheticData(config, batch, device=self.device)
        torch.manual_seed(config.seed)
        self.model = SuperquadricNet(config.network).to(self.device).train()
        if config.channels_last:
            to_channels_last(self.model)
        self.optimizer, _ = make_optimizer(self.model, config.optim, 1)
        self.k_matrix = self.data.camera.matrix(device=self.device)
        self.renderer = reprojection_renderer(config, self.data.camera, self.device)
        self._fixed: TrainingBatch | None = None

    def close(self) -> None:
        """Stop the renderer's worker processes."""
        if self.renderer is not None:
            self.renderer.close()

    def context(self, step: int) -> Any:
        """Step ``step``'s loss context (renderer reseeded, subset generator seeded)."""
        from sq_mitsuba.training.step import loss_context

        return loss_context(self.config, self.renderer, step)

    def step(self, step: int, host: dict[str, Any] | None = None) -> None:
        """One training step exactly as the loop runs it (without logging): the batch made
        (draws on the host, pixels to the device, augmentation there), then
        :func:`~sq_mitsuba.training.step.training_step`. ``host``: step ``step``'s
        :meth:`SyntheticData.host_batch` made beforehand, as the loop's prefetch
        makes it (then only its copy to the device and augmentation count here)."""
        from sq_mitsuba.training.step import NotFiniteError, training_step

        if host is None:
            host = self.data.host_batch(step, pin=self.device.type == "cuda")
        batch = self.data.device_batch(host, self.device)
        try:
            training_step(self.model, self.optimizer, batch, self.k_matrix,
                          self.context(step), self.config.optim.grad_clip)
        except NotFiniteError as error:
            raise RuntimeError(f"bench train: step {step}: {error}") from None

    def network_step(self) -> None:
        """The network alone on one fixed batch already on the device: forward, backward of
        the sum of its outputs' means (every head gets a gradient), AdamW step. What the
        hardware allows a step to cost; :meth:`step` over it is the price of the rest."""
        if self._fixed is None:
            self._fixed = self.data.batch(0, self.device)
        output = self.model(self._fixed.image, self.k_matrix)
        loss = sum(value.float().mean() for f in dataclasses.fields(output)
                   if isinstance(value := getattr(output, f.name), torch.Tensor)
                   and value.requires_grad)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()  # type: ignore[union-attr]
        self.optimizer.step()

    def timed_parts(self, step: int) -> dict[str, float]:
        """The same step cut into parts, each timed (seconds): ``data``, ``encoder``, each
        weighted loss term by name, ``update``. The terms are back-propagated one at a time
        to detached network outputs, whose gradients then run the encoder's backward pass;
        the update equals :meth:`step`'s up to float summation order."""
        from sq_mitsuba.checks import value_checks
        from sq_mitsuba.training.loss_terms import compute_terms, enabled_terms, total_loss
        from sq_mitsuba.training.step import gradient_norm

        cfg = self.config
        names = enabled_terms(cfg.loss)
        times = dict.fromkeys((*STEP_PARTS[:2], *names, STEP_PARTS[2]), 0.0)
        start = time.perf_counter()
        batch = self.data.batch(step)
        times["data"] = time.perf_counter() - start
        self.optimizer.zero_grad(set_to_none=True)
        context = self.context(step)
        with value_checks(False):
            start = time.perf_counter()
            output = self.model(batch.image, self.k_matrix)
            forward_s = time.perf_counter() - start
            pairs = {f.name: getattr(output, f.name) for f in dataclasses.fields(output)
                     if isinstance(getattr(output, f.name), torch.Tensor)
                     and getattr(output, f.name).requires_grad}
            leaves = dataclasses.replace(output, **{name: value.detach().requires_grad_(True)
                                                    for name, value in pairs.items()})
            for name in names:
                start = time.perf_counter()
                terms = compute_terms(leaves, batch, context, (name,))
                total_loss(terms, {name: cfg.loss.weights[name]}).backward()
                times[name] += time.perf_counter() - start
        start = time.perf_counter()
        grads = [(pairs[name], getattr(leaves, name).grad) for name in pairs
                 if getattr(leaves, name).grad is not None]
        torch.autograd.backward([o for o, _ in grads], [g for _, g in grads])
        times["encoder"] = forward_s + time.perf_counter() - start
        start = time.perf_counter()
        gradient_norm(self.model, cfg.optim.grad_clip)
        self.optimizer.step()
        times["update"] += time.perf_counter() - start
        return times


def _train_figures(report: Report, name: str, repeats: int, overrides: Sequence[str] = ()
                   ) -> dict[str, float]:
    """Rows and notes of config ``name`` with ``--set`` style ``overrides`` (a comparison row,
    without target); returns the median seconds of each part (:meth:`StepBench.timed_parts`)."""
    from sq_mitsuba.config import apply_overrides
    from sq_mitsuba.training.step import mitsuba_for

    config = apply_overrides(load_config(name), overrides)
    suffix = "".join(f", {o}" for o in overrides)
    label = f"{name}.toml{suffix}"
    target = None if overrides else TARGETS[name]
    size = config.network.image_size
    with mitsuba_for(torch.device("cpu"), config.reprojection.deterministic):
        trainer = StepBench(config)
        try:
            trainer.step(0)  # warm-up: Dr.Jit kernels, workers, allocator, AdamW state
            steps = []
            for step in range(1, repeats + 1):
                start = time.perf_counter()
                trainer.step(step)
                steps.append(time.perf_counter() - start)
            parts = [trainer.timed_parts(repeats + 1 + i) for i in range(repeats)]
        finally:
            trainer.close()
        workers = 0 if trainer.renderer is None else trainer.renderer.workers
    rep = config.reprojection
    rendered = BATCH if rep.items is None else min(rep.items, BATCH)
    rate = BATCH / statistics.median(steps)
    wanted = "" if target is None else f" (target >= {target:.0f})"
    report.timings.append(Timing(
        f"train step, {label}, per image", [s / BATCH for s in steps],
        None if target is None else 1 / target,
        note=f"batch {BATCH}, {size} px input, {rate:.1f} images/s{wanted}; reprojection "
             f"{rendered} of {BATCH} items at {rep.resolution or size} px, level {rep.level}, "
             f"spp {rep.spp}, {workers or 'no'} render workers; channels-last "
             f"{'on' if config.channels_last else 'off'}"))
    medians = {p: statistics.median(t[p] for t in parts) for p in parts[0]}
    whole = sum(medians.values())
    shares = ", ".join(f"{p} {1e3 * medians[p]:.0f} ms ({100 * medians[p] / whole:.0f} %)"
                       for p in medians)
    report.notes.append(
        f"{label} step parts (median of {repeats} decomposed steps, sum "
        f"{1e3 * whole:.0f} ms vs {1e3 * statistics.median(steps):.0f} ms for the real step): "
        f"{shares} (each weighted loss term by name; update = gradient clipping, AdamW); "
        f"1-minute load "
        f"average after it: {load_average():.2f}")
    if name == "a":
        report.timings.append(Timing(
            f"reprojection forward + backward, 128 x 128, level 3, spp 16, per image{suffix}",
            [t["reprojection"] / rendered for t in parts],
            None if overrides else REPROJECTION_TARGET_S,
            note=f"a.toml's reprojection part of the decomposed step / items rendered (one "
                 f"Dr.Jit thread per process, {workers or 'no'} worker processes, as in "
                 f"training)"))
    return medians


# ------------------------------------------------------------------------------ inference


def _interleaved(calls: dict[str, Callable[[], object]], repeats: int, warmup: int
                 ) -> dict[str, list[float]]:
    """Seconds of each call, the calls alternating so that load changes hit all alike."""
    for _ in range(warmup):
        for fn in calls.values():
            fn()
    samples: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, fn in calls.items():
            start = time.perf_counter()
            fn()
            samples[name].append(time.perf_counter() - start)
    return samples


def _inference_figures(report: Report, options: BenchOptions) -> None:
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.inference.predictor import Predictor
    from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet

    torch.manual_seed(0)
    network = SuperquadricNet(NetworkConfig(image_size=INPUT)).eval()
    with torch.no_grad():  # a fresh network's last layers hide the image: perturb every weight
        for value in network.parameters():
            value.add_(0.05 * torch.randn_like(value))
        for name, value in network.named_buffers():
            if name.endswith("running_var"):
                value.uniform_(0.5, 2.0)
    camera = Camera.default(INPUT)
    eager, fast = Predictor(network, camera), Predictor(network, camera, fast=True)
    traced = Predictor(network, camera, fast=True, traced=True)
    one, many = torch.rand(1, INPUT, INPUT), torch.rand(BATCH, INPUT, INPUT)
    with torch.no_grad():
        deviation = float((fast.predict(one).rotation - eager.predict(one).rotation
                           ).abs().max())

    def in_threads(threads: int, fn: Callable[[], object]) -> Callable[[], object]:
        def call() -> object:
            previous = torch.get_num_threads()
            torch.set_num_threads(threads)
            try:
                return fn()
            finally:
                torch.set_num_threads(previous)
        return call

    threads = options.threads
    calls = {
        "eager": lambda: eager.predict(one),
        "fast": lambda: fast.predict(one),
        "fast, traced": lambda: traced.predict(one),
        "fast, 1 thread": in_threads(1, lambda: fast.predict(one)),
    }
    notes = {
        "eager": "Predictor(fast=False)",
        "fast": f"Predictor(fast=True): BatchNorm folded, channels_last, inference_mode; "
                f"largest rotation difference from eager {deviation:.1e}",
        "fast, traced": "Predictor(fast=True, traced=True): the same through a TorchScript "
                        "trace + freeze (made in the warm-up)",
        "fast, 1 thread": "the same as fast with torch.set_num_threads(1)",
    }
    from sq_mitsuba.inference.loading import load_model
    from sq_mitsuba.model.checkpoint import SHIPPED_MODEL

    if SHIPPED_MODEL.is_file():
        shipped = load_model(fast=True)
        label = f"shipped model ({shipped.image_size} px network), fast"
        calls[label] = lambda: shipped.predict(one)
        notes[label] = (f"sq_mitsuba.load_model(fast=True) on the same {INPUT} px image, "
                        f"resized to its input")
    if threads == 1:
        del calls["fast, 1 thread"]
    samples = _interleaved(calls, max(5, options.repeats), max(2, options.warmup))
    for name, values in samples.items():
        target = INFERENCE_TARGET_S if "fast" in name else None
        used = 1 if "1 thread" in name else threads
        report.timings.append(Timing(
            f"predict latency, batch 1, {INPUT} px: {name}", values, target,
            note=f"{used} thread(s); {notes[name]}"))
    batches = _interleaved({"eager": lambda: eager.predict(many),
                            "fast": lambda: fast.predict(many)},
                           max(1, min(options.repeats, 3)), 1)
    for name, values in batches.items():
        report.timings.append(Timing(
            f"predict, batch {BATCH}, {INPUT} px: {name}, per image",
            [v / BATCH for v in values],
            note=f"{BATCH / statistics.median(values):.0f} images/s, {threads} thread(s)"))
    report.notes.append(f"inference: 1-minute load average after it: {load_average():.2f}")


def step_ratio(config: Any, batch: int, device: torch.device, repeats: int, warmup: int
               ) -> dict[str, list[float]]:
    """Seconds per step of the network alone (:meth:`StepBench.network_step`) and of the full
    training step (:meth:`StepBench.step`) of ``config`` at ``batch`` images on ``device``,
    alternating (``warmup`` untimed rounds first) so that load changes hit both alike; the
    device is waited for after each. Returns ``{"network": [...], "step": [...]}``, and
    ``"prefetched"`` (the step with its host share made beforehand, as the loop's prefetch
    thread makes it) where ``data.prefetch`` is on for ``device``."""
    from sq_mitsuba.config import apply_overrides
    from sq_mitsuba.training.prefetch import prefetch_enabled
    from sq_mitsuba.training.step import mitsuba_for

    config = apply_overrides(config, [f"optim.batch_size={batch}", f'device="{device.type}"'])

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    samples: dict[str, list[float]] = {"network": [], "step": []}
    with mitsuba_for(device, config.reprojection.deterministic):
        trainer = StepBench(config, batch, device)
        calls: dict[str, Callable[[], None]] = {
            "network": trainer.network_step, "step": lambda: trainer.step(step)}
        if prefetch_enabled(config.data.prefetch, device):
            # As the loop runs it: the host share made beforehand by the prefetch.
            samples["prefetched"] = []
            calls["prefetched"] = lambda: trainer.step(step, host)
        try:
            for step in range(warmup + repeats):
                if "prefetched" in calls:  # made untimed, as the prefetch makes it
                    host = trainer.data.host_batch(step, pin=device.type == "cuda")
                for name, call in calls.items():
                    sync()
                    start = time.perf_counter()
                    call()
                    sync()
                    if step >= warmup:
                        samples[name].append(time.perf_counter() - start)
        finally:
            trainer.close()
    return samples


def _ratio_figures(report: Report, options: BenchOptions) -> None:
    """The headline rows: ``shipped.toml``'s network alone and full step at batch 32 and
    ``options.batch``, images/s each and the ratio full / network alone."""
    device = torch.device(options.device)
    batches = sorted({BATCH, options.batch or BATCH})
    repeats = max(3, min(options.repeats, 10))
    for batch in batches:
        samples = step_ratio(load_config(RATIO_CONFIG), batch, device, repeats,
                             max(1, options.warmup))
        rates = {name: [batch / s for s in values] for name, values in samples.items()}
        for name, label in (("network", "network alone (forward, backward, AdamW)"),
                            ("step", "full training step (training_step, batch made)"),
                            ("prefetched", "full training step, host share prefetched")):
            if name not in rates:
                continue
            rate = Timing(name, rates[name])
            report.timings.append(Timing(
                f"{RATIO_CONFIG}.toml {label}, batch {batch}, per image",
                [s / batch for s in samples[name]],
                note=f"{rate.median:.1f} images/s (IQR {rate.spread[0]:.1f} - "
                     f"{rate.spread[1]:.1f}), {options.device}"))
        # The headline is the step as the loop runs it on this device.
        loop = "prefetched" if "prefetched" in samples else "step"
        pairs = Timing("ratio", [n / s for n, s in zip(samples["network"], samples[loop],
                                                        strict=True)])
        inline = ("" if loop == "step" else f"; batch made inline "
                  f"{statistics.median(rates['step']):.1f} images/s")
        report.notes.insert(0, (
            f"**headline, batch {batch} on {options.device}: the full step runs at "
            f"{100 * pairs.median:.1f} % of the network alone** (full / network-alone images/s, "
            f"median of {repeats} alternating pairs, IQR {100 * pairs.spread[0]:.1f} - "
            f"{100 * pairs.spread[1]:.1f} %; network alone "
            f"{statistics.median(rates['network']):.1f} images/s, full step "
            f"{statistics.median(rates[loop]):.1f} images/s"
            f"{' with its host share prefetched as the loop does' if loop != 'step' else ''}, "
            f"medians of the same pairs{inline})"))


def run(options: BenchOptions) -> Report:
    # A --batch this machine cannot hold is refused before any work, by train's estimate.
    from sq_mitsuba.machine import too_much_memory
    from sq_mitsuba.training.step import step_memory

    config = load_config(RATIO_CONFIG)
    largest = max(BATCH, options.batch or BATCH)
    estimate = step_memory(dataclasses.replace(config, optim=dataclasses.replace(
        config.optim, batch_size=largest)), torch.device(options.device))
    if estimate is not None and estimate.need > estimate.memory:
        workers = f" with {estimate.workers} reprojection worker(s)" if estimate.workers else ""
        raise ValueError(too_much_memory(
            f"--batch: {largest} images of {config.network.image_size} px on the CPU{workers}",
            estimate.need, estimate.memory, "lower --batch"))
    torch.set_num_threads(options.threads)
    step_only = options.step_only or options.device != "cpu"
    report = Report("train-step" if step_only else "train", options=options)
    report.notes.append(f"load average at the start: {load_average():.2f} on "
                        f"{os.cpu_count()} cores (above ~2, other processes inflate these "
                        "timings)")
    _ratio_figures(report, options)
    if step_only:  # the rest measures the CPU recipes
        return report
    repeats = max(1, min(options.repeats, 5))  # each repeat is a training step of 32 images
    for name in ("a", "cpu"):
        _train_figures(report, name, repeats)
    # What the render workers and channels-last buy, each measured in the same run.
    _train_figures(report, "a", repeats, ("reprojection.workers=0",))
    _train_figures(report, "cpu", repeats, ("channels_last=false",))
    _inference_figures(report, options)
    report.notes.append(
        "training on synthetic in-memory batches (random assemblies' silhouettes and "
        "analytic surface/occupancy samples, see the module docstring): no image decoding, "
        "which the training cache makes a memory copy; the network is randomly initialised")
    return report
