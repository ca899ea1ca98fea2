"""One batch of an evaluation (:func:`sq_mitsuba.evaluation.evaluate.evaluate`): its images
read by the network, searched and refined (``refine``), and every method scored
(:func:`evaluate_batch`), as a :class:`~sq_mitsuba.evaluation.journal.BatchRecord`, the unit
the journal keeps for ``--resume``."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

from torch import Tensor

from sq_mitsuba.evaluation.journal import BatchRecord
from sq_mitsuba.evaluation.scoring import ModelData, score
from sq_mitsuba.evaluation.split import collate
from sq_mitsuba.evaluation.tables import EXTRAS, label_record
from sq_mitsuba.geometry.assembly import Assembly

__all__ = ["evaluate_batch"]


def evaluate_batch(predictor: Any, dataset: Any, chunk: Sequence[int], number: int,
                   camera: Any, options: Any, renderer: Any, models: ModelData,
                   baseline: tuple[Assembly, Tensor, Tensor] | None, wanted: set[int],
                   ranked: set[int], stage: Callable[[str], None], warm: bool) -> BatchRecord:
    """Batch ``number`` (1, 2, ...) of an evaluation predicted, fitted and scored.

    Its scores depend on that batch alone, not on the batches before it: each image is scored
    with silhouette samples of its own (:func:`~sq_mitsuba.evaluation.scoring.image_seed`,
    whatever batch or place it has), and the search and refinement seed each call. So a
    resumed evaluation computes a batch as an uninterrupted one does.

    Args:
        predictor: the evaluation's (fast path) Predictor; dataset: the split's
            ``Spe3rDataset``; chunk: the batch's items (indices into the split, B of them).
        camera: the network's input camera; options: the evaluation's
            :class:`~sq_mitsuba.evaluation.evaluate.EvalOptions` (not imported: evaluate
            imports this module).
        renderer: the scoring SilhouetteRenderer (S x S); models: per-model symmetries and
            volume points.
        baseline: the trivial baseline's assembly (1, M), rotation (1, 3, 3) and translation
            (1, 3), or None.
        wanted, ranked: the items kept as qualitative examples and as mesh-ranking entries.
        stage: called with the name of each stage reached (for the progress bar).
        warm: the network has run already (else one untimed call first, not counted).

    Returns:
        The batch's :class:`~sq_mitsuba.evaluation.journal.BatchRecord` (its ``loop`` seconds
        without the warm-up call).
    """
    from sq_mitsuba.geometry.metrics import mask_iou

    batch_started = time.perf_counter()
    stage("reading")
    batch = collate([dataset[i] for i in chunk])
    size = len(chunk)
    stage("network")
    warmup_seconds = search_seconds = refine_seconds = 0.0
    if not warm:
        # One untimed call first: the first run of a network sets up its kernels (over
        # a second on a CPU), which would otherwise count as network time.
        tick = time.perf_counter()
        predictor.predict(batch["image"], camera)
        warmup_seconds = time.perf_counter() - tick
    tick = time.perf_counter()
    # The search starts from the unturned reading and reads its own turned copies;
    # the network row's copies reuse that reading's pass (read_turns).
    unturned = predictor.predict(batch["image"], camera)
    prediction = unturned if options.turns == 1 else predictor.read_turns(
        batch["image"], unturned, options.turns, camera)
    network_seconds = time.perf_counter() - tick
    rows: list[dict[str, Any]] = []
    examples: list[dict[str, Any]] = []
    to_rank: list[tuple[int, int, str, Assembly]] = []
    model_indices = [int(m) for m in batch["model_index"]]
    symmetries = [models.symmetry(m) for m in model_indices]
    volumes = [models.volume(m) for m in model_indices]
    candidates: dict[str, tuple[Assembly, Tensor, Tensor]] = {
        "network": (prediction.assembly, prediction.rotation, prediction.translation)}
    extras: dict[str, dict[str, Tensor]] = {}
    sources: dict[str, str] = {}
    if options.refine:
        stage("search and refinement")
        gt_masks = batch["mask"][:, 0] > 0.5
        fitted = predictor.refine(batch["image"], unturned, camera, mask=options.mask,
                                  search=options.search,
                                  refinement=options.refinement)
        fit = fitted.fit
        search_seconds, refine_seconds = fit.search_seconds, fit.seconds
        mask_iou_gt = mask_iou(fit.mask.double().cpu(), gt_masks.double())
        candidates["search"] = (Assembly(fit.start.assembly.params.detach().double()),
                                fit.search_rotation, fit.search_translation)
        candidates["refined"] = (fitted.assembly, fitted.rotation, fitted.translation)
        for method in ("search", "refined"):
            extras[method] = {"search_score": fit.search_score,
                              "refine_iou_after": fit.iou,
                              "mask_iou": mask_iou_gt}
            sources[method] = fit.mask_source
        if options.refine_ground_truth:
            # The one-pass reading, as refine takes (the turned start is reused from fit).
            upper = predictor.refine(batch["image"], unturned, camera,
                                     mask=gt_masks, search=options.search,
                                     refinement=options.refinement, reuse=fit)
            candidates["refined_gt"] = (upper.assembly, upper.rotation,
                                        upper.translation)
            extras["refined_gt"] = {"search_score": upper.fit.search_score,
                                    "refine_iou_after": upper.fit.iou}
            sources["refined_gt"] = "ground truth"
    if baseline is not None:
        candidates["baseline"] = (Assembly(baseline[0].params.expand(size, -1, -1)),
                                  baseline[1].expand(size, -1, -1),
                                  baseline[2].expand(size, -1))
    stage("scoring")
    # Scored on the CPU with the dataset's tensors, whatever device the predictor reads on.
    candidates = {method: (Assembly(assembly.params.detach().cpu()), rotation.detach().cpu(),
                           translation.detach().cpu())
                  for method, (assembly, rotation, translation) in candidates.items()}
    extras = {method: {k: v.detach().cpu() if isinstance(v, Tensor) else v
                       for k, v in values.items()}
              for method, values in extras.items()}
    scores = {method: {**score(assembly, rotation, translation, batch, renderer, symmetries,
                               volumes, options.level), **extras.get(method, {})}
              for method, (assembly, rotation, translation) in candidates.items()}
    # Image by image, each image's methods together: per_image.csv's order is then the
    # images' whatever the batch size.
    for k, item in enumerate(chunk):
        for method, metrics in scores.items():
            row = {"model": batch["model"][k], "index": int(batch["index"][k]),
                   "method": method, "mask_source": sources.get(method, ""),
                   **label_record(dataset.items[item][2])}
            row.update({name: float(value[k]) for name, value in metrics.items()})
            for name in EXTRAS:  # NaN: not searched (no target segmented) -> blank
                if name in row and not math.isfinite(row[name]):
                    row[name] = ""
            rows.append(row)
    for k, item in enumerate(chunk):
        if item in ranked:
            to_rank.append((int(batch["index"][k]), model_indices[k], batch["model"][k],
                            Assembly(prediction.assembly.params[k:k + 1].detach())))
        if item in wanted:
            example = {"image": batch["image"][k, 0], "mask": batch["mask"][k, 0],
                       "model": batch["model"][k], "index": int(batch["index"][k]),
                       "gt_rotation": batch["rotation"][k],
                       "gt_translation": batch["translation"][k]}
            for method, (assembly, rotation, translation) in candidates.items():
                example[method] = (assembly[k], rotation[k].detach(),
                                   translation[k].detach())
            examples.append(example)
    seconds = {"network": network_seconds, "search": search_seconds, "refine": refine_seconds,
               "loop": time.perf_counter() - batch_started - warmup_seconds}
    return BatchRecord(list(chunk), rows, examples, to_rank, seconds)
