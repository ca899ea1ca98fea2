"""Data layer: mesh I/O and processing, procedural spacecraft, model libraries, frame
sampling and datasets in the SPE3R layout. Imports the geometry and render layers.

``Spe3rDataset`` (the torch Dataset over the SPE3R layout) is importable from here; it is
loaded on first use so that mesh processing does not pay for the dataset's imports.
"""

from __future__ import annotations

from typing import Any

__all__ = ["Spe3rDataset"]


def __getattr__(name: str) -> Any:
    if name == "Spe3rDataset":
        from sq_mitsuba.data.spe3r import Spe3rDataset

        return Spe3rDataset
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
