"""The run folder: its files, the checks before a run starts, the checkpoints it writes, and
those it reads (``last.pt`` to resume, checked against the run; ``init_from``'s weights).

A run folder holds ``config.json``, ``log.csv``, ``val.csv``, ``curves.png``, ``last.pt`` and
``best.pt`` (see :mod:`sq_mitsuba.training.train`). Checkpoints (written atomically by
:func:`~sq_mitsuba.model.checkpoint.write_checkpoint`) hold the config, the model,
optimiser and scheduler states, the RNG states (torch, numpy, python; per process in a
distributed run), the data-order state, the dataset fingerprint and the git commit.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from sq_mitsuba.config import flatten_dict, from_dict, to_dict
from sq_mitsuba.io import atomic_path, check_output_folder, nearest_existing, read_json
from sq_mitsuba.model.checkpoint import load_weights, read_checkpoint, write_checkpoint
from sq_mitsuba.outputs import remove_stray_temporaries
from sq_mitsuba.training.cache import manifest_hash
from sq_mitsuba.training.config import TrainConfig
from sq_mitsuba.training.distributed import unwrap
from sq_mitsuba.training.run.state import TrainError, TrainRun

if TYPE_CHECKING:
    from sq_mitsuba.model.network import SuperquadricNet

__all__ = [
    "BEST",
    "CONFIG_FILE",
    "CURVES_FILE",
    "LAST",
    "LOG_FILE",
    "RESUME_FREE",
    "VAL_FILE",
    "check_cache_dir",
    "check_out_dir",
    "check_resumable",
    "config_difference",
    "git_commit",
    "load_initial_weights",
    "not_finite_error",
    "read_resumed",
    "remove_stale_temporaries",
    "save_checkpoint",
]

LOG_FILE, VAL_FILE, CURVES_FILE = "log.csv", "val.csv", "curves.png"
LAST, BEST, CONFIG_FILE = "last.pt", "best.pt", "config.json"
CHECKPOINT_FORMAT, CHECKPOINT_VERSION = "sq_mitsuba.checkpoint", 1
#: Config fields that may differ between a checkpoint and the run that resumes it.
RESUME_FREE = frozenset({"data.cache_dir", "data.prefetch", "data.prefetch_workers",
                         "reprojection.workers"})


def check_out_dir(out_dir: Path, resume: bool) -> None:
    """Refuse (one line) a run folder that cannot be written, or (without ``resume``) one that
    holds a run's checkpoint, or (with it) one without ``last.pt``. Creates nothing.

    A folder whose run stopped before its first checkpoint (its ``config.json`` and logs
    alone) holds nothing to resume: a new run starts over in it, rewriting them."""
    existing = nearest_existing(out_dir.absolute())
    if existing != out_dir.absolute() and not existing.is_dir():
        raise TrainError(f"{out_dir}: output folder is not writable ({existing} is a file)")
    if existing.is_dir() and not os.access(existing, os.W_OK | os.X_OK):
        raise TrainError(f"{out_dir}: output folder is not writable (permission denied on "
                         f"{existing})")
    if resume and not (out_dir / LAST).is_file():
        raise TrainError(f"{out_dir}: nothing to resume (no {LAST})")
    if not resume and (out_dir / LAST).exists():
        raise TrainError(f"{out_dir}: already holds a training run; resume it (--resume) or "
                         "choose another output folder")
    if not resume and (out_dir / BEST).exists():  # stopped at once before its first last.pt
        raise TrainError(f"{out_dir}: holds a run's {BEST} but no {LAST} to resume from (the "
                         f"run stopped before its first checkpoint); move {BEST} away to start "
                         "over there, or choose another output folder")
    if not resume and not _holds_a_run_config(out_dir / CONFIG_FILE):
        theirs = [name for name in (CONFIG_FILE, LOG_FILE, VAL_FILE, CURVES_FILE)
                  if (out_dir / name).exists()]
        if theirs:  # not a stopped run's: a user's files a run would overwrite
            raise TrainError(f"{out_dir}: holds {', '.join(theirs)}, not of a training run, "
                             "which a run would overwrite; choose another output folder")


def _holds_a_run_config(path: Path) -> bool:
    """Whether ``path`` is a training run's ``config.json`` (its network and optim tables)."""
    try:
        config = read_json(path)
    except (OSError, ValueError):
        return False
    return isinstance(config, dict) and {"network", "optim"} <= set(config)


