"""Evaluate passes: one assembly and every pose from N frames, against each frame alone.

:func:`evaluate_passes` reads a dataset of passes (``sq-mitsuba dataset render
--pass-frames F``: each model's images are passes of F frames in order, their labels holding
``pass`` and ``frame_in_pass``; with ``ordered=False`` also a dataset of independent images,
each model's images one unordered set of views) and scores, for each N of ``counts``, the
first N frames of every pass with every metric of ``sq-mitsuba eval``
(:func:`~sq_mitsuba.evaluation.scoring.score`), per frame, for three methods:

- ``network``: the network's own reading of each frame (one pass, no turned copies);
- ``single``: the shipped single-image path, each frame alone
  (``Predictor.predict(images, refine=True)``: the turned copies, the mask, the pose search,
  the refinement), run once per pass on its first ``max(counts)`` frames (the frames are
  independent, so its first N are the N-frame result);
- ``sequence`` (N >= 2): ``Predictor.predict_sequence`` on the first N frames (one assembly,
  N poses; ``ordered``, and ``sequence`` its :class:`SequenceOptions`).

Beside the metrics, each row holds ``relative_rotation_deg``: the angle between the
estimated and the true rotation from the frame before to this one (blank for frame 0), how
well the frames agree with each other whatever their absolute rotation.

Files written to the output folder (each atomically, ``passes.json`` last: it marks a finished
evaluation):

- ``per_frame.csv``: one row per pass, N, method and frame;
- ``summary.csv`` / ``summary.md``: mean, std and median of every metric per N and method;
- ``quality_vs_frames.png``: body-frame Chamfer-L1, camera-frame Chamfer, 2D IoU, folded
  rotation and relative rotation against N, one line per method;
- ``passes.json``: settings, checkpoint, the passes scored, the time taken and the seconds
  per frame of each method per N (mean and median over the passes).

Convention: the timings are this machine's and this run's, so they stay in ``passes.json``
alone (as ``sq-mitsuba eval`` keeps its own in ``eval.json``): two runs of the same settings,
weights and data write the three tables byte for byte alike, a resumed run's included.

A rerun into the same folder takes up where an interrupted one stopped: each pass's rows are
kept in ``.passes_partial/`` (with the run's identity: the options, the network's weights,
the data and the Mitsuba variant, as ``eval --resume``'s journal) until ``passes.json`` is
written, and the passes scored already are read back, not scored again (a pass takes about a
minute on 2 cores). A partial run of other settings is discarded, with a warning.

Convention: the frames are read and scored at the dataset's own resolution (what ``predict
--sequence`` is given by a user), not at the network's input size as ``sq-mitsuba eval``
scores single images; the 2D IoU is that of the assembly's silhouette at each frame's pose
against the frame's true mask there.
"""

from __future__ import annotations

import json
import math
import shutil
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.config import in_range, to_dict, validate
from sq_mitsuba.evaluation.journal import RUN_FILE
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.inference.refine import RefineOptions
from sq_mitsuba.inference.search import SEARCH_REFINEMENT, SearchOptions
from sq_mitsuba.inference.sequence import SequenceOptions
from sq_mitsuba.outputs import json_record, refuse_present

__all__ = ["OUTPUT_FILES", "PassOptions", "PassResult", "evaluate_passes", "pass_groups",
           "relative_rotation_errors", "score_frames"]

PARTIAL = ".passes_partial"
"""The folder of each finished pass's rows, inside the output folder, until ``passes.json``."""
OUTPUT_FILES = ("per_frame.csv", "summary.csv", "summary.md", "quality_vs_frames.png",
                "passes.json")
"""What :func:`evaluate_passes` writes."""
METHODS = ("network", "single", "sequence")
"""The methods scored, in the tables' order (module docstring)."""
PLOTTED = (("chamfer_l1_paper", "body-frame Chamfer-L1", "mean"),
           ("camera_chamfer", "camera-frame Chamfer / distance", "mean"),
           ("iou_2d", "2D IoU", "mean"),
           ("rotation_error_folded_deg", "folded rotation (deg)", "median"),
           ("relative_rotation_deg", "relative rotation (deg)", "median"))
"""The figure's panels: metric, title, statistic (the targets' own: means of the shape and
outline, medians of the rotations)."""


