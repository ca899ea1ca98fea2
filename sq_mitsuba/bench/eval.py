"""``sq-mitsuba bench eval``: evaluation throughput and ``predict`` latency at 128 px.

A randomly initialised default network (EfficientNet-B0, M = 5, 128 px input; its predictions
are meaningless, but the work per image is that of a trained one, refinement aside: a trained
network's start may converge in fewer steps) on a small dataset rendered for the occasion
(two generated spacecraft, ``IMAGES`` images each at 128 px, 16 spp, both test models):

- evaluation: :func:`sq_mitsuba.evaluation.evaluate.evaluate` over the split, network and
  every metric, without figures or baseline (one-off costs), then with ``refine`` (the
  default search + refinement, against a segmented and the ground-truth mask); per-image time
  of the loop, images/s its inverse;
- predict latency per image: the network alone (batch of one, BatchNorm folded); the network
  followed by exactly 50 refinement steps (patience 50) against the image's mask (the
  refinement alone, as before the search existed); the network and the global pose search
  (default :class:`~sq_mitsuba.inference.search.SearchOptions`: 4 + 1,024 candidate rotations
  scored at 32 px, the best 128 again at 64 px); the network and the search + refinement
  (:func:`~sq_mitsuba.inference.search.search_and_refine` with its defaults); the shipped
  model's whole path with the default and with the outline refinement; and
  ``predict_files`` whole (network, overlay silhouette, OBJ, GLB, JSON and PNG writes).

Everything runs on the CPU (Mitsuba's LLVM variant, scipy KD-trees); ``--device`` is not used.
"""

from __future__ import annotations

import os
import statistics
import tempfile
from pathlib import Path

from sq_mitsuba.bench import (
    BenchOptions,
    Report,
    Timing,
    bench_dataset,
    load_average,
    time_callable,
)

RESOLUTION = 128
IMAGES = 4
REFINE_STEPS = 50


def _dataset(root: Path) -> Path:
    return bench_dataset(root, 2, 0, IMAGES, RESOLUTION, 3, "eval")


