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

Several checkpoints of one network, fine-tuned from one start, export as one: the average of
their weights (:mod:`sq_mitsuba.model.weight_average`), its ``source`` listing each, its
baseline computed over ``data_root`` (theirs describe their own weights and are not kept).
With ``start`` (the file they were fine-tuned from) that average goes part way back to the
start: ``start_share`` x the start + (1 - ``start_share``) x the fine-tunes' average.

Convention: half precision rounds each weight to 11 significant bits; the exported network's
outputs differ from the float32 network's by ~1e-3 relative, far below what the metrics
resolve (the model card's figures are measured with the exported file).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from sq_mitsuba.config import in_range, validate
from sq_mitsuba.data.spe3r.layout import check_outside_datasets
from sq_mitsuba.inference.predictor import Predictor
from sq_mitsuba.inputs import load_torch_file
from sq_mitsuba.io import check_inputs_kept, check_output_folder
from sq_mitsuba.model.checkpoint import (
    FORMAT,
    VERSION,
    model_from_checkpoint,
    read_checkpoint,
    write_checkpoint,
)
from sq_mitsuba.model.weight_average import average_checkpoints

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
    start_share: float = in_range(0.0, 0.99, default=0.5)
    """With a ``start`` checkpoint: its share of the exported weights, the fine-tunes' average
    the rest (0: the average alone)."""
    keep_existence: bool = False
    """With a ``start`` checkpoint: the existence column of the generators' last layer (its
    weights and bias) is the fine-tunes' average alone, not mixed back (a start grown to
    existence holds every primitive at probability 0.9, so its share keeps the primitives the
    fine-tunes switch off)."""


def _exported_state(state: dict[str, torch.Tensor], half: bool) -> dict[str, torch.Tensor]:
    """Weights on the CPU; floating-point ones in half precision when ``half``."""
    out = {}
    for key, value in state.items():
        value = value.detach().cpu()
        out[key] = value.half() if half and value.is_floating_point() else value.clone()
    return out


def _file_sha256(path: Path) -> str:
    """sha256 (hex) of a file's bytes: which start an export went back to, by content."""
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _trained_on(payload: dict[str, Any]) -> dict[str, Any]:
    """The training dataset a checkpoint records (a training checkpoint's ``dataset``, an
    exported one's ``source.dataset``); empty when it records none."""
    record = payload.get("dataset")
    if not isinstance(record, dict):
        source = payload.get("source")
        record = source.get("dataset") if isinstance(source, dict) else None
    return record if isinstance(record, dict) else {}


def baseline_data_note(payloads: Sequence[dict[str, Any]], data_root: Path) -> str | None:
    """One line when ``data_root`` is none of the datasets the checkpoints were trained on (by
    the content fingerprints they record; ``data_root`` is hashed once), else None."""
    from sq_mitsuba.training.cache import dataset_fingerprint

    recorded = [_trained_on(payload).get("fingerprint") for payload in payloads]
    known = [fingerprint for fingerprint in recorded if isinstance(fingerprint, str)]
    if known and dataset_fingerprint(data_root) in known:
        return None
    if len(payloads) > 1:
        return (f"{data_root} is none of the averaged checkpoints' training datasets: the "
                f"baseline describes {data_root}")
    if not known:
        return (f"the checkpoint records no training dataset: the baseline describes "
                f"{data_root}, which may not be the one it was trained on")
    return (f"{data_root} is not the dataset the checkpoint was trained on "
            f"({_trained_on(payloads[0]).get('root')}, fingerprint {known[0][:12]}): the "
            f"baseline describes {data_root}")


def _file_identity(path: Path) -> object:
    """What names one file: its device and inode (a hard link or a symlink is the same file),
    or the resolved path where it cannot be read (its absence is reported later)."""
    try:
        info = path.stat()
    except OSError:
        return path.resolve()
    return (info.st_dev, info.st_ino)


def check_replaceable(out: Path) -> None:
    """Refuse an existing ``out`` that is not an exported model: re-exporting replaces one,
    but a training run's ``last.pt`` (which ``--resume`` needs), a checkpoint written by hand
    or a user's file named by mistake is never overwritten.

    An exported model is an sq_mitsuba checkpoint with the ``source`` record
    :func:`export_model` writes and no ``optimizer`` (a training checkpoint's); read with
    ``weights_only=True``, as every checkpoint is.

    Raises:
        ValueError: ``out <out>: ...`` naming what it is.
    """
    if not out.exists():
        return
    if not out.is_file():
        raise ValueError(f"out {out}: exists and is not a file; give the file to write")
    try:
        payload = load_torch_file(out, "checkpoint")
    except ValueError:
        payload = None
    keep = "; export replaces only an exported model: choose another --out"
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"out {out}: exists and is not an sq_mitsuba checkpoint{keep}")
    if "optimizer" in payload:
        raise ValueError(f"out {out}: a training checkpoint (its optimiser state is what "
                         f"--resume needs){keep}")
    if "source" not in payload:
        raise ValueError(f"out {out}: an sq_mitsuba checkpoint, but not an exported model "
                         f"(no 'source' record){keep}")