@dataclass(frozen=True)
class PassOptions:
    """Settings of ``sq-mitsuba study passes``."""

    split: Literal["val", "test"] = "test"
    "Dataset split whose passes are scored."
    counts: tuple[int, ...] = in_range(1, 10_000, default=(1, 2, 4, 8))
    "Frames N taken from the start of each pass (every N at most the passes' length)."
    passes: int | None = in_range(1, 1_000_000, default=None)
    "Score at most this many passes, spread evenly over the split (None: all)."
    ordered: bool = True
    """The frames are given to ``predict_sequence`` in the order they were taken (a pass: the
    frames kept on one constant-rate turn); False: as an unordered set, and a dataset of
    independent images is scored too, each model's images as one set of views
    (:func:`pass_groups`)."""
    sequence: SequenceOptions = field(default_factory=SequenceOptions)
    "The joint fit's settings (``predict_sequence``'s ``options``)."
    search: SearchOptions = field(default_factory=SearchOptions)
    "The single-image path's pose search (``predict(refine=True)``'s, the shipped default)."
    refinement: RefineOptions = field(default_factory=lambda: SEARCH_REFINEMENT)
    "The single-image path's refinement after the search (the shipped default)."
    surface_points: int = in_range(1, 1_000_000, default=2500)
    "Ground-truth surface points per frame for the Chamfer distances."
    volume_points: int = in_range(1, 1_000_000, default=20_000)
    "Uniform points per model for the 3D IoU (at most those of samples.npz)."
    level: int = in_range(0, 5, default=2)
    "Icosphere level of the primitive meshes for surface points and silhouettes (2: 162)."
    silhouette_spp: int = in_range(1, 1024, default=16)
    "Samples per pixel of the silhouettes scored by the 2D IoU."
    fast: bool = True
    "Predict with the batch-norm-folded network (same output up to ~1e-5; faster on CPU)."


@dataclass
class PassResult:
    """What :func:`evaluate_passes` did.

    Attributes:
        rows: one dict per pass, N, method and frame (the ``per_frame.csv`` rows, with the
            seconds per frame of the row's method on its pass).
        summary: {(N, method): {metric: (mean, std, median)}}, the timings aside.
        passes: the passes scored, as ``model/pass`` names.
        out_dir: output folder; files: the files written.
    """

    rows: list[dict[str, Any]]
    summary: dict[tuple[int, str], dict[str, tuple[float, float, float]]]
    passes: list[str]
    out_dir: Path
    files: list[Path]
    seconds: dict[tuple[int, str], tuple[float, float]] = field(default_factory=dict)
    "{(N, method): (mean, median) seconds per frame over the passes} (``single``, ``sequence``)."

    def describe(self) -> str:
        """A few lines: the main figures per N and method."""
        lines = [f"scored {len(self.passes)} pass(es): means, (m) medians"]
        for (count, method), stats in sorted(self.summary.items()):
            lines.append(f"  N={count} {method}: " + ", ".join(
                f"{name} {stats[name][2 if how == 'median' else 0]:.3f}{' (m)' * (how == 'median')}"
                for name, _, how in PLOTTED if name in stats)
                + (f", {self.seconds[(count, method)][1]:.2f} s a frame (m)"
                   if (count, method) in self.seconds else ""))
        lines.append(f"wrote {len(self.files)} files to {self.out_dir}")
        return "\n".join(lines)


def relative_rotation_errors(rotation: Tensor, truth: Tensor) -> Tensor:
    """(N,) per frame k >= 1 the angle (deg) between the estimated and the true rotation from
    frame k - 1 to frame k; NaN for frame 0.

    Args:
        rotation, truth: (N, 3, 3) body -> camera rotations of the N frames in order.
    """
    from sq_mitsuba.geometry.metrics import rotation_error_deg

    rotation, truth = rotation.double(), truth.double()
    errors = torch.full((rotation.shape[0],), math.nan, dtype=torch.float64)
    if rotation.shape[0] > 1:
        estimate = rotation[1:] @ rotation[:-1].transpose(-1, -2)
        true = truth[1:] @ truth[:-1].transpose(-1, -2)
        errors[1:] = rotation_error_deg(estimate, true).double()
    return errors


