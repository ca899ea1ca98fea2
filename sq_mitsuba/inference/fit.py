"""Test-time fitting: an assembly of superquadrics fitted to binary masks seen from known poses.

Analysis by synthesis: Adam moves the raw (unconstrained) parameters of M primitives, squashed
by :meth:`Assembly.from_raw`, so that their Mitsuba silhouettes at the given poses match the
masks; the losses of all views are summed into one backward pass per step. The settings are
a :class:`FitOptions` (the ``sq-mitsuba fit`` options and their defaults come from it).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from sq_mitsuba.checks import check_rotations, check_tensor
from sq_mitsuba.config import bounds, in_range, validate
from sq_mitsuba.geometry.assembly import NUM_PARAMS, Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.metrics import mask_iou
from sq_mitsuba.geometry.rotation import IDENTITY_6D
from sq_mitsuba.machine import available_memory, too_much_memory
from sq_mitsuba.model.losses import silhouette_loss
from sq_mitsuba.render.backend import one_thread
from sq_mitsuba.render.silhouette.renderer import (
    DEFAULT_SPP,
    SilhouetteRenderer,
    render_assembly,
    render_assembly_loss,
)

#: Bytes per pixel of one silhouette render and its backward pass (Dr.Jit LLVM on the CPU;
#: measured growth 60-75 B/px from 512 x 512 to 2048 x 2048 at spp 16, independent of spp,
#: because the renderer runs one view at a time and does not store samples).
RENDER_BYTES_PER_PIXEL = 80
#: Bytes per pixel and view that a fit keeps at its resolution: float64 targets, the step's
#: coverage and three snapshots, and the figure's overlays.
VIEW_BYTES_PER_PIXEL = 6 * 8


@dataclass(frozen=True)
class FitOptions:
    """Settings of :func:`fit_assembly` (test-time fitting of M superquadrics to masks)."""

    num_primitives: int = in_range(1, 64, default=1)
    "Number of superquadrics M."
    steps: int = in_range(1, 1_000_000, default=150)
    "Adam steps."
    resolution: int = in_range(8, None, default=64)
    "Width in pixels of the fitted silhouettes (the height keeps the masks' aspect)."
    lr: float = in_range(0, 1, default=0.05, low_inclusive=False)
    "Adam learning rate on the raw parameters (at most 1: steps of about ``lr`` in them)."
    loss: Literal["mse", "iou"] = "mse"
    "Per-view loss, summed over views: 'mse' (the paper's) or 'iou' (1 - soft IoU)."
    spp: int = in_range(1, 4096, default=DEFAULT_SPP)
    "Samples per pixel of the rendered silhouettes (forward pass)."
    sppp: int | None = field(default=None, metadata=bounds(1, 4096))
    "Silhouette samples per pixel of the backward pass (None: a fixed budget per image)."
    seed: int = in_range(0, 2**31 - 1, default=0)
    "Seed of the start spread (M > 1) and of the renderer's samples."
    level: int = in_range(0, 5, default=3)
    "Icosphere level of each primitive's mesh (3: 642 vertices)."
    deterministic: bool = True
    """Render on one Dr.Jit thread, so that the same seed gives the same fit to the last bit
    (several threads sum gradients in the order of their timing: two runs part in the last
    digits); False: all threads, faster."""


def fit_memory_bytes(views: int, width: int, height: int) -> int:
    """Rough memory (bytes) a fit of ``views`` masks at ``width`` x ``height`` pixels needs."""
    return width * height * (RENDER_BYTES_PER_PIXEL + views * VIEW_BYTES_PER_PIXEL)


def check_fit_memory(views: int, camera: Camera, resolution: int) -> None:
    """``ValueError`` (with the estimate) when fitting at ``resolution`` needs more memory
    than this machine has (see :func:`fit_memory_bytes`)."""
    height = max(1, round(camera.height * resolution / camera.width))
    need = fit_memory_bytes(views, resolution, height)
    memory = available_memory()
    if memory is not None and need > memory:
        raise ValueError(too_much_memory(
            f"resolution: {resolution} ({resolution} x {height} px, {views} view(s))", need,
            memory, "lower the fit's resolution"))


@dataclass
class FitResult:
    """What :func:`fit_assembly` found.

    Attributes:
        assembly: the fitted assembly, batch size 1, detached.
        raw: its raw parameters (1, M, 16).
        targets: the masks at the fitting resolution (V, h, w) in [0, 1].
        losses: total loss per step (steps,).
        ious: IoU per step and view (steps, V), of the silhouettes the step rendered.
        snapshots: (step, silhouettes (V, h, w)) at the start, middle and end; the last one
            renders the final parameters.
        final_iou: IoU per view (V,) of the final parameters (both images thresholded at 0.5).
        options: the settings of the fit.
    """

    assembly: Assembly
    raw: Tensor
    targets: Tensor
    losses: list[float] = field(default_factory=list)
    ious: list[list[float]] = field(default_factory=list)
    snapshots: list[tuple[int, Tensor]] = field(default_factory=list)
    final_iou: Tensor | None = None
    options: FitOptions = field(default_factory=FitOptions)

    @property
    def mean_iou(self) -> float:
        return float(self.final_iou.mean()) if self.final_iou is not None else float("nan")


class Adam:
    """``torch.optim.Adam`` with its defaults (betas 0.9 and 0.999, eps 1e-8, no weight decay),
    and optionally ``LinearLR``'s warm-up, without ``torch.optim``.

    Why ours: creating any ``torch.optim`` optimiser imports ``torch._dynamo`` (2.5 s on 2 CPU
    cores), a quarter of what ``predict --refine`` on one image costs; the fits here move a
    few tensors and need the update alone. Its steps are torch's operations in torch's order
    (its single-tensor CPU path): the same parameters bit for bit (tests/test_refine.py).

    Args:
        params: the tensors to move (leaf tensors with ``requires_grad``); one whose ``grad``
            is None at a step is left alone, its step count included, as torch does.
        lr: the learning rate.
        warmup: W >= 0 steps of linear warm-up, as ``LinearLR(start_factor=1 / (W + 1),
            end_factor=1, total_iters=W)`` stepped after each step: step k (from 0) at
            (k + 1) / (W + 1) of ``lr``, then ``lr`` (LinearLR's running product of factors,
            as it rounds).
    """

    _BETA1, _BETA2, _EPS = 0.9, 0.999, 1e-8

    def __init__(self, params: Sequence[Tensor], lr: float, warmup: int = 0) -> None:
        self.params = list(params)
        self._start = 1.0 / (warmup + 1)
        self._warmup = warmup
        self._epoch = 0
        self.lr = lr * self._start  # LinearLR's first rate (lr itself without warm-up)
        self._steps = [0.0] * len(self.params)
        self._exp_avg = [torch.zeros_like(p, memory_format=torch.preserve_format)
                         for p in self.params]
        self._exp_avg_sq = [torch.zeros_like(p, memory_format=torch.preserve_format)
                            for p in self.params]

    def zero_grad(self) -> None:
        """Every parameter's ``grad`` to None."""
        for param in self.params:
            param.grad = None

    @torch.no_grad()
    def step(self) -> None:
        """One Adam step of every parameter with a gradient, then the warm-up's rate."""
        beta1, beta2 = self._BETA1, self._BETA2
        for i, param in enumerate(self.params):
            grad = param.grad
            if grad is None:
                continue
            self._steps[i] += 1.0
            step = self._steps[i]
            exp_avg, exp_avg_sq = self._exp_avg[i], self._exp_avg_sq[i]
            exp_avg.lerp_(grad, 1 - beta1)
            exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            step_size = self.lr / (1 - beta1**step)
            denom = (exp_avg_sq.sqrt() / (1 - beta2**step) ** 0.5).add_(self._EPS)
            param.addcdiv_(exp_avg, denom, value=-step_size)
        if self._warmup:
            self._epoch += 1
            if self._epoch <= self._warmup:  # LinearLR's recursive form, as it rounds
                self.lr = self.lr * (1.0 + (1.0 - self._start) / (
                    self._warmup * self._start + (self._epoch - 1) * (1.0 - self._start)))


