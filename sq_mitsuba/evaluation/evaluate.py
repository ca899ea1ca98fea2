"""Evaluate a trained model on a dataset split: per-image metrics, tables, charts, figures.

:func:`evaluate` runs the network over the ``val`` or ``test`` split of an SPE3R-layout
dataset and scores every image with every metric of ``METRICS``
(:mod:`sq_mitsuba.evaluation.scoring`, computed by :mod:`sq_mitsuba.geometry.metrics`), for
up to four methods:

- ``network``: the network's prediction;
- ``search``: the global pose search (:func:`sq_mitsuba.inference.search.search_poses`: the
  network's rotation (with ``search.candidates = "hypotheses"`` its top-K hypotheses too), or a
  uniform grid for a network without them, each times the four half turns, scored by Mitsuba
  silhouettes) against the mask read from the image, with the assembly of the search's start
  (the network's reading from the search's turned copies, ``search.turns``, 8 by default for
  a rotation-distribution head: not the ``network`` row's reading, so its shape metrics can
  differ from that row's) (``refine``);
- ``refined``: that search followed by refinement of its best few against the same mask,
  the shipped path whole (``Predictor.refine``, :mod:`sq_mitsuba.inference.pipeline`, as
  ``Predictor.predict(images, refine=True)`` runs it); the mask is
  the network's mask head when it has one (``mask = "network"``), else the threshold
  segmentation of the image (:func:`sq_mitsuba.data.segmentation.segment_target`), named in
  the ``mask_source`` column; an image with nothing to segment (an eclipse, a black frame),
  or whose segmentation warns of a lit Earth merged with the target, keeps the search's start
  (the network's reading from the search's turned copies, 8 by default, not the ``network``
  row's single reading), with blank search columns;
- ``refined_gt``: search and refinement against the ground-truth mask, an upper bound
  (``refine`` and ``refine_ground_truth``);
- ``baseline``: a trivial floor, the mean training assembly (the mean of the network's raw
  outputs over training images, squashed) at the mean training pose (chordal mean rotation,
  mean translation of the training labels).

Files written to the output folder (each atomically):

- ``per_image.csv``: one row per image and method: every metric (:data:`METRICS`), the
  refinement's own IoUs where refined (:data:`EXTRAS`), and the label's lighting record
  (:data:`LIGHTING`: phase angle, Earth in view, eclipse, target visibility);
- ``per_model.csv`` / ``per_model.md``: mean, std and median per model and method;
- ``summary.csv`` / ``summary.md``: mean, std and median per method over the split;
- ``per_model.png``: bars with std error bars per model and method (as the paper's Fig. 10);
- ``qualitative.png``: input, reprojected silhouette, predicted assembly (one colour per
  primitive), its surface points and the ground-truth mesh (as the paper's Fig. 12);
- ``consistency.png``: several images of a model with their predicted assemblies in one fixed
  view of the body frame (as the paper's Fig. 11);
- ``mesh_ranking.csv`` (``mesh_ranking`` > 0): for that many network predictions, spread
  evenly, the rank of the image's own model among every model of the split by Chamfer-L1 to
  the prediction (:mod:`sq_mitsuba.evaluation.mesh_ranking`: is the shape read from the image?);
- ``eval.json``: settings, checkpoint, counts, symmetries per model, images/s, the mesh
  ranking's medians, and the run's ``identity`` (the checkpoint's weights hash, the data's
  fingerprint and its model files' hash, the Mitsuba variant, the package version:
  :mod:`sq_mitsuba.evaluation.journal`).

While it runs, the hidden folder ``.eval_partial/`` (:mod:`sq_mitsuba.evaluation.journal`)
holds ``run.json`` (the options, the checkpoint's and the data's identity, the Mitsuba
variant, the package version, the evaluated indices) and one ``batch_<number>.pt`` per
finished batch (its rows, qualitative examples, mesh-ranking entries and seconds), each
written atomically; it is removed once ``eval.json`` is written. ``resume`` (``sq-mitsuba
eval --resume``) reads the batches an interrupted run of the same settings, checkpoint, data,
variant and version finished
instead of computing them again, and ends with the same files (timings aside); a journal of
another run is refused in one line naming what differs, and a run without ``resume`` clears
it first. Each image is scored on its own, its silhouettes' samples seeded by the image (its
model and index): per_image.csv's rows (image by image, its methods together) and its scores
are the same whatever ``batch_size`` and ``limit``, but for the network's last-bit rounding.

The folder holds one evaluation: the files of this list that an earlier run into it (its
``eval.json`` or journal there) wrote and this one does not (the figures after ``figures =
False``, a mesh ranking) are removed once it has written its own, and a lighting breakdown of
the earlier ``per_image.csv`` (``lighting.*``,
:func:`sq_mitsuba.evaluation.study.lighting_breakdown`) before its first table; in a folder
that holds no earlier evaluation nothing is removed, and a file of an output's name is refused
before any work (:func:`earlier_evaluation`). It lies outside the dataset, which evaluation
only reads, and takes one run at a time (:func:`sq_mitsuba.outputs.output_lock`; another run
into it is refused in one line before any work).

Timing: the network's first call sets up its kernels; it is made once, untimed, on the first
batch computed (after a resume: the first the journal does not hold) before the timed call,
so ``network_ms_per_image`` is the warm figure. A resumed run counts the journal's seconds.

Convention: 2D IoU compares the predicted assembly's silhouette at the *predicted* pose with
the ground-truth mask (for every method, the refined ones included), both at the network's
input resolution and thresholded at 0.5. Chamfer distances use the assembly's surface points
without those inside another primitive, against the model's surface samples, in the unit-size
body frame. 3D IoU uses points uniform in the cube around the model (``samples.npz``'s
``uniform_points``), so it estimates the volume IoU; balanced near-surface points would not.
Convention: it is the IoU within that unit cube (the model's longest side spans it): predicted
volume outside the cube is not counted, so an assembly that overshoots the model's extent
scores above its true volume IoU (on the demo's 30 assemblies by 0.002 on average, 0.009 at
most; a sphere twice the model's size would score 0.52 for a true 0.13).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from sq_mitsuba.config import in_range, to_dict, validate
from sq_mitsuba.evaluation.batch import evaluate_batch
from sq_mitsuba.evaluation.journal import JOURNAL, RUN_FILE, EvalJournal, run_identity
from sq_mitsuba.evaluation.methods import METHODS
from sq_mitsuba.evaluation.scoring import ModelData, baseline_prediction
from sq_mitsuba.evaluation.split import check_predictor, evenly, open_split
from sq_mitsuba.evaluation.tables import write_tables
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.inference.refine import RefineOptions
from sq_mitsuba.inference.search import SEARCH_REFINEMENT, SearchOptions
from sq_mitsuba.io import atomic_write_json
from sq_mitsuba.outputs import json_record, refuse_present, remove_unwritten

MESH_RANKING_FILE = "mesh_ranking.csv"
"""Per ranked image: its own model's rank among the split's meshes (``mesh_ranking`` > 0)."""
OUTPUT_FILES = ("per_image.csv", "per_model.csv", "per_model.md", "summary.csv", "summary.md",
                "per_model.png", "qualitative.png", "consistency.png", "eval.json")
"""What :func:`evaluate` writes (the PNGs unless ``figures`` is off)."""
LIGHTING_STEM = "lighting"
"""The name of a lighting breakdown's files in an evaluation folder (LIGHTING_FILES)."""
GROUP_TABLE_SUFFIXES = ("csv", "md", "png")
"""What a table of metrics by group is written as: long CSV, markdown and figure."""
LIGHTING_FILES = tuple(f"{LIGHTING_STEM}.{suffix}" for suffix in GROUP_TABLE_SUFFIXES)
"""What :func:`sq_mitsuba.evaluation.study.lighting_breakdown` writes into an evaluation folder
from its ``per_image.csv`` (removed when an evaluation rewrites that file)."""


