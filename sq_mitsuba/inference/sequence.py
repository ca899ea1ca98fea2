"""A pass of images: one assembly and every pose from N views of the same spacecraft.

One silhouette cannot show the far side of a target, its depth, or which end of an axis is
"+"; several views of one rigid body can. :func:`predict_sequence` (and
``Predictor.predict_sequence``) takes N images of one spacecraft and returns one assembly in
its body frame and the pose of every image:

1. **Each frame alone**: ``Predictor.predict(images, refine=True)`` with the refinement cut
   to one step (:data:`FRAMES_REFINEMENT`): the network's reading from turned copies, the
   mask and the pose search; the joint fit refines.
2. **One body frame**: each frame's reading is in a body frame fixed only up to the four half
   turns (the principal axes' signs cannot be seen). The frame whose fit matches its mask best
   is the reference; every other frame's half turn is chosen so that its assembly, turned, lies
   nearest the reference's (Chamfer distance of the surface clouds): resolved across frames.
   Frames whose readings lie within ``options.near_views_deg`` of each other under one half turn
   are taken to be nearby views and that half turn relates them
   (:func:`align_half_turns_by_views`): a pass given unordered keeps its frames' half turns
   consistent where a near-symmetric shape cannot tell them. With the frames' relative rotations
   given (a servicer's navigation: ``R_j = Q_j R_0``), one rotation ``R_0`` is kept instead, the
   chordal mean of the frames' readings carried back by their ``Q_j``, each under the half turn
   that brings it nearest the others' (:func:`align_half_turns_by_relative`). **Frames in order**
   (``ordered=True``, a pass, one unit of time apart) turn steadily: the half turns by shape
   also make the motion smoothest, and the constant-rate turn most frames' readings agree with
   is found by consensus (:func:`~sq_mitsuba.inference.body_frame.along_motion`); the reference
   is then the best-fitting frame that agrees, and with ``options.motion = "fitted"`` (the
   default) every frame starts on the turn and the joint fit keeps the frames on one
   constant-rate turn, its rate fitted with the rest, so a frame misread alone no longer pulls
   the shared shape its own way. Where no turn has the agreement of a quarter of the frames
   (``options.motion_min_share``), they keep their readings; given relative rotations take
   precedence over the pass's own turn.
3. **One shape, N poses, fitted at once** (:func:`fit_sequence`, the refinement's shared
   mode): the shared assembly (from the reference's reading, or with ``start="best"`` the
   reading that fits all frames best, :func:`choose_start`; every shape parameter free, held
   near the start by a weak prior) and each frame's rotation and translation (or, with
   relative rotations, the one ``R_0``) move together by Adam so that the Mitsuba silhouettes
   match every frame's mask (in order, ``motion="fitted"``: ``R_0`` and the rate of turn
   move, not N rotations; ``"held"``: ``R_0`` alone); the best step by the mean IoU is kept.
   The scale stays the network's (the frames' depths keep their geometric mean). Where the
   frames move alone (unordered, ``motion="free"`` or ``"start"``, or no motion found, and no
   given rotations), a frame the fit left below half its own fit's IoU is refitted alone, pose
   only, with the shared shape (:func:`~sq_mitsuba.inference.lost_frames.place_lost_frames`;
   its depth then moves alone).
4. **An oriented-box body frame** (``options.canonical``, off): the result in the frame of
   ``--align obb`` models (:func:`canonical_frame`: the fitted assembly's minimum-volume box's
   axes by extent, centred), not the models' built axes (their true surface's box: ~30 deg).

Convention: poses map body to camera, ``x_cam = R_j x_body + t_j`` (OpenCV frame); the body
frame is the reference frame's reading, turned by no half turn; relative rotations are given
as ``Q_j = R_j R_0^T`` (frame 0 first, ``Q_0 = I``). The result's tensors: float64, CPU.

Limits: frames that all show one outline constrain the shape's depth no better than one
image; a symmetric target's half turns stay ambiguous, harmlessly for the shape, not for the
relative poses of unordered unrelated views (order, nearby views or given rotations resolve it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.checks import check_rotations, check_switch
from sq_mitsuba.config import in_range, non_negative
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import matrix_to_quaternion, mean_rotation
from sq_mitsuba.inference.body_frame import (
    align_half_turns_by_relative,
    align_half_turns_by_views,
    align_half_turns_in_order,
    along_motion,
    canonical_frame,
    reframed,
)
from sq_mitsuba.inference.images import array_to_tensor, prepare_images
from sq_mitsuba.inference.lost_frames import place_lost_frames
from sq_mitsuba.inference.pipeline import checked_options, masks_to_fit
from sq_mitsuba.inference.prediction import Prediction, SequencePrediction
from sq_mitsuba.inference.refine import RefineOptions, refine_pose_and_shape
from sq_mitsuba.inference.search import (
    SEARCH_REFINEMENT,
    SearchOptions,
    _recentred,
    soft_iou,
)

#: The frames' own path in a sequence: the pose search's best candidate (``keep=1``: no
#: screening) and one refinement step, since the joint fit refines every pose after it. On
#: passes of 8 frames of 4 unseen spacecraft, against the shipped refinement per frame, the
#: joint fit's mean 2D IoU 0.762 -> 0.779 in a quarter of the frames' time (notebook, "Passes").
FRAMES_SEARCH = SearchOptions(keep=1)
FRAMES_REFINEMENT = replace(SEARCH_REFINEMENT, steps=1, patience=1)

__all__ = ["FRAMES_REFINEMENT", "FRAMES_SEARCH", "SequenceOptions", "SequencePrediction",
           "align_half_turns_by_views", "align_half_turns_in_order", "along_motion",
           "canonical_frame", "choose_start", "fit_sequence", "predict_sequence", "reframed",
           "sequence_from_frames", "stage_refine_options"]


@dataclass(frozen=True)
class SequenceOptions:
    """Settings of the joint fit of one shape and N poses to N masks."""

    steps: int = in_range(1, 10_000, default=60)
    """Adam steps of the joint fit (shape and poses together): on 8-frame passes of 12 held-out
    spacecraft 60 at level 1 gave 2D IoU 0.740 in 0.9 x the time of 40 at level 2 (0.718), 80
    0.746 at 1.3 x (eval/experiments/README.md, "Passes")."""
    shape_steps: int = in_range(0, 10_000, default=0)
    "Adam steps of the shape alone first, the poses held (0: none; 20: 2D IoU 0.779 -> 0.752)."
    start: Literal["reference", "best"] = "reference"
    """The shared shape's start: the best-fitting frame's reading, or the reading (or the
    readings' mean) that fits every frame's mask best at the frames' poses ("best": on the
    same passes camera-frame Chamfer 0.083 -> 0.079, mean 2D IoU 0.779 -> 0.762)."""
    lr: float = in_range(0, 1, default=0.03, low_inclusive=False)
    "Adam's learning rate (raw shape parameters, rotation vectors, relative shifts), <= 1."
    warmup: int = in_range(0, 10_000, default=10)
    """Steps over which the learning rate rises to ``lr`` (``RefineOptions.warmup``; 0: none):
    0 / 10 gave 2D IoU 0.623 / 0.633 on 12 training-family passes, 0.732 / 0.733 held out."""
    resolution: int = in_range(8, 1024, default=64)
    "Width in pixels at which the silhouettes are fitted."
    level: int = in_range(0, 5, default=1)
    """Icosphere level of the primitives' meshes (1: 42 vertices; 2: 162). At 64 px level 1
    fits as well as 2 (40 steps, the passes above: 2D IoU 0.712 against 0.718; in family
    0.809 against 0.821) in 2/3 of the time (a step is mostly the scenes' update)."""
    spp: int = in_range(1, 1024, default=4)
    "Samples per pixel of the fitted silhouettes."
    sppp: int | None = in_range(1, 4096, default=1)
    """Silhouette-edge samples per pixel of the gradient, every stage and lost frames' refit
    (``RefineOptions.sppp``; None: 4 at 64 px). 1: passes in 2/3 of the time, within noise."""
    shape: Literal["free", "size", "pose"] = "free"
    "What of the shared shape moves: every parameter, the sizes only, or nothing."
    prior_weight: float = non_negative(0.01)
    "Weight of the squared change of the raw shape parameters (keeps the network's reading)."
    depth_prior: float = non_negative(1.0)
    """Weight of the squared change of each frame's log depth about the frames' mean
    (``RefineOptions.depth_prior``; 1: a frame moved 10 % costs what 0.01 of IoU gains): a
    frame whose mask lost dark arrays or a boom ran off without it (up to 112 % of its
    distance) to shrink its silhouette. On 8-frame passes of 11 unseen training-family
    spacecraft (0 / 1 / 10): camera-frame Chamfer 1.55 / 1.02 / 0.99 x the reading's, 2D IoU
    0.625 / 0.633 / 0.634; held out 2D IoU 0.727 -> 0.735."""
    patience: int = in_range(1, 10_000, default=12)
    "Stop after this many steps without a better mean IoU."
    seed: int = in_range(0, 2**31 - 1, default=0)
    "Seed of the silhouettes' sampling."
    motion: Literal["fitted", "held", "start", "free"] = "fitted"
    """For frames in order (``ordered=True``), what the pass's constant-rate turn (the one most
    frames' readings agree with, :func:`~sq_mitsuba.geometry.pass_motion.
    constant_rate_motion`) does. "fitted": every frame
    starts on it and stays on one constant-rate turn through the joint fit, whose start
    rotation and rate move with the shape; "held": the same with the rate held; "start": a
    frame that disagrees starts from the motion instead of its reading, then every frame moves
    alone; "free": every frame starts from its own reading. Measured on passes of 8 frames
    (eval/MODEL_CARD.md, "A pass of images"; held-out families / archetypes): "fitted" 2D IoU
    0.702 / 0.780 and relative rotations 9.2 / 2.4 deg median, "free" 0.655 / 0.773 and
    11.9 / 6.4 deg. A frame's time is its index; unordered frames and given relative
    rotations (which take precedence) are not affected."""
    motion_threshold_deg: float = in_range(1.0, 179.0, default=25.0)
    "A frame within this angle of the pass's motion agrees with it (``motion``)."
    motion_max_rate_deg: float = in_range(1e-3, 179.0, default=45.0)
    "The fastest turn of the pass's motion, degrees per frame (half-turn flips are not turns)."
    motion_min_share: float = in_range(0.0, 1.0, default=0.25)
    """The share of the frames (and at least 3; two frames always take the motion through
    both) that must agree with the pass's motion, else every frame keeps its reading. Longer
    passes show more aspects, and
    fewer frames are read on one turn: on 12 tuning passes of 16 frames (0.5 / 0.34 / 0.25)
    relative rotations 17.1 / 14.8 / 6.5 deg mean, 2D IoU 0.645 / 0.645 / 0.650, body-frame
    Chamfer-L1 0.146 / 0.142 / 0.156; of 8 frames (0.5 / 0.25) 13.5 / 10.3 deg, 0.633 / 0.637,
    0.149 / 0.154 (eval/experiments/README.md, "Passes")."""
    near_views_deg: float = in_range(0.0, 90.0, default=45.0)
    """Unordered frames (``ordered=False``) whose readings lie within this angle under one half
    turn are nearby views, given consistent half turns (:func:`align_half_turns_by_views`); 0:
    each by its shape alone. On 12 in-family passes given unordered (0 / 30 / 45 / 60):
    relative rotations 143 / 10.9 / 10.1 / 10.6 deg median, 2D IoU 0.620 / 0.639 / 0.640 /
    0.639; independent views unchanged (eval/experiments/README.md, "Passes")."""
    grow: int = in_range(0, 16, default=0)
    """Primitives the joint fit may add, one at a time, where the silhouettes miss the masks
    (:func:`~sq_mitsuba.inference.grow.grow_primitive`: an array or boom the reading left out),
    each followed by ``grow_steps`` steps; 0: none. Off: on 8-frame passes of 12 held-out
    spacecraft 3 grown raised the 2D IoU 0.740 -> 0.747 (in family 0.821 -> 0.831) and the
    body-frame Chamfer-L1 0.187 -> 0.202 (placed where the misread body frame puts them)."""
    grow_steps: int = in_range(1, 10_000, default=20)
    "Adam steps of the joint fit after each grown primitive."
    canonical: bool = False
    """Express the result in the body frame of ``--align obb`` models: the fitted assembly's
    minimum-volume box's axes by extent, its centre of mass at the origin (else the reference
    reading's; ``half_turns`` and ``reference`` keep referring to that). Off: even the true
    surface's box lies 31-34 deg (median) from the default models' built axes."""

    def __post_init__(self) -> None:
        if self.grow and self.shape != "free":
            raise ValueError(f"grow: {self.grow} primitives grown need shape 'free' (a grown "
                             f"primitive changes the shape), got shape {self.shape!r}")


def stage_refine_options(options: SequenceOptions, steps: int, poses: bool) -> RefineOptions:
    """One stage's :class:`RefineOptions`: ``poses`` False holds the rotations and depths."""
    return RefineOptions(steps=steps, lr=options.lr, warmup=options.warmup,
                         resolution=options.resolution, level=options.level,
                         prior_weight=options.prior_weight, shape=options.shape, loss="iou",
                         rotation="free" if poses else "fixed", depth="free" if poses else "fixed",
                         depth_prior=options.depth_prior, patience=options.patience,
                         spp=options.spp, sppp=options.sppp, seed=options.seed)


def fit_sequence(assembly: Assembly, rotation: Tensor, translation: Tensor, masks: Tensor,
                 camera: Camera, options: SequenceOptions | None = None,
                 relative_rotations: Tensor | None = None, relative_times: Tensor | None = None
                 ) -> tuple[Assembly, Tensor, Tensor, Tensor, int, list[float]]:
    """One shared assembly and N poses fitted at once to N masks through Mitsuba silhouettes
    (:func:`~sq_mitsuba.inference.refine.refine_pose_and_shape`, ``shared=True``): the shape
    alone for ``options.shape_steps`` steps (the poses held), then with the poses.

    Args:
        assembly: the start, batch size 1, in the body frame.
        rotation: (N, 3, 3) body -> camera rotations to start from; translation: (N, 3).
        masks: (N, H, W) target masks at ``camera``'s resolution (bool or float in [0, 1]).
        camera: intrinsics of the masks; options: :class:`SequenceOptions`.
        relative_rotations: (N, 3, 3) ``Q_j`` with ``R_j = Q_j R_0``, or None. Given, the
            frames share one rotation ``R_0 = Q_0^T rotation[0]`` that moves, not N.
        relative_times: (N,) the frames' times when ``relative_rotations`` is a constant-rate
            turn (``Q_j = exp((t_j - t_0) [w])``): its rate moves too; None: the ``Q_j`` held.

    Returns:
        The assembly (batch size 1), rotation (N, 3, 3), translation (N, 3), each frame's IoU
        (N,) at the best step (by the mean IoU), the steps taken and the loss per step.
    """
    options = checked_options(options, SequenceOptions(), "options")
    assembly = Assembly(assembly.params.detach().double())
    rotation, translation = rotation.detach().double(), translation.detach().double()
    stages = [(options.shape_steps, False)] if options.shape_steps and \
        options.shape != "pose" else []
    stages.append((options.steps, True))
    grows_left = options.grow
    steps, losses, ious = 0, [], None
    while stages:
        count, poses = stages.pop(0)
        result = refine_pose_and_shape(assembly, rotation, translation, masks, camera,
                                       stage_refine_options(options, count, poses), shared=True,
                                       relative_rotations=relative_rotations,
                                       relative_times=relative_times)
        assembly, rotation, translation = result.assembly, result.rotation, result.translation
        if relative_times is not None:  # the rate moved: the next stage turns from here
            relative_rotations = rotation @ rotation[0].T
        ious, steps, losses = result.iou_after, steps + result.steps, losses + result.losses
        if not stages and grows_left:  # after the last stage: a grown primitive, fitted too
            grows_left -= 1
            grown = _grown(assembly, rotation, translation, masks, camera, options)
            if grown is not None:
                assembly = grown
                stages.append((options.grow_steps, True))
    assert ious is not None
    return assembly, rotation, translation, ious, steps, losses


def _grown(assembly: Assembly, rotation: Tensor, translation: Tensor, masks: Tensor,
           camera: Camera, options: SequenceOptions) -> Assembly | None:
    """The assembly with a primitive grown where the silhouettes miss the masks, or None."""
    from sq_mitsuba.inference.fit import resize_masks
    from sq_mitsuba.inference.grow import grow_primitive

    small = camera.rescaled(options.resolution)
    targets = resize_masks(masks.double(), small.height, small.width)
    grown, before, after = grow_primitive(assembly, rotation, translation, targets, small,
                                          options.level, options.spp, options.seed)
    return grown if after > before else None


def _scores(assembly: Assembly, rotation: Tensor, translation: Tensor, targets: Tensor,
            renderer: Any, level: int) -> tuple[Tensor, Tensor]:
    """Soft IoUs (P,) of one assembly (batch size 1) at P poses against P targets (P, h, w)
    at ``renderer``'s size, each translation recentred on its target (P, 3): the whole lot
    in one Mitsuba launch (and one more for the recentred poses)."""
    vertices, faces = Assembly(assembly.params.detach().double()).merged_mesh(level)
    coverage = renderer.render(vertices[0], faces, rotation, translation).double()
    translation = _recentred(translation.double(), coverage, targets, renderer.camera, False)
    coverage = renderer.render(vertices[0], faces, rotation, translation).double()
    return soft_iou(coverage, targets), translation


def choose_start(readings: Assembly, rotation: Tensor, translation: Tensor, targets: Tensor,
                 renderer: Any, level: int, mean: bool = True
                 ) -> tuple[Assembly, Tensor, Tensor]:
    """The start of the shared shape: of the N readings (already in one body frame) and,
    with ``mean``, their parameters' mean, the one whose silhouettes at every frame's pose fit
    every frame's mask best (mean soft IoU; :func:`_scores`).

    Args:
        readings: N assemblies (batch size N) in the common body frame.
        rotation: (N, 3, 3) the frames' poses in that frame; translation: (N, 3).
        targets: (N, h, w) the masks at ``renderer``'s size.

    Returns:
        The chosen assembly (batch size 1), the frames' translations recentred for it (N, 3)
        and every candidate's mean score (N or N + 1,).
    """
    params = readings.params.detach().double()
    candidates = list(params.split(1))
    if mean:
        candidates.append(params.mean(0, keepdim=True))
    scored = [_scores(Assembly(c), rotation, translation, targets, renderer, level)
              for c in candidates]
    means = torch.tensor([float(score.mean()) for score, _ in scored], dtype=torch.float64)
    return Assembly(candidates[int(means.argmax())]), scored[int(means.argmax())][1], means


def _check_relative(relative_rotations: Any, count: int) -> Tensor | None:
    if relative_rotations is None:
        return None
    if isinstance(relative_rotations, np.ndarray):
        relative_rotations = array_to_tensor(relative_rotations)
    if not isinstance(relative_rotations, Tensor) or relative_rotations.shape != (count, 3, 3) \
            or relative_rotations.is_complex():  # .double() would drop imaginary parts
        shape = tuple(getattr(relative_rotations, "shape", ()))
        raise ValueError(f"relative_rotations: expected ({count}, 3, 3) real (one per frame), "
                         f"got {shape or type(relative_rotations).__name__} "
                         f"{getattr(relative_rotations, 'dtype', '')}".rstrip())
    relative = relative_rotations.detach().double().cpu()
    check_rotations("relative_rotations", relative)
    return relative


def predict_sequence(predictor: Any, images: Tensor | np.ndarray, camera: Camera | None = None,
                     *, relative_rotations: Tensor | np.ndarray | None = None,
                     ordered: bool = False, mask: Any = None,
                     options: SequenceOptions | None = None,
                     search: Any = None, refinement: Any = None,
                     progress: bool = False) -> SequencePrediction:
    """One assembly and every pose from N images of the same spacecraft (module docstring).

    Args:
        predictor: a :class:`~sq_mitsuba.inference.predictor.Predictor`.
        images: (N, H, W) or (N, 1, H, W), N >= 2 frames of one spacecraft, one size, uint8
            or float in [0, 1], in any order.
        camera: the frames' camera (default: the predictor's).
        relative_rotations: (N, 3, 3) ``Q_j = R_j R_0^T`` when known (e.g. from navigation),
            else None.
        ordered: the frames are in the order they were taken, equally spaced in time (a
            pass): the half turns are chosen for the smoothest motion too
            (:func:`align_half_turns_in_order`) and the frames put on the pass's turn
            (``options.motion``).
        mask: the masks to fit, as ``Predictor.predict(refine=True)`` takes them (default: the
            network's mask head, or the segmentation).
        options: the joint fit's :class:`SequenceOptions`.
        search, refinement: the per-frame search's and refinement's settings (default
            :data:`FRAMES_SEARCH` and :data:`FRAMES_REFINEMENT`: the joint fit refines).
        progress: show the stage in progress (the frames' reading, their search and
            refinement, the joint fit) on a progress bar.

    Raises:
        ValueError: one line naming ``images`` (fewer than two frames, sizes, NaN), ``ordered``,
            ``relative_rotations`` or the frame whose mask holds no target.
    """
    from sq_mitsuba.progress import progress_bar

    started = time.perf_counter()
    options = checked_options(options, SequenceOptions(), "options")
    checked = prepare_images(images, predictor.model.config.in_channels)
    count = checked.shape[0]
    if count < 2:
        raise ValueError(f"images: a sequence needs at least 2 frames, got {count} (use "
                         "Predictor.predict for one image)")
    relative = _check_relative(relative_rotations, count)
    ordered = check_switch("ordered", ordered)
    # The network's pass first (milliseconds): a frame it sees no target in is refused before
    # the search of every frame (a mask given is fitted whatever the score).
    with progress_bar(total=3, desc=f"{count} frames: network", unit="stage",
                      disable=not progress) as bar:
        network = predictor.predict(checked, camera)
        bar.update()
        bar.set_description(f"{count} frames: search and refinement")
        frames = _frames(predictor, checked, network, camera, mask, search, refinement)
        bar.update()
        bar.set_description(f"{count} frames: one assembly, every pose")
        result = sequence_from_frames(frames, relative, ordered, options, started=started,
                                      frames_seconds=time.perf_counter() - started)
        bar.update()
    return result


def _frames(predictor: Any, checked: Tensor, network: Prediction, camera: Camera | None,
            mask: Any, search: Any, refinement: Any) -> Prediction:
    """Each frame's own search and refinement, after refusing a frame without a target."""
    if mask is not None and not isinstance(mask, str):  # the user's masks: before any search
        empty = [k for k, kept in enumerate(masks_to_fit(network, checked, mask)[1]) if not kept]
        if empty:
            raise ValueError(f"mask: frame {empty[0]}'s mask holds no target pixel; leave the "
                             "frame out of the sequence, or give a mask of its target")
    elif network.target is not None and not bool(network.target.all()):
        k = int((~network.target).nonzero()[0])
        raise ValueError(f"images: frame {k} shows no target (its score "
                         f"{float(network.target_score[k]):.2f}); leave it out of the sequence, "
                         "or give the frames' masks (predict_sequence's mask, predict --mask)")
    frames = predictor.refine(checked, network, camera, mask=mask,
                              search=FRAMES_SEARCH if search is None else search,
                              refinement=FRAMES_REFINEMENT if refinement is None else refinement)
    empty = [k for k in range(checked.shape[0]) if not bool(frames.fit.fitted[k])]
    if empty:
        raise ValueError(f"images: frame {empty[0]} has no target in its mask "
                         f"({frames.fit.mask_source}); leave it out of the sequence, or give "
                         "the frames' masks (predict_sequence's mask, predict --mask)")
    return frames


def sequence_from_frames(frames: Prediction, relative: Tensor | None = None,
                         ordered: bool = False, options: SequenceOptions | None = None, *,
                         started: float | None = None, frames_seconds: float = 0.0
                         ) -> SequencePrediction:
    """Steps 2-4 of the module docstring from the frames' own fitted predictions.

    Args:
        frames: ``Predictor.predict(images, refine=True)`` of N >= 2 frames, every frame
            fitted (``frames.fit.fitted``).
        relative: (N, 3, 3) relative rotations ``Q_j``, or None.
        ordered, options: see :func:`predict_sequence`.
        started, frames_seconds: the clock at the start of the whole sequence and the time
            the frames took (for :attr:`SequencePrediction.seconds`).

    Raises:
        ValueError: naming ``frames`` (unfitted, scaled, fewer than 2) or ``relative_rotations``.
    """
    from sq_mitsuba.inference.fit import resize_masks
    from sq_mitsuba.render.silhouette.batch import PoseSilhouettes

    started = time.perf_counter() if started is None else started
    options = checked_options(options, SequenceOptions(), "options")
    fit = frames.fit
    if fit is None or len(fit.iou) < 2 or not bool(fit.iou.isfinite().all()) or frames.scale != 1:
        raise ValueError("frames: expected N >= 2 frames, each fitted (no NaN IoU), at unit size "
                         "(predict(images, refine=True))")
    relative = _check_relative(relative, len(fit.iou))
    reference = int(torch.argmax(fit.iou))
    if relative is not None:  # the given rotations settle the half turns, shapes or not
        turns = align_half_turns_by_relative(frames.rotation, relative, reference)
    elif ordered:
        turns = align_half_turns_in_order(frames.assembly, frames.rotation, reference,
                                          options.level)
    else:
        turns = align_half_turns_by_views(frames.assembly, frames.rotation, reference,
                                          options.level, options.near_views_deg)
    rotation = frames.rotation.double() @ turns  # x_ref = S x_j  =>  R_j x_j = (R_j S) x_ref
    times, poses = None, "readings"  # the frames' times (the rate moves); what set the poses
    if relative is not None:  # given, they take precedence over the pass's own motion
        poses = "given"
        carried = relative.transpose(-1, -2) @ rotation  # each frame's estimate of R_0
        rotation = relative @ mean_rotation(carried)
    elif ordered and options.motion != "free":
        on_motion = along_motion(frames.rotation, turns, fit.iou, options.motion_threshold_deg,
                                 options.motion in ("held", "fitted"),
                                 options.motion_max_rate_deg, options.motion_min_share)
        if on_motion is not None:
            rotation, turns, reference, motion_relative = on_motion
            poses = "motion start" if options.motion == "start" else "motion"
            if options.motion in ("held", "fitted"):
                relative = motion_relative  # one rotation (and with "fitted" the rate) moves
            if options.motion == "fitted":
                times = torch.arange(len(rotation), dtype=torch.float64)
    translation = frames.translation.double()
    # Forward silhouettes of one shape at every frame's pose, in one launch: the scores of
    # the start's candidates and of the frames' rotations searched again.
    scorer = PoseSilhouettes(frames.camera.rescaled(options.resolution), seed=options.seed)
    targets = resize_masks((fit.mask.double() > 0.5).double(), scorer.camera.height,
                           scorer.camera.width)
    params = frames.assembly.params.detach().double()
    rows = frames.primitive_index  # None, or (N, W) with -1 for a frame's stand-ins
    if options.start == "best":
        readings = Assembly(torch.cat([reframed(Assembly(params[j:j + 1]), turns[j],
                                                torch.zeros(3, dtype=torch.float64)).params
                                       for j in range(len(params))]))
        # The readings' mean only where every frame kept the same primitives.
        same = rows is None or bool((rows == rows[:1]).all())
        start, translation, scores = choose_start(readings, rotation, translation, targets,
                                                  scorer, options.level, mean=same)
        chosen = min(int(scores.argmax()), len(params) - 1)  # the mean: any frame's rows
    else:
        start, chosen = Assembly(params[reference:reference + 1]), reference
    if rows is not None:  # the shared shape holds the chosen reading's own primitives
        start = Assembly(start.params[:, rows[chosen].to(start.params.device) >= 0])
    started_at = rotation, translation
    assembly, rotation, translation, ious, steps, losses = fit_sequence(
        start, rotation, translation, fit.mask, frames.camera, options, relative, times)
    if relative is None:  # frames that move alone: one the fit lost is placed again
        rotation, translation, ious = place_lost_frames(
            assembly, rotation, translation, ious, fit.iou.to(ious), *started_at, fit.mask,
            frames.camera, stage_refine_options(options, options.steps, poses=True))
    if options.canonical:
        # x_cam = R x + t = R P^T x' + (t + R c): the poses follow the body frame.
        frame, centre = canonical_frame(assembly)
        assembly = reframed(assembly, frame, centre)
        translation = translation + rotation @ centre
        rotation = rotation @ frame.T
    return SequencePrediction(
        assembly=assembly, rotation=rotation, translation=translation,
        quaternion=matrix_to_quaternion(rotation), frames=frames, reference=reference,
        half_turns=turns, iou=ious, frame_iou=fit.iou.clone(), steps=steps, poses=poses,
        seconds=time.perf_counter() - started, losses=losses, frames_seconds=frames_seconds)
