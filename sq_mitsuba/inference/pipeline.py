"""The shipped path from images to poses fitted to them, in one place.

``Predictor.predict(images, refine=True)`` (and ``Predictor.refine`` for a caller that already
holds the network's reading) runs, for a batch of B images:

1. the network's reading of each image (one pass);
2. the same read again from ``turns`` in-plane turns of the image
   (:meth:`~sq_mitsuba.inference.predictor.Predictor.read_turns`: the rotation and its
   hypotheses from the copies' product, the assembly, position and mask as their means, the
   primitives kept by their mean existence), when
   the network has a rotation-distribution head and the camera's roll is an image rotation;
3. the mask to fit: the mask head's (the turned copies' mean, above 0.5), or the threshold
   segmentation of the image (:func:`~sq_mitsuba.data.segmentation.segment_target`), or one
   the caller gives;
4. the global pose search and the refinement against that mask
   (:func:`~sq_mitsuba.inference.search.search_and_refine`), items with an empty mask, or
   (but for a mask the caller gives) an image without a target (``Prediction.target``),
   left at the search's start with NaN scores.

The evaluation (``eval --refine``), ``predict --refine``, the demo, the illumination study and
``bench eval`` all call it; nothing else strings these steps together.

Convention: the fitted pose and assembly are float64 (the search and the refinement run in
double precision); everything else keeps the network's dtype.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any, TypeVar

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.config import validate
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import matrix_to_quaternion
from sq_mitsuba.inference.images import array_to_tensor
from sq_mitsuba.inference.prediction import Fit, MaskChoice, Prediction
from sq_mitsuba.inference.refine import RefineOptions
from sq_mitsuba.inference.search import SEARCH_REFINEMENT, SearchOptions, search_and_refine

T = TypeVar("T")

__all__ = ["checked_mask", "checked_options", "fit_options", "fit_prediction", "masks_to_fit",
           "search_start", "segmented"]


def fit_options(search: SearchOptions | None, refinement: RefineOptions | None
                ) -> tuple[SearchOptions, RefineOptions]:
    """The search's and the refinement's settings (None: the defaults), checked.

    Raises:
        ValueError: naming ``search`` or ``refinement`` (a wrong type), or
            :class:`~sq_mitsuba.config.ConfigError` naming the field
            (``search.turns: expected a value in [1, 64], got 500``).
    """
    return (checked_options(search, SearchOptions(), "search"),
            checked_options(refinement, SEARCH_REFINEMENT, "refinement"))


def checked_options(value: Any, default: T, name: str) -> T:
    """``value`` (None: ``default``) checked as an options object of ``default``'s class.

    Raises:
        ValueError: naming ``name`` for another type (a dict: build the class from it);
            :class:`~sq_mitsuba.config.ConfigError` naming ``name.field`` for a bad field.
    """
    value = default if value is None else value
    kind = type(default)
    if not isinstance(value, kind):
        hint = f" (build one from it: {kind.__name__}(**d))" if isinstance(value, dict) else ""
        raise ValueError(f"{name}: expected a {kind.__name__}, got {type(value).__name__}{hint}")
    validate(value, name)
    return value


def search_start(predictor: Any, images: Tensor, network: Prediction, camera: Camera,
                 turns: int | None, default_turns: int) -> tuple[Prediction, int]:
    """The reading the search starts from, and the turns it was read from.

    Args:
        predictor: the :class:`~sq_mitsuba.inference.predictor.Predictor` that read
            ``network`` from ``images``.
        images: the images as the predictor takes them.
        network: the predictor's (unturned) reading of ``images``.
        camera: the images' camera.
        turns: in-plane turns to read the start from; None: ``default_turns`` where the
            predictor can turn these images, else 1. An explicit T > 1 that the predictor
            cannot turn is an error (``read_turns``).
        default_turns: the search's setting (:attr:`SearchOptions.turns`).
    """
    if turns is None:
        turns = default_turns if predictor.can_turn(camera) else 1
    if turns <= 1:
        return network, 1
    return predictor.read_turns(images, network, turns, camera), turns


def masks_to_fit(start: Prediction, images: Tensor, mask: MaskChoice
                 ) -> tuple[Tensor, Tensor, str]:
    """The masks (B, H, W) bool to fit, which items have a target in theirs (B,) bool, and
    their source (one of :data:`~sq_mitsuba.inference.prediction.MASK_SOURCES`).

    Args:
        start: the reading the search starts from (its ``mask``, when the network has a head).
        images: (B, C, H, W) float in [0, 1], the checked images.
        mask: see :data:`MaskChoice`.

    Raises:
        ValueError: naming ``mask``: an unknown choice, a wrong type, dtype or shape, NaN or
            float values outside [0, 1].
    """
    mask = checked_mask(mask, images)
    if isinstance(mask, str):
        if mask == "network" and start.mask is not None:
            masks = start.mask.detach().cpu() > 0.5
            return masks, masks.flatten(1).any(dim=1), "network"
        masks, usable = segmented(images)
        return masks, usable, "segmentation"
    return mask, mask.flatten(1).any(dim=1), "given"


def checked_mask(mask: MaskChoice, images: Tensor) -> str | Tensor:
    """``mask`` checked against the images (B, C, H, W): the choice ("network" for None), or
    the given masks as (B, H, W) bool on the CPU; a one-line ValueError naming ``mask``
    otherwise (called before the network's turned copies run, and again by
    :func:`masks_to_fit`)."""
    count, height, width = images.shape[0], images.shape[-2], images.shape[-1]
    if mask is None or isinstance(mask, str):
        choice = mask or "network"
        if choice not in ("network", "segmentation"):
            raise ValueError(f"mask: expected 'network', 'segmentation' or masks, got {mask!r}")
        return choice
    if isinstance(mask, np.ndarray):
        if mask.dtype.kind not in "biuf":
            raise ValueError(f"mask: expected a bool or float array, got dtype {mask.dtype}")
        mask = array_to_tensor(mask)
    if not isinstance(mask, Tensor):
        raise ValueError(f"mask: expected 'network', 'segmentation', a tensor or an array, got "
                         f"{type(mask).__name__}")
    if tuple(mask.shape) != (count, height, width):
        raise ValueError(f"mask: expected shape ({count}, {height}, {width}) (one per image, at "
                         f"the images' size), got {tuple(mask.shape)}")
    mask = mask.detach().cpu()
    if mask.is_floating_point():
        if not bool(torch.isfinite(mask).all()):
            raise ValueError("mask: contains NaN or infinite values")
        low, high = (float(mask.amin()), float(mask.amax())) if mask.numel() else (0.0, 0.0)
        if low < 0.0 or high > 1.0:
            raise ValueError(f"mask: float values must lie in [0, 1], got [{low:.4g}, "
                             f"{high:.4g}]")
        mask = mask > 0.5
    elif mask.dtype != torch.bool:
        mask = mask != 0
    return mask


def segmented(images: Tensor) -> tuple[Tensor, Tensor]:
    """Masks (B, H, W) bool segmented from images (B, C, H, W), and which are usable (B,):
    segmented, and without the segmentation's warning (a lit Earth merged with the target: in
    the illumination study, fitting such masks lowered the 2D IoU from 0.32 to 0.21)."""
    from sq_mitsuba.data.segmentation import segment_target

    masks, usable = [], []
    for image in images.mean(dim=1).double().cpu().numpy():
        try:
            segmentation = segment_target(image)
            masks.append(torch.from_numpy(segmentation.mask))
            usable.append(segmentation.warning is None)
        except ValueError:  # nothing bright (an eclipse, a black frame): no target to refine to
            masks.append(torch.zeros(image.shape, dtype=torch.bool))
            usable.append(False)
    return torch.stack(masks), torch.tensor(usable)


def fit_prediction(predictor: Any, images: Tensor, network: Prediction, *,
                   turns: int | None = None, mask: MaskChoice = None,
                   search: SearchOptions | None = None, refinement: RefineOptions | None = None,
                   reuse: Fit | None = None) -> Prediction:
    """The network's reading ``network`` of ``images`` searched and refined against each
    image's mask (the module docstring lists the steps).

    Args:
        predictor: the predictor that read ``network``.
        images: (B, C, H, W) float in [0, 1], the checked images at their own size.
        network: the predictor's reading of ``images`` (one pass).
        turns: see :func:`search_start` (None: ``search.turns`` where the network and the
            camera can turn, else 1).
        mask: see :data:`MaskChoice`.
        search: the search's settings (default :class:`SearchOptions`).
        refinement: the refinement's (default :data:`SEARCH_REFINEMENT`).
        reuse: an earlier fit of the same images and network reading: its start (the turned
            copies' reading) is reused, not read again (``turns`` is then its own).

    Returns:
        The fitted :class:`Prediction`: its assembly and pose the refined ones, its ``network``
        the reading passed in, its ``fit`` what was fitted.

    Raises:
        ValueError: naming ``search`` or ``refinement`` (:func:`fit_options`, before any
            work), ``turns`` or ``mask``.
    """
    # Checked before the turned copies run, and whether or not any item is fitted.
    search, refinement = fit_options(search, refinement)
    mask = checked_mask(mask, images)
    camera = network.camera
    started = time.perf_counter()
    if reuse is None:
        start, turns = search_start(predictor, images, network, camera, turns, search.turns)
    else:
        start, turns = reuse.start, reuse.turns
    turns_seconds = time.perf_counter() - started
    masks, usable, source = masks_to_fit(start, images, mask)
    if source != "given" and network.target is not None:
        usable = usable & network.target.detach().cpu()  # no target: nothing to search for

    params = start.assembly.params.detach().double().cpu()
    rotation = start.rotation.detach().double().cpu()
    translation = start.translation.detach().double().cpu()
    count = len(rotation)
    nan = torch.full((count,), float("nan"), dtype=torch.float64)
    search_score, iou = nan.clone(), nan.clone()
    search_rotation, search_translation = rotation.clone(), translation.clone()
    fitted_params = params.clone()
    fitted_rotation, fitted_translation = rotation.clone(), translation.clone()
    candidates = torch.full((count, 0, 3, 3), float("nan"), dtype=torch.float64)
    candidate_scores = torch.full((count, 0), float("nan"), dtype=torch.float64)
    search_seconds = 0.0
    chosen = torch.nonzero(usable).flatten()
    if len(chosen):
        # A regressed rotation (no distribution) is searched over a uniform grid of SO(3).
        hypotheses = None if start.rotation_log_probabilities is None else \
            start.rotation_hypotheses.detach().cpu()[chosen]
        own = None if start.primitive_index is None else start.primitive_index.cpu() >= 0
        result = search_and_refine(Assembly(params[chosen]), rotation[chosen],
                                   translation[chosen], masks[chosen], camera, hypotheses,
                                   search, refinement, None if own is None else own[chosen])
        search_rotation[chosen] = result.search_rotation.double()
        search_translation[chosen] = result.search_translation.double()
        search_score[chosen] = result.search.score.double()
        fitted_params[chosen] = result.assembly.params.detach().double()
        fitted_rotation[chosen] = result.rotation.double()
        fitted_translation[chosen] = result.translation.double()
        iou[chosen] = result.iou.double()
        scored = result.search.candidates.shape[1]
        candidates = torch.full((count, scored, 3, 3), float("nan"), dtype=torch.float64)
        candidate_scores = torch.full((count, scored), float("nan"), dtype=torch.float64)
        candidates[chosen] = result.search.candidates.double()
        candidate_scores[chosen] = result.search.scores.double()
        search_seconds = result.search_seconds
    fit = Fit(mask=masks, mask_source=source, fitted=usable, start=start, turns=turns,
              search_rotation=search_rotation, search_translation=search_translation,
              search_score=search_score, candidates=candidates,
              candidate_scores=candidate_scores, iou=iou, turns_seconds=turns_seconds,
              search_seconds=turns_seconds + search_seconds,
              seconds=time.perf_counter() - started)
    return replace(start, assembly=Assembly(fitted_params), rotation=fitted_rotation,
                   translation=fitted_translation,
                   quaternion=matrix_to_quaternion(fitted_rotation),
                   pixel=camera.project(fitted_translation), depth=fitted_translation[:, 2],
                   network=network, fit=fit, primitives=None)
