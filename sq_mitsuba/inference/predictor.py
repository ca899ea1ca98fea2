"""Inference API: images of any size in, superquadric assemblies and camera-frame poses out.

:class:`Predictor` wraps a trained :class:`~sq_mitsuba.model.network.SuperquadricNet` and
the camera the images were taken with; :func:`sq_mitsuba.load_model` builds one from a
checkpoint. Example::

    predictor = sq_mitsuba.load_model("run/checkpoint.pt")
    prediction = predictor.predict(images)          # (B, H, W) uint8 or float in [0, 1]
    prediction.item_assembly(0).export("item0.glb")  # image 0's own primitives
    prediction.rotation, prediction.translation     # x_cam = R x_body + t
    prediction.rotation_hypotheses                  # (B, K, 3, 3), best first
    prediction.mask                                 # (B, H, W) in [0, 1], or None
    prediction.target, prediction.target_score      # (B,) does each image show a target?
    predictor.predict(images, turns=8).rotation     # read from 8 in-plane turns (grid head)
    predictor.read_turns(images, prediction, 8)     # the same, reusing the unturned pass
    fitted = predictor.predict(images, refine=True)  # pose searched and refined to the mask
    fitted.network, fitted.fit.iou                  # the network's reading; what was fitted

Convention:
    - Images are resized to the network's S x S input (``config.image_size``) by antialiased
      bilinear interpolation, the training images' filter
      (:func:`~sq_mitsuba.inference.images.resize_images`). Pixel edges scale with the
      image, so the intrinsics follow by :meth:`~sq_mitsuba.geometry.camera.Camera.rescaled`;
      a non-square image is stretched to S x S and its intrinsics stretch with it, so the pose
      stays consistent (though the network was trained on unstretched squares).
    - A camera for another image size with the same aspect ratio is taken to have the same
      field of view and is rescaled to the images' size first.
    - Poses map body to camera in the OpenCV frame (x right, y down, z forward):
      ``x_cam = R x_body + t``; quaternions are scalar-first with w >= 0.
    - Every image gets a target-present score (``Prediction.target_score``, see
      :func:`~sq_mitsuba.inference.images.target_scores`); an image scoring below the
      predictor's ``min_target`` shows no target (``Prediction.target`` False): its assembly
      and pose mean nothing, and ``refine`` does not fit it.
    - A network with existence probabilities: a prediction drops the primitives whose
      probability is below the predictor's ``min_existence`` (each item keeps its most
      probable one) before the search, the refinement or any file see it; a reading from
      turned copies, by their mean probability (an image rolled by one of the turns alike;
      the copies are combined in :mod:`~sq_mitsuba.inference.turned_copies`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from sq_mitsuba.checks import check_int, check_switch, python_scalar
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.image_turns import check_rotation_exact, z_rotation
from sq_mitsuba.geometry.rotation import matrix_to_quaternion
from sq_mitsuba.inference.images import (
    DEFAULT_MIN_TARGET,
    camera_for,
    check_camera,
    check_min_target,
    prepare_images,
    resize_images,
    target_scores,
)
from sq_mitsuba.inference.prediction import Fit, MaskChoice, Prediction, SequencePrediction
from sq_mitsuba.inference.traced import RUN_CHUNK, TracedNetwork, run_in_chunks
from sq_mitsuba.inference.turned_copies import (
    check_turns_memory,
    hypotheses_from_logits,
    reading_from_turns,
    turn_angles,
    turned_images,
)
from sq_mitsuba.model.existence import EXISTENCE_THRESHOLD, gathered_primitives, kept_primitives
from sq_mitsuba.model.network import NetworkOutput, SuperquadricNet
from sq_mitsuba.model.rotation_grid import RotationGridPoseHead, turned_cells

if TYPE_CHECKING:  # the search and refinement load Mitsuba's bridge: imported when used
    from sq_mitsuba.inference.refine import RefineOptions
    from sq_mitsuba.inference.search import SearchOptions
    from sq_mitsuba.inference.sequence import SequenceOptions

__all__ = ["Prediction", "Predictor", "prepare_images"]

#: Rotation hypotheses a Predictor gives per image by default (distribution heads).
DEFAULT_HYPOTHESES = 8
#: The existence probability from which a prediction keeps a primitive, by default.
DEFAULT_MIN_EXISTENCE = EXISTENCE_THRESHOLD
# Side of Prediction.fingerprint (blocks of the network input), and the largest difference
# of a block's mean at which two inputs are the same images (a fifth of an 8-bit grey level:
# the same pixels given as uint8 or float differ by rounding, 1e-7).
_FINGERPRINT_SIDE = 8
_FINGERPRINT_TOLERANCE = 1e-3


class _Prepared(NamedTuple):
    """Images ready for the network, and their given size (for the mask's and pixel's scale)."""

    images: Tensor  # (B, C, S, S) on the network's device and dtype
    height: int
    width: int
    checked: Tensor  # (B, C, H, W) float in [0, 1], the images at their own size


class Predictor:
    """A trained network and its camera, ready to predict.

    Args:
        model: the network; used in eval mode (its own mode is restored after each call).
        camera: intrinsics of the images :meth:`predict` gets by default (the dataset camera).
        fast: predict with a BatchNorm-folded, channels-last copy of the network (the same
            output up to ~1e-5 relative; faster on CPU; folding takes about 0.1 s). The copy
            is a snapshot of the weights now.
        traced: with ``fast``, run the folded copy through a TorchScript trace, made once per
            input shape. Convention: off by default. A trace costs 0.7-2.6 s per shape and
            saves about a quarter of the network's time at batch 1 (13 against 18 ms, 96 px,
            2 cores) and nothing at batch 7 (the 8-turn reading's turned copies): it pays
            for a stream of hundreds of single frames, not for a few images or batches.
        hypotheses: K, the rotation hypotheses per image of a distribution head.
        min_target: the target-present score from which an image shows a target
            (``Prediction.target``; see :func:`~sq_mitsuba.inference.images.target_scores`
            for how the default, 0.92, was chosen); 0 takes every image for one.
        min_existence: for a network with existence probabilities, the probability from
            which a prediction keeps a primitive (an item keeps its most probable one
            whatever it is); 0 keeps every primitive. Unused by other networks.
    """

    def __init__(self, model: SuperquadricNet, camera: Camera, fast: bool = False,
                 traced: bool = False, hypotheses: int = DEFAULT_HYPOTHESES,
                 min_target: float = DEFAULT_MIN_TARGET,
                 min_existence: float = DEFAULT_MIN_EXISTENCE) -> None:
        if not isinstance(model, SuperquadricNet):
            raise ValueError(f"model: expected a SuperquadricNet, got {type(model).__name__}")
        if not isinstance(camera, Camera):
            raise ValueError(f"camera: expected a Camera, got {type(camera).__name__}")
        hypotheses = check_int("hypotheses", hypotheses)
        self.min_target = check_min_target(min_target)
        self.min_existence = check_min_target(min_existence, "min_existence")
        self.model = model
        self.camera = camera
        if traced and not fast:
            raise ValueError("traced: traces the folded network of the fast path; give "
                             "fast=True too")
        self.fast = bool(fast)
        self.traced = bool(traced)
        self.hypotheses = hypotheses
        self._folded = model.folded(channels_last=True) if self.fast else None
        self._traced = TracedNetwork(self._folded) if self.traced else None
        # turned_cells of the grid per (turns, device), for predict(turns=T).
        self._turned_cells: dict[tuple, Tensor] = {}
        #: The checkpoint the model came from (set by ``load_model``), for records.
        self.source: Path | None = None
        #: The trivial baseline stored with the checkpoint (set by ``load_model``), or None:
        #: the mean raw output (1, M, 16) of the network over training images, with the mean
        #: rotation (1, 3, 3) and translation (1, 3) of their labels.
        self.baseline: tuple[Tensor, Tensor, Tensor] | None = None

    def __repr__(self) -> str:
        device = next(self.model.parameters()).device
        return (f"Predictor(source={str(self.source) if self.source else None!r}, "
                f"image_size={self.image_size}, camera={self.camera.width} x "
                f"{self.camera.height}, device={device}, fast={self.fast}, "
                f"min_target={self.min_target:g})")

    @property
    def image_size(self) -> int:
        """Side S of the network's square input."""
        return self.model.config.image_size

    @property
    def num_primitives(self) -> int:
        """M, the superquadrics the network predicts per image (before existence drops any)."""
        return self.model.config.num_primitives

    def predict(self, images: Tensor | np.ndarray, camera: Camera | None = None, *,
                turns: int | None = None, refine: bool = False, mask: MaskChoice = None,
                search: SearchOptions | None = None,
                refinement: RefineOptions | None = None) -> Prediction:
        """Predict assemblies and poses for a batch of images.

        Args:
            images: (B, H, W) or (B, 1, H, W) (C = ``in_channels``), uint8 or float in [0, 1],
                any H, W (see the module docstring for the resizing).
            camera: intrinsics of these images (default: the predictor's camera); a camera for
                another size of the same aspect ratio is rescaled.
            turns: T >= 1; with T > 1 (a distribution head only) the rotation and its
                hypotheses come from T copies of each image turned in-plane by 360 / T deg
                steps, their distributions mapped back and multiplied
                (:func:`~sq_mitsuba.model.rotation_grid.turned_log_probabilities`): T times
                the network's cost. The assembly, the image position, the depth and the mask
                are the means over the T copies, each mapped back to the image (test-time
                augmentation). Needs a camera whose roll is a rotation of the network's
                S x S input: the principal point at the image centre and fx / W = fy / H
                (fx = fy once stretched to S x S; so a non-square image with square pixels
                cannot turn). None: 1, or with ``refine`` the search's ``turns`` (8 by
                default) where this network and camera can turn, else 1.
            refine: fit the pose to each image's mask: the turned copies' reading, the global
                pose search by render and compare and the refinement through Mitsuba
                silhouettes (:mod:`~sq_mitsuba.inference.pipeline`; about 0.7 s an image
                on 2 CPU cores, ``bench eval``). The result's ``network`` is the network's own
                reading, its ``fit`` what was fitted.
            mask: with ``refine``, the mask to fit: "network" (default: the mask head, or the
                segmentation for a network without one), "segmentation" (the threshold
                segmentation of the image), or masks (B, H, W): bool, float in [0, 1]
                (above 0.5 is the target) or integer (non-zero is the target).
            search, refinement: with ``refine``, the search's and the refinement's settings
                (defaults: :class:`~sq_mitsuba.inference.search.SearchOptions` and
                :data:`~sq_mitsuba.inference.search.SEARCH_REFINEMENT`).

        Returns:
            :class:`Prediction` on the model's device (fitted: the pose and assembly float64,
            on the CPU).

        Raises:
            ValueError: naming ``images``, ``camera``, ``turns``, ``refine``, ``mask``, or
                ``search`` / ``refinement`` (or their field: ``search.turns``).
        """
        refine, turns = check_switch("refine", refine), python_scalar(turns)
        if not refine:
            unused = [name for name, value in (("mask", mask), ("search", search),
                                               ("refinement", refinement)) if value is not None]
            if unused:
                raise ValueError(f"{unused[0]}: only used with refine=True")
        else:  # the fit's settings, checked before the network runs
            from sq_mitsuba.inference.pipeline import fit_options

            search, refinement = fit_options(search, refinement)
        x, camera = self._prepared(images, camera)
        if turns is not None:
            self.check_turns(turns, camera)
        network = self._predicted(x, camera)
        if refine:
            from sq_mitsuba.inference.pipeline import fit_prediction

            return fit_prediction(self, x.checked, network, turns=turns, mask=mask,
                                  search=search, refinement=refinement)
        return network if turns is None or turns == 1 else self._with_turns(x, network, turns)

    def refine(self, images: Tensor | np.ndarray, network: Prediction,
               camera: Camera | None = None, *, turns: int | None = None,
               mask: MaskChoice = None, search: SearchOptions | None = None,
               refinement: RefineOptions | None = None, reuse: Fit | None = None) -> Prediction:
        """``predict(images, camera, refine=True, ...)`` for a caller that holds the network's
        reading already: ``network`` (this predictor's ``predict(images, camera)``) searched and
        refined against each image's mask; the network is not run again (but for the turned
        copies).

        Args:
            reuse: an earlier fit of the same images and reading (its ``fit``), whose turned
                copies are reused: to fit another mask (the ground truth's, say) at the cost of
                the search alone.
            The others: see :meth:`predict`.

        Raises:
            ValueError: naming ``images``, ``camera``, ``turns``, ``mask``, ``network``,
                ``reuse``, or ``search`` / ``refinement`` (or their field).
        """
        from sq_mitsuba.inference.pipeline import fit_prediction

        turns = python_scalar(turns)
        x, camera = self._prepared(images, camera)
        count = x.images.shape[0]
        _check_unit_scale(network=network, reuse=getattr(reuse, "start", None))
        if not isinstance(network, Prediction) or network.fit is not None \
                or network.camera != camera or network.rotation.shape[0] != count:
            raise ValueError(f"network: expected this predictor's own reading of the "
                             f"{count} images ({camera.width} x {camera.height} px, "
                             "this camera)")
        if network.turns != 1:  # the fit reads the turned copies itself, from the one pass
            raise ValueError(f"network: read from {network.turns} turned copies; pass the "
                             "one-pass reading (predict(images) without turns), and turns here")
        if not self._same_images(network, x):
            raise ValueError(f"network: a reading of other images than these {count} (its "
                             "fingerprint differs); read these with predict(images)")
        if reuse is not None and not (isinstance(reuse, Fit) and turns in (None, reuse.turns)
                                      and self._same_images(reuse.start, x)
                                      and reuse.start.camera == camera):
            raise ValueError(f"reuse: expected the fit of these {count} images under this "
                             "camera, from as many turned copies as turns asks (its start's "
                             "fingerprint or camera differs)")
        if turns is not None:  # as predict checks it
            self.check_turns(turns, camera)
        return fit_prediction(self, x.checked, network, turns=turns, mask=mask, search=search,
                              refinement=refinement, reuse=reuse)

    def predict_sequence(self, images: Tensor | np.ndarray, camera: Camera | None = None, *,
                         relative_rotations: Tensor | np.ndarray | None = None,
                         ordered: bool = False, mask: MaskChoice = None,
                         options: SequenceOptions | None = None,
                         search: SearchOptions | None = None,
                         refinement: RefineOptions | None = None,
                         progress: bool = False) -> SequencePrediction:
        """One assembly and every pose from N >= 2 images of the same spacecraft: each frame
        read by the shipped path, the half turns resolved across frames, then one shape and N
        poses fitted to every frame's mask at once
        (:func:`~sq_mitsuba.inference.sequence.predict_sequence` documents every argument;
        ``SequenceOptions`` is :class:`sq_mitsuba.inference.sequence.SequenceOptions`).

        Returns:
            A :class:`~sq_mitsuba.inference.prediction.SequencePrediction`.
        """
        from sq_mitsuba.inference.sequence import predict_sequence

        return predict_sequence(self, images, camera, relative_rotations=relative_rotations,
                                ordered=ordered, mask=mask, options=options, search=search,
                                refinement=refinement, progress=progress)

    def read_turns(self, images: Tensor | np.ndarray, prediction: Prediction, turns: int,
                   camera: Camera | None = None) -> Prediction:
        """``prediction`` (this predictor's, for ``images``) read again from ``turns`` in-plane
        turns of the images: equal to ``predict(images, camera, turns=turns)`` (see there),
        but the unturned copy is not run again (a caller that needs both readings pays T, not
        T + 1, network passes).

        Raises:
            ValueError: naming ``images``, ``camera``, ``turns`` or ``prediction``.
        """
        turns = python_scalar(turns)
        x, camera = self._prepared(images, camera)
        self.check_turns(turns, camera)  # 1 runs for every network and camera, as in predict
        count = x.images.shape[0]
        _check_unit_scale(prediction=prediction)
        log_p = getattr(prediction, "rotation_log_probabilities", None)
        # This predictor's reading has log-probabilities over its grid exactly when its head
        # is a distribution head (a regressing head's, read with turns=1, has none).
        cells = (count, self.model.config.rotation_cells) \
            if isinstance(self.model.pose_head, RotationGridPoseHead) else None
        if not isinstance(prediction, Prediction) or prediction.turns != 1 \
                or (None if log_p is None else tuple(log_p.shape)) != cells \
                or prediction.camera != camera or prediction.fit is not None \
                or (prediction.existence is None) != (prediction.primitives is None):
            raise ValueError(f"prediction: expected this predictor's one-pass reading of the "
                             f"{count} images ({camera.width} x {camera.height} px, this camera)")
        if not self._same_images(prediction, x):
            raise ValueError(f"prediction: a reading of other images than these {count} (its "
                             "fingerprint differs); read these with predict(images)")
        return prediction if turns == 1 else self._with_turns(x, prediction, turns)

    def _prepared(self, images: Tensor | np.ndarray,
                  camera: Camera | None) -> tuple[_Prepared, Camera]:
        """Checked images resized to the network's input (B, C, S, S), on its device and
        dtype, and the camera of the given images."""
        x = prepare_images(images, self.model.config.in_channels)
        height, width = x.shape[-2:]
        try:  # a user's camera checked first (the predictor's own was when it was loaded)
            camera = camera_for(self.camera if camera is None else check_camera(camera),
                                width, height)
        except ValueError:
            if camera is not None:
                raise
            raise ValueError(f"camera: none given, and the predictor's camera is for "
                             f"{self.camera.width} x {self.camera.height} images, the images are "
                             f"{width} x {height} (another aspect ratio); pass theirs, e.g. "
                             f"Camera.from_fov(fov_x_deg, {width}, {height})") from None
        parameter = next(self.model.parameters())
        resized = resize_images(x.to(device=parameter.device, dtype=parameter.dtype),
                                self.image_size)
        return _Prepared(resized, height, width, x), camera

    @staticmethod
    def _fingerprint(x: _Prepared) -> Tensor:
        """(B, C, 8, 8) the network input averaged over 8 x 8 blocks, float32 on the CPU."""
        return F.adaptive_avg_pool2d(x.images.detach().float(), _FINGERPRINT_SIDE).cpu()

    def _same_images(self, prediction: Prediction, x: _Prepared) -> bool:
        """Whether ``prediction`` was read from the images ``x`` (by its fingerprint; True for
        a Prediction without one)."""
        stored = prediction.fingerprint
        if stored is None:
            return True
        mine = self._fingerprint(x)
        return tuple(stored.shape) == tuple(mine.shape) and \
            float((stored.float().cpu() - mine).abs().max()) <= _FINGERPRINT_TOLERANCE

    def _predicted(self, x: _Prepared, camera: Camera) -> Prediction:
        """The unturned network pass on prepared images, as a :class:`Prediction`."""
        size = self.image_size
        matrix = camera.rescaled(size, size).matrix(x.images.dtype, x.images.device)
        output = self._run(x.images, matrix)
        # Clones made outside inference mode are ordinary tensors, so callers (test-time
        # refinement) can start autograd from them.
        rotation = output.rotation.clone()
        hypotheses, scores = hypotheses_from_logits(self.model.pose_head, output.rotation_logits,
                                                    rotation, self.hypotheses)
        mask = None
        if output.mask_logits is not None:
            mask = F.interpolate(output.mask_logits.clone(), size=(x.height, x.width),
                                 mode="bilinear", align_corners=False).sigmoid()[:, 0]
        log_p = None
        if output.rotation_logits is not None:
            log_p = output.rotation_logits.float().log_softmax(dim=-1).to(rotation)
        scale = rotation.new_tensor([x.width / size, x.height / size])
        score = target_scores(x.images, output.mask_logits, x.checked).to(rotation)
        params = output.assembly.params.clone()
        existence, rows, primitives = output.existence, None, None
        if existence is not None:
            existence, primitives = existence.clone(), params
            rows = kept_primitives(existence, self.min_existence)
            params = gathered_primitives(params, rows)
        return Prediction(
            assembly=Assembly(params),
            rotation=rotation,
            translation=output.translation.clone(),
            quaternion=matrix_to_quaternion(rotation),
            pixel=output.pixel.clone() * scale,
            depth=output.depth.clone(),
            camera=camera,
            rotation_hypotheses=hypotheses,
            rotation_scores=scores,
            mask=mask,
            rotation_log_probabilities=log_p,
            target_score=score,
            target=score >= self.min_target,
            fingerprint=self._fingerprint(x),
            existence=existence,
            primitive_index=rows,
            primitives=primitives,
        )

    def can_turn(self, camera: Camera | None = None) -> bool:
        """Whether ``predict(turns=T > 1)`` runs for images of ``camera`` (default: the
        predictor's): a distribution head, and a camera whose roll is an image rotation."""
        try:
            self.check_turns(2, camera)
        except ValueError:
            return False
        return True

    def check_turns(self, turns: int, camera: Camera | None = None, images: int = 1) -> None:
        """One-line ``ValueError`` naming ``turns`` unless ``predict(turns=turns)`` runs for
        ``images`` images of ``camera`` (default: the predictor's) a call, memory included, so
        that a caller can refuse it before any work; 1 runs for every network and camera."""
        if type(turns) is int and turns == 1:  # True == 1, but is no count
            return
        self._check_turns(turns, self.camera if camera is None else camera)
        check_turns_memory(check_int("images", images), turns)

    def _check_turns(self, turns: int, camera: Camera) -> None:
        """One-line ``ValueError`` naming ``turns`` unless ``predict(turns=T)`` can run for
        images of ``camera`` (at their own size)."""
        turns = check_int("turns", turns, 1, 360)
        if not isinstance(self.model.pose_head, RotationGridPoseHead):
            raise ValueError("turns: reading the rotation from turned copies needs a "
                             "rotation-distribution head (network.pose_head = 'grid')")
        side = self.image_size
        stretched = camera.rescaled(side, side)  # the camera of the network's input
        try:
            check_rotation_exact(stretched)
        except ValueError:
            # The copies turn the S x S input: the stretched camera is the one that must roll.
            raise ValueError(
                f"turns: the images' camera ({camera.width} x {camera.height} px, fx "
                f"{camera.fx:g}, fy {camera.fy:g}, principal point ({camera.cx:g}, "
                f"{camera.cy:g})) stretched to the network's {side} x {side} input has fx "
                f"{stretched.fx:g}, fy {stretched.fy:g}, principal point ({stretched.cx:g}, "
                f"{stretched.cy:g}); turned copies need fx = fy and the principal point at "
                f"({side / 2:g}, {side / 2:g}) there: use turns=1 (predict --turns 1)") from None

    def _run(self, x: Tensor, matrix: Tensor) -> NetworkOutput:
        """The network (eager, or a fast path) on prepared images, in eval mode; more than
        ``RUN_CHUNK`` of them in chunks (:func:`~sq_mitsuba.inference.traced.run_in_chunks`)."""
        if x.shape[0] > RUN_CHUNK:
            return run_in_chunks(self._run, x, matrix, RUN_CHUNK)
        network = self.model
        if self._traced is not None:
            with torch.inference_mode():
                return self._traced(x, matrix)
        if self._folded is not None:  # a copy of its own, always in eval mode
            with torch.inference_mode():
                return self._folded(x, matrix)
        was_training = network.training
        try:
            with torch.inference_mode():
                return network.eval()(x, matrix)
        finally:
            network.train(was_training)

    def _with_turns(self, x: _Prepared, prediction: Prediction, turns: int) -> Prediction:
        """``prediction`` (the unturned pass on ``x``) read again from ``turns`` in-plane
        turns of ``x`` (:mod:`~sq_mitsuba.inference.turned_copies`)."""
        head, side = self.model.pose_head, self.image_size
        angles = turn_angles(turns)
        key = (turns, x.images.device)
        if key not in self._turned_cells:
            self._turned_cells[key] = turned_cells(head.grid_rotations(), z_rotation(angles))
        matrix = prediction.camera.rescaled(side, side).matrix(x.images.dtype, x.images.device)
        output = self._run(turned_images(x.images, angles), matrix)
        return reading_from_turns(prediction, output, angles, self._turned_cells[key], head,
                                  side=side, width=x.width, height=x.height,
                                  min_existence=self.min_existence, hypotheses=self.hypotheses)


def _check_unit_scale(**readings: object) -> None:
    """One-line ``ValueError`` naming a reading ``Prediction.scaled`` made (fits need unit size)."""
    for name, reading in readings.items():
        if isinstance(reading, Prediction) and reading.scale != 1.0:
            raise ValueError(f"{name}: scaled to a target of {reading.scale:g} m "
                             "(Prediction.scaled); refine the unit-size reading, then scale")