@dataclass(frozen=True)
class EvalOptions:
    """Settings of ``sq-mitsuba eval``."""

    split: Literal["val", "test"] = "val"
    "Dataset split to evaluate: 'val' (held-out images of training models) or 'test' (new models)."
    limit: int | None = in_range(1, 10_000_000, default=None)
    "Evaluate at most this many images, spread evenly over the split (None: all)."
    batch_size: int = in_range(1, 1024, default=16)
    "Images per network batch (the search's too; the refinement runs image by image)."
    turns: int = in_range(1, 360, default=1)
    """The network row read from this many in-plane turned copies of each image (test-time
    augmentation, no rendering: the rotation from the copies' distributions multiplied, the
    shape, image position and depth their means; a rotation-distribution head only). The
    shipped model on the held-out families with 8: body-frame Chamfer-L1 0.140 -> 0.137,
    folded rotation 52.4 -> 45.9 deg median, 2D IoU 0.464 -> 0.467, for 8 x the network's
    time (eval/MODEL_CARD.md)."""
    refine: bool = False
    "Also search the pose and refine it at test time (rows search, refined, refined_gt)."
    mask: Literal["network", "segmentation"] = "network"
    "Mask read from the image: the network's mask head (segmentation for a model without one)."
    refine_ground_truth: bool = True
    "With refine, also search and refine against the ground-truth mask (an upper bound)."
    search: SearchOptions = field(default_factory=SearchOptions)
    "Global pose search settings."
    refinement: RefineOptions = field(default_factory=lambda: SEARCH_REFINEMENT)
    """Refinement after the search (by default the pose only, its rotation held near the
    search's: shape changes degraded Chamfer-L1; see inference.search.SEARCH_REFINEMENT)."""
    baseline: bool = True
    """Also score the trivial baseline: from the dataset's train split, or, for a dataset of test
    models only, the one the checkpoint stores."""
    baseline_images: int = in_range(1, 1_000_000, default=256)
    "Training images (spread evenly) whose mean prediction and mean pose make the baseline."
    level: int = in_range(0, 5, default=3)
    "Icosphere level of the primitive meshes for surface points and silhouettes (3: 642)."
    surface_points: int = in_range(1, 1_000_000, default=2500)
    "Ground-truth surface points per image for the Chamfer distances."
    volume_points: int = in_range(1, 1_000_000, default=100_000)
    "Uniform points per model for the 3D IoU (at most those of samples.npz)."
    silhouette_spp: int = in_range(1, 1024, default=32)
    "Samples per pixel of the silhouettes scored by the 2D IoU."
    fast: bool = True
    "Predict with the batch-norm-folded network (same output up to ~1e-5; faster on CPU)."
    figures: bool = True
    "Draw per_model.png, qualitative.png and consistency.png."
    mesh_ranking: int = in_range(0, 10_000_000, default=0)
    """Network predictions ranked by Chamfer-L1 against every model of the split (0: off; a
    split of one model is refused)."""
    qualitative: int = in_range(1, 64, default=6)
    "Rows (images, spread over the split) of the qualitative grid."
    consistency_models: int = in_range(1, 16, default=3)
    "Models shown in the consistency figure."
    consistency_views: int = in_range(1, 16, default=6)
    "Images per model in the consistency figure."
    figure_size: int = in_range(32, 1024, default=192)
    "Width in pixels of the ray-cast pictures in the figures."


