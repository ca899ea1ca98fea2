"""The journal of an evaluation in progress: what ``sq-mitsuba eval --resume`` continues from.

:func:`sq_mitsuba.evaluation.evaluate.evaluate` writes, inside its output folder, the hidden
folder :data:`JOURNAL` (``.eval_partial/``):

- ``run.json``, written before the first batch: the run's identity (:func:`run_identity`):
  the options (``to_dict``), the checkpoint (its path, for the messages, and a sha256 of the
  network's weights and stored baseline, with the predictor's ``hypotheses``,
  ``min_existence`` and device), the data (its resolved root,
  :func:`sq_mitsuba.training.cache.dataset_fingerprint`: manifest, camera, splits and labels,
  and a sha256 of the model files the scoring reads: :func:`models_sha256`), the Mitsuba
  variant, the package version, and the evaluated indices of the split;
- ``batch_<number>.pt``, one per finished batch (``torch.save``, loadable with
  ``weights_only=True``): its dataset items, its ``per_image.csv`` rows, its qualitative
  examples and mesh-ranking entries (assemblies as their ``params`` tensors), and its seconds
  (:class:`BatchRecord`).

Every file is written atomically (temporary file, then rename): a kill leaves a batch whole or
absent, never half written. The journal is removed once ``eval.json`` is written.

A run with ``resume`` reads the batches of a journal whose ``run.json`` matches its own identity
and computes only the others; a journal of another run is refused in one line naming the first
field that differs (:func:`identity_difference`), before any work. A run without ``resume``
clears the journal first. A batch file that cannot be read, or does not hold the batch it is
named for, is refused in one line naming it (delete it to recompute that batch); it is never
silently recomputed, so a resumed evaluation is either exact or refused as far as the identity
reaches. It does not reach the images and masks (the baseline's training images included),
which are not hashed (too slow; a re-rendered dataset comes with new labels, which are), nor
the versions of torch and Mitsuba (only the variant).
"""

from __future__ import annotations

import hashlib
import io
import shutil
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from sq_mitsuba.config import flatten_dict
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.inputs import one_line
from sq_mitsuba.io import atomic_write_bytes, atomic_write_json, read_json
from sq_mitsuba.version import __version__

__all__ = ["JOURNAL", "RUN_FILE", "BatchRecord", "EvalJournal", "checkpoint_identity",
           "data_identity", "finished_evaluation", "identity_difference", "journal_difference",
           "models_sha256", "run_identity"]

#: The journal's folder inside the output folder.
JOURNAL = ".eval_partial"
#: The run's identity inside :data:`JOURNAL`.
RUN_FILE = "run.json"
#: Written last by a finished evaluation (:mod:`sq_mitsuba.evaluation.evaluate`).
FINISHED_FILE = "eval.json"
#: Version of the journal's files: a journal of another version is refused as another run's.
FORMAT = 3  # 2: the scored models' files and the package version joined the identity;
#            3: per_image.csv's segmentation_iou became mask_iou (rows of 2 lack it)


# ------------------------------------------------------------------------------- identity


def _hash_tensor(digest: Any, name: str, tensor: Tensor) -> None:
    """Feed ``name``, dtype, shape and the bytes of ``tensor`` (any shape) to ``digest``."""
    data = tensor.detach().to("cpu").contiguous()
    digest.update(f"{name}|{data.dtype}|{tuple(data.shape)}|".encode())
    digest.update(data.reshape(-1).view(torch.uint8).numpy().tobytes())


def checkpoint_identity(predictor: Any) -> dict[str, Any]:
    """What identifies the model evaluated: ``path`` (``predictor.source``, for messages only:
    a copied checkpoint is the same model), ``sha256`` of the network's weights and buffers
    (``state_dict``, names sorted) and of the checkpoint's stored baseline, the rotation
    ``hypotheses``, ``min_existence`` and the network's ``device``."""
    digest = hashlib.sha256()
    for name, tensor in sorted(predictor.model.state_dict().items()):
        _hash_tensor(digest, name, tensor)
    for k, tensor in enumerate(getattr(predictor, "baseline", None) or ()):
        _hash_tensor(digest, f"baseline.{k}", tensor)
    parameter = next(predictor.model.parameters(), None)
    return {"path": str(getattr(predictor, "source", None) or ""), "sha256": digest.hexdigest(),
            "hypotheses": getattr(predictor, "hypotheses", None),
            "min_existence": getattr(predictor, "min_existence", None),
            "device": str(parameter.device) if parameter is not None else "cpu"}