def score_frames(assembly: Assembly, rotation: Tensor, translation: Tensor,
                 batch: dict[str, Any], renderer: Any, symmetry: Tensor,
                 volume: tuple[Tensor, Tensor], level: int) -> dict[str, Tensor]:
    """Every metric (N,) of the N frames of one pass in order: ``sq-mitsuba eval``'s
    (:func:`~sq_mitsuba.evaluation.scoring.score`, the model's ``symmetry`` and ``volume``
    for every frame) and ``relative_rotation_deg`` (:func:`relative_rotation_errors`)."""
    from sq_mitsuba.evaluation.scoring import score

    # The network's own reading stays on the model's device; the truth is on the CPU.
    assembly, rotation = Assembly(assembly.params.detach().cpu()), rotation.detach().cpu()
    translation, count = translation.detach().cpu(), rotation.shape[0]
    metrics = score(assembly, rotation, translation, batch, renderer, [symmetry] * count,
                    [volume] * count, level)
    metrics["relative_rotation_deg"] = relative_rotation_errors(rotation.detach(),
                                                                batch["rotation"])
    return metrics


def pass_groups(dataset: Any, views: bool = False) -> dict[tuple[int, int], list[int]]:
    """The items of a dataset of passes grouped by (model index, pass), each in frame order.

    Args:
        views: a dataset of independent images (no ``pass`` labels) is read as one set of
            views per model, ``(model index, 0)``, its images in their order (an unordered
            set: ``study passes --no-ordered``); a dataset of passes is read as passes.

    Raises:
        ValueError: the dataset's labels are not a pass's (no ``frame_in_pass``) and not
            ``views``, or a pass has frames missing or twice.
    """
    if views and not any(label.get("frame_in_pass") is not None and label.get("pass") is not None
                         for _, _, label in dataset.items):
        sets: dict[tuple[int, int], list[int]] = {}
        for item, (model_index, _, _) in sorted(enumerate(dataset.items),
                                                key=lambda entry: entry[1][:2]):
            sets.setdefault((model_index, 0), []).append(item)
        return dict(sorted(sets.items()))
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for item, (model_index, _, label) in enumerate(dataset.items):
        frame = label.get("frame_in_pass")
        if frame is None or label.get("pass") is None:
            fix = ("other images are labelled as passes: render the dataset again" if views
                   else "render one with dataset render --pass-frames F, or score each "
                   "model's images as an unordered set with --no-ordered")
            raise ValueError(f"{dataset.root}: not a dataset of passes ({label.get('filename')} "
                             f"of model {dataset.models[model_index]} has no pass and "
                             f"frame_in_pass; {fix})")
        groups.setdefault((model_index, int(label["pass"])), []).append((int(frame), item))
    ordered = {}
    for (model_index, number), frames in sorted(groups.items()):
        frames.sort()
        if [f for f, _ in frames] != list(range(len(frames))):
            raise ValueError(f"{dataset.root}: pass {number} of model "
                             f"{dataset.models[model_index]} has frames "
                             f"{[f for f, _ in frames]}, not 0 to {len(frames) - 1} once each")
        ordered[(model_index, number)] = [item for _, item in frames]
    return ordered