@dataclass
class EvalResult:
    """What :func:`evaluate` did.

    Attributes:
        rows: one dict per image and method (the ``per_image.csv`` rows, values unformatted).
        summary: {method: {metric: (mean, std, median)}}.
        images: images evaluated; images_per_second: over the whole loop (network, refinement
            and scoring); network_ms_per_image: the network alone.
        out_dir: output folder; files: the files written.
        resumed: batches read from an interrupted run's journal (``resume``), not computed.
    """

    rows: list[dict[str, Any]]
    summary: dict[str, dict[str, tuple[float, float, float]]]
    images: int
    images_per_second: float
    network_ms_per_image: float
    out_dir: Path
    files: list[Path]
    resumed: int = 0

    def describe(self) -> str:
        """A few lines: throughput and the network's main numbers."""
        lines = [f"evaluated {self.images} images: {self.images_per_second:.2f} images/s "
                 f"(network alone {self.network_ms_per_image:.1f} ms/image)"
                 + (f"; {self.resumed} batch(es) resumed from the journal"
                    if self.resumed else "")]
        # The rotation up to the four half turns of the body axes, at the median (the raw
        # error is near chance for any reader: an axis's two ends often look alike).
        for method, stats in self.summary.items():
            lines.append(f"  {method}: Chamfer-L1 {stats['chamfer_l1_paper'][0]:.3f}, 2D IoU "
                         f"{stats['iou_2d'][0]:.3f}, rotation up to the half turns "
                         f"{stats['rotation_error_folded_deg'][2]:.1f} deg (median)")
        lines.append(f"wrote {len(self.files)} files to {self.out_dir}")
        return "\n".join(lines)