def data_identity(data_root: str | Path, split: str | None = None) -> dict[str, str]:
    """The dataset's resolved ``root``, its ``fingerprint`` (manifest, camera, splits and
    every model's labels; not the images) and ``models_sha256`` (:func:`models_sha256`, of the
    evaluated ``split``'s models, or of every model)."""
    from sq_mitsuba.training.cache import dataset_fingerprint

    return {"root": str(Path(data_root).resolve()), "fingerprint": dataset_fingerprint(data_root),
            "models_sha256": models_sha256(data_root, split)}


def models_sha256(data_root: str | Path, split: str | None = None) -> str:
    """sha256 of the files of ``<model>/models/`` that scoring reads: ``samples.npz`` (the
    Chamfer and 3D IoU points, symmetry detection), ``symmetries.json`` and the mesh (points
    where there are no samples; the figures), each named, an absent one as absent. Of the models
    an evaluation of ``split`` scores ("val": the training models' held-out images, "test": the
    test models; None: every model in ``splits.csv``): a large library's other models are never
    read, and hashing them would cost seconds at every start. A few MB a model."""
    from sq_mitsuba.data.spe3r.layout import MESH_FILE, MODELS, SAMPLES_FILE, read_splits
    from sq_mitsuba.data.symmetry import SYMMETRIES_FILE

    root = Path(data_root)
    digest = hashlib.sha256()
    splits = read_splits(root / "splits.csv")
    scored = {"val": "train"}.get(split or "", split)  # val images are of training models
    for model in sorted(m for m in splits if split is None or splits[m] == scored):
        for name in (SAMPLES_FILE, SYMMETRIES_FILE, MESH_FILE):
            path = root / model / MODELS / name
            if not path.is_file():
                digest.update(f"{model}/{name}|absent|".encode())
                continue
            digest.update(f"{model}/{name}|{path.stat().st_size}|".encode())
            with open(path, "rb") as handle:
                for block in iter(lambda: handle.read(1 << 20), b""):
                    digest.update(block)
            digest.update(b"|")
    return digest.hexdigest()


def run_identity(predictor: Any, data_root: str | Path, options: dict[str, Any],
                 indices: Sequence[int] | None = None) -> dict[str, Any]:
    """The identity of an evaluation: ``options`` (``to_dict`` of its EvalOptions), the
    checkpoint's and the data's (above), the Mitsuba variant that renders its silhouettes
    (``renderer``: the CPU's and the GPU's differ in the last digits, so batches of the two
    would not make the uninterrupted run's figures), the package ``version`` (the scoring
    code) and, where given, the split's evaluated ``indices``."""
    from sq_mitsuba.render.backend import mitsuba

    identity = {"format": FORMAT, "options": options,
                "checkpoint": checkpoint_identity(predictor),
                "data": data_identity(data_root, options.get("split")),
                "renderer": mitsuba().variant(), "version": __version__}
    if indices is not None:
        identity["images"] = [int(i) for i in indices]
    return identity


def _shown(key: str, value: Any) -> str:
    if value == "<absent>":  # a field one of the two runs does not have
        return "absent"
    if key == "images" and isinstance(value, list) and len(value) > 4:
        return f"{len(value)} images"
    if key.endswith("sha256") or key.endswith("fingerprint"):
        return f"{str(value)[:12]}..."
    return repr(value)


def identity_difference(old: dict[str, Any], new: dict[str, Any]) -> str | None:
    """The first field where two identities (:func:`run_identity`) differ, in words
    (``option surface_points: 500 there, 400 now``), or None when they match. The
    checkpoint's path is not compared (only named): its weights are."""
    a, b = flatten_dict(old), flatten_dict(new)
    for key in [*b, *(k for k in a if k not in b)]:
        if key == "checkpoint.path" or a.get(key, "<absent>") == b.get(key, "<absent>"):
            continue
        there, now = _shown(key, a.get(key, "<absent>")), _shown(key, b.get(key, "<absent>"))
        if key.startswith("options."):
            return f"option {key[len('options.'):]}: {there} there, {now} now"
        if key.startswith("checkpoint."):
            paths = (a.get("checkpoint.path") or "the model", b.get("checkpoint.path")
                     or "the model")
            what = "weights" if key == "checkpoint.sha256" else key[len("checkpoint."):]
            return (f"checkpoint: {what} of {paths[0]} {there} there, of {paths[1]} "
                    f"{now} now")
        if key == "data.fingerprint":
            return f"data {b.get('data.root')}: labels or manifest changed ({there} there, " \
                f"{now} now)"
        if key == "data.models_sha256":
            return f"data {b.get('data.root')}: a model's samples.npz, symmetries.json or " \
                f"mesh changed ({there} there, {now} now)"
        if key == "version":
            return f"sq_mitsuba version: {there} there, {now} now"
        return f"{key.replace('.', ' ')}: {there} there, {now} now"
    return None


