"""Export a training checkpoint as a small inference checkpoint (what the package ships).

A training checkpoint (``RUN/best.pt`` or ``last.pt``) carries the optimiser and scheduler
states, RNG states and the full-precision weights: about three times the size of the weights
alone. :func:`export_model` keeps what inference needs:

- the config, the dataset camera and the weights, floating-point tensors in half precision by
  default (BatchNorm's integer counters unchanged; :func:`~sq_mitsuba.model.checkpoint.
  model_from_checkpoint` loads them back into a float32 network);
- ``baseline``: the trivial baseline of :mod:`sq_mitsuba.evaluation.evaluate`, computed with
  the exported (rounded) weights over training images of ``data_root``, so that a user
  without the training data can still compare against it (``Predictor.baseline``);
- ``source``: where it came from (training step and epoch, dataset fingerprint and manifest
  hash, git commit, the run's validation history).

Convention: half precision rounds each weight to 11 significant bits; the exported network's
outputs differ from the float32 network's by ~1e-3 relative, far below what the metrics
resolve (the model card's figures are measured with the exported file).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from sq_mitsuba.config import in_range, validate
from sq_mitsuba.inference.predictor import Predictor
from sq_mitsuba.io import check_output_folder
from sq_mitsuba.model.checkpoint import (
    FORMAT,
    VERSION,
    model_from_checkpoint,
    read_checkpoint,
    write_checkpoint,
)

__all__ = ["ExportOptions", "export_model"]

# Training-run records worth keeping with the shipped weights (everything else is resumption
# state: optimiser, scheduler, RNG, data order).
_SOURCE_KEYS = ("step", "epoch", "total_steps", "dataset", "git", "best", "validation",
                "world_size")


@dataclass(frozen=True)
class ExportOptions:
    """How :func:`export_model` writes the inference checkpoint."""

    half: bool = True
    "Store floating-point weights in half precision (half the size; see the module note)."
    baseline_images: int = in_range(1, 1_000_000, default=256)
    "Training images (spread evenly) whose mean prediction and mean pose make the baseline."
    batch_size: int = in_range(1, 4096, default=32)
    "Images per network batch while computing the baseline."


def _exported_state(state: dict[str, torch.Tensor], half: bool) -> dict[str, torch.Tensor]:
    """Weights on the CPU; floating-point ones in half precision when ``half``."""
    out = {}
    for key, value in state.items():
        value = value.detach().cpu()
        out[key] = value.half() if half and value.is_floating_point() else value.clone()
    return out


def export_model(checkpoint: str | Path, data_root: str | Path | None, out: str | Path,
                 options: ExportOptions | None = None) -> Path:
    """Write an inference checkpoint for ``checkpoint`` to ``out`` (atomically).

    Args:
        checkpoint: a training checkpoint (or any checkpoint :func:`read_checkpoint` reads).
        data_root: the training dataset (its train split gives the baseline); None: no
            baseline is stored.
        out: the file to write; its folder is created.
        options: see :class:`ExportOptions`.

    Returns:
        ``out`` as a Path.

    Raises:
        ValueError / FileNotFoundError: a corrupt or mismatched checkpoint (or one whose
            weights are not finite), ``out`` a folder, or a dataset without training images;
            checked before ``out`` is touched.
    """
    options = options or ExportOptions()
    validate(options)
    checkpoint, out = Path(checkpoint), Path(out)
    if out.is_dir():
        raise ValueError(f"out {out}: is a folder; give the file to write (e.g. "
                         f"{out / 'model.pt'})")
    payload = read_checkpoint(checkpoint)
    model_from_checkpoint(payload, str(checkpoint))  # refuse a mismatched file early
    check_output_folder(out.parent)
    exported: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "config": payload["config"],
        "model": _exported_state(payload["model"], options.half),
        "camera": payload["camera"],
        "source": {"checkpoint": checkpoint.name,
                   **{key: payload[key] for key in _SOURCE_KEYS if key in payload}},
    }
    if data_root is not None:
        from sq_mitsuba.evaluation.scoring import baseline_prediction

        # The baseline of the weights as shipped (rounded), not of the float32 originals.
        model, camera = model_from_checkpoint(exported, str(out))
        raw, rotation, translation = baseline_prediction(
            Predictor(model, camera), Path(data_root), options.baseline_images,
            options.batch_size)
        exported["baseline"] = {"raw": raw.float(), "rotation": rotation.float(),
                                "translation": translation.float()}
    return write_checkpoint(out, exported)
