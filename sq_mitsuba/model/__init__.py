"""Model layer: the network and what defines it. The EfficientNet-Lite0 encoder and its
ImageNet weights (:mod:`.encoder`, :mod:`.pretrained`), the superquadric, pose and mask heads
(:mod:`.heads`, :mod:`.rotation_grid` for the rotation distribution), the network that joins
them (:mod:`.network`, :mod:`.network_config`), the paper's losses (:mod:`.losses`) and the
checkpoint files that hold trained weights (:mod:`.checkpoint`, the shipped model in
``weights/``). Imports the geometry, render and data layers.

``SuperquadricNet`` and ``NetworkConfig`` are importable from here, loaded on first use.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_PUBLIC = {"SuperquadricNet": "network", "NetworkConfig": "network"}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(import_module(f"{__name__}.{_PUBLIC[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
