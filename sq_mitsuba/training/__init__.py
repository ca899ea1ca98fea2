"""Training layer: the trainer (:mod:`.train`) and its parts. The training step
(:mod:`.step`) and its weighted loss terms (:mod:`.loss_terms`), the data cache, stream and
augmentation (:mod:`.cache`, :mod:`.data_stream`, :mod:`.augment`, :mod:`.batch`), the
schedule, validation, random streams and distributed set-up, the run folder with its log and
resumable state (:mod:`.run`), and the strict config (:mod:`.config`). Imports the model layer
and those below it; never the inference layer.

``train`` and ``TrainConfig`` are importable from here, loaded on first use.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_PUBLIC = {"train": "train", "TrainConfig": "config"}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(import_module(f"{__name__}.{_PUBLIC[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