def evaluate_passes(predictor: Any, data_root: str | Path, out_dir: str | Path,
                    options: PassOptions | None = None, progress: bool = True,
                    label: str | None = None) -> PassResult:
    """Score ``predictor`` on the passes of a dataset split (module docstring).

    Every input is checked before the work starts: the network's input channels, the dataset
    and split (not empty, a dataset of passes, each pass at least ``max(counts)`` frames,
    every frame scored readable, of ``camera.json``'s size and, where passes are fitted, with
    a target in the mask the fit takes), and the output folder (writable, outside the dataset,
    not locked by another run).

    Args:
        label: the run's name in ``passes.json`` (default: the checkpoint's folder name).

    Raises:
        ValueError: one line naming what and where.
    """
    from sq_mitsuba.evaluation.evaluate import check_data_folder, check_outside_data
    from sq_mitsuba.evaluation.split import check_predictor, evenly, open_split
    from sq_mitsuba.inference.loading import with_fast_path
    from sq_mitsuba.io import check_output_folder
    from sq_mitsuba.outputs import output_lock

    options = options or PassOptions()
    validate(options)
    if not options.counts:
        raise ValueError("counts: expected at least one number of frames")
    check_predictor(predictor)
    data_root, out_dir = Path(data_root), Path(out_dir)
    check_data_folder(data_root)
    check_output_folder(out_dir, OUTPUT_FILES)
    check_outside_data(out_dir, data_root)
    if not ({"passes", "counts", "options"} <= json_record(out_dir / "passes.json").keys()
            or json_record(out_dir / PARTIAL / RUN_FILE)):  # no pass study wrote here: others'
        refuse_present(out_dir, OUTPUT_FILES, "an output of study passes, but no earlier "
                       "pass study there wrote it")
    # At the dataset's own resolution (image_size None: camera.json's width).
    dataset = open_split(data_root, options.split, None, options.surface_points)
    groups = pass_groups(dataset, views=not options.ordered)
    longest, keys = max(options.counts), sorted(groups)
    keys = [keys[k] for k in evenly(len(keys), options.passes)]
    short = [key for key in keys if len(groups[key]) < longest]  # of the passes read only
    if short:
        model_index, number = short[0]
        raise ValueError(f"counts: {longest} frames asked, but pass {number} of model "
                         f"{dataset.models[model_index]} has {len(groups[short[0]])} "
                         f"({len(short)} pass(es) too short)")
    # Every frame of a dataset shows its target: each is fitted whatever its target score.
    predictor = with_fast_path(predictor, options.fast, min_target=0.0)
    _check_frames(predictor, dataset, {k: groups[k][:longest] for k in keys},
                  sequences=longest >= 2, progress=progress)
    with output_lock(out_dir, command="sq-mitsuba study passes"):
        return _evaluate_passes(predictor, dataset, {k: groups[k] for k in keys}, out_dir,
                                options, progress, label)


def _check_frames(predictor: Any, dataset: Any, groups: dict[tuple[int, int], list[int]],
                  sequences: bool, progress: bool) -> None:
    """Refuse, before any pass is scored, a frame that would stop the study part-way: one that
    cannot be read whole (image or mask), one of another size than ``camera.json``'s and,
    where passes are fitted (``sequences``), one whose mask to fit holds no target (the
    network's reading from turned copies, as ``predict_sequence`` takes it: milliseconds a
    frame). One line naming the file."""
    from sq_mitsuba.inference.images import prepare_images
    from sq_mitsuba.inference.pipeline import masks_to_fit
    from sq_mitsuba.inference.sequence import FRAMES_SEARCH
    from sq_mitsuba.progress import progress_bar

    described = dataset.camera  # camera.json's
    camera = described.rescaled(dataset.image_size, dataset.image_size)  # as the study reads
    for (model_index, number), items in progress_bar(
            groups.items(), desc="checking frames", unit="pass", disable=not progress,
            leave=False):
        images = []
        for item in items:
            image, _ = dataset.read_pair(item)  # decoded whole, the mask's size checked
            if image.shape != (described.height, described.width):
                raise ValueError(f"{dataset.image_file(item)}: {image.shape[1]} x "
                                 f"{image.shape[0]} px, but camera.json describes "
                                 f"{described.width} x {described.height} px images")
            images.append(image)
        if not sequences:
            continue
        frames = torch.from_numpy(np.stack(images))
        turns = FRAMES_SEARCH.turns if predictor.can_turn(camera) else 1
        start = predictor.predict(frames, camera, turns=turns)
        usable = masks_to_fit(start, prepare_images(frames, predictor.model.config.in_channels),
                              None)[1]
        if not bool(usable.all()):
            frame = int((~usable).nonzero()[0])
            raise ValueError(
                f"{dataset.image_file(items[frame])}: frame {frame} of pass {number} of "
                f"{dataset.models[model_index]} holds no target to fit (the network's mask of "
                "it is empty: in eclipse, or too small?); no pass through it can be fitted: "
                "score fewer frames (--counts), or leave the model out of the split")