# ------------------------------------------------------------------------------- driver


def evaluate(predictor: Any, data_root: str | Path, out_dir: str | Path,
             options: EvalOptions | None = None, progress: bool = True,
             label: str | None = None, resume: bool = False) -> EvalResult:
    """Evaluate ``predictor`` (a :class:`sq_mitsuba.inference.predictor.Predictor`) on a
    dataset split and write the files listed in the module docstring.

    Every input is checked before the work starts (and before a journal is touched): the
    network's input channels, the dataset and split (not empty, images of ``camera.json``'s
    size, readable finite points, two models or more for ``mesh_ranking``), the train split,
    or else a baseline the checkpoint stores, when the baseline is on, and the output folder
    (writable, outside the dataset, not locked by another run).

    Args:
        label: the run's name in ``eval.json`` (the report's row label; default: the
            checkpoint's folder name).
        resume: continue from the journal an interrupted run of the same settings, checkpoint
            and data left in ``out_dir`` (:mod:`sq_mitsuba.evaluation.journal`; none: start
            afresh); its batches are not computed again. Without it, a journal is cleared.
    """
    from sq_mitsuba.io import check_output_folder
    from sq_mitsuba.outputs import output_lock

    options = options or EvalOptions()
    validate(options)
    options = effective_options(options)
    check_predictor(predictor)
    data_root, out_dir = Path(data_root), Path(out_dir)
    check_data_folder(data_root)
    check_output_folder(out_dir, (*OUTPUT_FILES, MESH_RANKING_FILE))
    check_outside_data(out_dir, data_root)
    with output_lock(out_dir, command="sq-mitsuba eval"):  # re-entrant: the CLI holds it
        return _evaluate(predictor, data_root, out_dir, options, progress, label, resume)


def effective_options(options: EvalOptions) -> EvalOptions:
    """``options`` as a run uses them: without ``refine`` the refinement's own settings
    (``mask``, ``search``, ``refinement``, ``refine_ground_truth``) act on nothing, so they
    are its defaults (in ``eval.json`` and the run's identity: a ``--resume`` is not refused,
    nor a finished evaluation run again, over a setting that changed nothing)."""
    if options.refine:
        return options
    defaults = EvalOptions()
    return replace(options, mask=defaults.mask, search=defaults.search,
                   refinement=defaults.refinement,
                   refine_ground_truth=defaults.refine_ground_truth)


def check_data_folder(data_root: Path) -> None:
    """A dataset folder that is not there is named as such (not by the first file missing)."""
    if not data_root.is_dir():
        raise ValueError(f"{data_root}: dataset folder not found" if not data_root.exists()
                         else f"{data_root}: not a folder (a dataset is a folder)")