def default_raw(num_primitives: int, generator: torch.Generator | None = None,
                spread: float = 0.3) -> Tensor:
    """Raw parameters (1, M, 16) of the default start: identical blobs (size 0.255, shape
    0.5, no taper, identity rotation), centred for M = 1 and otherwise spread by normal raw
    translations of std ``spread`` so that the primitives do not receive identical
    gradients."""
    raw = torch.zeros(1, num_primitives, NUM_PARAMS, dtype=torch.float64)
    raw[..., 8:14] = torch.tensor(IDENTITY_6D, dtype=torch.float64)
    if num_primitives > 1:
        raw[..., 5:8] = spread * torch.randn(1, num_primitives, 3, generator=generator,
                                             dtype=torch.float64)
    return raw


def resize_masks(masks: Tensor, height: int, width: int) -> Tensor:
    """Masks (V, H, W) averaged down (area) or up (nearest) to (V, height, width) in [0, 1];
    "area" where neither side grows."""
    masks = masks.to(torch.float64)[:, None]
    if masks.shape[-2:] == (height, width):
        return masks[:, 0]
    shrink = height <= masks.shape[-2] and width <= masks.shape[-1]
    mode = "area" if shrink else "nearest"
    return F.interpolate(masks, size=(height, width), mode=mode)[:, 0].clamp(0, 1)


