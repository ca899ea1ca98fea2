"""Validation during training: mean Chamfer-L1 (the paper's convention), 2D IoU, rotation
error and the mask head's IoU over a fixed subset of the val split, with the metrics of
:mod:`sq_mitsuba.geometry.metrics` that evaluation reports too.

``mask_iou`` is the IoU of the mask head's mask (logits upsampled bilinearly to the image's
size, probability > 0.5) against the true mask, as ``sq-mitsuba eval`` reports it; NaN for a
network without a mask head.

A network with existence probabilities is validated on the primitives the predictor keeps by
default (probability at least 0.5, each item's most probable one always), as evaluation
scores it."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.metrics import chamfer_l1, mask_iou, rotation_error_deg
from sq_mitsuba.model.existence import EXISTENCE_THRESHOLD, gathered_primitives, kept_primitives
from sq_mitsuba.model.losses import counted_surface_samples
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly
from sq_mitsuba.training.cache import ImageCache, PointCache
from sq_mitsuba.training.config import TrainConfig
from sq_mitsuba.training.random_streams import STREAMS, seed_of

__all__ = ["HIGHER_IS_BETTER", "VAL_METRICS", "improves", "validate"]

#: Validation metrics, in ``val.csv`` order.
VAL_METRICS = ("chamfer_l1", "iou_2d", "rotation_error_deg", "mask_iou")
HIGHER_IS_BETTER = {"chamfer_l1": False, "iou_2d": True, "rotation_error_deg": False,
                    "mask_iou": True}


def improves(metric: str, value: float, best: dict | None) -> bool:
    """Whether ``value`` of ``metric`` beats ``best`` (a checkpoint's ``best`` entry, or None)."""
    if best is None:
        return True
    return value > best["value"] if HIGHER_IS_BETTER[metric] else value < best["value"]


def validate(model: nn.Module, cache: ImageCache, points: PointCache, config: TrainConfig,
             camera: Camera, renderer: SilhouetteRenderer, device: torch.device
             ) -> dict[str, float]:
    """Mean Chamfer-L1, 2D IoU, rotation error (deg) and mask IoU over the cached validation
    subset."""
    cfg = config.validation
    was_training = model.training
    model.eval()
    metrics: dict[str, list[Tensor]] = {name: [] for name in VAL_METRICS}
    k_matrix = camera.matrix(device=device)
    renderer.reseed(seed_of(config.seed, STREAMS["render"], 2**31))
    try:
        with torch.no_grad():
            for start in range(0, len(cache), cfg.batch_size):
                rows = np.arange(start, min(len(cache), start + cfg.batch_size))
                batch = cache.batch(rows)
                output = model(batch["image"].to(device), k_matrix)
                params = output.assembly.params.detach().to("cpu", torch.float64)
                if output.existence is not None:  # stand-ins pad items keeping fewer
                    kept = kept_primitives(output.existence.detach().cpu(), EXISTENCE_THRESHOLD)
                    params = gathered_primitives(params, kept)
                assembly = Assembly(params)
                surface, keep = counted_surface_samples(assembly, cfg.level)
                gt = []
                for row, model_index in zip(rows, batch["model_index"].tolist(), strict=True):
                    rng = np.random.default_rng(seed_of(config.seed, 7, int(
                        cache.dataset_index[row])))
                    gt.append(points.sample(model_index, rng, config.data.num_surface, 2)[0])
                metrics["chamfer_l1"].append(chamfer_l1(
                    surface, torch.from_numpy(np.stack(gt)), "paper", pred_mask=keep))
                rotation = output.rotation.detach().to("cpu", torch.float64)
                translation = output.translation.detach().to("cpu", torch.float64)
                silhouettes = render_assembly(assembly, rotation, translation, renderer,
                                              cfg.level)
                metrics["iou_2d"].append(mask_iou(silhouettes, batch["mask"][:, 0].double()))
                metrics["rotation_error_deg"].append(rotation_error_deg(
                    rotation, batch["rotation"].double()))
                metrics["mask_iou"].append(_mask_head_iou(output.mask_logits, batch["mask"]))
    finally:
        model.train(was_training)
    return {name: float(torch.cat(values).mean()) for name, values in metrics.items()}


def _mask_head_iou(logits: Tensor | None, masks: Tensor) -> Tensor:
    """(B,) IoU of the mask head's mask against ``masks`` (B, 1, H, W); NaN without a head."""
    if logits is None:
        return torch.full((masks.shape[0],), float("nan"), dtype=torch.float64)
    up = F.interpolate(logits.detach().float().cpu(), size=masks.shape[-2:], mode="bilinear",
                       align_corners=False)
    return mask_iou((up[:, 0] > 0).double(), (masks[:, 0] > 0.5).double())
