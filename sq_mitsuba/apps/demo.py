"""``sq-mitsuba demo``: one image in, a superquadric assembly and a pose out, on spacecraft the
model never saw, as a web page.

:func:`run_demo` goes through the whole product in one call:

1. generate a few procedural spacecraft from a catalogue seed disjoint from training
   (:attr:`DemoOptions.seed`; the shipped model trains on catalogue seed 0), every one of them
   a test model;
2. path-trace a few images of each in the default space scene (the ``sq-mitsuba dataset
   render`` writer), with masks and pose labels;
3. predict each image with the network (the shipped model, or a checkpoint), search its pose
   globally and refine it at test time through the renderer against the mask read from the
   image (the network's mask head, or the threshold segmentation for a model without one; the
   rows name it), and score the network, the searched and refined prediction and the trivial
   baseline with the evaluation's own
   :func:`~sq_mitsuba.evaluation.scoring.score` (every metric of ``sq-mitsuba eval``);
4. render a pass of a few frames of the first spacecraft and predict one assembly and every
   pose from them (``predict --sequence``), scored per frame beside each frame alone
   (:mod:`sq_mitsuba.apps.demo_pass`);
5. write a page, ``index.html`` and its Markdown twin ``index.md``
   (:mod:`sq_mitsuba.apps.demo_page`), with the pictures, metrics and the files of each
   predicted assembly (assembly JSON, GLB, pose JSON, as ``sq-mitsuba predict`` writes them).

With ``train`` the model is first trained from scratch at a small size (a small library of the
training catalogue, a small dataset, ``train/configs/tiny.toml`` with the overrides of
:class:`DemoTraining`), and the page shows its training curves.

Output folder (``out``)::

    index.html, index.md          the page and its Markdown twin
    demo.json                     settings, checkpoint, baseline source, counts, wall time
    per_image.csv, summary.{csv,md}, per_model.{csv,md}   every metric (evaluate's tables)
    images/<stem>.{network,refined,assembly,truth}.png    pictures of each image
    assemblies/<stem>.{network,refined}.{assembly.json,glb}, <stem>.pose.json
    models/                       the generated spacecraft (model library)
    data/                         the rendered dataset (SPE3R layout: images, masks, labels)
    pass/                         the pass: its data, ``predict --sequence``'s files, per_frame.csv
    train/                        with ``train``: its library, dataset and run folder

Convention: the folder is replaced as a whole. Everything is written into a temporary folder
beside ``out`` (``.<name>.new.<host>-<pid>.*``), which is renamed over it at the end, so a
failed or interrupted run leaves the previous demo as it was; a run killed before it could
delete its temporary folder leaves it behind, and the next demo into ``out`` deletes it.
``out`` must be absent, empty, or a previous demo (holding a ``demo.json`` a demo wrote, and
nothing at its top that a demo does not write): the demo never deletes a folder it did not
write. Nor may it be the working folder or one above it (checked before any work).

Convention: as in ``sq-mitsuba eval``, the network sees each image resized to its input size;
refinement, the 2D IoU and the other metrics work at that size; the pictures of the page are
drawn at the rendered resolution.
"""

from __future__ import annotations

import glob
import math
import os
import re
import shutil
import socket
import time
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.apps.demo_files import (
    DEMO_FORMAT,
    MANIFEST,
    foreign_entry,
    is_demo_record,
    write_demo_page,
    write_outputs,
)
from sq_mitsuba.apps.demo_options import (
    DemoOptions,
    DemoResult,
    DemoTraining,
)
from sq_mitsuba.config import to_dict, validate
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.processes import process_alive

# ------------------------------------------------------------------------------ checks


def repository_config(name: str) -> Path:
    """``train/configs/<name>`` of the repository this package is installed from (editable).

    Raises:
        FileNotFoundError: the repository's train/configs/ is not there (a non-editable
            install ships no training configs).
    """
    configs = Path(__file__).resolve().parents[2] / "train" / "configs"
    path = configs / name
    if not path.is_file():
        raise FileNotFoundError(
            f"--train needs the training config {path}, which is not there: train/configs/ "
            "is part of the repository, not of the installed package; run the demo from a "
            "checkout installed with `pip install -e .` (make setup)")
    return path


