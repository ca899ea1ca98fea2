"""What the trainer's modules share: the run being trained (:class:`TrainRun`), what it did
(:class:`TrainResult`), and how it stops when it cannot go on (:class:`TrainError`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from sq_mitsuba.training.config import TrainConfig
from sq_mitsuba.training.distributed import World

__all__ = ["TrainError", "TrainResult", "TrainRun"]


class TrainError(ValueError):
    """A training run that cannot start or go on; the message is one line."""


@dataclass(frozen=True)
class TrainRun:
    """One training job, as :func:`~sq_mitsuba.training.train.train` resolved it before any
    work: the config, where the data and the run folder are, what it resumes, and where this
    process runs."""

    config: TrainConfig
    data_root: Path
    "SPE3R-layout dataset (``train`` split trains, ``val`` validates)."
    out_dir: Path
    "The run folder."
    fingerprint: str
    "The dataset's fingerprint (:func:`~sq_mitsuba.training.cache.dataset_fingerprint`)."
    device: torch.device
    world: World
    checkpoint: dict[str, Any] | None = None
    "The payload of ``last.pt`` when resuming, else None."
    max_steps: int | None = None
    "Stop after this many steps in total (None: the end of the schedule)."
    max_seconds: float | None = None
    "Stop after the first step that ends this long after the first step started (None: never)."
    progress: bool = True
    "Show a progress bar (rank 0)."

    @property
    def start_step(self) -> int:
        """Steps done before this call (the checkpoint's)."""
        return 0 if self.checkpoint is None else int(self.checkpoint["step"])


@dataclass
class TrainResult:
    """What :func:`~sq_mitsuba.training.train.train` did."""

    out_dir: Path
    steps: int
    "Optimiser steps completed in total (resumed runs count the earlier ones)."
    total_steps: int
    "Steps of the full schedule (epochs x steps per epoch)."
    last_checkpoint: Path | None
    best_checkpoint: Path | None
    losses: list[float] = field(default_factory=list)
    "Total loss of each step run by this call."
    validation: list[dict[str, float]] = field(default_factory=list)
    "Every validation of the run so far (resumed runs include the earlier ones)."
    images_per_second: float = float("nan")
    "Mean training throughput of this call (after its first step, which compiles kernels)."
    train_seconds: float = 0.0
    "Wall time of this call's steps (validation, checkpoints and set-up excluded)."
    notes: list[str] = field(default_factory=list)
    "What the run wants said (one line each), e.g. that best.pt is the last state."