def check_mesh_ranking(mesh_ranking: int, models: Sequence[str], source: str,
                       setting: str = "mesh_ranking") -> None:
    """Refuse ``mesh_ranking`` > 0 among fewer than two ``models`` (nothing to rank an image's
    own model against), rather than skip it unsaid; ``source`` says what holds them and
    ``setting`` names the option (a study's is ``evaluation.mesh_ranking``)."""
    if mesh_ranking and len(models) < 2:
        raise ValueError(f"{setting} {mesh_ranking}: ranks each prediction among the models of "
                         f"{source}, which has {len(models)} ({', '.join(models)}); set "
                         f"{setting}=0 or give two models or more")


def check_outside_data(out_dir: Path, data_root: Path) -> None:
    """Refuse an output folder that is the dataset folder or lies inside it (an evaluation
    only reads its dataset)."""
    from sq_mitsuba.io import inside_folder

    if inside_folder(out_dir, data_root):
        raise ValueError(f"out {out_dir}: inside the dataset folder {data_root}, which "
                         "evaluation only reads; choose an output folder outside it")


def _evaluate(predictor: Any, data_root: Path, out_dir: Path, options: EvalOptions,
              progress: bool, label: str | None, resume: bool) -> EvalResult:
    """:func:`evaluate` once the options and the output folder are checked and locked."""
    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.inference.loading import with_fast_path
    from sq_mitsuba.progress import progress_bar
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    image_size = predictor.image_size
    dataset = open_split(data_root, options.split, image_size, options.surface_points)
    check_mesh_ranking(options.mesh_ranking, dataset.models,
                       f"the {options.split!r} split of {data_root}")
    stored_baseline = None
    if options.baseline:  # its images are read too: refused now, not after the split's work
        train_split = Spe3rDataset(data_root, "train", image_size=image_size, num_surface=1,
                                   num_occupancy=2)
        if len(train_split):
            train_split.check()
        else:
            # A dataset of test models only (held-out families, real spacecraft): the baseline
            # is the one the checkpoint stores, the mean over the model's own training images.
            stored_baseline = getattr(predictor, "baseline", None)
            if stored_baseline is None:  # now: the journal below is not yet touched
                raise ValueError(f"{data_root}: no images for the baseline (the 'train' split "
                                 "is empty and the checkpoint stores none); evaluate without "
                                 "it (--no-baseline)")
    camera = dataset.camera.rescaled(image_size, image_size)
    predictor.check_turns(options.turns, camera, options.batch_size)
    indices = evenly(len(dataset), options.limit)
    chunks = [indices[start:start + options.batch_size]
              for start in range(0, len(indices), options.batch_size)]
    earlier = earlier_evaluation(out_dir, options)  # what may be replaced or removed
    # Before any work: a journal of another run is refused (resume) or cleared (a fresh run).
    identity = run_identity(predictor, data_root, to_dict(options), indices)
    out_dir.mkdir(parents=True, exist_ok=True)
    journal = EvalJournal(out_dir, identity, chunks, resume)
    # Every image of a dataset shows its target: the evaluation fits each one, whatever its
    # target-present score (min_target 0), so that the methods are scored on the same images.
    predictor = with_fast_path(predictor, options.fast, min_target=0.0)
    started = time.perf_counter()
    baseline = None
    if stored_baseline is not None:
        base_raw, base_rotation, base_translation = stored_baseline
        baseline = (Assembly.from_raw(base_raw), base_rotation, base_translation)
    elif options.baseline:
        base_raw, base_rotation, base_translation = baseline_prediction(
            predictor, data_root, options.baseline_images, options.batch_size,
            progress=progress)
        baseline = (Assembly.from_raw(base_raw), base_rotation, base_translation)
    renderer = SilhouetteRenderer(camera, spp=options.silhouette_spp)
    models = ModelData(dataset, options.volume_points)
    wanted = {indices[k] for k in evenly(len(indices), options.qualitative)}
    ranked = {indices[k] for k in evenly(len(indices), options.mesh_ranking)} \
        if options.mesh_ranking else set()
    to_rank: list[tuple[int, int, str, Assembly]] = []  # item, model index, model, assembly
    rows: list[dict[str, Any]] = []
    examples: list[dict[str, Any]] = []
    seconds = dict.fromkeys(("network", "search", "refine", "loop"), 0.0)
    warm = False  # the network's untimed first call is made (with the first batch computed)
    with progress_bar(total=len(indices), unit="img", disable=not progress, dynamic_ncols=True,
                      desc=f"eval {options.split}") as bar:
        for number, chunk in enumerate(chunks, start=1):

            def stage(name: str, number: int = number, size: int = len(chunk)) -> None:
                # The bar counts images once a batch is scored; between, it names the batch
                # (images in it) and the stage it is at.
                bar.set_postfix_str(f"batch {number}/{len(chunks)} ({size} img): {name}")

            record = journal.get(number)  # a batch an interrupted run finished (resume)
            if record is None:
                record = journal.save(number, evaluate_batch(
                    predictor, dataset, chunk, number, camera, options, renderer, models,
                    baseline, wanted, ranked, stage, warm))
                warm = True
            rows += record.rows
            examples += record.examples
            to_rank += record.to_rank
            for key in seconds:
                seconds[key] += record.seconds[key]
            bar.update(len(chunk))
            bar.set_postfix_str(f"batch {number}/{len(chunks)} done, "
                                f"{bar.n / max(seconds['loop'], 1e-9):.2f} img/s")
    loop_seconds, network_seconds, search_seconds, refine_seconds = (
        seconds[key] for key in ("loop", "network", "search", "refine"))
    # eval.json, written last, marks a finished evaluation: an earlier run's goes before this
    # one's first file, so that a folder left half rewritten (an interrupt among the writes)
    # is not taken for either run by `report`. So does a lighting breakdown of the earlier
    # per_image.csv: it would not match this one's. An interrupt in the loop above loses no
    # batch the journal holds (--resume).
    for name in ("eval.json", *(LIGHTING_FILES if earlier else ())):  # a user's stay
        if (out_dir / name).is_file():
            (out_dir / name).unlink()
    summary = write_tables(rows, out_dir)
    files = [out_dir / name for name in OUTPUT_FILES[:5]]
    ranking = None
    if to_rank:
        from sq_mitsuba.evaluation.mesh_ranking import write_mesh_ranking

        ranking = write_mesh_ranking(dataset, to_rank, out_dir / MESH_RANKING_FILE,
                                     options.surface_points, options.level, progress)
        files.append(out_dir / MESH_RANKING_FILE)
    if options.figures:
        from sq_mitsuba.evaluation.figures import (
            plot_consistency,
            plot_per_model,
            plot_qualitative,
        )

        figure_camera = dataset.camera.rescaled(options.figure_size, options.figure_size)
        renderer.reseed(0)  # the figure's silhouettes: whichever batches this run computed
        # Seconds each (ray-cast pictures): a bar, not silence after the evaluation's own.
        drawn = progress_bar(total=3, desc="figures", unit="fig", disable=not progress,
                             leave=False)
        files.append(plot_per_model(rows, out_dir / "per_model.png"))
        drawn.update()
        files.append(plot_qualitative(examples, dataset, camera, figure_camera, renderer,
                                      out_dir / "qualitative.png", options.level))
        drawn.update()
        by_model: dict[int, list[int]] = {}
        for item in indices:
            by_model.setdefault(dataset.items[item][0], []).append(item)
        shown = [by_model[m] for m in sorted(by_model)]
        shown = [shown[k] for k in evenly(len(shown), options.consistency_models)]
        views = [[group[k] for k in evenly(len(group), options.consistency_views)]
                 for group in shown]
        files.append(plot_consistency(dataset, views, predictor, camera, figure_camera,
                                      out_dir / "consistency.png", options.level))
        drawn.close()
    images = len(indices)
    images_per_second = images / loop_seconds
    atomic_write_json(out_dir / "eval.json", {
        "data": str(data_root), "split": options.split, "images": images,
        "models": sorted({r["model"] for r in rows}),
        "methods": [m for m in METHODS if any(r["method"] == m for r in rows)],
        "label": label if label is not None else default_label(predictor),
        "checkpoint": str(getattr(predictor, "source", None) or ""),
        "num_primitives": predictor.num_primitives, "image_size": image_size,
        "options": to_dict(options),
        # The identity but for what eval.json holds already or by number (options, images).
        "identity": {key: value for key, value in identity.items()
                     if key not in ("options", "images")},
        "symmetries": {dataset.models[m]: len(models.symmetry(m))
                       for m in sorted({dataset.items[i][0] for i in indices})},
        "images_per_second": round(images_per_second, 4),
        "network_ms_per_image": round(1000 * network_seconds / images, 3),
        "search_ms_per_image": round(1000 * search_seconds / images, 3),
        "search_refine_ms_per_image": round(1000 * refine_seconds / images, 3),
        "mesh_ranking": ranking,
        "loop_seconds": round(loop_seconds, 3),
        "wall_seconds": round(time.perf_counter() - started, 3),
    })
    files.append(out_dir / "eval.json")
    journal.clear()
    if earlier:  # an earlier evaluation's files: never those of a folder that held none
        remove_unwritten(out_dir, (*OUTPUT_FILES, MESH_RANKING_FILE), files)
    return EvalResult(rows, summary, images, images_per_second,
                      1000 * network_seconds / images, out_dir, files, len(journal.records))