def _evaluate_passes(predictor: Any, dataset: Any, groups: dict[tuple[int, int], list[int]],
                     out_dir: Path, options: PassOptions, progress: bool,
                     label: str | None) -> PassResult:
    """:func:`evaluate_passes` once its inputs are checked and the folder locked."""
    from sq_mitsuba.evaluation.evaluate import default_label
    from sq_mitsuba.evaluation.scoring import ModelData
    from sq_mitsuba.evaluation.split import collate
    from sq_mitsuba.io import atomic_write_json, atomic_write_text
    from sq_mitsuba.progress import progress_bar
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    started = time.perf_counter()
    camera = dataset.camera.rescaled(dataset.image_size, dataset.image_size)
    renderer = SilhouetteRenderer(camera, spp=options.silhouette_spp)
    models = ModelData(dataset, options.volume_points)
    counts = sorted(set(options.counts))
    longest, names = counts[-1], []
    rows: list[dict[str, Any]] = []
    (out_dir / "passes.json").unlink(missing_ok=True)  # the finished mark goes first
    done = _partial_passes(out_dir, predictor, dataset.root, options)
    with progress_bar(total=len(groups), unit="pass", disable=not progress,
                      desc=f"passes {options.split}") as bar:
        for (model_index, number), items in groups.items():
            model = dataset.models[model_index]
            names.append(f"{model}/{number}")
            kept = out_dir / PARTIAL / f"{model}__{number}.json"
            if kept.name in done:  # scored by an interrupted run of the same settings
                rows += done[kept.name]
                bar.update()
                continue
            first_row = len(rows)
            shot = collate([dataset[i] for i in items[:longest]])
            bar.set_postfix_str(f"{model}: each frame alone")
            tick = time.perf_counter()
            alone = predictor.predict(shot["image"], camera, refine=True,
                                      search=options.search, refinement=options.refinement)
            alone_seconds = (time.perf_counter() - tick) / longest
            network = alone.network
            symmetry, volume = models.symmetry(model_index), models.volume(model_index)
            for count in counts:
                batch = {key: value[:count] for key, value in shot.items()  # names too:
                         if isinstance(value, Tensor | list)}  # each frame's own samples
                methods: dict[str, tuple[Assembly, Tensor, Tensor, float]] = {
                    "network": (network.assembly[:count], network.rotation[:count],
                                network.translation[:count], math.nan),
                    "single": (alone.assembly[:count], alone.rotation[:count],
                               alone.translation[:count], alone_seconds)}
                if count >= 2:
                    bar.set_postfix_str(f"{model}: {count} frames")
                    tick = time.perf_counter()
                    sequence = predictor.predict_sequence(
                        shot["image"][:count], camera, ordered=options.ordered,
                        options=options.sequence)
                    methods["sequence"] = (
                        Assembly(sequence.assembly.params.expand(count, -1, -1)),
                        sequence.rotation, sequence.translation,
                        (time.perf_counter() - tick) / count)
                for method, (assembly, rotation, translation, seconds) in methods.items():
                    metrics = score_frames(assembly, rotation, translation, batch, renderer,
                                           symmetry, volume, options.level)
                    for k in range(count):
                        rows.append({"model": model, "pass": number, "frames": count,
                                     "method": method, "frame": k,
                                     "seconds_per_frame": seconds,
                                     **{name: float(value[k]) for name, value in metrics.items()}})
            atomic_write_text(kept, json.dumps(rows[first_row:]))
            bar.update()
    summary, files = _write_outputs(rows, out_dir, counts, len(groups))
    seconds = _seconds_per_frame(rows)
    atomic_write_json(out_dir / "passes.json", {
        "data": str(dataset.root), "split": options.split, "passes": names,
        "counts": counts, "resolution": dataset.image_size,
        "label": label if label is not None else default_label(predictor),
        "checkpoint": str(getattr(predictor, "source", None) or ""),
        "options": to_dict(options), "wall_seconds": round(time.perf_counter() - started, 3),
        "seconds_per_frame": [{"frames": count, "method": method, "mean": round(mean, 4),
                               "median": round(median, 4)}
                              for (count, method), (mean, median) in seconds.items()]})
    files.append(out_dir / "passes.json")
    shutil.rmtree(out_dir / PARTIAL, ignore_errors=True)
    return PassResult(rows, summary, names, out_dir, files, seconds)


def _seconds_per_frame(rows: list[dict[str, Any]]) -> dict[tuple[int, str], tuple[float, float]]:
    """{(N, method): (mean, median)} of the seconds per frame over the passes, one value a
    pass (every frame row of a pass carries its pass's), for the methods that are timed."""
    per_pass: dict[tuple[int, str], dict[tuple[str, Any], float]] = {}
    for row in rows:
        if math.isfinite(row["seconds_per_frame"]):
            per_pass.setdefault((row["frames"], row["method"]), {})[
                (row["model"], row["pass"])] = row["seconds_per_frame"]
    return {key: (float(np.mean(list(values.values()))),
                  float(np.median(list(values.values()))))
            for key, values in sorted(per_pass.items(),
                                      key=lambda item: (item[0][0], METHODS.index(item[0][1])))}