def check_demo_folder(out: Path) -> None:
    """``out`` may be absent, an empty folder, or a previous demo; its parent writable.

    A previous demo: its ``demo.json`` is one a demo wrote (:func:`is_demo_record`) and the
    folder holds nothing a demo does not write (:data:`DEMO_OUTPUTS`), for the demo replaces
    its output folder as a whole and must not delete what it did not write.

    Raises:
        ValueError: ``out`` is a file, a link, the working folder or a folder above it (it cannot be
            renamed away, and holds what the run did not write), a folder that holds
            something else, or not writable.
    """
    from sq_mitsuba.io import check_output_folder

    check_output_folder(out)
    if out.is_symlink():  # the folder is swapped in as a whole: the link, not its target, went
        raise ValueError(f"out {out}: a link (to {os.readlink(out)}), which the demo would "
                         "replace by a folder, leaving its target empty; give the target "
                         "itself as --out")
    here, resolved = Path.cwd().resolve(), out.resolve()
    if resolved == here or resolved in here.parents:
        where = "the working folder" if resolved == here else "a folder above the working one"
        raise ValueError(f"out {out}: {where}, which the demo would replace as a whole; "
                         "choose a new folder (e.g. --out demo_output)")
    if out.is_dir() and any(out.iterdir()):
        if not is_demo_record(out / MANIFEST):
            held = f"a {MANIFEST} no demo wrote" if (out / MANIFEST).exists() else \
                f"no {MANIFEST}"
            raise ValueError(f"out {out}: holds files but {held}, so it is not a demo's "
                             "output, and the demo replaces its folder as a whole; choose "
                             "another --out or an empty folder")
        foreign = foreign_entry(out)
        if foreign is not None:
            raise ValueError(f"out {out}: holds {foreign.name}, which the demo does not write "
                             "and would delete with the folder it replaces as a whole; move it "
                             "or choose another --out")
    # The new demo is written beside `out` and renamed over it: the parent must take files.
    check_output_folder(out.absolute().parent)


# ------------------------------------------------------------------------------ driver


def run_demo(options: DemoOptions | None = None, out_dir: str | Path = "demo_output",
             checkpoint: str | Path | None = None, progress: bool = True) -> DemoResult:
    """Run the demo (see the module docstring) into ``out_dir``.

    Every input is checked before any work: the options, the output folder, and the model
    (``checkpoint``, or the shipped model when None; with ``options.train``, the training
    config instead, and ``checkpoint`` must be None).

    Raises:
        FileNotFoundError: no shipped model and no ``checkpoint``; a missing checkpoint file;
            with ``train``, a missing training config.
        ValueError: bad options, an unusable output folder or checkpoint.
    """
    from sq_mitsuba.evaluation.split import check_predictor
    from sq_mitsuba.inference.loading import load_model
    from sq_mitsuba.io import staging_folder
    from sq_mitsuba.outputs import output_lock

    started = time.perf_counter()
    options = options or DemoOptions()
    validate(options)
    out_dir = Path(out_dir)
    check_demo_folder(out_dir)
    predictor = training_config = None
    if options.train:
        if checkpoint is not None:
            raise ValueError("checkpoint: --train trains its own model; leave out --checkpoint")
        training_config = _training_config(options.training)
    else:
        predictor = load_model(checkpoint)
        check_predictor(predictor)
    # One demo at a time per folder: two into one --out both said "open index.html" and the
    # folder held the last one's. The lock lies beside the folder, which is swapped whole.
    with output_lock(out_dir, file=True, command="demo"):
        remove_stale_staging(out_dir)
        staging = staging_folder(f".{out_dir.name}.new.{_run_tag()}.", out_dir.absolute().parent)
        try:
            result = _build(options, staging, predictor, training_config, progress, started)
            _swap(staging, out_dir)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    result.out_dir = out_dir
    result.page = out_dir / result.page.name
    result.markdown = out_dir / result.markdown.name
    result.wall_seconds = time.perf_counter() - started
    return result


def _run_tag() -> str:
    """``<host>-<pid>`` of this process, the host's name made of letters, digits and '_': a
    demo's temporary folders are named by it, since a process id alone is only this machine's
    (another machine sharing the disk has its own, and may be running its demo there)."""
    return f"{re.sub(r'[^A-Za-z0-9]', '_', socket.gethostname())}-{os.getpid()}"


