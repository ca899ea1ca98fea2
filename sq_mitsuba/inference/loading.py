"""A ready :class:`~sq_mitsuba.inference.predictor.Predictor` from a checkpoint file, or from
the model shipped with the package (``sq_mitsuba.load_model``)."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from sq_mitsuba.inference.predictor import Predictor
from sq_mitsuba.model import checkpoint

__all__ = ["load_model", "with_fast_path"]


def load_model(path: str | os.PathLike[str] | None = None, *, fast: bool = False,
               device: str | torch.device = "cpu") -> Predictor:
    """A :class:`Predictor` from a checkpoint, with the dataset camera as its default camera.

    Args:
        path: checkpoint file; None: the model shipped with the package
            (``sq_mitsuba/model/weights/model.pt``).
        fast: predict with BatchNorm folded into the convolutions (see :class:`Predictor`).
        device: where the network runs.

    Raises:
        FileNotFoundError: no such file, or no shipped model (saying how to get one).
        ValueError: ``<path>: ...`` for a corrupt or mismatched checkpoint.
    """
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
    predictor = Predictor(model.to(device), camera, fast=fast)
    predictor.source = path
    predictor.baseline = checkpoint.checkpoint_baseline(payload, str(path))
    return predictor


def with_fast_path(predictor: Predictor, fast: bool) -> Predictor:
    """``predictor``, or, when ``fast`` and it has none, a copy predicting with the
    BatchNorm-folded network (folding takes about a second: done once the inputs are
    checked)."""
    if not fast or predictor.fast:
        return predictor
    folded = Predictor(predictor.model, predictor.camera, fast=True)
    folded.source = predictor.source
    folded.baseline = predictor.baseline
    return folded
