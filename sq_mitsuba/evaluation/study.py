"""Illumination study: how the metrics change with the sun's phase angle, the Earth behind the
target, and eclipses.

:func:`illumination_study` renders fixed poses of the given models under a sweep of sun phase
angles (0 to 180 degrees in steps of ``step``), each with and without the Earth in view, plus
eclipse frames (the sun behind the Earth), then evaluates the model on every one with
:func:`sq_mitsuba.evaluation.evaluate.evaluate`: the network, the global pose search and the
search + refinement, both against the mask read from the image itself (the network's mask
head, or the threshold segmentation for a model without one), by default. Every sweep point
is an ordinary dataset, rendered by :func:`sq_mitsuba.data.spe3r.render_dataset` with scene
overrides
(``sun.phase_deg=[a,a]``, ``earth.probability_in_view=0|1``, ``eclipse.probability=0|1``), so
the images are exactly what the dataset renderer makes: the same seed and image index draw
the same pose whatever the lighting (the pose is drawn before the lighting), and a rerun into
the same folder resumes: its renders, and its evaluations: a sweep point whose ``eval.json``
records the same evaluation options, checkpoint weights and data
(:func:`sq_mitsuba.evaluation.journal.finished_evaluation`) is read back from its
``per_image.csv``, not evaluated again, and an interrupted one continues from its journal
(``evaluate(..., resume=True)``; a journal of other settings is cleared instead).

Output folder:

- ``models/``: copies of the chosen models (with their ``symmetries.json``), marked ``test``;
- ``renders/<point>/``: one SPE3R-layout dataset per sweep point (``phase_030_space``,
  ``phase_030_earth``, ..., ``eclipse``);
- ``evals/<point>/``: the evaluation of each (tables and ``eval.json``);
- ``per_image.csv``: every evaluated row with its sweep point (``point``, ``background``:
  space, earth or eclipse, ``phase_set_deg``) beside the recorded lighting;
- ``illumination.csv`` / ``illumination.md``: mean, std and median of every metric per
  background, phase angle and method; ``illumination.png``: every metric against the phase
  angle, one line per background and method, shaded ± std, eclipses as markers;
- ``study.json``: settings, sweep points, counts and times.

:func:`lighting_breakdown` does the same grouping for a regular evaluation folder, from the
lighting recorded in its ``per_image.csv``: phase-angle bins of ``step`` degrees, Earth in
view or not, eclipses apart (``lighting.csv``, ``lighting.md``, ``lighting.png``).

Convention: on the plots and in the tables, an eclipse group sits at the mean of its recorded
phase angles; a frame of a sweep point that the sampler had to keep in the Earth's shadow
(possible with the Earth in view and the sun behind the target) stays in its sweep point, and
its ``eclipse`` column says so.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from sq_mitsuba.config import apply_overrides, in_range, to_dict, validate
from sq_mitsuba.data.spe3r import RenderOptions
from sq_mitsuba.evaluation.evaluate import (
    GROUP_TABLE_SUFFIXES,
    LIGHTING_STEM,
    EvalOptions,
    check_mesh_ranking,
)
from sq_mitsuba.evaluation.scoring import METRICS
from sq_mitsuba.evaluation.tables import (
    SHOWN,
    csv_text,
    format_stats,
    markdown_table,
    markdown_text,
    summarise,
)
from sq_mitsuba.inputs import finite_number, read_csv_table
from sq_mitsuba.io import atomic_write_json, atomic_write_text

#: Background names: the Earth out of view, in view, and eclipse frames.
BACKGROUNDS = ("space", "earth", "eclipse")


def _study_evaluation() -> EvalOptions:
    return EvalOptions(split="test", refine=True, refine_ground_truth=False, baseline=False,
                       figures=False)


@dataclass(frozen=True)
class StudyOptions:
    """Settings of ``sq-mitsuba study illumination``."""

    poses: int = in_range(1, 100_000, default=8)
    "Fixed poses (images) per model, the same at every sweep point."
    step: float = in_range(1.0, 180.0, default=15.0)
    "Step in degrees of the phase-angle sweep from 0 to 180 (and of the bins of --eval)."
    split: Literal["train", "test", "all"] = "test"
    "Models of the library to use, by its splits.csv ('all': every model)."
    max_models: int | None = in_range(1, 100_000, default=None)
    "Use at most this many of them (spread evenly over their sorted names; None: all)."
    render: RenderOptions = field(default_factory=RenderOptions)
    "Dataset renderer settings (images_per_model, shard and overwrite are set by the study:"
    " its values here are not used; the CLI refuses them in --set)."
    evaluation: EvalOptions = field(default_factory=_study_evaluation)
    "Evaluation settings (split 'test' and no baseline, whatever they say here: every study"
    " model is a test model)."


#: Fields the study sets itself, whatever the options say (its --poses as every model's
#: images, one run of the test split without a baseline), with the option that sets them.
STUDY_SET = {"render.images_per_model": "--poses", "render.shard": None,
             "render.overwrite": None, "evaluation.split": None, "evaluation.baseline": None}


def _render_point(models: Path, out: Path, render: RenderOptions) -> Any:
    """One sweep point's images: ``render_dataset``, its refusal of a folder of another run
    told in the study's own terms (it has no --overwrite: the folder goes)."""
    from sq_mitsuba.data.spe3r import render_dataset
    from sq_mitsuba.data.spe3r.layout import DatasetError

    try:
        return render_dataset(models, out, render, progress=False)
    except DatasetError as error:
        instead = f"delete {out.parent.parent} to start over, or give another --out"
        text = str(error).replace("images_per_model (--images-per-model)", "--poses").replace(
            "images_per_model", "--poses").replace(
            "use --overwrite to start over, or another --out",
            f"a study of other settings: {instead}").replace(
            "render into another folder, or use --overwrite", instead)
        raise DatasetError(text) from None


