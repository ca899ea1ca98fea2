"""A ready :class:`~sq_mitsuba.inference.predictor.Predictor` from a checkpoint file, or from
the model shipped with the package (``sq_mitsuba.load_model``)."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from sq_mitsuba.checks import check_switch
from sq_mitsuba.inference.images import DEFAULT_MIN_TARGET, check_min_target
from sq_mitsuba.inference.predictor import DEFAULT_MIN_EXISTENCE, Predictor
from sq_mitsuba.model import checkpoint

__all__ = ["check_device", "load_model", "with_fast_path"]


def check_device(device: str | torch.device) -> torch.device:
    """``device`` as a ``torch.device`` that this torch can use, or a one-line ``ValueError``
    naming ``device`` (an unknown name, CUDA on a torch without it or a machine without a
    GPU, a GPU index past the last, or the meta device)."""
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(f"device: {device!r} is not a torch device (e.g. 'cpu', 'cuda', "
                         "'cuda:1')") from None
    if parsed.type == "meta":
        raise ValueError("device: 'meta' tensors hold no values; predict on 'cpu' or 'cuda'")
    if parsed.type == "cuda":
        if not torch.cuda.is_available():
            why = ("this torch build has no CUDA" if torch.version.cuda is None
                   else "no CUDA device is visible")
            raise ValueError(f"device: {str(parsed)!r} is not available ({why}, torch "
                             f"{torch.__version__}); use device='cpu'")
        if parsed.index is not None and parsed.index >= torch.cuda.device_count():
            raise ValueError(f"device: {str(parsed)!r} is not available (this machine has "
                             f"{torch.cuda.device_count()} CUDA device(s))")
        return parsed
    if parsed.type != "cpu":
        try:
            torch.empty(1, device=parsed)
        except Exception as error:  # each backend fails in its own way (RuntimeError, ...)
            from sq_mitsuba.inputs import one_line

            reason = one_line(error)
            raise ValueError(f"device: {str(parsed)!r} is not available ({reason})") from None
    return parsed


def load_model(path: str | os.PathLike[str] | None = None, *, fast: bool = False,
               traced: bool = False, device: str | torch.device = "cpu",
               min_target: float = DEFAULT_MIN_TARGET,
               min_existence: float = DEFAULT_MIN_EXISTENCE) -> Predictor:
    """A :class:`Predictor` from a checkpoint, with the dataset camera as its default camera.

    Args:
        path: checkpoint file; None: the model shipped with the package
            (``sq_mitsuba/model/weights/model.pt``).
        fast: predict with BatchNorm folded into the convolutions (see :class:`Predictor`).
        traced: with ``fast``, through a TorchScript trace per input shape (pays for a stream
            of hundreds of single frames; see :class:`Predictor`).
        device: where the network runs.
        min_target: the target-present score from which an image shows a target (see
            :class:`Predictor`).
        min_existence: the existence probability from which a prediction keeps a primitive
            (a network with existence probabilities; see :class:`Predictor`).

    Raises:
        FileNotFoundError: no such file, or no shipped model (saying how to get one).
        ValueError: ``<path>: ...`` for a corrupt or mismatched checkpoint; naming ``path``
            (an empty one), ``device`` (one this torch cannot use), ``min_target`` or
            ``min_existence``; all checked before the checkpoint is read.
    """
    if isinstance(path, str | os.PathLike) and not os.fspath(path):
        raise ValueError("path: empty; give a checkpoint file, or None for the model shipped "
                         "with sq_mitsuba")
    fast, traced = check_switch("fast", fast), check_switch("traced", traced)
    if traced and not fast:
        raise ValueError("traced: traces the folded network of the fast path; give fast=True "
                         "too")
    device = check_device(device)
    min_target = check_min_target(min_target)
    min_existence = check_min_target(min_existence, "min_existence")
    if path is None:
        if not checkpoint.SHIPPED_MODEL.is_file():
            raise FileNotFoundError(
                f"no trained model is shipped with sq_mitsuba yet ({checkpoint.SHIPPED_MODEL} is "
                "absent); "
                "train one with `sq-mitsuba train` and pass its checkpoint: load_model(path)")
        path = checkpoint.SHIPPED_MODEL
    path = Path(path)
    payload = checkpoint.read_checkpoint(path)
    model, camera = checkpoint.model_from_checkpoint(payload, str(path))
    predictor = Predictor(model.to(device), camera, fast=fast, traced=traced,
                          min_target=min_target, min_existence=min_existence)
    predictor.source = path
    predictor.baseline = checkpoint.checkpoint_baseline(payload, str(path))
    return predictor


def with_fast_path(predictor: Predictor, fast: bool, *, min_target: float | None = None,
                   min_existence: float | None = None) -> Predictor:
    """``predictor``, or a copy: predicting with the BatchNorm-folded network when ``fast``
    and it has none (folding takes about 0.1 s: done once the inputs are checked), with
    the thresholds ``min_target`` and ``min_existence`` when given and other than its own."""
    min_target = predictor.min_target if min_target is None else check_min_target(min_target)
    min_existence = predictor.min_existence if min_existence is None else \
        check_min_target(min_existence, "min_existence")
    folds = fast and not predictor.fast
    same = (min_target, min_existence) == (predictor.min_target, predictor.min_existence)
    if not folds and same:
        return predictor
    if not folds:  # the same network and fast path, other thresholds
        import copy

        changed = copy.copy(predictor)
        changed.min_target, changed.min_existence = min_target, min_existence
        return changed
    folded = Predictor(predictor.model, predictor.camera, fast=True,
                       hypotheses=predictor.hypotheses, min_target=min_target,
                       min_existence=min_existence)
    folded.source = predictor.source
    folded.baseline = predictor.baseline
    return folded