def remove_stale_staging(out_dir: Path) -> list[Path]:
    """Delete the temporary folders of earlier demos into ``out_dir`` whose process is gone
    (killed before it could clean up: ``.<name>.new.<host>-<pid>.*`` beside ``out_dir``, or
    ``.<name>.new.<pid>.*`` of a version before the host), this machine's only; a running
    demo's folder stays, and another machine's. Returns the folders deleted."""
    host = _run_tag().rpartition("-")[0]
    removed = []
    for path in out_dir.absolute().parent.glob(f".{glob.escape(out_dir.name)}.new.*.*"):
        tag = path.name[len(f".{out_dir.name}.new."):].split(".")[0]
        owner, _, pid = tag.rpartition("-")
        if owner in ("", host) and pid.isdigit() and path.is_dir() \
                and not process_alive(int(pid)):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def _training_config(training: DemoTraining) -> Any:
    from sq_mitsuba.config import apply_overrides
    from sq_mitsuba.training.config import load_train_config

    config = load_train_config(repository_config(training.config))
    return apply_overrides(config, list(training.overrides))


def _swap(staging: Path, out_dir: Path) -> None:
    """Rename ``staging`` over ``out_dir`` (the old one is removed only once the new one is in
    place)."""
    old = None
    if out_dir.exists():
        old = out_dir.absolute().parent / f".{out_dir.name}.old.{_run_tag()}"
        if old.exists():
            shutil.rmtree(old)
        os.rename(out_dir, old)
    try:
        os.rename(staging, out_dir)
    except BaseException:
        if old is not None:
            os.rename(old, out_dir)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _build(options: DemoOptions, out: Path, predictor: Any, training_config: Any,
           progress: bool, started: float) -> DemoResult:
    """Every stage, into the (new, empty) folder ``out``."""
    from sq_mitsuba.data.library import GenerateOptions, generate_library
    from sq_mitsuba.data.spe3r import RenderOptions, render_dataset
    from sq_mitsuba.data.spe3r.layout import write_splits
    from sq_mitsuba.evaluation.scoring import baseline_prediction
    from sq_mitsuba.evaluation.tables import write_tables
    from sq_mitsuba.inference.loading import with_fast_path
    from sq_mitsuba.io import atomic_write_json

    stages: dict[str, float] = {}
    preset = options.preset
    curves = None
    baseline_source = ""
    baseline = None
    if training_config is not None:
        tick = time.perf_counter()
        predictor, curves, run_data = _train(options.training, training_config, out / "train",
                                             options.points, progress)
        stages["train"] = time.perf_counter() - tick
        predictor = with_fast_path(predictor, True)
        baseline = baseline_prediction(predictor, run_data, options.baseline_images,
                                       options.batch_size)
        baseline_source = ("the mean prediction over this run's training images, at the mean "
                           "pose of their labels")
    elif predictor.baseline is not None:
        baseline = predictor.baseline
        baseline_source = ("stored with the checkpoint: the mean prediction over its training "
                           "images, at the mean pose of their labels")

    tick = time.perf_counter()
    library = out / "models"
    summary = generate_library(GenerateOptions(out=library, count=preset.models,
                                               seed=options.seed, points=options.points),
                               progress=progress)
    if summary.failures:
        name, reason = next(iter(summary.failures.items()))
        raise ValueError(f"spacecraft {name} could not be generated: {reason}")
    # Every demo spacecraft is new to the model: all of them are test models.
    write_splits(library, [(name, "test") for name in sorted(summary.written)])
    stages["generate"] = time.perf_counter() - tick

    tick = time.perf_counter()
    data = out / "data"
    rendered = render_dataset(library, data, RenderOptions(
        images_per_model=preset.images, seed=options.seed, resolution=preset.resolution,
        spp=preset.spp), progress=progress)
    if rendered.failures:
        name, reason = next(iter(rendered.failures.items()))
        raise ValueError(f"images of {name} could not be rendered: {reason}")
    stages["render"] = time.perf_counter() - tick

    # BatchNorm folded once (about 0.1 s): the same predictions up to ~1e-5, faster.
    fast = with_fast_path(predictor, True)
    if baseline is None:
        baseline = baseline_prediction(fast, data, options.baseline_images,
                                       options.batch_size, split="test")
        baseline_source = ("the checkpoint stores none, so it was computed here: the mean "
                           "prediction over the demo's own images at the mean pose of their "
                           "labels (a floor that has seen the true poses, so a generous one)")
    tick = time.perf_counter()
    records, rows = _predict_and_score(fast, data, options, baseline, progress)
    stages["predict, refine, score"] = time.perf_counter() - tick

    tick = time.perf_counter()
    write_outputs(records, data, out, options, progress)
    table = write_tables(rows, out)
    stages["pictures and files"] = time.perf_counter() - tick
    if curves is not None:
        shutil.copyfile(curves, out / "images" / "training_curves.png")
    passed, pass_skipped = None, None
    if preset.pass_frames >= 2:
        from sq_mitsuba.apps.demo_pass import render_pass, run_pass

        tick = time.perf_counter()
        first = sorted(summary.written)[0]
        pass_data = render_pass(library, first, out / "pass", preset.pass_frames,
                                preset.resolution, preset.spp, options.seed, progress)
        try:
            passed = run_pass(fast, pass_data, out / "pass", options.surface_points,
                              options.points, options.level, options.silhouette_spp, progress,
                              overlay_spp=options.overlay_spp)
        except ValueError as error:  # a frame without a target to fit: the images stand
            pass_skipped = f"the pass of {first} could not be fitted: {error}"
            warnings.warn(pass_skipped, stacklevel=2)
        stages["pass"] = time.perf_counter() - tick
    checkpoint = str(getattr(predictor, "source", None) or "")
    if training_config is not None:
        checkpoint = str(Path("train") / "run" / Path(checkpoint).name)
    wall = time.perf_counter() - started
    record = {
        "format": DEMO_FORMAT,  # the mark of a folder the demo wrote (check_demo_folder)
        "options": to_dict(options), "checkpoint": checkpoint, "baseline": baseline_source,
        "network": {"image_size": predictor.image_size,
                    "num_primitives": predictor.num_primitives},
        "images": len(records), "models": sorted({r["model"] for r in records}),
        "pass": (pass_skipped and {"skipped": pass_skipped}) if passed is None else {
            "model": passed.model, "frames": passed.frames, "resolution": passed.resolution,
            "seconds": round(passed.seconds, 2),
            "summary": {method: {name: value if math.isfinite(value) else None
                                 for name, value in means.items()}
                        for method, means in passed.summary.items()}},
        "stage_seconds": {k: round(v, 2) for k, v in stages.items()},
        "wall_seconds_before_page": round(wall, 2),
    }
    atomic_write_json(out / MANIFEST, record)
    page, markdown = write_demo_page(out, options, records, table, checkpoint, baseline_source,
                                     curves is not None, stages, wall, passed, pass_skipped)
    return DemoResult(out, page, markdown, len(records), len(record["models"]), table,
                      checkpoint, baseline_source, wall, stages, passed)


