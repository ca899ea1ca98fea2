"""The part targets of a dataset: one fitted assembly per training model, made once by
``sq-mitsuba dataset fit-parts`` and read when the ``parts`` loss term is weighted.

Each model's fit lives beside its mesh as ``<model>/models/part_targets.npz`` (``raw`` (M, 16)
float64, the fitted raw parameters; ``chamfer`` the fit's squared-L2 Chamfer loss; ``steps``),
so a library grown later gets fits for its new models only, and the dataset's fingerprint (its
labels and splits) is unchanged by them. :mod:`sq_mitsuba.model.part_targets` says why and
how they are fitted.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.data.spe3r.layout import MODELS, model_points
from sq_mitsuba.geometry.assembly import NUM_PARAMS
from sq_mitsuba.io import atomic_write_bytes
from sq_mitsuba.model.part_targets import fit_to_surface
from sq_mitsuba.progress import progress_bar

__all__ = ["PART_TARGETS_FILE", "PartTargetError", "fit_part_targets", "load_part_targets",
           "part_targets_path"]

PART_TARGETS_FILE = "part_targets.npz"


class PartTargetError(ValueError):
    """A missing or unreadable part-target file; the message is one line naming it."""


def part_targets_path(root: Path, model: str) -> Path:
    """Where ``model``'s fit is kept in dataset ``root``."""
    return Path(root) / model / MODELS / PART_TARGETS_FILE


def _read(path: Path, num_primitives: int) -> np.ndarray:
    """The (M, 16) raw parameters of one file, checked; PartTargetError naming it."""
    try:
        with np.load(path) as archive:
            raw = np.asarray(archive["raw"], dtype=np.float64)
    except FileNotFoundError:
        raise PartTargetError(f"{path}: missing (make it with `sq-mitsuba dataset fit-parts "
                              f"--data {path.parents[2]} --primitives {num_primitives}`)") from None
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, EOFError) as error:
        # A truncated archive is a BadZipFile (or an EOFError inside it), not an OSError.
        raise PartTargetError(f"{path}: cannot read part targets "
                              f"({type(error).__name__}: {error})") from None
    if raw.shape != (num_primitives, NUM_PARAMS):
        raise PartTargetError(f"{path}: holds {raw.shape[0] if raw.ndim else 0} primitives "
                              f"of shape {raw.shape}, the network has {num_primitives} (fit "
                              f"again with --primitives {num_primitives})")
    if not np.isfinite(raw).all():
        raise PartTargetError(f"{path}: part targets hold NaN or infinity")
    return raw


def load_part_targets(root: Path, models: Sequence[str], num_primitives: int) -> Tensor:
    """(len(models), M, 16) float32: every model's fitted raw parameters, in ``models``'
    order (a dataset's model list, as its items' ``model_index`` counts them). One-line
    PartTargetError for the first model whose file is missing, unreadable or of another M."""
    table = [_read(part_targets_path(root, model), num_primitives) for model in models]
    return torch.from_numpy(np.stack(table)).float()


def fit_part_targets(root: Path, models: Sequence[str], num_primitives: int, steps: int = 300,
                     points: int = 1000, batch: int = 16, progress: bool = True) -> int:
    """Fit and write the part targets of every model of ``models`` in dataset ``root`` that
    lacks a readable one for ``num_primitives`` (an interrupted call resumes); returns how
    many were fitted. Each model's ``points`` surface points are drawn with a fixed seed and
    fitted in float32, so a fit is reproducible; each file is written whole or not at all."""
    todo = []
    for model in models:
        try:
            _read(part_targets_path(root, model), num_primitives)
        except PartTargetError:
            todo.append(model)
    bar = progress_bar(total=len(todo), unit="model", desc="part targets", disable=not progress)
    for start in range(0, len(todo), batch):
        chunk = todo[start:start + batch]
        clouds = []
        for model in chunk:
            surface = model_points(Path(root) / model)["surface"]
            rng = np.random.default_rng(0)
            pick = rng.choice(len(surface), points, replace=len(surface) < points)
            clouds.append(torch.from_numpy(np.asarray(surface[pick], dtype=np.float32)))
        raw, chamfer = fit_to_surface(torch.stack(clouds), num_primitives, steps=steps)
        for k, model in enumerate(chunk):
            buffer = io.BytesIO()
            np.savez(buffer, raw=raw[k].double().numpy(), chamfer=np.float64(chamfer[k]),
                     steps=np.int64(steps))
            atomic_write_bytes(part_targets_path(root, model), buffer.getvalue())
        bar.update(len(chunk))
    bar.close()
    return len(todo)