def _binary_masks(masks: Tensor) -> Tensor:
    """Masks as the fit reads them: floats checked to lie in [0, 1] (a 0-255 mask would
    weigh each pixel 255 times, and its area mean when resized would widen it), integers
    read as non-zero (as ``predict(mask=...)`` reads them), bools as they are."""
    if masks.is_floating_point():
        low, high = (float(masks.amin()), float(masks.amax())) if masks.numel() else (0, 0)
        if low < 0.0 or high > 1.0:
            raise ValueError(f"masks: float values must lie in [0, 1], got [{low:.4g}, "
                             f"{high:.4g}]")
        return masks
    return masks if masks.dtype == torch.bool else masks != 0


def fit_assembly(
    masks: Tensor,
    camera: Camera,
    rotations: Tensor,
    translations: Tensor,
    options: FitOptions | None = None,
    *,
    init_raw: Tensor | None = None,
    progress: bool = False,
    callback: Callable[[int, float, Tensor], None] | None = None,
    **overrides: Any,
) -> FitResult:
    """Fit an assembly of ``options.num_primitives`` superquadrics to binary masks with known
    poses.

    Args:
        masks: (V, H, W) masks of V views (bool, float in [0, 1], or integers read as
            non-zero) at ``camera``'s resolution.
        camera: intrinsics of the masks (rescaled internally to ``options.resolution`` pixels
            wide).
        rotations: (V, 3, 3) body-to-camera rotations; translations: (V, 3), OpenCV frame:
            ``x_cam = R x_body + t``.
        options: a :class:`FitOptions` (default settings when None).
        init_raw: (1, M, 16) raw start instead of :func:`default_raw`.
        progress: show a progress bar (sq_mitsuba.progress).
        callback: called as ``callback(step, loss, coverage)`` after each step.
        overrides: fields of :class:`FitOptions` replacing those of ``options``
            (``fit_assembly(..., num_primitives=2, steps=50)``).

    Returns:
        A :class:`FitResult`.

    Raises:
        ValueError: bad tensors, a bad option (a ``ConfigError`` naming the field), or a
            resolution that needs more memory than the machine has (see
            :func:`check_fit_memory`); all before any rendering.
    """
    options = options if options is not None else FitOptions()
    if not isinstance(options, FitOptions):
        raise ValueError(f"options: expected FitOptions, got {type(options).__name__}")
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(FitOptions)})
    if unknown:
        raise TypeError(f"fit_assembly: unknown option(s) {', '.join(unknown)}")
    options = dataclasses.replace(options, **overrides)
    validate(options)
    if not isinstance(camera, Camera):
        raise ValueError(f"camera: expected a Camera (the masks' intrinsics), got "
                         f"{type(camera).__name__}")
    if callback is not None and not callable(callback):
        raise ValueError(f"callback: expected a function of (step, loss, coverage), got "
                         f"{type(callback).__name__}")
    check_tensor("masks", masks, (None, None), min_dims=3, floating=False)
    if masks.dim() != 3 or masks.shape[0] < 1:
        raise ValueError(f"masks: expected shape (V, H, W), got {tuple(masks.shape)}")
    masks = _binary_masks(masks)
    if tuple(masks.shape[1:]) != (camera.height, camera.width):
        raise ValueError(f"masks: size {tuple(masks.shape[1:])} differs from the camera's "
                         f"{(camera.height, camera.width)} (height, width)")
    views = masks.shape[0]
    check_rotations("rotations", rotations)  # before the renderer: a scaled pose is no pose
    check_tensor("translations", translations, (3,), min_dims=2)
    if rotations.shape != (views, 3, 3) or translations.shape != (views, 3):
        raise ValueError(f"rotations, translations: expected ({views}, 3, 3) and ({views}, 3) "
                         f"for {views} masks, got {tuple(rotations.shape)} and "
                         f"{tuple(translations.shape)}")
    if bool((translations[:, 2] <= 0).any()):
        raise ValueError("translations: the object must lie in front of the camera (t_z > 0)")
    check_fit_memory(views, camera, options.resolution)
    num_primitives, steps, loss, level = (options.num_primitives, options.steps, options.loss,
                                          options.level)

    fit_camera = camera.rescaled(options.resolution)
    targets = resize_masks(masks, fit_camera.height, fit_camera.width)
    rotations = rotations.to(torch.float64)
    translations = translations.to(torch.float64)
    generator = torch.Generator().manual_seed(options.seed)
    if init_raw is None:
        raw = default_raw(num_primitives, generator)
    else:
        check_tensor("init_raw", init_raw, (num_primitives, NUM_PARAMS), min_dims=3)
        if init_raw.shape != (1, num_primitives, NUM_PARAMS):  # one assembly for every view
            raise ValueError(f"init_raw: expected (1, {num_primitives}, {NUM_PARAMS}), got "
                             f"{tuple(init_raw.shape)}")
        raw = init_raw.detach().to(torch.float64).clone()
        try:  # before the renderer starts, and named as given (not the "params" it becomes)
            Assembly.from_raw(raw)
        except ValueError as error:
            raise ValueError(f"init_raw: {str(error).removeprefix('params: ')}") from None
    raw.requires_grad_(True)
    with one_thread(options.deterministic):
        renderer = SilhouetteRenderer(fit_camera, spp=options.spp, sppp=options.sppp,
                                      seed=options.seed)
        optimizer = Adam([raw], lr=options.lr)
        result = FitResult(assembly=Assembly.from_raw(raw.detach()), raw=raw.detach(),
                           targets=targets, options=options)
        middle = steps // 2

        iterator: Sequence[int] | object = range(steps)
        bar = None
        if progress:
            from sq_mitsuba.progress import progress_bar

            bar = progress_bar(range(steps), desc="fit", unit="step", leave=True)
            iterator = bar
        for step in iterator:  # type: ignore[union-attr]
            optimizer.zero_grad()
            # One BVH rebuild per view: each view's loss is back-propagated right after its render.
            total, coverage = render_assembly_loss(
                Assembly.from_raw(raw), rotations, translations, renderer,
                lambda view, i: silhouette_loss(view[None], targets[i, None].to(view.dtype), loss),
                level)
            total.backward()
            optimizer.step()
            with torch.no_grad():
                ious = mask_iou(coverage, targets)
            result.losses.append(float(total.detach()))
            result.ious.append([float(v) for v in ious])
            if step in (0, middle):
                result.snapshots.append((step, coverage.detach().clone()))
            if bar is not None:
                bar.set_postfix(loss=f"{float(total.detach()):.4f}",
                                iou=f"{float(ious.mean()):.3f}")
            if callback is not None:
                callback(step, float(total.detach()), coverage.detach())

        final = Assembly.from_raw(raw.detach())
        with torch.no_grad():
            coverage = render_assembly(final, rotations, translations, renderer, level)
        result.snapshots.append((steps, coverage))
        result.assembly, result.raw = final, raw.detach().clone()
        result.final_iou = mask_iou(coverage, targets)
        return result
