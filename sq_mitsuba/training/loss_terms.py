"""The training loss, one place per term: a registry of named terms and their configuration.

A term is one function ``term(output, batch, context) -> Tensor`` (a scalar, the mean over the
process's batch) plus one :class:`LossTerm` entry in :data:`LOSS_TERMS`, whose name is also its
weight's key in ``loss.weights`` and its column in ``log.csv``. Training
(:mod:`sq_mitsuba.training.step`), the run log and ``sq-mitsuba bench train``'s
per-term timing all read the registry, so adding a term is one function and one
:func:`register_term` call (or entry); a config that weighs an unknown term is refused when it
is built, and one whose network lacks an output a weighted term needs is refused before
training starts (:func:`check_terms`).

The terms (weights of the paper's configuration in :data:`PUBLISHED_WEIGHTS`):

- ``chamfer``: squared-L2 Chamfer distance between the assembly's surface samples and the
  mesh points (paper Eq. 12; Euclidean with ``loss.chamfer_distance``); for a network with
  existence probabilities (``network.existence``) its expectation over which primitives exist;
- ``occupancy``: balanced BCE of the union occupancy at labelled points (Eq. 14);
- ``reprojection``: pixel MSE of the Mitsuba silhouette at the true pose against the mask;
- ``rotation``: rotation angle in radians, minimised over the model's symmetries (the paper's);
- ``rotation_6d``: squared distance of the raw 6D rotation output to the true matrix's first
  two rows, minimised over the symmetries (not in the paper; see the model card);
- ``rotation_grid``: cross-entropy of a distribution head's grid scores against every
  symmetric equivalent of the true rotation;
- ``translation``: relative translation error;
- ``overlap``: summed occupancy above ``loss.beta`` (Eq. 18);
- ``taper``: mean squared taper;
- ``mask``: binary cross-entropy of the mask head against the mask;
- ``parsimony``: the expected number of primitives of a network with existence probabilities
  (off by default; a config that weighs it for a network without them is refused);
- ``surface_depth``: mean absolute error of the depth head's map of the visible surface against
  the one the batch's surface points give at the true pose
  (:mod:`sq_mitsuba.model.surface_depth`; off by default);
- ``surface_normal``: mean squared distance of the normal head's map of the visible surface
  to the mean normal of the batch's surface points seen in each cell at the true pose
  (:mod:`sq_mitsuba.model.surface_normals`; off by default);
- ``parts``: each primitive's Chamfer distance to the part it is paired with in the model's
  own fitted assembly (:mod:`sq_mitsuba.model.part_targets`; off by default; the dataset's
  part targets, ``sq-mitsuba dataset fit-parts``, are read when it is weighted).

Convention: only the Chamfer and parsimony terms read the existence probabilities. The
occupancy, reprojection, overlap and taper terms see every primitive, present or not: they
pull every primitive into the target's solid and silhouette, where a primitive the predictor
then drops costs nothing but coverage, which the Chamfer term's target -> prediction
direction prices; weighing them too (an expected union occupancy, a silhouette per existence
pattern) would cost a reformulation of each, or renders, for a second-order gain.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from sq_mitsuba.config import bounds, in_range, positive
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.model.existence import existence_surface_samples
from sq_mitsuba.model.losses import (
    chamfer_loss,
    counted_surface_samples,
    mask_loss,
    occupancy_loss,
    overlap,
    parsimony_loss,
    probabilistic_chamfer_loss,
    reprojection_loss,
    rotation_6d_loss,
    rotation_distribution_loss,
    rotation_loss,
    taper_loss,
    translation_loss,
)
from sq_mitsuba.model.network import NetworkOutput
from sq_mitsuba.model.part_targets import matched_part_loss
from sq_mitsuba.model.surface_depth import surface_depth_loss, visible_depth_map
from sq_mitsuba.model.surface_normals import surface_normal_loss, visible_normal_map
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer
from sq_mitsuba.training.batch import TrainingBatch

__all__ = [
    "LOSS_TERMS",
    "PUBLISHED_WEIGHTS",
    "LossConfig",
    "LossContext",
    "LossTerm",
    "LossTermError",
    "ReprojectionConfig",
    "check_terms",
    "compute_terms",
    "register_term",
    "short_term_name",
    "total_loss",
]

#: Term weights of the paper's configuration (the default of ``loss.weights``).
PUBLISHED_WEIGHTS = {"chamfer": 10.0, "occupancy": 1.0, "reprojection": 1.0, "rotation": 0.1,
                     "translation": 0.1, "overlap": 0.1, "taper": 0.01}


class LossTermError(ValueError):
    """A loss configuration the registry or the network cannot serve; the message is one
    line."""


# ------------------------------------------------------------------------------ config


@dataclass(frozen=True)
class LossConfig:
    """Loss terms and their weights (a term absent from ``weights``, or weighted 0, is off and
    costs nothing)."""

    weights: dict[str, float] = field(default_factory=lambda: dict(PUBLISHED_WEIGHTS),
                                      metadata=bounds(0, None))
    """Weight of each term by name (the names of ``sq_mitsuba.training.loss_terms``: chamfer,
    occupancy, reprojection, rotation, rotation_6d, rotation_grid, translation, overlap, taper,
    mask, parsimony, parts, surface_depth, surface_normal). A table in a file lists every term
    that trains (parsimony, the price of a primitive of a network with network.existence, is
    off unless weighed); --set loss.weights.taper=0 changes one."""
    sharpness: float = positive(10.0)
    "Sharpness s of the occupancy sigmoid g = sigmoid(s (1 - f)) (paper Eq. 14)."
    beta: float = positive(1.25)
    "Summed occupancy tolerated before the overlap penalty starts (paper Eq. 18)."
    level: int = in_range(0, 5, default=3)
    "Icosphere level of the assembly's surface samples for the Chamfer loss (3: 642 each)."
    chamfer_distance: Literal["squared", "euclidean"] = "squared"
    """The Chamfer term's distances: squared (the paper's Eq. 12: an uncertain reading is drawn
    to the mean of the shapes it might be) or Euclidean (each point pulled alike: towards
    their median; the evaluation's Chamfer-L1 is of this kind)."""

    def __post_init__(self) -> None:
        unknown = sorted(set(self.weights) - set(LOSS_TERMS))
        if unknown:
            raise ValueError(f"unknown loss term {unknown[0]!r} in weights (known: "
                             f"{', '.join(LOSS_TERMS)})")

    def enabled(self) -> tuple[str, ...]:
        """Names of the terms with a non-zero weight, in registry order."""
        return tuple(name for name in LOSS_TERMS if self.weights.get(name, 0.0) != 0)


@dataclass(frozen=True)
class ReprojectionConfig:
    """The differentiable-silhouette (reprojection) term."""

    resolution: int | None = in_range(8, 1024, default=None)
    "Side in pixels of the rendered silhouettes and target masks; None: network.image_size."
    level: int = in_range(0, 5, default=3)
    "Icosphere level of each primitive's mesh (3: 642 vertices, as the paper)."
    items: int | None = in_range(1, 100_000, default=None)
    """Images rendered per step and process, drawn at random from the process's batch (an
    unbiased estimate of the batch mean; all of them when the batch is smaller); None: every
    image."""
    spp: int = in_range(1, 1024, default=16)
    "Samples per pixel of the forward silhouette."
    sppp: int | None = in_range(1, 1024, default=None)
    "Silhouette samples per pixel of the backward pass; None: the renderer's fixed budget."
    deterministic: bool = True
    """On the CPU, render with one Dr.Jit thread while training: Mitsuba's backward pass sums
    vertex gradients with atomic adds whose order varies between threads, so with several
    threads two runs (or a run and its resumption) differ in the last float bits, which
    training amplifies. One thread repeats every run exactly. Worker processes (``workers``)
    always render on one thread each, so they are exact either way."""
    workers: int | None = in_range(0, 256, default=None)
    """Processes that share the rendered items of a step, each on one Dr.Jit thread (CPU
    only; the losses and gradients equal a one-process run's bit for bit, so a run may resume
    with another count). None: one per CPU core available, shared among torchrun's processes
    (none when that leaves one); 0: render in the training process."""


@dataclass
class LossContext:
    """What the terms share besides the network output and the batch."""

    loss: LossConfig
    reprojection: ReprojectionConfig = field(default_factory=ReprojectionConfig)
    renderer: SilhouetteRenderer | None = None
    """The reprojection term's :class:`~sq_mitsuba.render.silhouette.renderer.SilhouetteRenderer`
    (None when that term is off), reseeded by the training step."""
    generator: torch.Generator | None = None
    "Draws the reprojection term's subset of items (seeded per step by the training step)."
    part_targets: Tensor | None = None
    """(models, M, 16) the training models' fitted raw parameters, by ``model_index`` (the
    ``parts`` term's targets; None when that term is off)."""
    camera_matrix: Tensor | None = None
    "(3, 3) intrinsics at the network's input size (the training step sets them)."


# ------------------------------------------------------------------------------ registry


#: A term: (network output, batch, context) -> scalar tensor.
TermFunction = Callable[[NetworkOutput, TrainingBatch, LossContext], Tensor]


@dataclass(frozen=True)
class LossTerm:
    """One registered term."""

    name: str
    "Its key in ``loss.weights`` and its column in ``log.csv``."
    function: TermFunction
    "(output, batch, context) -> scalar tensor, the mean over the batch."
    needs: tuple[str, ...] = ()
    "The network-output fields it reads (a network whose output lacks one cannot train it)."


#: Every term, in log and summation order.
LOSS_TERMS: dict[str, LossTerm] = {}


def short_term_name(name: str) -> str:
    """A loss term's name for the progress bar: its first five letters, or for a name of
    several words the first four of the first and the initials of the rest, so that terms
    sharing a first word stay apart ("surface_depth" "surf_d", "surface_normal" "surf_n")."""
    first, *rest = name.split("_")
    return first[:5] if not rest else first[:4] + "_" + "".join(word[:1] for word in rest)


def register_term(name: str, function: TermFunction, needs: tuple[str, ...] = ()) -> LossTerm:
    """Add a term to :data:`LOSS_TERMS` (appended to the order); returns its entry."""
    if not name.isidentifier() or name in LOSS_TERMS:
        raise ValueError(f"{name!r}: a loss term needs a new identifier as its name")
    LOSS_TERMS[name] = LossTerm(name, function, tuple(needs))
    return LOSS_TERMS[name]


def chamfer_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.chamfer_loss` of the assembly's counted surface
    samples (level ``loss.level``) against ``batch.surface_points``; with existence logits,
    :func:`~sq_mitsuba.model.losses.probabilistic_chamfer_loss` (equal to it when every
    primitive surely exists)."""
    probabilities = output.existence
    squared = context.loss.chamfer_distance == "squared"
    if probabilities is not None:
        points, inside = existence_surface_samples(output.assembly, context.loss.level)
        return probabilistic_chamfer_loss(points, inside, probabilities.to(points),
                                          batch.surface_points.to(points), squared=squared)
    points, keep = counted_surface_samples(output.assembly, context.loss.level)
    return chamfer_loss(points, keep, batch.surface_points.to(points), squared=squared)


def occupancy_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.occupancy_loss` at the batch's labelled points."""
    assembly = output.assembly
    return occupancy_loss(assembly, batch.occupancy_points.to(assembly.params),
                          batch.occupancy_labels, context.loss.sharpness)


def overlap_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.overlap` of the per-primitive occupancy at the
    batch's occupancy points."""
    assembly = output.assembly
    points = batch.occupancy_points.to(assembly.params)
    return overlap(assembly.occupancy(points, context.loss.sharpness), context.loss.beta)


def reprojection_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.reprojection_loss` of the predicted assembly at the
    true pose against the masks (resized to the renderer's resolution by area averaging), on
    ``reprojection.items`` items drawn by ``context.generator``."""
    renderer = context.renderer
    if renderer is None:
        raise LossTermError("reprojection: the term is weighted but no renderer was made")
    assembly = output.assembly
    masks = batch.mask[:, 0]
    size = tuple(renderer.resolution)
    if tuple(masks.shape[-2:]) != size:
        masks = F.interpolate(masks[:, None], size=size, mode="area")[:, 0]
    # At most the process's batch: a smaller batch (tests, many processes) renders all.
    items = context.reprojection.items
    items = None if items is None or items >= len(masks) else items
    return reprojection_loss(assembly, batch.rotation.to(assembly.params),
                             batch.translation.to(assembly.params), masks, renderer,
                             context.reprojection.level, items, context.generator)


def rotation_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.rotation_loss` (radians, symmetry-aware), batch
    mean."""
    rotation = output.rotation
    return rotation_loss(rotation, batch.rotation.to(rotation),
                         batch.symmetries.to(rotation)).mean()


def rotation_6d_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.rotation_6d_loss` of ``output.rotation_6d``
    (symmetry-aware), batch mean."""
    raw = output.rotation_6d
    return rotation_6d_loss(raw, batch.rotation.to(raw), batch.symmetries.to(raw)).mean()


def translation_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.translation_loss` (relative error), batch mean."""
    translation = output.translation
    return translation_loss(translation, batch.translation.to(translation)).mean()


def taper_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.taper_loss` of the assembly."""
    return taper_loss(output.assembly)


def rotation_grid_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.rotation_distribution_loss` of
    ``output.rotation_logits`` (every symmetric equivalent right), batch mean."""
    logits = output.rotation_logits
    return rotation_distribution_loss(logits, batch.rotation.to(logits),
                                      batch.symmetries.to(logits)).mean()


def mask_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.mask_loss` of ``output.mask_logits``."""
    return mask_loss(output.mask_logits, batch.mask)


def parsimony_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.losses.parsimony_loss` of the existence probabilities."""
    return parsimony_loss(output.existence)


def surface_depth_term(output: NetworkOutput, batch: TrainingBatch,
                       context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.surface_depth.surface_depth_loss` of the depth head's map
    against :func:`~sq_mitsuba.model.surface_depth.visible_depth_map` of the batch's surface
    points at the true pose."""
    predicted = output.surface_depth
    if context.camera_matrix is None:
        raise LossTermError("surface_depth: the term is weighted but no camera was given")
    stride = math.ceil(batch.image.shape[-1] / predicted.shape[-1])
    target, valid = visible_depth_map(batch.surface_points.to(predicted), batch.rotation,
                                      batch.translation, context.camera_matrix,
                                      batch.image.shape[-1], stride)
    return surface_depth_loss(predicted, target, valid)


def surface_normal_term(output: NetworkOutput, batch: TrainingBatch,
                        context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.surface_normals.surface_normal_loss` of the normal head's map
    against :func:`~sq_mitsuba.model.surface_normals.visible_normal_map` of the batch's
    surface points and normals at the true pose."""
    predicted = output.surface_normals
    if context.camera_matrix is None:
        raise LossTermError("surface_normal: the term is weighted but no camera was given")
    if batch.surface_normals is None:
        raise LossTermError("surface_normal: the term is weighted but the batch holds no "
                            "surface normals")
    stride = math.ceil(batch.image.shape[-1] / predicted.shape[-1])
    target, valid = visible_normal_map(batch.surface_points.to(predicted),
                                       batch.surface_normals.to(predicted), batch.rotation,
                                       batch.translation, context.camera_matrix,
                                       batch.image.shape[-1], stride)
    return surface_normal_loss(predicted, target, valid)


def parts_term(output: NetworkOutput, batch: TrainingBatch, context: LossContext) -> Tensor:
    """:func:`~sq_mitsuba.model.part_targets.matched_part_loss` of the assembly against each
    image's model's fitted assembly (``context.part_targets``), icosphere level 1."""
    table = context.part_targets
    if table is None:
        raise LossTermError("parts: the term is weighted but no part targets were read")
    assembly = output.assembly
    targets = table[batch.model_index.cpu()].to(assembly.params)
    return matched_part_loss(assembly, Assembly.from_raw(targets), level=1)


register_term("chamfer", chamfer_term, ("assembly",))
register_term("occupancy", occupancy_term, ("assembly",))
register_term("reprojection", reprojection_term, ("assembly",))
register_term("rotation", rotation_term, ("rotation",))
register_term("rotation_6d", rotation_6d_term, ("rotation_6d",))
register_term("rotation_grid", rotation_grid_term, ("rotation_logits",))
register_term("translation", translation_term, ("translation",))
register_term("overlap", overlap_term, ("assembly",))
register_term("taper", taper_term, ("assembly",))
register_term("mask", mask_term, ("mask_logits",))
register_term("parsimony", parsimony_term, ("existence_logits",))
register_term("parts", parts_term, ("assembly",))
register_term("surface_depth", surface_depth_term, ("surface_depth",))
register_term("surface_normal", surface_normal_term, ("surface_normals",))


# ------------------------------------------------------------------------------ use


def _weights(config: LossConfig | Mapping[str, float]) -> Mapping[str, float]:
    return config.weights if isinstance(config, LossConfig) else config


def enabled_terms(config: LossConfig | Mapping[str, float]) -> tuple[str, ...]:
    """Names of the registered terms weighted non-zero, in registry order; an unknown name is
    a :class:`LossTermError`."""
    weights = _weights(config)
    unknown = sorted(set(weights) - set(LOSS_TERMS))
    if unknown:
        raise LossTermError(f"loss.weights.{unknown[0]}: unknown loss term (known: "
                            f"{', '.join(LOSS_TERMS)})")
    return tuple(name for name in LOSS_TERMS if weights.get(name, 0.0) != 0)


def check_terms(config: LossConfig, output: NetworkOutput,
                distributed_model: torch.nn.Module | None = None) -> None:
    """Refuse (one line) a config whose weighted terms need an output field that ``output``
    (a network output) lacks or leaves None, or that weighs nothing; with
    ``distributed_model`` (the network of a distributed run, ``output`` its forward pass with
    gradients), also one whose optional output (a head's) no weighted term reads while
    trainable parameters feed it alone: DistributedDataParallel waits for a gradient of
    every parameter its outputs reach, so such a run stopped at its second step with torch's
    error, after a first update of unaveraged gradients (one process trains it as it is)."""
    names = enabled_terms(config)
    if not names:
        raise LossTermError("loss.weights: every term has weight 0")
    for name in names:
        for needed in LOSS_TERMS[name].needs:
            if getattr(output, needed, None) is None:
                raise LossTermError(f"loss.weights.{name}: the term needs the network output "
                                    f"'{needed}', which this network does not produce")
    if distributed_model is None:
        return
    optional = {f for term in LOSS_TERMS.values() for n in term.needs for f in _FIELDS.get(n, (n,))}
    read = {f for name in names for n in LOSS_TERMS[name].needs for f in _FIELDS.get(n, (n,))}
    tensors = {k: v for k, v in vars(output).items()
               if isinstance(v, Tensor) and v.requires_grad}
    unread = [k for k in tensors if k in optional and k not in read]
    fed = _reached(distributed_model, [v for k, v in tensors.items() if k not in unread])
    alone = {k: _reached(distributed_model, [tensors[k]]) - fed for k in unread}
    unread = [k for k in unread if alone[k]]
    if unread:
        heads = sorted({name.split(".")[0] for k in unread for name in alone[k]})
        count = len(set().union(*(alone[k] for k in unread)))
        raise LossTermError(
            f"network output {', '.join(repr(k) for k in unread)}: no weighted loss term reads "
            f"it, so {count} parameters ({', '.join(h + '.*' for h in heads)}) get no "
            "gradient, which a distributed run cannot train; weigh a term that reads it (e.g. "
            "loss.weights.mask for network.mask_head), leave the head out, freeze it "
            "(optim.trainable) or train in one process")


# The output fields behind a need that is no field: the assembly is read from raw, turned by
# view_to_body, its primitives weighed by existence_logits.
_FIELDS = {"assembly": ("raw", "view_to_body", "existence_logits")}


def _reached(model: torch.nn.Module, tensors: list[Tensor]) -> set[str]:
    """Names of the trainable parameters of ``model`` that ``tensors`` depend on."""
    named = [(n, p) for n, p in model.named_parameters() if p.requires_grad]
    if not tensors or not named:
        return set()
    total = torch.stack([t.float().sum() for t in tensors]).sum()
    grads = torch.autograd.grad(total, [p for _, p in named], allow_unused=True,
                                retain_graph=True)
    return {n for (n, _), g in zip(named, grads, strict=True) if g is not None}


def compute_terms(output: NetworkOutput, batch: TrainingBatch, context: LossContext,
                  names: tuple[str, ...] | None = None) -> dict[str, Tensor]:
    """The value of each term of ``names`` (default: those ``context.loss`` weighs non-zero),
    each a scalar tensor, in registry order."""
    names = enabled_terms(context.loss) if names is None else names
    # Convention: a view-frame shape is scored in the body frame through the true rotation.
    output = output.with_true_rotation(batch.rotation.to(output.rotation))
    return {name: LOSS_TERMS[name].function(output, batch, context) for name in names}


def total_loss(terms: Mapping[str, Tensor], weights: LossConfig | Mapping[str, float]
               ) -> Tensor:
    """Weighted sum of scalar loss terms, ``sum_name weights[name] * terms[name]``, in
    registry order.

    Terms whose weight is 0 are skipped (their values are not read, so a NaN there does no
    harm); every term with a non-zero weight must be present, and every name registered.
    """
    weights = _weights(weights)
    unknown = sorted(set(terms) - set(LOSS_TERMS))
    if unknown:
        raise LossTermError(f"terms: unknown term {unknown[0]!r} (expected names from "
                            f"{', '.join(LOSS_TERMS)})")
    active = enabled_terms(weights)
    if not active:
        raise LossTermError("weights: every term has weight 0")
    missing = [name for name in active if name not in terms]
    if missing:
        raise LossTermError(f"terms: {missing[0]!r} is missing but has weight "
                            f"{weights[missing[0]]}")
    total: Tensor | None = None
    for name in active:
        term = terms[name]
        if not isinstance(term, Tensor) or term.numel() != 1:
            shape = tuple(term.shape) if isinstance(term, Tensor) else type(term).__name__
            raise LossTermError(f"terms[{name!r}]: expected a scalar tensor, got {shape}")
        weighted = weights[name] * term.reshape(())
        total = weighted if total is None else total + weighted
    assert total is not None
    return total
