"""The dataset split an evaluation reads: opened with one-line errors (:func:`open_split`),
sampled evenly (:func:`evenly`) and batched (:func:`collate`), for a network that can read it
(:func:`check_predictor`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["check_predictor", "collate", "evenly", "open_split"]


def collate(items: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Dataset items -> one batch: tensors stacked, other values in lists."""
    out: dict[str, Any] = {}
    for key in items[0]:
        values = [item[key] for item in items]
        out[key] = torch.stack(values) if isinstance(values[0], Tensor) else values
    return out


def evenly(count: int, limit: int | None) -> list[int]:
    """``limit`` indices spread evenly over ``range(count)`` (all when None or larger)."""
    if limit is None or limit >= count:
        return list(range(count))
    return sorted({int(i) for i in np.linspace(0, count - 1, limit).round()})


def check_predictor(predictor: Any) -> None:
    """Refuse a network that cannot read SPE3R-layout images (grey, one channel)."""
    channels = predictor.model.config.in_channels
    if channels != 1:
        source = getattr(predictor, "source", None) or "model"
        raise ValueError(f"{source}: the network takes {channels}-channel images; datasets in "
                         "the SPE3R layout are grey (1 channel)")


def open_split(data_root: str | Path, split: str, image_size: int | None,
               surface_points: int) -> Any:
    """The :class:`~sq_mitsuba.data.spe3r.Spe3rDataset` of ``split`` at ``image_size`` (None:
    the dataset's own, ``camera.json``'s width), with
    ``surface_points`` per item; a one-line error when it is missing or empty, or when
    :meth:`~sq_mitsuba.data.spe3r.Spe3rDataset.check` refuses it (images of another size
    than ``camera.json``'s, a ``samples.npz`` missing an array or holding NaN)."""
    from sq_mitsuba.data.spe3r import Spe3rDataset

    dataset = Spe3rDataset(data_root, split, image_size=image_size,
                           num_surface=surface_points, num_occupancy=2)
    if len(dataset) == 0:
        why = {"test": "splits.csv lists no test models",
               "train": "splits.csv lists no training models",
               # A training model's val images are [0.4 n, 0.5 n) and [0.9 n, n) of its n.
               "val": "it holds images [0.4 n, 0.5 n) and [0.9 n, n) of each training model's "
                      "n: none without training models, nor for n of 1-4, 6 or 8 (render 10 or "
                      "more images a model, or evaluate --split test)"}
        skipped = f"; left out: {', '.join(dataset.skipped)}" if dataset.skipped else ""
        raise ValueError(f"{data_root}: the {split!r} split is empty "
                         f"({why.get(split, 'no images')}{skipped})")
    dataset.check()  # images of camera.json's size, readable finite points: before any work
    return dataset
