"""The run's records: ``log.csv`` (one row per step), ``val.csv`` (one per validation),
TensorBoard events when the package is importable, and ``curves.png``.

``log.csv``'s columns: step, epoch, learning rate, total loss and each registered loss term
(:data:`~sq_mitsuba.training.loss_terms.LOSS_TERMS`; the mean over the global batch, empty
when the term is off), gradient norm before clipping, images/s. Numbers are written exactly
(floats by ``repr``), so two runs' logs compare bit for bit.
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sq_mitsuba.io import atomic_path, atomic_write_text
from sq_mitsuba.training.loss_terms import LOSS_TERMS
from sq_mitsuba.training.run.folder import LOG_FILE, VAL_FILE
from sq_mitsuba.training.validation import VAL_METRICS

__all__ = ["RunLog", "format_number", "plot_curves"]


class RunLog:
    """log.csv and val.csv (rank 0), truncated to the resumed step, plus TensorBoard.

    Args:
        out_dir: the run folder.
        resume_step: the step a resumed run continues from (later rows are dropped); None for
            a new run.
        val_upto: keep val.csv's rows up to this step instead (None: ``resume_step``); a
            resumed run that first runs the validation of ``resume_step`` drops its row.
        terms: the loss-term columns (default: every registered term, in registry order).
    """

    def __init__(self, out_dir: Path, resume_step: int | None, tensorboard: bool = True,
                 terms: Sequence[str] | None = None, val_upto: int | None = None) -> None:
        self.terms = tuple(LOSS_TERMS) if terms is None else tuple(terms)
        self.out_dir = out_dir
        self.log_path, self.val_path = out_dir / LOG_FILE, out_dir / VAL_FILE
        self.log_fields = ["step", "epoch", "lr", "loss", *self.terms, "grad_norm",
                           "images_per_s"]
        self.val_fields = ["step", "epoch", *VAL_METRICS]
        self.rows: list[dict[str, float]] = []
        self.val_rows: list[dict[str, float]] = []
        if resume_step is not None:
            self.rows = self._read(self.log_path, resume_step)
            self.val_rows = self._read(self.val_path,
                                       resume_step if val_upto is None else val_upto)
        self._rewrite(self.log_path, self.log_fields, self.rows)
        self._rewrite(self.val_path, self.val_fields, self.val_rows)
        self._log = open(self.log_path, "a", newline="", encoding="utf-8")
        self._writer = csv.DictWriter(self._log, self.log_fields, lineterminator="\n")
        self.tensorboard = None
        if tensorboard:
            with contextlib.suppress(ImportError):
                from torch.utils.tensorboard import SummaryWriter

                # TensorBoard hides every tag's events from purge_step on, so it purges from
                # the first step either CSV drops (the training rows after resume_step, the
                # validations after val_upto) and the training rows kept from there on are
                # written again: it then shows what the CSVs hold.
                purge = None
                if resume_step is not None:
                    purge = 1 + (resume_step if val_upto is None
                                 else min(resume_step, val_upto))
                self.tensorboard = SummaryWriter(str(out_dir / "tensorboard"), purge_step=purge)
                for row in self.rows if purge is not None else ():
                    if int(row["step"]) >= purge:
                        self._train_scalars(row)

    @staticmethod
    def _read(path: Path, upto: int) -> list[dict[str, float]]:
        """Complete rows of an earlier log up to step ``upto`` (a row cut by a kill is
        dropped, and so are steps after the checkpoint, which the resumed run repeats)."""
        if not path.is_file():
            return []
        rows = []
        with open(path, newline="", encoding="utf-8") as handle:
            for row in csv.DictReader(handle):
                if None in row or any(v is None for v in row.values()):
                    continue  # too many or too few fields: a line cut short
                try:
                    values = {k: float(v) for k, v in row.items() if v != ""}
                except ValueError:
                    continue
                if "step" in values and values["step"] <= upto:
                    rows.append(values)
        return rows

    @staticmethod
    def _rewrite(path: Path, fields: list[str], rows: list[dict[str, float]]) -> None:
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fields, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: format_number(row.get(k)) for k in fields})
        atomic_write_text(path, buffer.getvalue())

    def step(self, row: dict[str, float]) -> None:
        self.rows.append(row)
        self._writer.writerow({k: format_number(row.get(k)) for k in self.log_fields})
        self._log.flush()
        if self.tensorboard is not None:
            self._train_scalars(row)

    def _train_scalars(self, row: dict[str, float]) -> None:
        step = int(row["step"])
        for key in ("loss", "lr", "images_per_s", *self.terms):
            if row.get(key) is not None:
                self.tensorboard.add_scalar(f"train/{key}", row[key], step)

    def validation(self, row: dict[str, float]) -> None:
        self.val_rows.append(row)
        self._rewrite(self.val_path, self.val_fields, self.val_rows)
        if self.tensorboard is not None:
            for key in VAL_METRICS:
                if math.isfinite(row.get(key, math.nan)):
                    self.tensorboard.add_scalar(f"val/{key}", row[key], int(row["step"]))

    def close(self) -> None:
        self._log.close()
        if self.tensorboard is not None:
            self.tensorboard.close()


def format_number(value: float | None) -> str:
    """Exact text of a logged number (repr round-trips floats); whole numbers as integers."""
    if value is None:
        return ""
    if isinstance(value, int) or (isinstance(value, float) and value.is_integer()
                                  and abs(value) < 2**53):
        return str(int(value))
    return repr(float(value))


def plot_curves(rows: Sequence[dict[str, float]], val_rows: Sequence[dict[str, float]],
                path: Path, terms: Sequence[str] | None = None) -> Path:
    """``curves.png``: each loss term per step (log scale) and each validation metric that
    has a value. ``terms``: the term columns (default: every registered term)."""
    terms = tuple(LOSS_TERMS) if terms is None else tuple(terms)
    from matplotlib.figure import Figure

    # A panel per validation metric with a value: a run resumed from before a metric existed,
    # a network without a mask head or a run not yet validated has none to show.
    metrics = [name for name in VAL_METRICS
               if any(r.get(name) is not None and np.isfinite(r[name]) for r in val_rows)]
    figure = Figure(figsize=(12 if metrics else 5, 4))
    axes = np.atleast_1d(figure.subplots(1, 1 + len(metrics)))
    steps = [r["step"] for r in rows]
    settled: list[float] = []  # values after the first steps, which set the y range
    skip = max(10, len(rows) // 50)
    for name in ("loss", *terms):
        values = [r.get(name) for r in rows]
        if any(v is not None and v > 0 for v in values):
            axes[0].plot(steps, [v if v is not None and v > 0 else np.nan for v in values],
                         label=name, linewidth=0.8)
            settled += [v for v in values[skip:] if v is not None and v > 0]
    axes[0].set_yscale("log")
    if settled:  # a regulariser starting near 0 (taper) would otherwise squash every curve
        low, high = np.percentile(settled, [0.5, 100.0])
        axes[0].set_ylim(0.5 * low, 2.0 * high)
    axes[0].set_xlabel("step")
    axes[0].set_title("training loss (global batch mean)")
    axes[0].legend(fontsize=7)
    for axis, name in zip(axes[1:], metrics, strict=True):
        axis.plot([r["step"] for r in val_rows], [r.get(name, np.nan) for r in val_rows],
                  marker="o")
        axis.set_xlabel("step")
        axis.set_title(f"val {name}")
    # Fixed margins: tight_layout would lay every label out once more before the save, as
    # long as the save itself, and a training run writes this figure at every close.
    figure.subplots_adjust(left=0.12 if not metrics else 0.05, right=0.98, bottom=0.13,
                           top=0.92, wspace=0.3)
    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=100, format="png")
    return path