@dataclass(frozen=True)
class SweepPoint:
    """One lighting of the sweep: its name, background, phase angle and scene overrides."""

    name: str
    background: str
    phase_deg: float | None
    overrides: tuple[str, ...]


def sweep_points(step: float) -> list[SweepPoint]:
    """Phase angles 0, step, ..., up to 180 deg, each without and with the Earth in view,
    then the eclipse point."""
    points = []
    angles = [float(k * step) for k in range(int(180.0 / step + 1e-9) + 1)]
    for angle in angles:
        for background, in_view in (("space", 0), ("earth", 1)):
            points.append(SweepPoint(
                f"phase_{angle:05.1f}_{background}".replace(".0_", "_"), background, angle,
                (f"sun.phase_deg=[{angle!r},{angle!r}]", f"earth.probability_in_view={in_view}",
                 "eclipse.probability=0")))
    points.append(SweepPoint("eclipse", "eclipse", None, ("eclipse.probability=1",)))
    return points


@dataclass
class StudyResult:
    """What :func:`illumination_study` or :func:`lighting_breakdown` did."""

    rows: list[dict[str, Any]]
    table: list[dict[str, Any]]
    out_dir: Path
    files: list[Path]

    def describe(self) -> str:
        return f"{len(self.rows)} rows in {len(self.table)} groups; wrote " + \
            ", ".join(str(p) for p in self.files)


# ------------------------------------------------------------------------------- grouping


