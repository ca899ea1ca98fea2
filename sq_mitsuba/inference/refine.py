"""Test-time refinement: analysis by synthesis from the network's prediction.

Starting from a predicted assembly and pose, Adam moves the assembly's raw parameters and a
pose correction so that the Mitsuba silhouette matches the target's mask; a quadratic prior
keeps the raw parameters near the prediction. Each batch item is refined on its own (the
losses of the items are summed, and Adam's steps are per element; but its silhouette samples
are drawn by its place in the batch, and the batch stops together: the search,
:func:`~sq_mitsuba.inference.search.search_and_refine`, therefore calls this image by image,
so that an image's fit does not depend on its batch), and each item returns the
best parameters seen, by IoU, the start included: refinement never makes an item worse at the
refinement resolution. With ``shape = "pose"`` only the pose moves: the assembly stays the
network's (the default after the global search, :mod:`sq_mitsuba.inference.search`, where
fitting the outline by deforming the shape was measured to worsen Chamfer-L1).

Convention: the pose correction is ``R = exp([w]_x) R0`` (a rotation vector w applied in the
camera frame) and ``t = t0 + |t0| dt``, so one learning rate suits rotation (radians) and
translation (a fraction of the distance); with ``depth = "fixed"`` the correction's z component
stays zero, so t_z is the start's: a silhouette fixes the depth only through the predicted
shape's size, whose error it would otherwise turn into a depth error. Raw parameters are those of
:meth:`sq_mitsuba.geometry.assembly.Assembly.from_raw`; :func:`raw_from_assembly` inverts it.

Shared shape (``shared=True``, :mod:`sq_mitsuba.inference.sequence`): the B items are B views of
one body, so one assembly (batch size 1) moves with B poses, and the best step is kept by the
mean IoU over the views (one state for all). Its translation moves as ``t = t0 exp(d - mean d)
+ |t0| (dx, dy, 0)``: the views' depths change by factors whose geometric mean is 1, because
silhouettes from one camera cannot tell a shape s times larger at s times the distance, so the
start's mean depth keeps the scale. With ``relative_rotations`` (``Q_j``, ``R_j = Q_j R_0``)
one rotation ``R_0`` moves instead of B; with ``relative_times`` as well (the relative
rotations a constant-rate turn, ``Q_j = exp((t_j - t_0) [w])``), its rate moves too:
``R_j = exp(tau_j [w + d]) R_0`` with ``tau_j = (t_j - t_0) / max |t_k - t_0|``, ``w`` the whole
turn over that span (read from the view nearest view 0 in time) and ``d`` its correction.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

from sq_mitsuba.checks import check_rotations, check_tensor
from sq_mitsuba.config import in_range, non_negative, validate
from sq_mitsuba.geometry.assembly import FIELDS, Assembly, ParameterRanges
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import axis_angle_to_matrix, matrix_to_axis_angle
from sq_mitsuba.model.existence import gathered_primitives
from sq_mitsuba.model.losses import silhouette_loss
from sq_mitsuba.render.backend import one_thread

# Keeps squashed values strictly inside their open ranges before the inverse squash.
_EDGE = 1e-4
# RefineOptions.shape -> the assembly's fields (geometry.assembly.FIELDS) that move.
_MOVING_FIELDS: dict[str, tuple[str, ...]] = {
    "free": tuple(FIELDS), "extent": ("size", "translation"), "size": ("size",), "pose": ()}


@dataclass(frozen=True)
class RefineOptions:
    """Test-time refinement settings."""

    steps: int = in_range(1, 10_000, default=50)
    "Adam steps at most (fewer when no item improves for `patience` steps)."
    lr: float = in_range(0, 1, default=0.03, low_inclusive=False)
    """Adam learning rate on the raw parameters and the pose correction: at most 1, Adam's
    steps being about ``lr`` in the raw parameters (1e30 ran into NaN poses deep inside)."""
    warmup: int = in_range(0, 10_000, default=0)
    """Steps over which the learning rate rises linearly to ``lr`` (0: from the first step).
    Adam's first step moves every parameter by about ``lr`` whatever its gradient's size, so
    a start that already fits can be thrown off its fit; ``patience`` counts from the end of
    the warm-up."""
    resolution: int = in_range(8, 1024, default=64)
    "Width in pixels of the silhouettes compared (the mask is averaged down to it)."
    level: int = in_range(0, 5, default=2)
    "Icosphere level of each primitive's mesh (2: 162 vertices)."
    prior_weight: float = non_negative(0.01)
    "Weight of the mean squared change of the raw parameters (keeps the result near the start)."
    shape: Literal["free", "extent", "size", "pose"] = "free"
    """What moves besides the pose: 'free' (every raw shape parameter), 'extent' (each
    primitive's sizes and position; its exponents, orientation and tapers stay), 'size'
    (the sizes only) or 'pose' (the shape stays)."""
    rotation: Literal["free", "fixed"] = "free"
    "The rotation: 'free', or 'fixed' at the start's (the translation and the shape still move)."
    rotation_prior: float = non_negative(0.0)
    """Weight of the squared angle (radians^2) of the rotation's change: 1 makes a 10 deg turn
    cost what 0.03 of IoU gains (keeps a searched rotation where the outline of a rough shape
    would pull it away)."""
    seen_sizes: bool = False
    """Scale each primitive's size change along an axis by 1 - (a . v)^2, a the axis and v the
    line of sight to the primitive's centre (at the start pose): a silhouette does not see an
    extent along the line of sight, so that one stays the network's."""
    depth: Literal["free", "fixed"] = "free"
    "The translation's depth t_z: 'free', or 'fixed' at the start's (only t_x, t_y move)."
    depth_prior: float = non_negative(0.0)
    """Weight of the squared change of each item's depth: of ``t_z`` in units of the start's
    distance ``|t0|``, or with ``shared`` of each view's log depth (the views' mean change,
    which the scale keeps at 0, is not penalised). With the "iou" loss, 1 makes a 10 % move
    cost what 0.01 of that item's soft IoU gains. Keeps a view whose mask misses much of the
    target from running off to shrink its silhouette."""
    loss: Literal["iou", "mse"] = "iou"
    "Per-item silhouette loss: 'iou' (1 - soft IoU, steady gradients far from the target) or 'mse'."
    patience: int = in_range(1, 10_000, default=15)
    "Stop when no item's IoU improved for this many steps."
    spp: int = in_range(1, 1024, default=16)
    "Silhouette samples per pixel in the forward pass."
    sppp: int | None = in_range(1, 4096, default=None)
    """Silhouette-edge samples per pixel of the backward pass (None: the renderer's budget of
    16,384 a view, whatever the resolution: 4 a pixel at 64 px). Fewer make each step cheaper
    and its gradient noisier; a count per pixel grows with the resolution."""
    seed: int = in_range(0, 2**31 - 1, default=0)
    "Seed of the renderer's samples."
    deterministic: bool = True
    """Refine on one Dr.Jit thread, so that the same image gives the same pose and shape to
    the last bit: several threads sum the silhouettes' gradients with atomic additions in the
    order of their timing. False: all threads. (The search before it renders forward only,
    its samples summed in a fixed order: bit-identical on any number of threads, so it keeps
    them all.)"""


#: The refinement for an outline rather than a shape: every shape parameter follows the mask
#: too, for up to 100 steps (the rest as the search's default,
#: :data:`~sq_mitsuba.inference.search.SEARCH_REFINEMENT`). On the model card's
#: held-out families (all 400 images) the 2D IoU after the search and this refinement is
#: 0.737 with the shipped model where the default's is 0.594, and the body-frame Chamfer-L1
#: 0.164 (the constant baseline's 0.151; W-25-S2, shipped before it, on 120 of the images:
#: 0.172 where the default's is 0.141): an outline
#: seen under a rotation tens of degrees off is carried into the shape. For overlays and
#: tracking, not for the 3D shape.
OUTLINE_REFINEMENT = RefineOptions(steps=100, patience=30, shape="free", depth="fixed",
                                   rotation_prior=1.0)


@dataclass
class RefineResult:
    """What :func:`refine_pose_and_shape` returns; tensors are detached.

    Attributes:
        assembly: refined assembly, batch size B.
        rotation: (B, 3, 3); translation: (B, 3).
        iou_before: (B,) IoU of the start at the refinement resolution.
        iou_after: (B,) IoU of the returned parameters (>= iou_before up to render noise).
        steps: Adam steps taken.
        losses: the silhouette loss (summed over items) of each step.
    """

    assembly: Assembly
    rotation: Tensor
    translation: Tensor
    iou_before: Tensor
    iou_after: Tensor
    steps: int
    losses: list[float] = field(default_factory=list)


def raw_from_assembly(assembly: Assembly, ranges: ParameterRanges | None = None) -> Tensor:
    """Raw parameters (B, M, 16) whose :meth:`Assembly.from_raw` gives ``assembly`` back
    (values on the edge of a range are pulled inside by a relative 1e-4)."""
    ranges = ranges if ranges is not None else ParameterRanges()
    params = assembly.params.detach()

    def logit(x: Tensor) -> Tensor:
        x = x.clamp(_EDGE, 1 - _EDGE)
        return torch.log(x) - torch.log1p(-x)

    def atanh(x: Tensor) -> Tensor:
        return torch.atanh(x.clamp(-1 + _EDGE, 1 - _EDGE))

    raw = params.clone()
    raw[..., FIELDS["size"]] = logit((params[..., FIELDS["size"]] - ranges.size_min)
                                     / ranges.size_span)
    raw[..., FIELDS["shape"]] = logit(params[..., FIELDS["shape"]])
    raw[..., FIELDS["translation"]] = atanh(params[..., FIELDS["translation"]]
                                            / ranges.translation_scale)
    raw[..., FIELDS["taper"]] = atanh(params[..., FIELDS["taper"]] / ranges.taper_scale)
    return raw


def _seen_fraction(assembly: Assembly, rotation: Tensor, translation: Tensor) -> Tensor:
    """(B, M, 3): per primitive axis, 1 - (a . v)^2 with a the axis in the camera frame and v
    the unit line of sight to the primitive's centre; 0 for an axis along the line of sight."""
    params = assembly.params.detach().to(rotation.dtype)
    primitives = Assembly(params)
    axes = rotation[:, None] @ primitives.rotation  # (B, M, 3, 3): columns are the axes
    centres = (rotation[:, None] @ primitives.translation[..., None])[..., 0] \
        + translation[:, None]
    sight = centres / torch.linalg.vector_norm(centres, dim=-1, keepdim=True)
    along = (axes * sight[..., None]).sum(dim=-2)  # (B, M, 3): a_i . v
    return 1.0 - along.square()


def refine_pose_and_shape(assembly: Assembly, rotation: Tensor, translation: Tensor,
                          masks: Tensor, camera: Camera,
                          options: RefineOptions | None = None, *, shared: bool = False,
                          relative_rotations: Tensor | None = None,
                          relative_times: Tensor | None = None,
                          own: Tensor | None = None) -> RefineResult:
    """Refine B predictions against B target masks through the Mitsuba silhouette.

    Args:
        assembly: predicted assembly, batch size B (1 with ``shared``).
        rotation: (B, 3, 3) predicted body-to-camera rotations; translation: (B, 3).
        masks: (B, H, W) target masks (bool or float in [0, 1]) at ``camera``'s resolution.
        camera: intrinsics of the masks.
        options: :class:`RefineOptions` (default settings when None).
        shared: the B items are views of one body: one assembly (batch size 1) for all, the
            best step by the mean IoU, the depths' geometric mean held (module docstring).
        relative_rotations: with ``shared``, (B, 3, 3) ``Q_j`` such that ``R_j = Q_j R_0``: one
            rotation ``R_0 = Q_0^T rotation[0]`` moves, not B; None: each view's own.
        relative_times: with ``relative_rotations`` of a constant-rate turn, (B,) the views'
            times: the rate of turn moves too (module docstring); None: the ``Q_j`` held.
        own: (B, M) bool, the rows that are their item's own primitives; False marks a
            stand-in a batch pads an item with (its first row shrunk: where the shape moves,
            rebuilt from that row at every step, so it stays inside it and out of sight, and
            left out of the shape prior's mean, so an item's fit does not depend on its
            batch-mates' counts); None: every row.

    Returns:
        :class:`RefineResult` holding, per item (with ``shared``: for all items at once), the
        best of the start and every step.
    """
    from sq_mitsuba.geometry.metrics import mask_iou
    from sq_mitsuba.inference.fit import Adam, resize_masks
    from sq_mitsuba.render.silhouette.renderer import (
        SilhouetteRenderer,
        render_assembly,
        render_assembly_loss,
    )

    options = options if options is not None else RefineOptions()
    validate(options)
    if shared and options.seen_sizes:  # seen_sizes scales per view, a shared shape has one
        raise ValueError("options.seen_sizes: not with a shared shape (shared=True)")
    if shared and assembly.batch_size != 1:
        raise ValueError(f"assembly: a shared shape has batch size 1, got {assembly.batch_size}")
    # rotation first: relative_times and the batch size are checked against its length.
    check_rotations("rotation", rotation)
    if relative_rotations is not None and not shared:
        raise ValueError("relative_rotations: only with a shared shape (shared=True)")
    if relative_times is not None:
        if relative_rotations is None:
            raise ValueError("relative_times: only with relative_rotations")
        check_tensor("relative_times", relative_times, ())
        if tuple(relative_times.shape) != (rotation.shape[0],) or len(
                torch.unique(relative_times)) != len(relative_times):
            raise ValueError(f"relative_times: expected {rotation.shape[0]} distinct times, "
                             f"got shape {tuple(relative_times.shape)}")
    batch = rotation.shape[0] if shared else assembly.batch_size
    check_tensor("translation", translation, (3,), min_dims=2)
    check_tensor("masks", masks, (None, None), min_dims=3, floating=False)
    if rotation.shape != (batch, 3, 3) or translation.shape != (batch, 3) or \
            masks.dim() != 3 or masks.shape[0] != batch:
        raise ValueError(f"rotation, translation, masks: expected ({batch}, 3, 3), ({batch}, 3) "
                         f"and ({batch}, H, W) for an assembly batch of {batch}, got "
                         f"{tuple(rotation.shape)}, {tuple(translation.shape)}, "
                         f"{tuple(masks.shape)}")
    if tuple(masks.shape[1:]) != (camera.height, camera.width):
        raise ValueError(f"masks: size {tuple(masks.shape[1:])} differs from the camera's "
                         f"{(camera.height, camera.width)} (height, width)")
    if bool((translation[:, 2] <= 0).any()):
        raise ValueError("translation: the target must lie in front of the camera (t_z > 0)")

    fit_camera = camera.rescaled(options.resolution)
    targets = resize_masks(masks.float(), fit_camera.height, fit_camera.width)
    renderer = SilhouetteRenderer(fit_camera, spp=options.spp, sppp=options.sppp,
                                  seed=options.seed)
    dtype = torch.float64
    rotation0 = rotation.detach().to(dtype)
    translation0 = translation.detach().to(dtype)
    distance = torch.linalg.vector_norm(translation0, dim=-1, keepdim=True)
    raw0 = raw_from_assembly(assembly).to(dtype)
    moving = options.shape != "pose"
    # 1 where a raw parameter moves: the shape option's fields of every primitive.
    free_fields = torch.zeros(raw0.shape[-1], dtype=dtype)
    for name in _MOVING_FIELDS[options.shape]:
        free_fields[FIELDS[name]] = 1.0
    free_fields = free_fields.expand_as(raw0).clone()
    if own is not None:
        if tuple(own.shape) != tuple(raw0.shape[:2]) or own.dtype != torch.bool or \
                not bool(own[:, 0].all()):
            raise ValueError(f"own: expected ({raw0.shape[0]}, {raw0.shape[1]}) bool, each "
                             f"item's first row its own, got {tuple(own.shape)} {own.dtype}")
        own = own.cpu()
    if options.seen_sizes:
        free_fields[..., FIELDS["size"]] *= _seen_fraction(assembly, rotation0, translation0)
    change = torch.zeros_like(raw0, requires_grad=moving)
    relative = None if relative_rotations is None else relative_rotations.detach().to(dtype)
    rotation_vector = torch.zeros(1 if relative is not None else batch, 3, dtype=dtype,
                                  requires_grad=True)
    shift = torch.zeros(batch, 3, dtype=dtype, requires_grad=True)
    rate = torch.zeros(3, dtype=dtype, requires_grad=relative_times is not None)
    times = rate0 = None
    if relative is not None and relative_times is not None:
        # The turn's rate from view 0 and the view nearest it in time (a turn read between
        # views far apart could pass half a turn and wrap), in units of the views' time span:
        # the correction d is then the extra turn at the view farthest from view 0.
        times = relative_times.detach().to(dtype)
        times = times - times[0]
        span = times.abs().max()
        times = times / span
        nearest = int(torch.where(times == 0, torch.inf, times.abs()).argmin())
        rate0 = matrix_to_axis_angle(relative[nearest] @ relative[0].T) / times[nearest]
    # Zeroes the z component of the correction when the depth is held.
    shift_axes = torch.tensor([1.0, 1.0, 0.0 if options.depth == "fixed" else 1.0], dtype=dtype)
    pose_parameters = [shift] if options.rotation == "fixed" else [rotation_vector, shift]
    if times is not None and options.rotation != "fixed":
        pose_parameters.append(rate)
    warm = options.warmup  # step k of the warm-up at (k + 1) / (warmup + 1) of the rate
    optimizer = Adam([change, *pose_parameters] if moving else pose_parameters,
                     lr=options.lr, warmup=warm)

    def current_raw() -> Tensor:
        return raw0 + change * free_fields

    standing_in = own is not None and moving and not bool(own.all())
    rows = torch.where(own, torch.arange(own.shape[1]), -1) if standing_in else None

    def shaped(raw: Tensor) -> Assembly:
        """The assembly of ``raw``; where the shape moves, each stand-in rebuilt from its
        item's first row as the batch made it (a held one was left in sight by its host)."""
        current = Assembly.from_raw(raw)
        return Assembly(gathered_primitives(current.params, rows)) if standing_in else current

    def pose() -> tuple[Tensor, Tensor]:
        if not shared:
            return (axis_angle_to_matrix(rotation_vector) @ rotation0,
                    translation0 + distance * shift * shift_axes)
        spin = axis_angle_to_matrix(rotation_vector)
        if times is not None and rate0 is not None:  # R_j = exp(tau_j (w + d)) R_0
            rotations = axis_angle_to_matrix(times[:, None] * (rate0 + rate)) @ \
                (spin[0] @ rotation0[0])
        elif relative is not None:
            rotations = relative @ (spin[0] @ relative[0].T @ rotation0[0])
        else:
            rotations = spin @ rotation0
        # The depths' geometric mean stays the start's: the scale is the start's.
        depth = shift[:, 2] * shift_axes[2]
        scale = torch.exp(depth - depth.mean())[:, None]
        lateral = shift * shift_axes.new_tensor([1.0, 1.0, 0.0])
        return rotations, translation0 * scale + distance * lateral

    best_iou = torch.full((batch,), -1.0, dtype=dtype)
    best_raw, best_rotation, best_translation = raw0.clone(), rotation0.clone(), \
        translation0.clone()
    iou_before = None
    stale = steps = 0
    losses: list[float] = []

    def remember(ious: Tensor, raw_now: Tensor, rotation_now: Tensor,
                 translation_now: Tensor) -> bool:
        if shared:  # one state for all views: better by the mean IoU
            if float(ious.mean()) <= float(best_iou.mean()):
                return False
            best_iou[:], best_raw[:] = ious, raw_now
            best_rotation[:], best_translation[:] = rotation_now, translation_now
            return True
        better = ious > best_iou
        best_iou[better] = ious[better]
        best_raw[better] = raw_now[better]
        best_rotation[better] = rotation_now[better]
        best_translation[better] = translation_now[better]
        return bool(better.any())

    with one_thread(options.deterministic):  # the same start, the same result
        for step in range(options.steps):
            optimizer.zero_grad()
            rotation_now, translation_now = pose()
            raw = current_raw()
            current = shaped(raw)
            silhouette, coverage = render_assembly_loss(
                current, rotation_now, translation_now, renderer,
                lambda view, i: silhouette_loss(view[None], targets[i, None].to(view.dtype),
                                                options.loss), options.level)
            moved = (raw - raw0) ** 2
            moved = moved.mean(dim=(1, 2)) if own is None else (moved * own[..., None]).sum(
                dim=(1, 2)) / (moved.shape[-1] * own.sum(dim=1).clamp_min(1))
            prior = options.prior_weight * moved.sum() \
                + options.rotation_prior * rotation_vector.square().sum()
            if options.depth_prior:  # the change of depth that pose() applies, squared
                depth = shift[:, 2] * shift_axes[2]
                prior = prior + options.depth_prior * (
                    depth - depth.mean() if shared else depth).square().sum()
            if shared:  # the one shape's prior weighs as much as B items' would
                prior = prior + (batch - 1) * options.prior_weight * ((raw - raw0) ** 2).mean()
            (silhouette + prior).backward()
            losses.append(float(silhouette.detach()))
            with torch.no_grad():
                ious = mask_iou(coverage, targets)
                if iou_before is None:
                    iou_before = ious.clone()
                improved = remember(ious, raw.detach(), rotation_now.detach(),
                                    translation_now.detach())
            optimizer.step()
            steps += 1
            stale = 0 if improved or step < warm else stale + 1
            if stale >= options.patience:
                break
        with torch.no_grad():
            rotation_now, translation_now = pose()
            raw = current_raw()
            coverage = render_assembly(shaped(raw), rotation_now, translation_now,
                                       renderer, options.level)
            remember(mask_iou(coverage, targets), raw.detach(), rotation_now, translation_now)
    assert iou_before is not None
    return RefineResult(shaped(best_raw), best_rotation, best_translation,
                        iou_before, best_iou.clone(), steps, losses)
