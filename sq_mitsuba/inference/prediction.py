"""What the predictor returns: :class:`Prediction` (assemblies and poses of a batch of images),
for a prediction fitted to the images' masks :class:`Fit` (what was fitted), and for N frames
of one spacecraft :class:`SequencePrediction` (one assembly, every pose).

Convention: poses map body to camera in the OpenCV frame (x right, y down, z forward),
``x_cam = R x_body + t``; quaternions are scalar-first with w >= 0; pixels are continuous
(the centre of pixel (i, j) is (j + 0.5, i + 0.5) in (u, v)).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera

__all__ = ["MASK_SOURCES", "Fit", "MaskChoice", "Prediction", "SequencePrediction"]

#: Where the mask a prediction was fitted to came from: the network's mask head, the threshold
#: segmentation of the image (:func:`sq_mitsuba.data.segmentation.segment_target`), or the
#: caller (a mask file, the ground truth).
MASK_SOURCES = ("network", "segmentation", "given")
#: The mask a prediction is fitted to: "network" (the mask head; the segmentation for a network
#: without one), "segmentation", or the masks themselves, (B, H, W) bool, float in [0, 1]
#: (above 0.5 is the target) or integer (non-zero is the target: a 0/255 uint8 mask reads as
#: it looks), a tensor or numpy array; None: "network".
MaskChoice = str | Tensor | np.ndarray | None


def _one_factor(factor: object) -> float:
    """``factor`` as one number (a 0-d tensor's value), or a one-line ``ValueError``: a
    prediction's lengths scale as one (the number itself is checked by
    :meth:`~sq_mitsuba.geometry.assembly.Assembly.scaled`)."""
    if isinstance(factor, Tensor) and factor.dim() == 0 and not factor.is_complex() \
            and factor.dtype != torch.bool:
        return float(factor)
    if isinstance(factor, Tensor) or isinstance(factor, bool) \
            or not isinstance(factor, numbers.Real):
        got = f"a tensor of shape {tuple(factor.shape)}" if isinstance(factor, Tensor) \
            else repr(factor)
        raise ValueError(f"factor: expected one number for the whole batch (the target's "
                         f"longest side in metres), got {got}")
    return float(factor)  # a Fraction or Decimal scaled the assembly, then failed on a tensor


@dataclass(frozen=True)
class Fit:
    """What :meth:`~sq_mitsuba.inference.predictor.Predictor.refine` fitted, for B images.

    Items not fitted (``fitted`` False: the image shows no target by its ``target_score``, or
    its mask is empty) are not searched: their pose is the search's start and their scores
    are NaN. A mask the caller gives is fitted whatever the target score.

    Attributes:
        mask: (B, H, W) bool, the mask each image was fitted to, at the images' size.
        mask_source: one of :data:`MASK_SOURCES`.
        fitted: (B,) bool, whether the item was searched and refined: its mask has a target,
            and (for the network's mask or the segmentation) the image shows a target
            (``Prediction.target``).
        start: the reading the search started from: the network's, or its means over turned
            copies of the images (``turns``).
        turns: the in-plane turns ``start`` was read from (1: the network's one pass).
        search_rotation: (B, 3, 3) and search_translation: (B, 3), the search's best pose
            (before the refinement).
        search_score: (B,) its soft IoU against the mask at the search resolution.
        candidates: (B, N, 3, 3) every rotation the search scored, and candidate_scores:
            (B, N) their soft IoUs at the coarse resolution (NaN rows where not fitted).
        iou: (B,) the IoU after refinement at the refinement resolution.
        turns_seconds, search_seconds, seconds: wall time of reading the turned copies, of
            the search with them (its start is their reading), and of the whole fit.
    """

    mask: Tensor
    mask_source: str
    fitted: Tensor
    start: Prediction
    turns: int
    search_rotation: Tensor
    search_translation: Tensor
    search_score: Tensor
    candidates: Tensor
    candidate_scores: Tensor
    iou: Tensor
    turns_seconds: float = 0.0
    search_seconds: float = 0.0
    seconds: float = 0.0


@dataclass(frozen=True)
class Prediction:
    """What :meth:`~sq_mitsuba.inference.predictor.Predictor.predict` returns for a batch of B
    images: the network's reading, or (``refine=True``) the pose searched and refined against
    each image's mask, with the network's own reading in ``network``.

    Tensors are ordinary tensors without gradient (computed under ``torch.inference_mode``,
    then copied out of it), so they may start an autograd computation such as refinement.

    Attributes:
        assembly: the B assemblies of M superquadrics, in the body frame. For a network with
            existence probabilities, the primitives each item keeps (``primitive_index``):
            (B, W, 16), W the most any item keeps, an item keeping fewer padded with
            invisible stand-ins (:mod:`sq_mitsuba.model.existence`); :meth:`item_assembly`
            gives one item's own primitives.
        rotation: (B, 3, 3) body -> camera rotation.
        translation: (B, 3) body origin in the camera frame (metres, for a target whose
            longest side is ``scale`` metres).
        quaternion: (B, 4) ``rotation`` as (w, x, y, z), w >= 0.
        pixel: (B, 2) image position (u, v) of the body origin, in pixels of the given images.
        depth: (B,) camera-frame z of the body origin (``translation[:, 2]``).
        camera: intrinsics of the given images (after any rescaling of the camera passed in).
        rotation_hypotheses: (B, K, 3, 3) distinct candidate rotations, best first: the modes
            of a distribution head (K = the predictor's ``hypotheses``), or ``rotation``
            alone (K = 1) for a regressing head. On a fitted prediction they, the scores, the
            mask and the log-probabilities stay the search's start's (float32, where the
            fitted pose and assembly are float64): the fitted ``rotation`` is none of them.
        rotation_scores: (B, K) the network's probability of each hypothesis (1 for a
            regressing head's single one).
        mask: (B, H, W) the mask head's probability that a pixel of the given images shows
            the target, or None for a network without a mask head.
        rotation_log_probabilities: (B, G) a distribution head's normalised log-probabilities
            over its grid of G rotations (read from turned copies where ``rotation`` is), or
            None for a regressing head.
        network: the network's own reading of the images (one pass, no turned copies) when
            this prediction was fitted to the images' masks; None when it is that reading.
        fit: what was fitted (:class:`Fit`: the masks, the search's candidates and scores, the
            IoU after refinement), or None for the network's reading.
        target_score: (B,) in [0, 1], how sure the predictor is that each image shows a
            target at all (:func:`~sq_mitsuba.inference.images.target_scores`: the mask
            head's most confident pixel, or the segmentation's for a network without a mask
            head, and 0 for an image of noise); from the network's one pass, also when the
            rest is read from turned copies.
        target: (B,) bool, ``target_score >= min_target`` (the predictor's threshold, 0.92 by
            default): the images that show a target. The others' assembly and pose are the
            network's output for an image without one, meaningless; ``refine`` does not fit
            them.
        fingerprint: (B, C, 8, 8) the network's input averaged over 8 x 8 blocks, with which
            ``read_turns`` and ``refine`` check that they are given the images this reading
            was made from.
        existence: (B, M) the network's probability that each of its M primitives exists
            (the copies' mean where the reading is from turned copies), or None for a network
            without existence probabilities.
        primitive_index: (B, W) int64, the network's primitive behind each row of
            ``assembly`` (those whose existence reaches the predictor's ``min_existence``,
            and each item's most probable one, in the network's order), -1 for a stand-in;
            None for a network without existence probabilities (every primitive, in order).
        primitives: (B, M, 16) all M of the network's primitives, kept or not, that
            ``primitive_index`` picks from (the copies' means where the reading is from turned
            copies, which decide anew which to keep); None for a network without existence
            probabilities (``assembly`` holds them all) and for a fitted prediction (its
            ``network`` and ``fit.start`` hold theirs).
        turns: the in-plane turned copies of each image the reading is from (1: one pass;
            a fitted prediction keeps its start's).
        scale: the target's longest side in metres that the lengths are for: 1, the unit
            size the network reads every target at, unless :meth:`scaled` set it.
    """

    assembly: Assembly
    rotation: Tensor
    translation: Tensor
    quaternion: Tensor
    pixel: Tensor
    depth: Tensor
    camera: Camera
    rotation_hypotheses: Tensor
    rotation_scores: Tensor
    mask: Tensor | None = None
    rotation_log_probabilities: Tensor | None = None
    network: Prediction | None = None
    fit: Fit | None = None
    target_score: Tensor | None = None
    target: Tensor | None = None
    fingerprint: Tensor | None = None
    existence: Tensor | None = None
    primitive_index: Tensor | None = None
    primitives: Tensor | None = None
    turns: int = 1
    scale: float = 1.0

    def __repr__(self) -> str:  # the fields hold whole images and grids: a summary
        kind = "network reading" if self.fit is None else "fitted"
        return (f"Prediction({self.rotation.shape[0]} images of {self.camera.width} x "
                f"{self.camera.height}, {kind}, assembly={self.assembly!r}, "
                f"turns={self.turns}, scale={self.scale:g})")

    def scaled(self, factor: float) -> Prediction:
        """This prediction for a target ``factor`` times the size the network assumes.

        Convention: the network reads every target at the dataset's unit size (the longest
        side of its aligned box 1), so its translations are metres for a target 1 m long. A
        target L metres long at the same pose is the whole scene scaled by L about the camera:
        the assembly and every translation and depth scale, the images stay the same (one
        camera cannot tell a larger target farther away), so ``scaled(L)`` is the metric
        reading when L is known. Rotations, pixels, masks and scores stay; the network's own
        reading and the fit's start and search pose are scaled alike, and ``scale`` records
        the factor (times any before). Apply it last: the predictor's ``refine`` and
        ``read_turns`` refuse a scaled reading (they work at the network's unit size).

        Args:
            factor: the target's longest side in metres (a finite number > 0; one for the
                whole batch).

        Raises:
            ValueError: one line naming ``factor`` when it is not a finite number > 0.
        """
        factor = _one_factor(factor)
        assembly = self.assembly.scaled(factor)  # checks the number before any other work
        primitives = None if self.primitives is None else \
            Assembly(self.primitives).scaled(factor).params
        network = None if self.network is None else self.network.scaled(factor)
        fit = None if self.fit is None else replace(
            self.fit, start=self.fit.start.scaled(factor),
            search_translation=self.fit.search_translation * factor)
        return replace(self, assembly=assembly, translation=self.translation * factor,
                       depth=self.depth * factor, network=network, fit=fit, primitives=primitives,
                       scale=self.scale * float(factor))

    def item_assembly(self, item: int) -> Assembly:
        """Batch item ``item``'s assembly (batch size 1) without stand-ins: its own
        primitives, what its files hold.

        Raises:
            IndexError: naming ``item`` outside the batch.
        """
        item = self.assembly._item(item, "item")  # an IndexError naming the item
        own = self.assembly[item]  # (1, W, 16)
        if self.primitive_index is None:
            return own
        real = self.primitive_index[item] >= 0
        return Assembly(own.params[:, real.to(own.params.device)])


@dataclass(frozen=True)
class SequencePrediction:
    """One assembly and N poses from N images of one spacecraft.

    Attributes:
        assembly: the shared assembly (batch size 1), in the body frame.
        rotation: (N, 3, 3) body -> camera rotation of each frame; translation: (N, 3).
        quaternion: (N, 4) ``rotation`` as (w, x, y, z), w >= 0.
        frames: the frames' own fitted readings (the shipped path, before the joint fit): one
            :class:`Prediction` whose batch is the N frames.
        reference: index of the frame whose body frame is the result's (before
            ``SequenceOptions.canonical``'s change of frame, which these two do not follow).
        half_turns: (N, 3, 3) the half turn S_j that carries frame j's reading into the
            reference body frame (``x_ref = S_j x_j``): for a frame that agrees with the
            pass's motion or given rotations, ``R_j S_j`` is its rotation there or the
            nearest to it; for a frame the motion replaced, its shape's half turn.
        iou: (N,) IoU of each frame's silhouette against its mask after the joint fit (at the
            fit's resolution; a frame the fit lost and that was placed again, its refit's:
            :mod:`~sq_mitsuba.inference.lost_frames`); frame_iou: (N,) the same of each
            frame's own fit (at its refinement's resolution).
        poses: what set the frames' rotations relative to each other: "motion" (frames in
            order kept on one constant-rate turn that enough of their readings agree with),
            "motion start" (``motion="start"``: the frames that disagree start from it, then
            every frame moves alone), "given" (the relative rotations passed in) or
            "readings" (each frame's own: unordered frames, ``motion="free"``, or a pass
            whose readings agree on no one turn).
        steps: Adam steps taken; seconds: wall time of the whole sequence (frames included);
            frames_seconds: of the frames' own path alone (network, search, refinement).
        scale: the target's longest side in metres the lengths are for (1: the network's
            unit size; :meth:`scaled`).
    """

    assembly: Assembly
    rotation: Tensor
    translation: Tensor
    quaternion: Tensor
    frames: Prediction
    reference: int
    half_turns: Tensor
    iou: Tensor
    frame_iou: Tensor
    steps: int = 0
    seconds: float = 0.0
    losses: list[float] = field(default_factory=list)
    poses: Literal["motion", "motion start", "given", "readings"] = "readings"
    frames_seconds: float = 0.0
    scale: float = 1.0

    def __repr__(self) -> str:
        return (f"SequencePrediction({self.rotation.shape[0]} frames, assembly="
                f"{self.assembly!r}, reference={self.reference}, steps={self.steps}, "
                f"scale={self.scale:g})")

    def scaled(self, factor: float) -> SequencePrediction:
        """This result for a target ``factor`` times the size the network assumes: the shared
        assembly, every translation and the frames' own predictions scaled
        (:meth:`Prediction.scaled`: the metric result when the target's longest side in
        metres is known; the images cannot tell it).

        Raises:
            ValueError: one line naming ``factor`` when it is not a finite number > 0.
        """
        factor = _one_factor(factor)
        return replace(self, assembly=self.assembly.scaled(factor),
                       translation=self.translation * factor,
                       frames=self.frames.scaled(factor), scale=self.scale * float(factor))