def group_table(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean, std and median of every metric per (background, phase_deg, method) of ``rows``
    (each row with ``background`` and ``phase_deg``); an eclipse group's ``phase_deg`` is the
    mean of its rows'. Sorted by background, phase angle and method."""
    from sq_mitsuba.evaluation.evaluate import METHODS

    stats = summarise(rows, ("background", "phase_deg", "method"),
                      metrics=(*METRICS, "phase_angle_deg"))
    table = []
    for (background, phase, method), values in stats.items():
        members = [r for r in rows if (r["background"], r["phase_deg"], r["method"]) ==
                   (background, phase, method)]
        entry: dict[str, Any] = {"background": background, "phase_deg": phase,
                                 "method": method, "images": len(members),
                                 "eclipse_frames": sum(_flag(r.get("eclipse"))
                                                       for r in members),
                                 "phase_recorded_deg": values["phase_angle_deg"][0]}
        for metric in METRICS:
            mean, std, median = values[metric]
            entry.update({f"{metric}_mean": mean, f"{metric}_std": std,
                          f"{metric}_median": median})
        table.append(entry)
    order = {m: k for k, m in enumerate(METHODS)}
    table.sort(key=lambda e: (BACKGROUNDS.index(e["background"]) if e["background"] in
                              BACKGROUNDS else 9, e["phase_deg"], order.get(e["method"], 9)))
    return table


def _flag(value: Any) -> bool:
    return value is True or str(value).strip().lower() in ("true", "1")


def write_group_tables(table: Sequence[dict[str, Any]], out_dir: Path, stem: str,
                       title: str) -> list[Path]:
    """``<stem>.csv`` (long: one row per group and metric), ``<stem>.md`` and ``<stem>.png``."""
    from sq_mitsuba.evaluation.figures import plot_illumination

    csv_path, md_path, png_path = (out_dir / f"{stem}.{suffix}"
                                   for suffix in GROUP_TABLE_SUFFIXES)
    header = ["background", "phase_deg", "method", "images", "eclipse_frames",
              "phase_recorded_deg", "metric", "mean", "std", "median"]
    body = [[e["background"], round(e["phase_deg"], 3), e["method"], e["images"],
             e["eclipse_frames"], round(e["phase_recorded_deg"], 3), metric,
             e[f"{metric}_mean"], e[f"{metric}_std"], e[f"{metric}_median"]]
            for e in table for metric in METRICS]
    atomic_write_text(csv_path, csv_text(header, body))
    md_rows = [[e["background"], f"{e['phase_deg']:.1f}", e["method"], e["images"],
                e["eclipse_frames"],
                *(format_stats(e[f"{m}_mean"], e[f"{m}_std"], e[f"{m}_median"])
                  for m in SHOWN)] for e in table]
    atomic_write_text(md_path, (
        f"# {markdown_text(title)}\n\nMean ± std (median) per background, phase angle and "
        f"method; every metric is in {csv_path.name}. An eclipse group's phase angle is the "
        "mean of its recorded ones.\n\n"
        + markdown_table(["background", "phase [deg]", "method", "images", "eclipse frames",
                          *SHOWN], md_rows)))
    plot_illumination(table, png_path, METRICS, title)
    return [csv_path, md_path, png_path]


# ------------------------------------------------------------------------------- the study


def _choose_models(models_dir: Path, options: StudyOptions) -> list[str]:
    from sq_mitsuba.data.spe3r.layout import DatasetError, read_splits
    from sq_mitsuba.data.spe3r.writer import check_library_models, find_models
    from sq_mitsuba.evaluation.split import evenly

    names = find_models(models_dir)
    if options.split != "all":
        splits_path = models_dir / "splits.csv"
        if not splits_path.is_file():
            raise DatasetError(f"{splits_path}: missing; use split 'all' to take every model")
        splits = read_splits(splits_path)
        names = [n for n in names if splits.get(n) == options.split]
    if not names:
        raise DatasetError(f"{models_dir}: no {options.split!r} models in splits.csv")
    chosen = [names[k] for k in evenly(len(names), options.max_models)]
    check_library_models(models_dir, chosen)  # in the library, before any work: named there
    return chosen


def _stage_models(models_dir: Path, names: Sequence[str], stage: Path) -> None:
    """Copy the models into ``stage`` with a splits.csv marking them all ``test``, and detect
    each one's symmetries once there, written as its ``symmetries.json`` (the renders copy it
    along, so no sweep point's evaluation detects them again)."""
    from sq_mitsuba.data.spe3r.layout import MODELS, write_splits
    from sq_mitsuba.data.symmetry import SYMMETRIES_FILE, model_symmetries

    stage.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copytree(models_dir / name / MODELS, stage / name / MODELS, dirs_exist_ok=True)
        if not (models_dir / name / MODELS / SYMMETRIES_FILE).is_file():
            # An earlier run's detection may be of a model since edited: detected afresh.
            (stage / name / MODELS / SYMMETRIES_FILE).unlink(missing_ok=True)
        try:
            model_symmetries(stage / name, write=True)  # the study owns its models/
        except (OSError, ValueError) as error:  # the copy is the library's file: name that
            raise ValueError(str(error).replace(str(stage / name), str(models_dir / name))) \
                from None
    write_splits(stage, [(name, "test") for name in names])  # quoted as every splits.csv


def illumination_study(checkpoint: str | Path | None, models_dir: str | Path,
                       out_dir: str | Path, options: StudyOptions | None = None,
                       progress: bool = True) -> StudyResult:
    """Render and evaluate the sweep described in the module docstring.

    Args:
        checkpoint: the model to study (None: the model shipped with the package).
        models_dir: a model library (``<model>/models/model_normalized.obj``, splits.csv).
        out_dir: output folder (a rerun with the same settings resumes its renders).
        options: :class:`StudyOptions`.
    """
    from sq_mitsuba.evaluation.evaluate import effective_options, evaluate
    from sq_mitsuba.evaluation.journal import (
        JOURNAL,
        RUN_FILE,
        finished_evaluation,
        journal_difference,
        run_identity,
    )
    from sq_mitsuba.evaluation.split import check_predictor
    from sq_mitsuba.inference.loading import load_model, with_fast_path
    from sq_mitsuba.io import check_output_folder, inside_folder
    from sq_mitsuba.progress import progress_bar

    options = options or StudyOptions()
    validate(options)
    models_dir, out_dir = Path(models_dir), Path(out_dir)
    predictor = load_model(checkpoint)
    check_predictor(predictor)
    names = _choose_models(models_dir, options)
    if inside_folder(out_dir, models_dir):  # its folders would be read as models next time
        raise ValueError(f"out {out_dir}: inside the model library {models_dir}; write the "
                         "study outside it")
    check_output_folder(out_dir)
    points = sweep_points(options.step)
    # Every scene override is checked before the first render.
    renders = {point.name: dataclasses.replace(
        options.render, images_per_model=options.poses, shard="0/1", overwrite=False,
        scene=apply_overrides(options.render.scene, point.overrides)) for point in points}
    evaluation = dataclasses.replace(options.evaluation, split="test", baseline=False)
    validate(evaluation)
    # Each sweep point's evaluation would refuse it, after the renders: refused now.
    check_mesh_ranking(evaluation.mesh_ranking, names, f"the study ({models_dir})",
                       "evaluation.mesh_ranking")
    predictor = with_fast_path(predictor, evaluation.fast)  # once, not per sweep point
    started = time.perf_counter()
    stage = out_dir / "models"
    _stage_models(models_dir, names, stage)
    rows: list[dict[str, Any]] = []
    seconds = {"render": 0.0, "evaluate": 0.0}
    images = len(names) * options.poses  # each point renders and evaluates them all
    for point in progress_bar(points, desc=f"illumination study ({images} images a point)",
                              unit="point", disable=not progress):
        tick = time.perf_counter()
        summary = _render_point(stage, out_dir / "renders" / point.name, renders[point.name])
        if summary.failures:
            model, reason = next(iter(summary.failures.items()))
            raise ValueError(f"{out_dir / 'renders' / point.name}: {model} failed to render "
                             f"({reason})")
        seconds["render"] += time.perf_counter() - tick
        tick = time.perf_counter()
        data, folder = out_dir / "renders" / point.name, out_dir / "evals" / point.name
        point_rows = None
        identity = run_identity(predictor, data, to_dict(effective_options(evaluation)))
        if finished_evaluation(folder, identity):
            with contextlib.suppress(OSError, ValueError):  # unreadable: evaluated again
                point_rows = read_per_image(folder / "per_image.csv")
        if point_rows is None:  # continued from its journal, unless that is another run's
            point_rows = evaluate(predictor, data, folder, evaluation, progress=False,
                                  resume=(folder / JOURNAL / RUN_FILE).is_file() and
                                  journal_difference(folder, identity) is None).rows
        seconds["evaluate"] += time.perf_counter() - tick
        for row in point_rows:
            phase = point.phase_deg if point.phase_deg is not None else \
                float(row["phase_angle_deg"])
            rows.append({"point": point.name, "background": point.background,
                         "phase_set_deg": "" if point.phase_deg is None else point.phase_deg,
                         "phase_deg": phase, **row})
    _eclipse_at_mean_phase(rows)
    from sq_mitsuba.evaluation.tables import COLUMNS

    columns = ["point", "background", "phase_set_deg", *COLUMNS]
    atomic_write_text(out_dir / "per_image.csv",
                      csv_text(columns, [[r.get(c, "") for c in columns] for r in rows]))
    table = group_table(rows)
    files = [out_dir / "per_image.csv", *write_group_tables(
        table, out_dir, "illumination",
        f"illumination study: {len(names)} model(s) x {options.poses} pose(s)")]
    atomic_write_json(out_dir / "study.json", {
        "checkpoint": str(getattr(predictor, "source", None) or ""),
        "models_dir": str(models_dir), "models": names,
        "points": [dataclasses.asdict(p) for p in points],
        "options": to_dict(options), "rows": len(rows),
        "render_seconds": round(seconds["render"], 2),
        "evaluate_seconds": round(seconds["evaluate"], 2),
        "wall_seconds": round(time.perf_counter() - started, 2),
    })
    files.append(out_dir / "study.json")
    return StudyResult(rows, table, out_dir, files)


def _eclipse_at_mean_phase(rows: list[dict[str, Any]]) -> None:
    """Put every eclipse row at the mean recorded phase angle of the eclipse rows (one group
    per method, not one per frame)."""
    phases = [float(r["phase_angle_deg"]) for r in rows if r["background"] == "eclipse"]
    if phases:
        mean = sum(phases) / len(phases)
        for row in rows:
            if row["background"] == "eclipse":
                row["phase_deg"] = mean


# ------------------------------------------------------------------------------- breakdown


def read_per_image(path: Path) -> list[dict[str, Any]]:
    """Rows of an evaluation's ``per_image.csv``; a one-line error naming the file when it is
    missing, empty, cut short or has no lighting record (:func:`sq_mitsuba.inputs.
    read_csv_table`)."""
    from sq_mitsuba.evaluation.tables import LIGHTING

    return read_csv_table(path, ("model", "method", *METRICS, *LIGHTING))


def lighting_breakdown(eval_dir: str | Path, out_dir: str | Path | None = None,
                       step: float | None = None) -> StudyResult:
    """Group a regular evaluation's ``per_image.csv`` by its recorded lighting: phase-angle
    bins of ``step`` degrees (default :class:`StudyOptions`' step; a bin is drawn at its
    centre), Earth in view or not, and eclipse frames apart; writes ``lighting.csv``,
    ``lighting.md`` and ``lighting.png`` into ``out_dir`` (default: ``eval_dir``)."""
    from sq_mitsuba.io import check_output_folder

    eval_dir = Path(eval_dir)
    out_dir = Path(out_dir) if out_dir is not None else eval_dir
    step = StudyOptions().step if step is None else float(step)
    if not 1.0 <= step <= 180.0:
        raise ValueError(f"step: expected a value in [1, 180], got {step:g}")
    source = eval_dir / "per_image.csv"
    if source.is_file() and not (eval_dir / "eval.json").is_file():  # written last by eval
        raise ValueError(f"{eval_dir}: an unfinished evaluation (no eval.json: interrupted, "
                         "or still running); finish it with the same eval command and "
                         "--resume first")
    raw = read_per_image(source)
    unlit = [r for r in raw if not r["phase_angle_deg"].strip()]
    if len(unlit) == len(raw):
        raise ValueError(f"{source}: no lighting record (phase_angle_deg is empty: a dataset "
                         "without one, such as the SPE3R release)")
    check_output_folder(out_dir)
    bins = math.ceil(180.0 / step - 1e-9)
    rows = []
    for row in raw:
        if row in unlit:
            continue
        phase = finite_number(row["phase_angle_deg"], f"{source}: phase_angle_deg of "
                              f"{row['model']} image {row.get('index', '?')}")
        if _flag(row["eclipse"]):
            background = "eclipse"
        else:
            background = "earth" if _flag(row["earth_in_view"]) else "space"
        low = min(int(phase // step), bins - 1) * step  # the last bin ends at 180
        rows.append({**row, "background": background,
                     "phase_deg": (low + min(low + step, 180.0)) / 2})
    _eclipse_at_mean_phase(rows)
    out_dir.mkdir(parents=True, exist_ok=True)
    table = group_table(rows)
    files = write_group_tables(table, out_dir, LIGHTING_STEM,
                               f"{source}: metrics by recorded lighting ({step:g} deg bins)")
    return StudyResult(rows, table, out_dir, files)