def _train(training: DemoTraining, config: Any, root: Path, points: int,
           progress: bool) -> tuple[Any, Path | None, Path]:
    """Library, dataset and training run of ``--train`` under ``root``; returns the
    predictor of the run's best checkpoint (else its last), its curves.png (None when it
    drew none) and the dataset folder."""
    from sq_mitsuba.data.library import GenerateOptions, generate_library
    from sq_mitsuba.data.spe3r import RenderOptions, render_dataset
    from sq_mitsuba.inference.loading import load_model
    from sq_mitsuba.training.train import CURVES_FILE, train

    library = root / "models"
    summary = generate_library(GenerateOptions(out=library, count=training.models,
                                               seed=training.catalogue_seed, points=points),
                               progress=progress)
    if summary.failures:
        name, reason = next(iter(summary.failures.items()))
        raise ValueError(f"training spacecraft {name} could not be generated: {reason}")
    data = root / "data"
    rendered = render_dataset(library, data, RenderOptions(
        images_per_model=training.images_per_model, seed=training.catalogue_seed,
        resolution=training.resolution, spp=training.spp), progress=progress)
    if rendered.failures:
        name, reason = next(iter(rendered.failures.items()))
        raise ValueError(f"training images of {name} could not be rendered: {reason}")
    result = train(config, data, root / "run", progress=progress)
    checkpoint = result.best_checkpoint or result.last_checkpoint
    if checkpoint is None:
        raise ValueError(f"{root / 'run'}: training wrote no checkpoint")
    curves = root / "run" / CURVES_FILE
    # Drawn at each validation: a run without val images (too few per model) has none.
    return load_model(checkpoint), curves if curves.is_file() else None, data