def export_model(checkpoint: str | Path | Sequence[str | Path], data_root: str | Path | None,
                 out: str | Path, options: ExportOptions | None = None,
                 notes: list[str] | None = None, start: str | Path | None = None) -> Path:
    """Write an inference checkpoint for ``checkpoint`` to ``out`` (atomically).

    Args:
        checkpoint: a training checkpoint (or any checkpoint :func:`read_checkpoint` reads),
            or several of one network fine-tuned from one start: their weights' average.
        data_root: the training dataset (its train split gives the baseline); None: no
            baseline is stored (for one checkpoint, one it stores is kept).
        out: the file to write; its folder is created. An exported model there is replaced
            (re-exporting); anything else there is refused.
        options: see :class:`ExportOptions`.
        start: the checkpoint ``checkpoint`` was fine-tuned from (its ``init_from``, e.g. the
            archetype model), or None. Given, the exported weights are ``options.start_share``
            x the start, grown to the fine-tunes' network as training grew it, plus the rest
            x the fine-tunes' average.
        notes: gets the lines worth saying (the CLI prints them): which images the
            baseline describes, and that ``data_root`` is not the checkpoint's training
            dataset (by the fingerprint the checkpoint records) when it is not.

    Returns:
        ``out`` as a Path.

    Raises:
        ValueError / FileNotFoundError: a corrupt or mismatched checkpoint (or one whose
            weights are not finite), one checkpoint file named twice, checkpoints that are not
            of one network (a field, the
            camera or a weight named), ``out`` a folder, an existing ``out`` that is not an
            exported model (:func:`check_replaceable`: a training checkpoint, any other
            file), ``out`` inside a dataset folder (:func:`~sq_mitsuba.data.spe3r.layout.
            check_outside_datasets`), a
            dataset without training images
            (or whose training images or points cannot be read), or ``data_root`` given for
            one checkpoint that stores a baseline already (it would be replaced; without
            ``data_root`` it is kept); checked before ``out`` is touched.
    """
    options = options or ExportOptions()
    validate(options)
    if options.keep_existence and start is None:
        raise ValueError("keep_existence: only with a start (without one the existence column "
                         "is the average already)")
    paths = [Path(checkpoint)] if isinstance(checkpoint, (str, os.PathLike)) else \
        [Path(path) for path in checkpoint]
    if not paths:
        raise ValueError("checkpoint: give at least one checkpoint to export")
    seen: dict[object, Path] = {}
    for path in paths:  # the same file twice would weigh one run double in the average
        first = seen.setdefault(_file_identity(path), path)
        if first is not path:
            raise ValueError(f"checkpoint {path}: given twice (as {first}); give each run's "
                             "checkpoint once")
    out = Path(out)
    if out.is_dir():
        raise ValueError(f"out {out}: is a folder; give the file to write (e.g. "
                         f"{out / 'model.pt'})")
    check_inputs_kept([*paths, *([Path(start)] if start is not None else [])], [out])
    check_outside_datasets(out, None if data_root is None else Path(data_root), "export")
    check_replaceable(out)
    payloads = [read_checkpoint(path) for path in paths]
    for path, payload in zip(paths, payloads, strict=True):
        model_from_checkpoint(payload, str(path))  # refuse a mismatched file early
    notes = notes if notes is not None else []
    start_record = None
    if start is not None:
        start = Path(start)
        start_payload = read_checkpoint(start)
        payload = average_checkpoints(payloads, [str(path) for path in paths],
                                      (start_payload, str(start)), options.start_share,
                                      keep_existence=options.keep_existence)
        start_record = {"checkpoint": start.name, "share": options.start_share,
                        "sha256": _file_sha256(start)}
        if options.keep_existence:
            start_record["existence"] = "the fine-tunes' average"
        recorded = {str(each["config"].get("init_from")) for each in payloads}
        if recorded != {str(start)} and {Path(r).name for r in recorded} != {start.name}:
            notes.append(f"start {start}: the checkpoints record init_from "
                         f"{', '.join(sorted(recorded))}")
    else:
        payload = payloads[0] if len(paths) == 1 else \
            average_checkpoints(payloads, [str(path) for path in paths])
    check_output_folder(out.parent)
    if data_root is not None:
        from sq_mitsuba.data.spe3r import Spe3rDataset

        data_root = Path(data_root)
        if payload.get("baseline") is not None:
            raise ValueError(f"{paths[0]}: stores a baseline already, which --data "
                             f"{data_root} would replace; export without --data to keep it")
        train = Spe3rDataset(data_root, "train", image_size=8, num_surface=1, num_occupancy=2)
        if not len(train):  # said here: the shared message's way out is eval's option
            raise ValueError(f"{data_root}: no images for the baseline (its 'train' split is "
                             "empty); give the training dataset as --data, or leave --data "
                             "out to store no baseline")
        train.check()  # images and points read by the baseline: refused before work
        note = baseline_data_note(payloads, data_root)
        if note is not None:
            notes.append(note)
    elif len(paths) > 1 or start is not None:
        notes.append("baseline: none stored (each averaged checkpoint's describes its own "
                     "weights); give --data for one")
    sources = [{"checkpoint": path.name, **{key: each[key] for key in _SOURCE_KEYS
                                            if key in each}}
               for path, each in zip(paths, payloads, strict=True)]
    averaged = len(paths) > 1 or start is not None
    if averaged:  # an exported ingredient keeps its record in "source"
        sources = [{**record, "source": each["source"]} if "source" in each else record
                   for record, each in zip(sources, payloads, strict=True)]
    elif isinstance(payload.get("source"), dict):  # an exported file exported again (to add
        # a baseline, say): its record stays whole (step, dataset, commit), the file named
        sources = [{**payload["source"], "exported_again_from": paths[0].name}]
    exported: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "config": payload["config"],
        "model": _exported_state(payload["model"], options.half),
        "camera": payload["camera"],
        "source": {"averaged": sources} if averaged else sources[0],
    }
    if start_record is not None:
        exported["source"]["start"] = start_record
    if data_root is not None:
        from sq_mitsuba.data.spe3r import MissingModelWarning
        from sq_mitsuba.evaluation.scoring import baseline_prediction

        # The baseline of the weights as shipped (rounded), not of the float32 originals.
        model, camera = model_from_checkpoint(exported, str(out))
        with warnings.catch_warnings():  # a model left out was said once, when checked above
            warnings.simplefilter("ignore", MissingModelWarning)
            raw, rotation, translation = baseline_prediction(
                Predictor(model, camera), Path(data_root), options.baseline_images,
                options.batch_size)
        exported["baseline"] = {"raw": raw.float(), "rotation": rotation.float(),
                                "translation": translation.float()}
        exported["source"]["baseline_data"] = str(data_root)
        notes.append(f"baseline: the mean prediction and pose over "
                     f"{min(options.baseline_images, len(train))} training images of "
                     f"{data_root}")
    elif payload.get("baseline") is not None:
        exported["baseline"] = payload["baseline"]  # kept, not silently dropped
        notes.append(f"baseline: kept from {paths[0]}")
    return write_checkpoint(out, exported)