def _partial_passes(out_dir: Path, predictor: Any, data_root: Path,
                    options: PassOptions) -> dict[str, list[dict[str, Any]]]:
    """The rows of each pass an interrupted run of the same settings, weights and data kept
    in ``out_dir / PARTIAL`` ({file name: rows}); any other partial run is discarded (said in
    a warning) and the folder made ready for this run's passes."""
    from sq_mitsuba.evaluation.journal import journal_difference, run_identity
    from sq_mitsuba.io import atomic_write_json

    folder = out_dir / PARTIAL
    identity = run_identity(predictor, data_root, to_dict(options))
    done: dict[str, list[dict[str, Any]]] = {}
    if (folder / RUN_FILE).is_file():
        difference = journal_difference(out_dir, identity, PARTIAL)
        if difference is None:
            try:  # not ".*": a killed write's temporary, no pass
                done = {path.name: json.loads(path.read_text(encoding="utf-8"))
                        for path in sorted(folder.glob("[!.]*__*.json"))}
            except (OSError, ValueError) as error:
                difference = f"unreadable: {error}"
        if difference is not None:
            warnings.warn(f"{folder}: an interrupted run's passes discarded ({difference})",
                          stacklevel=3)
    if not done:
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_json(folder / RUN_FILE, identity)
    return done


def _write_outputs(rows: list[dict[str, Any]], out_dir: Path, counts: list[int],
                   passes: int) -> tuple[dict[tuple[int, str], dict[str, tuple[float, ...]]],
                                         list[Path]]:
    """per_frame.csv, summary.csv / .md and the figure; the summary by (N, method)."""
    from sq_mitsuba.evaluation.scoring import METRICS
    from sq_mitsuba.evaluation.tables import csv_text, markdown_table, summarise
    from sq_mitsuba.io import atomic_write_text

    metrics = (*METRICS, "relative_rotation_deg")  # the timings: passes.json's alone
    header = ["model", "pass", "frames", "method", "frame", *metrics]
    atomic_write_text(out_dir / "per_frame.csv", csv_text(header, [
        ["" if isinstance(r[c], float) and not math.isfinite(r[c]) else r[c] for c in header]
        for r in rows]))
    grouped = summarise(rows, ("frames", "method"), metrics)
    order = sorted(grouped, key=lambda key: (key[0], METHODS.index(key[1])))
    summary = {key: grouped[key] for key in order}
    frames = {key: sum(1 for r in rows if (r["frames"], r["method"]) == key) for key in order}
    atomic_write_text(out_dir / "summary.csv", csv_text(
        ["frames", "method", "metric", "mean", "std", "median", "frames_scored"],
        [[*key, metric, *summary[key][metric], frames[key]] for key in order
         for metric in metrics]))
    shown = [name for name, _, _ in PLOTTED]
    atomic_write_text(out_dir / "summary.md", (
        f"Mean ± std (median) per number of frames N and method, over the frames of {passes} "
        "pass(es); every metric is in summary.csv.\n\n"
        + markdown_table(["N", "method", "frames", *shown],
                         [[*key, frames[key], *(_stats(summary[key][m]) for m in shown)]
                          for key in order])
        + "\nnetwork: the network's reading of each frame; single: each frame alone through "
        "the search and refinement; sequence: one assembly and N poses "
        "(predict_sequence). Rotations in degrees; relative rotation: between consecutive "
        "frames.\n"))
    from sq_mitsuba.evaluation.figures import plot_quality_vs_frames

    figure_path = plot_quality_vs_frames(summary, counts, out_dir / "quality_vs_frames.png",
                                         passes, PLOTTED, METHODS)
    return summary, [out_dir / name for name in OUTPUT_FILES[:3]] + [figure_path]


def _stats(stats: tuple[float, ...]) -> str:
    """``mean ± std (median)``, or a dash where the method has no value (frame 0's relative
    rotation, alone)."""
    from sq_mitsuba.evaluation.tables import format_stats

    return format_stats(*stats) if math.isfinite(stats[0]) else "–"