def _predict_and_score(predictor: Any, data: Path, options: DemoOptions,
                       baseline: tuple[Tensor, Tensor, Tensor], progress: bool
                       ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Predict, refine and score every image of the demo dataset.

    Returns:
        records: per image, the dataset item, its model and index, and per method a tuple
            (assembly of batch size 1, rotation (3, 3), translation (3,)), plus the
            refinement's IoUs; rows: the ``per_image.csv`` rows (one per image and method).
    """
    from sq_mitsuba.data.symmetry import model_symmetries
    from sq_mitsuba.evaluation.scoring import score, volume_points
    from sq_mitsuba.evaluation.split import collate, open_split
    from sq_mitsuba.evaluation.tables import label_record
    from sq_mitsuba.inference.search import SEARCH_REFINEMENT
    from sq_mitsuba.progress import progress_bar
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    dataset = open_split(data, "test", predictor.image_size, options.surface_points)
    camera = dataset.camera.rescaled(predictor.image_size, predictor.image_size)
    renderer = SilhouetteRenderer(camera, spp=options.silhouette_spp)
    refine_options = replace(SEARCH_REFINEMENT, steps=options.preset.refine_steps)
    symmetries: dict[int, Tensor] = {}
    volumes: dict[int, tuple[Tensor, Tensor]] = {}
    for index, model in enumerate(dataset.models):
        symmetries[index] = torch.as_tensor(np.asarray(model_symmetries(data / model)),
                                            dtype=torch.float64)
        volumes[index] = volume_points(data / model, options.points)
    base_assembly = Assembly.from_raw(baseline[0].double())
    records: list[dict[str, Any]] = []
    rows: list[dict[str, Any]] = []
    with progress_bar(total=len(dataset), unit="img", disable=not progress, dynamic_ncols=True,
                      desc="predict, refine, score") as bar:
        for start in range(0, len(dataset), options.batch_size):
            chunk = list(range(start, min(start + options.batch_size, len(dataset))))
            batch = collate([dataset[i] for i in chunk])
            size = len(chunk)
            refined = predictor.predict(batch["image"], camera, refine=True,
                                        refinement=refine_options)
            prediction, fit = refined.network, refined.fit
            candidates = {
                "network": (prediction.assembly, prediction.rotation, prediction.translation),
                "refined": (refined.assembly, refined.rotation, refined.translation),
                "baseline": (Assembly(base_assembly.params.expand(size, -1, -1)),
                             baseline[1].double().expand(size, -1, -1),
                             baseline[2].double().expand(size, -1)),
            }
            model_indices = [int(m) for m in batch["model_index"]]
            for method, (assembly, rotation, translation) in candidates.items():
                metrics = score(assembly, rotation, translation, batch, renderer,
                                [symmetries[m] for m in model_indices],
                                [volumes[m] for m in model_indices], options.level)
                if method == "refined":
                    metrics["search_score"] = fit.search_score
                    metrics["refine_iou_after"] = fit.iou
                for k, item in enumerate(chunk):
                    row = {"model": batch["model"][k], "index": int(batch["index"][k]),
                           "method": method, **label_record(dataset.items[item][2]),
                           "mask_source": fit.mask_source if method == "refined" else ""}
                    row.update({name: float(value[k]) for name, value in metrics.items()})
                    rows.append(row)
            for k, item in enumerate(chunk):
                record = {"item": item, "model": batch["model"][k],
                          "index": int(batch["index"][k]),
                          "filename": dataset.items[item][2]["filename"],
                          "gt_rotation": batch["rotation"][k].double(),
                          "gt_translation": batch["translation"][k].double()}
                # Each item's own primitives (no stand-ins of a network with existence).
                own = {"network": prediction.item_assembly(k), "refined": refined.item_assembly(k)}
                for method, (assembly, rotation, translation) in candidates.items():
                    item = own.get(method, Assembly(assembly.params[k:k + 1]))
                    record[method] = (Assembly(item.params.detach().double()),
                                      rotation[k].detach().double(),
                                      translation[k].detach().double())
                record["metrics"] = {
                    row["method"]: row for row in rows[-len(candidates) * size:]
                    if row["model"] == record["model"] and row["index"] == record["index"]}
                records.append(record)
            bar.update(size)
    return records, rows
