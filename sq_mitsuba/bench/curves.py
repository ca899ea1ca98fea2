"""``sq-mitsuba bench curves``: held-out Chamfer-L1 against training time, config by config.

:func:`learning_curves` trains each config for the same wall-clock budget on a real dataset,
one after the other, validating after each of ``points`` equal slices of it, and
:func:`run_curves` plots the curves and writes their table (into eval/BENCHMARKS.md with
``--write``).

Resumable: a config's run folder ``OUT/<label>/`` holds ``curve.json`` (the settings, and the
points so far) from its start, and after each point ``point_<k>.pt`` (the checkpoint at the
last point, k). A rerun into the same ``OUT`` with the same settings keeps the points
recorded, skips a finished config, and continues an unfinished one from its last point: the
checkpoint of that point comes back as ``last.pt``, so training cut between two points is
trained again and every point's time counts the training before it exactly once; a config cut
before its first point starts over. A run folder that holds something else (no
``curve.json``, or one of other settings) is refused, before any training, naming it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from sq_mitsuba.bench import BENCHMARKS_MD, load_average
from sq_mitsuba.bench.train import load_config

__all__ = [
    "CURVES_PNG",
    "CURVE_CONFIGS",
    "Curve",
    "check_curves_output",
    "curves_figure_path",
    "curves_report",
    "learning_curves",
    "plot_learning_curves",
    "run_curves",
]

#: Configs of :func:`learning_curves`: label -> (config file stem, ``--set`` overrides).
CURVE_CONFIGS: dict[str, tuple[str, tuple[str, ...]]] = {
    "a": ("a", ()),
    "cpu": ("cpu", ()),
    "cpu, no augmentation": ("cpu", ("augment.probability=0",)),
}
CURVES_PNG = BENCHMARKS_MD.parent / "figures" / "learning_curves.png"
#: What a config's run folder keeps between points (module docstring): the record, and the
#: checkpoint of its last point k.
CURVE_FILE, POINT_CHECKPOINT = "curve.json", "point_{point}.pt"


@dataclasses.dataclass
class Curve:
    """Held-out Chamfer-L1 of one config against its training time."""

    label: str
    seconds: list[float] = dataclasses.field(default_factory=list)
    "Training wall time (s, steps only) at each validation."
    steps: list[int] = dataclasses.field(default_factory=list)
    chamfer_l1: list[float] = dataclasses.field(default_factory=list)
    "Mean Chamfer-L1 (paper convention) over the validation images."
    images_per_second: float = float("nan")
    finished: bool = False
    "Every point measured, or the schedule ended before the last."
    images: int = 0
    "Training images of the timed steps (the first step of each slice is not timed)."
    timed: float = 0.0
    "Their training time (s): ``images_per_second`` is ``images / timed``."


def run_folder(out_dir: Path, label: str) -> Path:
    """``out_dir/<label>`` with commas dropped and spaces made underscores."""
    return out_dir / label.replace(",", "").replace(" ", "_")


def check_curves_output(data_root: str | Path, out_dir: str | Path) -> Path:
    """``out_dir`` as a Path, if the curves can write their runs there: not the dataset folder
    ``data_root`` nor inside it (the runs' logs, caches and evaluations would become part of
    the dataset, which they only read), and writable (:func:`~sq_mitsuba.io.
    check_output_folder`). Called before any training: the first evaluation would refuse it
    only after a slice of training, its files left in the dataset.

    Raises:
        ValueError: ``out <out_dir>: ...`` (one line).
    """
    from sq_mitsuba.io import check_output_folder, inside_folder

    if inside_folder(out_dir, data_root):
        raise ValueError(f"out {out_dir}: inside the dataset folder {data_root}, which the "
                         "curves only read; choose a folder outside it")
    return check_output_folder(out_dir)


def learning_curves(data_root: str | Path, out_dir: str | Path, minutes: float,
                    labels: Sequence[str] | None = None, points: int = 4,
                    val_images: int = 64, progress: bool = True,
                    configs: dict[str, Any] | None = None) -> list[Curve]:
    """Train each config for ``minutes`` of wall time, one after the other, validating
    held-out Chamfer-L1 ``points`` times (after each of ``points`` equal time slices).

    Each config trains in ``out_dir/<label>/`` with :func:`~sq_mitsuba.training.train.train`
    (``max_seconds`` per slice, resumed between slices, so one uninterrupted schedule); after
    each slice its ``last.pt`` is scored by :func:`~sq_mitsuba.evaluation.evaluate.evaluate`
    on ``val_images`` images of the val split (no refinement, baseline or figures). The
    validations are not counted in the training time. A rerun continues where one stopped
    (module docstring).

    Args:
        data_root: SPE3R-layout dataset (train and val splits).
        out_dir: created; one run folder per config.
        minutes: training budget of each config.
        labels: keys of :data:`CURVE_CONFIGS` (default: all three).
        configs: label -> TrainConfig, instead of :data:`CURVE_CONFIGS` (tests).

    Returns:
        One :class:`Curve` per config, in order.

    Raises:
        ValueError: one line naming the argument or the run folder (an ``out_dir`` inside
            ``data_root`` or not writable: :func:`check_curves_output`), before any training.
    """
    from sq_mitsuba.config import apply_overrides, to_dict

    if not minutes > 0:
        raise ValueError(f"minutes: expected > 0, got {minutes}")
    if points < 1:
        raise ValueError(f"points: expected >= 1, got {points}")
    if configs is None:
        labels = list(CURVE_CONFIGS) if labels is None else list(labels)
        for label in labels:
            if label not in CURVE_CONFIGS:
                raise ValueError(f"configs: unknown {label!r}; choose from {list(CURVE_CONFIGS)}")
        configs = {}
        for label in labels:
            stem, overrides = CURVE_CONFIGS[label]
            configs[label] = apply_overrides(load_config(stem), list(overrides))
    data_root, out_dir = Path(data_root), Path(out_dir)
    if not data_root.is_dir():
        raise ValueError(f"{data_root}: dataset folder not found")
    runs = {label: run_folder(out_dir, label) for label in configs}
    folders = [run.name for run in runs.values()]
    for label, folder in zip(configs, folders, strict=True):
        if folders.count(folder) > 1:
            raise ValueError(f"configs: {label!r} and another label share the run folder "
                             f"{folder!r}; name them apart")
    check_curves_output(data_root, out_dir)
    settings = {label: {"label": label, "minutes": minutes, "points": points,
                        "val_images": val_images, "data": str(data_root.resolve()),
                        "config": to_dict(config)} for label, config in configs.items()}
    settings = json.loads(json.dumps(settings))  # compared as curve.json holds them
    recorded = {label: _recorded(runs[label], settings[label]) for label in configs}
    out_dir.mkdir(parents=True, exist_ok=True)
    return [recorded[label] if recorded[label].finished else
            _measure(config, recorded[label], settings[label], data_root, runs[label], progress)
            for label, config in configs.items()]


def _recorded(run_dir: Path, settings: dict[str, Any]) -> Curve:
    """The points recorded in ``run_dir`` with ``settings``: none for a folder not there or
    one cut before its first point, which :func:`_measure` then starts over."""
    from sq_mitsuba.io import read_json

    label = settings["label"]
    if not run_dir.exists():
        return Curve(label)
    record = run_dir / CURVE_FILE
    stored = read_json(record) if record.is_file() else None
    if not isinstance(stored, dict) or stored.get("settings") != settings:
        raise ValueError(f"{run_dir}: holds a run that is not this curve's (no {CURVE_FILE}, "
                         f"or one of other settings); remove it or choose another --out")
    curve = Curve(label, [float(v) for v in stored["seconds"]],
                  [int(v) for v in stored["steps"]], [float(v) for v in stored["chamfer_l1"]],
                  float(stored["images_per_second"]), bool(stored["finished"]),
                  int(stored["images"]), float(stored["timed"]))
    if curve.seconds and not (run_dir / _point_checkpoint(len(curve.seconds))).is_file():
        raise ValueError(f"{run_dir}: the checkpoint of its point {len(curve.seconds)} "
                         f"({_point_checkpoint(len(curve.seconds))}) is missing; remove the "
                         "folder or choose another --out")
    return curve


def _point_checkpoint(point: int) -> str:
    """The file name of the checkpoint at ``point`` (1-based)."""
    return POINT_CHECKPOINT.format(point=point)


def _write_record(run_dir: Path, settings: dict[str, Any], curve: Curve) -> None:
    from sq_mitsuba.io import atomic_write_json

    atomic_write_json(run_dir / CURVE_FILE, {
        "settings": settings, "seconds": curve.seconds, "steps": curve.steps,
        "chamfer_l1": curve.chamfer_l1, "images_per_second": curve.images_per_second,
        "finished": curve.finished, "images": curve.images, "timed": curve.timed})


def _measure(config: Any, curve: Curve, settings: dict[str, Any], data_root: Path,
             run_dir: Path, progress: bool) -> Curve:
    """``curve`` continued to ``settings["points"]`` points in ``run_dir``.

    Order of writes: point k's checkpoint (a file of its own), then ``curve.json`` naming k
    points, then point k - 1's checkpoint removed; a run cut anywhere leaves ``curve.json``
    and the checkpoint of its last point in step."""
    from sq_mitsuba.evaluation.evaluate import EvalOptions, evaluate_checkpoint
    from sq_mitsuba.io import atomic_path
    from sq_mitsuba.training.train import train

    points, minutes = settings["points"], settings["minutes"]
    trained = curve.seconds[-1] if curve.seconds else 0.0
    if curve.seconds:  # the state at the last point; training after it is done again
        with atomic_path(run_dir / "last.pt") as tmp:
            shutil.copyfile(run_dir / _point_checkpoint(len(curve.seconds)), tmp)
    else:  # a new curve, or one cut before its first point (its folder ours: start over)
        shutil.rmtree(run_dir, ignore_errors=True)
        run_dir.mkdir(parents=True)
        _write_record(run_dir, settings, curve)
    for index in range(len(curve.seconds), points):
        result = train(config, data_root, run_dir, resume=index > 0, progress=progress,
                       max_seconds=60.0 * minutes / points)
        trained += result.train_seconds
        if result.images_per_second == result.images_per_second:
            done = (len(result.losses) - 1) * config.optim.batch_size
            curve.images += done
            curve.timed += done / result.images_per_second
        scored = evaluate_checkpoint(
            run_dir / "last.pt", data_root, run_dir / f"val_{index}",
            EvalOptions(split="val", limit=settings["val_images"], baseline=False,
                        figures=False),
            progress=False)
        method = next(iter(scored.summary))
        curve.seconds.append(trained)
        curve.steps.append(result.steps)
        curve.chamfer_l1.append(scored.summary[method]["chamfer_l1_paper"][0])
        curve.images_per_second = curve.images / curve.timed if curve.timed > 0 \
            else float("nan")
        curve.finished = index + 1 == points or result.steps >= result.total_steps
        with atomic_path(run_dir / _point_checkpoint(index + 1)) as tmp:
            shutil.copyfile(run_dir / "last.pt", tmp)
        _write_record(run_dir, settings, curve)
        (run_dir / _point_checkpoint(index)).unlink(missing_ok=True)
        if curve.finished:
            break
    return curve


def plot_learning_curves(curves: Sequence[Curve], path: Path = CURVES_PNG) -> Path:
    """Held-out Chamfer-L1 against training minutes, one line per config, as a PNG."""
    from matplotlib.figure import Figure

    from sq_mitsuba.evaluation.figures import literal  # a label as typed, not mathtext
    from sq_mitsuba.io import atomic_path

    figure = Figure(figsize=(6, 4))
    axis = figure.subplots()
    for curve in curves:
        axis.plot([s / 60 for s in curve.seconds], curve.chamfer_l1, marker="o",
                  label=literal(f"{curve.label} ({curve.images_per_second:.1f} images/s)"))
    axis.set_xlabel("training wall time (min)")
    axis.set_ylabel("val Chamfer-L1 (paper convention)")
    axis.set_title("held-out Chamfer-L1 at equal training time")
    axis.legend(fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=100, format="png")
    return path


def curves_report(curves: Sequence[Curve], minutes: float, data_root: Path,
                  figure: Path | None = None) -> str:
    """The ``curves`` section of BENCHMARKS.md: a table of every validation."""
    import datetime as _dt
    import platform

    from sq_mitsuba.evaluation.tables import markdown_text

    lines = ["### `sq-mitsuba bench curves`", "",
             f"Measured {_dt.date.today().isoformat()} on {platform.node() or 'host'} "
             f"({os.cpu_count()} cores, torch {torch.__version__}): {minutes:g} min of training "
             f"per config on {data_root}; 1-minute load average at the end "
             f"{load_average():.2f}.", "",
             "| config | images/s | training min | steps | val Chamfer-L1 |",
             "|---|---:|---:|---:|---:|"]
    for curve in curves:
        for seconds, steps, value in zip(curve.seconds, curve.steps, curve.chamfer_l1,
                                         strict=True):
            lines.append(f"| {markdown_text(curve.label)} | {curve.images_per_second:.1f} | "
                         f"{seconds / 60:.2f} | {steps} | {value:.4f} |")
    if figure is not None:
        lines += ["", f"Figure: `{figure.relative_to(BENCHMARKS_MD.parent)}`"
                  if figure.is_relative_to(BENCHMARKS_MD.parent) else f"Figure: `{figure}`"]
    return "\n".join(lines) + "\n"


def curves_figure_path(out_dir: str | Path, write: bool) -> Path:
    """Where ``bench curves`` draws its figure: with ``write`` the repository's
    (:data:`CURVES_PNG`, beside the table it belongs to), else in the runs' ``out_dir``."""
    return CURVES_PNG if write else Path(out_dir) / CURVES_PNG.name


def run_curves(data_root: str | Path, out_dir: str | Path, minutes: float,
               labels: Sequence[str] | None = None, write: bool = False,
               figure: Path | None = None, benchmarks: Path = BENCHMARKS_MD,
               progress: bool = True) -> str:
    """:func:`learning_curves`, its figure, and its table (recorded in ``benchmarks``
    between ``<!-- bench:curves:start/end -->`` with ``write``); returns the table.

    The figure goes to ``figure`` (default :func:`curves_figure_path`: a trial run leaves the
    recorded figure alone)."""
    from sq_mitsuba.bench import write_section

    if figure is None:
        figure = curves_figure_path(out_dir, write)
    curves = learning_curves(data_root, out_dir, minutes, labels, progress=progress)
    plot_learning_curves(curves, figure)
    text = curves_report(curves, minutes, Path(data_root), figure)
    if write:
        write_section("curves", text, benchmarks)
    return text