def finished_evaluation(out_dir: str | Path, identity: dict[str, Any]) -> bool:
    """Whether ``out_dir`` holds a finished evaluation (its ``eval.json``) of ``identity``
    (:func:`run_identity` without indices): the same options, checkpoint weights, data (model
    files included), Mitsuba variant and package version. An ``eval.json`` that cannot be
    read, or of a version without an identity (or without one of those fields, which older
    versions did not record), is not one."""
    try:
        info = read_json(Path(out_dir) / "eval.json")
    except (OSError, ValueError):
        return False
    if not isinstance(info, dict) or not isinstance(info.get("identity"), dict):
        return False
    recorded = {**info["identity"], "options": info.get("options")}
    return identity_difference(recorded, {k: v for k, v in identity.items()
                                          if k != "images"}) is None


def journal_difference(out_dir: str | Path, identity: dict[str, Any],
                       journal: str = JOURNAL) -> str | None:
    """How the journal in ``out_dir`` differs from ``identity`` (:func:`run_identity`, its
    indices compared only where given), in words; None where there is no journal or it is of
    this run (what ``resume`` would continue from). ``journal``: its folder's name (another
    command's partial run, e.g. ``study passes``')."""
    run_file = Path(out_dir) / journal / RUN_FILE
    if not run_file.is_file():
        return None
    try:
        recorded = read_json(run_file)
    except (OSError, ValueError) as error:  # "<run.json>: not valid JSON (...)"
        reason = " ".join(str(error).split()).removeprefix(f"{run_file}: ")
        return f"its {RUN_FILE} unreadable: {reason}"
    if not isinstance(recorded, dict):
        return "not a journal's identity"
    if "images" not in identity:
        recorded = {k: v for k, v in recorded.items() if k != "images"}
    return identity_difference(recorded, identity)


# ------------------------------------------------------------------------------- batches


@dataclass
class BatchRecord:
    """What the end of an evaluation needs from one batch.

    Attributes:
        items: the batch's dataset items (indices into the split), in order.
        rows: its ``per_image.csv`` rows (plain values), in order.
        examples: its qualitative examples: ``image`` (S, S), ``mask`` (S, S), ``model``,
            ``index``, ``gt_rotation`` (3, 3), ``gt_translation`` (3,) and, per method, a tuple
            (:class:`Assembly` of batch 1, rotation (3, 3), translation (3,)).
        to_rank: its mesh-ranking entries (image index, model index, model, Assembly of
            batch 1).
        seconds: ``network``, ``search``, ``refine`` (as summed for ``eval.json``) and
            ``loop`` (the batch's wall time, the network's warm-up left out).
    """

    items: list[int]
    rows: list[dict[str, Any]]
    examples: list[dict[str, Any]]
    to_rank: list[tuple[int, int, str, Assembly]]
    seconds: dict[str, float]

    def plain(self) -> dict[str, Any]:
        """The record as dicts, lists, numbers, strings and CPU tensors (``weights_only``)."""
        def tensor(value: Tensor) -> Tensor:
            return value.detach().to("cpu").clone()  # clone: not the whole batch's storage

        examples = []
        for example in self.examples:
            fields, methods = {}, {}
            for key, value in example.items():
                if isinstance(value, tuple):
                    assembly, rotation, translation = value
                    methods[key] = [tensor(assembly.params), tensor(rotation),
                                    tensor(translation)]
                else:
                    fields[key] = tensor(value) if isinstance(value, Tensor) else value
            examples.append({"fields": fields, "methods": methods})
        return {"format": FORMAT, "items": [int(i) for i in self.items],
                "rows": [dict(row) for row in self.rows], "examples": examples,
                "to_rank": [[int(i), int(m), str(name), tensor(assembly.params)]
                            for i, m, name, assembly in self.to_rank],
                "seconds": {key: float(value) for key, value in self.seconds.items()}}

    @classmethod
    def from_plain(cls, data: dict[str, Any]) -> BatchRecord:
        """The record of :meth:`plain`'s data (KeyError, TypeError, ValueError when it is
        not one)."""
        examples = []
        for example in data["examples"]:
            restored = dict(example["fields"])
            for method, (params, rotation, translation) in example["methods"].items():
                restored[method] = (Assembly(params), rotation, translation)
            examples.append(restored)
        to_rank = [(int(i), int(m), str(name), Assembly(params))
                   for i, m, name, params in data["to_rank"]]
        return cls([int(i) for i in data["items"]], list(data["rows"]), examples, to_rank,
                   {key: float(value) for key, value in data["seconds"].items()})


