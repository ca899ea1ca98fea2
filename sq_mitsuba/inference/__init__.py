"""Inference layer: a trained network at test time. The predictor (:mod:`.predictor`), loaded from
a checkpoint by :func:`load_model` (:mod:`.loading`); the render-and-compare pose search
(:mod:`.search`), the refinement of pose and shape against a mask (:mod:`.refine`), the fit of
an assembly to masks seen from known poses (:mod:`.fit`), and the one pipeline that joins them
(:mod:`.pipeline`, ``Predictor.predict(images, refine=True)``); for N images of one
spacecraft, one assembly and every pose (:mod:`.sequence`, its frames brought into one body
frame by :mod:`.body_frame`, primitives optionally grown where its silhouettes miss the
masks by :mod:`.grow`). Imports the model layer and those below it; never the training
layer.

``Predictor``, ``Prediction``, ``SequencePrediction``, ``load_model`` and the options of the
search, the refinement and the pass (``SearchOptions``, ``RefineOptions``,
``SequenceOptions``) are importable from here, loaded on first use.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_PUBLIC = {"Predictor": "predictor", "Prediction": "prediction",
           "SequencePrediction": "prediction", "load_model": "loading",
           "SearchOptions": "search", "RefineOptions": "refine", "SequenceOptions": "sequence"}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(import_module(f"{__name__}.{_PUBLIC[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