def earlier_evaluation(out_dir: Path, options: EvalOptions) -> bool:
    """Whether ``out_dir`` holds an earlier evaluation: an ``eval.json`` this command wrote or
    the journal of one (by their keys). Where it holds none, a file of a name this run writes
    is someone else's: refused in one line, before any work, rather than replaced."""
    if ({"split", "images", "methods", "options"} <= json_record(out_dir / "eval.json").keys()
            or {"format", "options", "checkpoint"} <= json_record(out_dir / JOURNAL / RUN_FILE)
            .keys()):
        return True
    refuse_present(out_dir, (*OUTPUT_FILES[:5], "eval.json",
                             *(OUTPUT_FILES[5:8] if options.figures else ()),
                             *((MESH_RANKING_FILE,) if options.mesh_ranking else ())),
                   "an output of eval, but no earlier evaluation there wrote it")
    return False


def default_label(predictor: Any) -> str:
    """The checkpoint's folder name (a training run's output folder; of the path resolved, not
    '..'), or its file stem, as --label takes it: '|' and line breaks (report.md's rows) '_'."""
    if not (source := getattr(predictor, "source", None)):
        return "model"
    from sq_mitsuba.model.checkpoint import SHIPPED_MODEL

    if (source := Path(source)) == SHIPPED_MODEL:
        return "shipped"
    name = next((n for n in (source.resolve().parent.name, source.stem) if n.strip()), "model")
    return "".join("_" if c in "|\r\n" else c for c in name)


def evaluate_checkpoint(checkpoint: str | Path | None, data_root: str | Path,
                        out_dir: str | Path, options: EvalOptions | None = None,
                        progress: bool = True, label: str | None = None,
                        resume: bool = False) -> EvalResult:
    """:func:`evaluate` the model of a checkpoint file (None: the model shipped with the
    package; a clear error when there is none); ``resume``: see :func:`evaluate`."""
    from sq_mitsuba.inference.loading import load_model

    options = options or EvalOptions()
    validate(options)
    check_data_folder(Path(data_root))  # before the model loads (seconds)
    predictor = load_model(checkpoint)  # evaluate folds it once the inputs are checked
    return evaluate(predictor, data_root, out_dir, options, progress=progress, label=label,
                    resume=resume)

