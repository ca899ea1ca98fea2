"""Differentiable silhouettes through Mitsuba's projective integrator, bridged into torch.

- :mod:`.renderer`: :class:`SilhouetteRenderer` and :func:`render_assembly` (one image per
  item, gradients to the vertices, as training's reprojection and the refinement use).
- :mod:`.batch`: :class:`PoseSilhouettes`, many poses of one assembly in one launch (forward
  only: the pose search).
- :mod:`.tiled`: :class:`TiledSilhouettes`, a whole batch in one launch each way, each item in
  its own tile of one film (the renderer's ``batched`` path, the default on CUDA).
- :mod:`.integrator`: the mask integrators registered with Mitsuba.
- :mod:`.workers` and :mod:`.worker_process`: the renders spread over worker processes.

The public names are importable from here; each is loaded on first use, so that importing the
package does not start Mitsuba.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_PUBLIC = {"SilhouetteRenderer": "renderer", "render_assembly": "renderer",
           "PoseSilhouettes": "batch"}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(import_module(f"{__name__}.{_PUBLIC[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
