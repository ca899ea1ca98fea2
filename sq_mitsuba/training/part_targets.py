"""The part targets of a dataset: one fitted assembly per training model, made once by
``sq-mitsuba dataset fit-parts`` and read when the ``parts`` loss term is weighted.

Each model's fit lives beside its mesh as ``<model>/models/part_targets.npz`` (``raw`` (M, 16)
float64, the fitted raw parameters; ``chamfer`` the fit's squared-L2 Chamfer loss; the settings
that made it: ``steps`` and ``points``), so a library grown later gets fits for its new models
only, and the dataset's fingerprint (its labels and splits) is unchanged by them.
:mod:`sq_mitsuba.model.part_targets` says why and how they are fitted.

A rerun of :func:`fit_part_targets` keeps a fit made with its settings (M, steps, points) and
fits again one made with others, saying which (so ``fit-parts --steps 300`` after a 100-step
run does not keep the 100-step fits). A file without ``points`` was made before it was
recorded, when every fit drew :data:`DEFAULT_FIT_POINTS` points (the CLI has no option for
it), so it counts as made with those; a file without ``steps`` (every file this module wrote
records it) is fitted again.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.data.mesh_io import check_npz_array
from sq_mitsuba.data.spe3r.layout import MODELS, model_points
from sq_mitsuba.geometry.assembly import NUM_PARAMS
from sq_mitsuba.io import atomic_write_bytes
from sq_mitsuba.model.part_targets import fit_to_surface
from sq_mitsuba.progress import progress_bar

__all__ = ["DEFAULT_FIT_POINTS", "PART_TARGETS_FILE", "PartTargetError", "PartTargetFits",
           "fit_part_targets", "load_part_targets", "part_targets_path"]

PART_TARGETS_FILE = "part_targets.npz"
DEFAULT_FIT_POINTS = 1000
#: The most primitives a fit may hold (`dataset fit-parts --primitives` takes 1-64).
MAX_FIT_PRIMITIVES = 64
"""Surface points a fit draws per model (the only value ever used by ``dataset fit-parts``)."""


class PartTargetError(ValueError):
    """A missing or unreadable part-target file; the message is one line naming it."""


def part_targets_path(root: Path, model: str) -> Path:
    """Where ``model``'s fit is kept in dataset ``root``."""
    return Path(root) / model / MODELS / PART_TARGETS_FILE


def _read(path: Path, num_primitives: int) -> np.ndarray:
    """The (M, 16) raw parameters of one file, checked; PartTargetError naming it."""
    try:
        with np.load(path) as archive:  # the size from its header first (a zip bomb stops)
            check_npz_array(archive, "raw", path, limit=num_primitives * NUM_PARAMS)
            raw = np.asarray(archive["raw"], dtype=np.float64)
    except FileNotFoundError:
        raise PartTargetError(f"{path}: missing (make it with `sq-mitsuba dataset fit-parts "
                              f"{path.parents[2]} --primitives {num_primitives}`)") from None
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


@dataclass(frozen=True)
class PartTargetFits:
    """What :func:`fit_part_targets` did."""

    fitted: int
    """Models fitted by this call (those fitted again included)."""
    refitted: dict[str, str] = field(default_factory=dict)
    """``{model: earlier settings}`` of the models whose fit was made with other settings and
    was fitted again, the settings as the options that made them (``"--steps 100"``)."""


def _other_settings(path: Path, num_primitives: int, steps: int, points: int) -> str | None:
    """Why the fit at ``path`` must be made: None when it is a usable fit made with these
    settings, "" when it is missing or unreadable, else its settings that differ, as options
    (``"--primitives 3, --steps 100"``)."""
    try:  # the file read once: its parameters and the settings it records
        with np.load(path) as archive:
            check_npz_array(archive, "raw", path, limit=MAX_FIT_PRIMITIVES * NUM_PARAMS)
            raw = np.asarray(archive["raw"], dtype=np.float64)
            recorded = {k: int(archive[k]) for k in ("steps", "points") if k in archive.files}
    except (OSError, KeyError, ValueError, TypeError, zipfile.BadZipFile, EOFError):
        return ""
    shape = raw.shape
    if len(shape) != 2 or shape[1] != NUM_PARAMS or (
            shape[0] == num_primitives and not np.isfinite(raw).all()):
        return ""  # not a usable fit of any M: fitted as a missing one
    differs = []
    if shape[0] != num_primitives:
        differs.append(f"--primitives {shape[0]}")
    if "steps" not in recorded:
        differs.append("--steps not recorded")
    elif recorded["steps"] != steps:
        differs.append(f"--steps {recorded['steps']}")
    # Before `points` was recorded every fit drew DEFAULT_FIT_POINTS (see the module docstring).
    if recorded.get("points", DEFAULT_FIT_POINTS) != points:
        differs.append(f"points {recorded.get('points', DEFAULT_FIT_POINTS)}")
    return ", ".join(differs) or None


def fit_part_targets(root: Path, models: Sequence[str], num_primitives: int, steps: int = 300,
                     points: int = DEFAULT_FIT_POINTS, batch: int = 16,
                     progress: bool = True) -> PartTargetFits:
    """Fit and write the part targets of every model of ``models`` in dataset ``root`` that
    lacks a readable one made with these settings (``num_primitives``, ``steps``, ``points``):
    an interrupted call resumes, and a fit made with other settings is fitted again (listed in
    the result's ``refitted``). Each model's ``points`` surface points are drawn with a fixed
    seed and fitted in float32, so a fit is reproducible; each file is written whole or not at
    all."""
    todo = []
    refitted = {}
    for model in models:
        why = _other_settings(part_targets_path(root, model), num_primitives, steps, points)
        if why is not None:
            todo.append(model)
        if why:
            refitted[model] = why
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
                     steps=np.int64(steps), points=np.int64(points))
            atomic_write_bytes(part_targets_path(root, model), buffer.getvalue())
        bar.update(len(chunk))
    bar.close()
    return PartTargetFits(len(todo), refitted)