def run(options: BenchOptions) -> Report:
    import torch

    from sq_mitsuba.apps.predict import PredictOptions, predict_files
    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.evaluation.evaluate import EvalOptions, evaluate
    from sq_mitsuba.evaluation.scoring import METRICS
    from sq_mitsuba.inference.loading import load_model
    from sq_mitsuba.inference.predictor import Predictor
    from sq_mitsuba.inference.refine import (
        OUTLINE_REFINEMENT,
        RefineOptions,
        refine_pose_and_shape,
    )
    from sq_mitsuba.inference.search import (
        SearchOptions,
        pose_candidates,
        search_poses,
    )
    from sq_mitsuba.model.checkpoint import SHIPPED_MODEL
    from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet

    torch.set_num_threads(options.threads)
    torch.manual_seed(0)
    report = Report("eval", options=options)
    network = SuperquadricNet(NetworkConfig(image_size=RESOLUTION)).eval()
    with tempfile.TemporaryDirectory(prefix="sq-bench-eval-") as tmp:
        root = Path(tmp)
        data = _dataset(root)
        dataset = Spe3rDataset(data, "test", image_size=RESOLUTION)
        camera = dataset.camera.rescaled(RESOLUTION, RESOLUTION)
        predictor = Predictor(network, camera, fast=True)
        repeats = max(1, min(options.repeats, 3))  # each repeat evaluates the whole split
        images = len(dataset)
        for refine in (False, True):
            eval_options = EvalOptions(split="test", refine=refine, baseline=False,
                                       figures=False, batch_size=images)
            rates = []

            def once(eval_options=eval_options, rates=rates) -> None:
                result = evaluate(predictor, data, root / "eval", eval_options, progress=False)
                rates.append(result.images_per_second)

            time_callable(once, repeats, warmup=1)  # warm-up: kernels, symmetries, points
            rates = rates[1:]
            name = "evaluate --refine, per image" if refine else "evaluate, per image"
            report.timings.append(Timing(
                name, [1.0 / r for r in rates],
                note=f"{images} images of {RESOLUTION} px in one batch; network + "
                     f"{'2 searches + refinements (segmented and GT mask) + ' if refine else ''}"
                     f"{len(METRICS)} metrics for each method"))
            report.notes.append(f"{name.split(',')[0]}: median "
                                f"{statistics.median(rates):.2f} images/s")

        item = dataset[0]
        image, mask = item["image"], item["mask"][:, :, :] > 0.5
        network_alone = time_callable(lambda: predictor.predict(image, camera),
                                      options.repeats, options.warmup)
        report.timings.append(Timing("predict: network alone, per image", network_alone,
                                     note=f"batch of 1, {RESOLUTION} px, BatchNorm folded"))
        refine_options = RefineOptions(steps=REFINE_STEPS, patience=REFINE_STEPS)
        steps_taken = []

        def predict_and_refine() -> None:
            prediction = predictor.predict(image, camera)
            result = refine_pose_and_shape(prediction.assembly, prediction.rotation,
                                           prediction.translation, mask, camera,
                                           refine_options)
            steps_taken.append(result.steps)

        refined = time_callable(predict_and_refine, max(1, min(options.repeats, 5)),
                                warmup=1)
        report.timings.append(Timing(
            f"predict: network + {REFINE_STEPS} refinement steps, per image", refined,
            note=f"refinement at {refine_options.resolution} px, level {refine_options.level}, "
                 f"spp {refine_options.spp}; steps taken {sorted(set(steps_taken))}"))
        search = SearchOptions()

        def predict_and_search() -> None:
            prediction = predictor.predict(image, camera)
            search_poses(prediction.assembly, pose_candidates(prediction.rotation, None,
                                                              search.grid),
                         prediction.translation, mask, camera, search)

        report.timings.append(Timing(
            "predict: network + search, per image",
            time_callable(predict_and_search, max(1, min(options.repeats, 5)), warmup=1),
            note=f"4 + {search.grid} rotations at {search.coarse_resolution} px, the best "
                 f"{search.fine} at {search.resolution} px, spp {search.spp}, recentred"))
        def predict_search_refine() -> None:
            predictor.predict(image, camera, refine=True, mask=mask)

        report.timings.append(Timing(
            "predict: network + search + refinement, per image",
            time_callable(predict_search_refine, max(1, min(options.repeats, 5)), warmup=1),
            note=f"Predictor.predict(refine=True) against the true mask: the best {search.keep} "
                 f"refined {search.screen_steps} steps each, the best of them to 25 steps "
                 "(pose only, rotation prior 1)"))
        if SHIPPED_MODEL.is_file():
            shipped = load_model(fast=True)
            for turns, what in ((1, "network alone"),
                                (search.turns, f"network from {search.turns} turned copies "
                                               "(what `predict` writes by default)")):
                report.timings.append(Timing(
                    f"predict: shipped model, {what}, per image",
                    time_callable(lambda t=turns: shipped.predict(image, camera, turns=t),
                                  options.repeats, options.warmup),
                    note=f"batch of 1, {RESOLUTION} px image, the {shipped.image_size} px "
                         "network, fast path"))
            report.timings.append(Timing(
                "predict: shipped model, loaded, then its first reading from turned copies",
                time_callable(lambda: load_model(fast=True).predict(
                    image, camera, turns=search.turns),
                              max(1, min(options.repeats, 5)), warmup=1),
                note="what a new `predict` process pays once: the checkpoint read, the "
                     "network folded, the table of where each rotation cell goes under the "
                     f"{search.turns} turns, one reading"))

            def shipped_turned_search_refine() -> None:
                shipped.predict(image, camera, refine=True)

            report.timings.append(Timing(
                "predict: shipped model + rotation from turns + search + refinement, per image",
                time_callable(shipped_turned_search_refine, max(1, min(options.repeats, 5)),
                              warmup=1),
                note=f"Predictor.predict(refine=True) with the shipped model (distribution and "
                     f"mask heads): the network, then {search.turns - 1} more in-plane turns of "
                     "the image, then the search of its rotation x 4 half turns against its own "
                     "mask and the default refinement"))

            def shipped_outline() -> None:
                shipped.predict(image, camera, refine=True, refinement=OUTLINE_REFINEMENT)

            report.timings.append(Timing(
                "predict: shipped model + rotation from turns + search + outline refinement, "
                "per image",
                time_callable(shipped_outline, max(1, min(options.repeats, 5)), warmup=1),
                note="the same with OUTLINE_REFINEMENT (every shape parameter follows the mask "
                     "too, 100 steps at most, patience 30)"))
        path = root / "input.png"
        from PIL import Image

        Image.fromarray((image[0].numpy() * 255 + 0.5).astype("uint8")).save(path)
        whole = time_callable(
            lambda: predict_files([path], root / "predicted", predictor, PredictOptions(),
                                  progress=False), max(1, min(options.repeats, 5)), warmup=1)
        report.timings.append(Timing(
            "predict_files: network + overlay + OBJ/GLB/JSON/PNG, per image", whole,
            note="one image per call (renderer built per call)"))
    load = load_average()
    report.notes.append(
        f"randomly initialised default network ({sum(p.numel() for p in network.parameters()):,}"
        f" parameters, M = {network.config.num_primitives}); dataset: 2 generated spacecraft x "
        f"{IMAGES} images, {RESOLUTION} px, 16 spp")
    report.notes.append(f"1-minute load average at the end: {load:.2f} on {os.cpu_count()} "
                        "cores (above ~2, other processes inflate these timings)")
    return report