def check_cache_dir(cache_dir: Path | None, data_root: Path | None = None) -> None:
    """Refuse (one line naming the field) a ``data.cache_dir`` that cannot be written, or one
    inside ``data_root`` or any other dataset folder (its caches would become part of a
    dataset that training only reads, and ``dataset check`` would flag them)."""
    from sq_mitsuba.data.spe3r.layout import check_outside_datasets

    if cache_dir is not None:
        try:
            check_output_folder(cache_dir)
            check_outside_datasets(cache_dir, data_root, "training")
        except ValueError as error:
            raise TrainError(f"data.cache_dir: {str(error).removeprefix('out ')}") from None


def read_resumed(out_dir: Path) -> dict[str, Any]:
    """The run's ``last.pt``, to resume from; one-line TrainError for a file that cannot be
    read or is not a training checkpoint (an exported model holds weights, not the run)."""
    try:
        checkpoint = read_checkpoint(out_dir / LAST)
    except (OSError, ValueError, RuntimeError) as error:
        raise TrainError(f"{out_dir / LAST}: cannot read checkpoint ({error})") from None
    missing = [key for key in ("optimizer", "scheduler", "config", "step") if key not in checkpoint]
    if missing:
        raise TrainError(f"{out_dir / LAST}: not a training checkpoint (no {missing[0]}: an "
                         "exported model?); resume from the run's own last.pt")
    threads = checkpoint.get("torch_threads")
    if isinstance(threads, int) and threads != torch.get_num_threads():
        # Matrix products split their sums by thread: steps differ in their last bits (a
        # 1e-4 product difference at step 1 grew to 7 % of the gradient's norm by step 4).
        warnings.warn(f"{out_dir / LAST}: the run trained with {threads} torch thread(s), this "
                      f"process has {torch.get_num_threads()}: the steps from here will not "
                      f"repeat an uninterrupted run's bit for bit (OMP_NUM_THREADS={threads} "
                      "would)", stacklevel=2)
    return checkpoint


def remove_stale_temporaries(out_dir: Path) -> list[Path]:
    """Delete the temporary files an earlier run killed mid-write left in ``out_dir`` (the
    ``.NAME.<8 random>.tmp.SUFFIX`` files of :func:`sq_mitsuba.io.atomic_path`); returns them.

    Matched by the project's one pattern (:data:`sq_mitsuba.outputs.TEMPORARY_NAME`, as every
    other command's clean-up): a user's hidden file that merely holds ".tmp" in its name is
    not the tool's, and stays."""
    return remove_stray_temporaries(out_dir)


def git_commit() -> dict[str, Any]:
    """The source's git commit and whether the work tree differs from it (None outside git)."""
    root = Path(__file__).resolve().parents[3]
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                                text=True, timeout=10, check=True).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                                cwd=root, capture_output=True, text=True, timeout=10,
                                check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": commit, "dirty": bool(status.strip())}


def config_difference(old: dict[str, Any], new: dict[str, Any]) -> str | None:
    """The first field (dotted) where two ``to_dict`` configs differ, as ``field: a vs b``."""
    a, b = flatten_dict(old), flatten_dict(new)
    for key in sorted(set(a) | set(b)):
        if key in RESUME_FREE:
            continue
        if a.get(key, "<absent>") != b.get(key, "<absent>"):
            return (f"{key} = {a.get(key, '<absent>')!r} in the checkpoint, "
                    f"{b.get(key, '<absent>')!r} in this run")
    return None