class EvalJournal:
    """The journal of one evaluation in ``out_dir`` (see the module docstring).

    Args:
        out_dir: the evaluation's output folder (locked by the caller).
        identity: this run's :func:`run_identity`.
        chunks: the items of every batch, in order (batch ``number`` is ``chunks[number - 1]``).
        resume: read the batches of a matching journal; otherwise clear any journal first.

    Raises:
        ValueError: with ``resume``, a journal of another run (naming the first field that
            differs) or a batch file that cannot be read or holds another batch (naming it);
            a file in the journal folder's place.
    """

    def __init__(self, out_dir: Path, identity: dict[str, Any],
                 chunks: Sequence[Sequence[int]], resume: bool) -> None:
        from sq_mitsuba.outputs import remove_stray_temporaries

        self.folder = Path(out_dir) / JOURNAL
        self.records: dict[int, BatchRecord] = {}
        if self.folder.exists() and not self.folder.is_dir():
            raise ValueError(f"{self.folder}: the evaluation's journal folder, but a file is "
                             "there; move it or write elsewhere (--out)")
        run_file = self.folder / RUN_FILE
        if resume and run_file.is_file():
            difference = journal_difference(out_dir, identity)
            if difference is not None:
                raise ValueError(f"{run_file}: not this evaluation's journal ({difference}); "
                                 "rerun without --resume to start afresh")
            remove_stray_temporaries(self.folder)
            self.records = self._read(chunks)
        else:
            # Said, not silent: hours of --refine batches go, or --resume finds nothing.
            finished = len(list(self.folder.glob("batch_*.pt"))) if self.folder.is_dir() else 0
            if finished and not resume:
                warnings.warn(f"{self.folder}: an interrupted evaluation's {finished} finished "
                              "batch(es) discarded (--resume would have continued them)",
                              stacklevel=2)
            elif resume:
                if (Path(out_dir) / FINISHED_FILE).is_file():  # --resume never replaces it
                    raise ValueError(f"{out_dir}: --resume, but the evaluation there is "
                                     f"finished ({FINISHED_FILE}; nothing to resume): rerun "
                                     "without --resume to evaluate again, or use another --out")
                warnings.warn(f"{out_dir}: no interrupted evaluation to resume (no "
                              f"{JOURNAL}/{RUN_FILE}): evaluating from the start", stacklevel=2)
            self.clear()
            atomic_write_json(run_file, identity)

    def _read(self, chunks: Sequence[Sequence[int]]) -> dict[int, BatchRecord]:
        records = {}
        for path in sorted(self.folder.glob("batch_*.pt")):
            number = path.stem[len("batch_"):]
            if not number.isdigit() or not 1 <= int(number) <= len(chunks):
                raise ValueError(f"{path}: not a batch of this evaluation ({len(chunks)} "
                                 "batches); delete it, or rerun without --resume")
            try:
                record = BatchRecord.from_plain(torch.load(path, map_location="cpu",
                                                           weights_only=True))
            except Exception as error:  # torch, pickle and zip fail in many ways
                reason = one_line(error)
                raise ValueError(f"{path}: unreadable journal batch ({reason}); delete it to "
                                 "compute that batch again, or rerun without --resume") \
                    from None
            if record.items != [int(i) for i in chunks[int(number) - 1]]:
                raise ValueError(f"{path}: holds other images than batch {int(number)} of "
                                 "this evaluation; delete it, or rerun without --resume")
            records[int(number)] = record
        return records

    def get(self, number: int) -> BatchRecord | None:
        """Batch ``number``'s record when the journal holds it (from an earlier run)."""
        return self.records.get(number)

    def save(self, number: int, record: BatchRecord) -> BatchRecord:
        """Write batch ``number``'s record (atomically); returns it as a resumed run will read
        it back (plain CPU tensors), so that a run and its resumption go on alike."""
        data = record.plain()
        buffer = io.BytesIO()
        torch.save(data, buffer)
        atomic_write_bytes(self.folder / f"batch_{number:06d}.pt", buffer.getvalue())
        return BatchRecord.from_plain(data)

    def clear(self) -> None:
        """Remove the journal folder and all it holds."""
        if self.folder.is_dir():
            shutil.rmtree(self.folder)