def check_resumable(checkpoint: dict[str, Any], config: TrainConfig, fingerprint: str,
                    out_dir: Path, data_root: Path) -> None:
    """Refuse (one line) to resume ``checkpoint`` (``out_dir``'s last.pt) with another config
    (naming the first differing field) or on another dataset than it was trained on."""
    recorded_config = checkpoint["config"]
    # A field added since the checkpoint was written counts at its default (older runs
    # resume); a config that no longer reads is compared as it was written.
    with contextlib.suppress(ValueError, TypeError):
        recorded_config = to_dict(from_dict(TrainConfig, recorded_config))
    difference = config_difference(recorded_config, to_dict(config))
    if difference is not None:
        raise TrainError(f"{out_dir / LAST}: the checkpoint is of another config: {difference}")
    recorded = checkpoint.get("dataset", {}).get("fingerprint")
    if recorded != fingerprint:
        raise TrainError(f"{out_dir / LAST}: the checkpoint was trained on another dataset "
                         f"({checkpoint.get('dataset', {}).get('root')}, fingerprint "
                         f"{str(recorded)[:12]}), {data_root} has {fingerprint[:12]}")


def load_initial_weights(model: SuperquadricNet, path: Path) -> None:
    """``init_from``: the file's weights into ``model``; layers the file lacks stay as built."""
    try:
        state = read_checkpoint(path)["model"]
    except (OSError, ValueError, RuntimeError, KeyError) as error:
        raise TrainError(f"init_from: {path}: cannot read weights ({error})") from None
    try:
        load_weights(model, state, f"init_from: {path}", partial=True)
    except ValueError as error:
        raise TrainError(str(error)) from None


def copy_checkpoint(source: Path, target: Path) -> None:
    """Copy the checkpoint file ``source`` to ``target`` (atomically): the same state, without
    serialising it again."""
    with atomic_path(target) as tmp:
        shutil.copyfile(source, tmp)
        with open(tmp, "rb") as stream:  # on disk before the rename, as write_checkpoint
            os.fsync(stream.fileno())


def save_checkpoint(path: Path, run: TrainRun, step: int, *, model: nn.Module,
                    optimizer: torch.optim.Optimizer, scheduler: Any, steps_per_epoch: int,
                    total_steps: int, train_images: int, rng: dict[str, Any],
                    best: dict[str, Any] | None, validation: list[dict[str, float]],
                    camera: dict[str, Any], git: dict[str, Any]) -> None:
    """Write the checkpoint of ``run`` after ``step`` steps to ``path`` (atomically).

    Args:
        rng: :func:`~sq_mitsuba.training.random_streams.rng_state` of this process, with
            ``ranks`` (every process's) in a distributed run.
        best, validation: the best validation so far and every validation.
        camera: the dataset camera's ``to_speed_dict``.
        git: :func:`git_commit`.
    """
    cfg = run.config
    images_seen = step * cfg.optim.batch_size
    write_checkpoint(path, {
        "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
        "config": to_dict(cfg), "model": _state_dict(model), "camera": camera,
        "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
        "step": step, "epoch": step // steps_per_epoch, "total_steps": total_steps,
        "steps_per_epoch": steps_per_epoch, "rng": rng,
        "data_order": {"scheme": "epoch-permutations", "seed": cfg.seed, "step": step,
                       "images_seen": images_seen, "epoch": images_seen // train_images,
                       "offset": images_seen % train_images, "train_images": train_images},
        "dataset": {"root": str(run.data_root), "fingerprint": run.fingerprint,
                    "manifest_sha256": manifest_hash(run.data_root),
                    "train_images": train_images},
        "git": git, "best": best, "validation": validation, "world_size": run.world.size,
        "torch_threads": torch.get_num_threads(),  # the steps' sums follow it (read_resumed)
    })


def _state_dict(model: nn.Module) -> dict[str, Tensor]:
    return {k: v.detach().cpu().clone() for k, v in unwrap(model).state_dict().items()}


def not_finite_error(step: int, terms: dict[str, Tensor], out_dir: Path) -> TrainError:
    """The error that stops a run at a step whose loss or gradient is not finite."""
    shown = ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in terms.items())
    last = out_dir / LAST
    kept = (f"the last checkpoint, {last} (step {checkpoint_step(last)}), is intact"
            if last.is_file() else "no checkpoint was written yet")
    return TrainError(f"step {step + 1}: the loss or its gradient is not finite "
                      f"({shown or 'non-finite network output'}); stopped without applying "
                      f"the step; {kept}")


def checkpoint_step(path: Path) -> int | str:
    try:
        return int(read_checkpoint(path)["step"])
    except Exception:  # only for a message
        return "?"

