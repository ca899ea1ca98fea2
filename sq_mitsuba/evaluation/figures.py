"""Figures of the fitting and evaluation results (PNG, written atomically)."""

from __future__ import annotations

from pathlib import Path

import torch

from sq_mitsuba.learning.fit import FitResult
from sq_mitsuba.render.silhouette import mask_iou


def plot_fit(result: FitResult, path: str | Path, title: str | None = None) -> Path:
    """PNG of the target masks against the fitted silhouettes at start, middle and end.

    One row per view; each snapshot overlays the silhouette (red) on the target (green):
    yellow where they agree. Written atomically.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sq_mitsuba.io import save_figure

    views = result.targets.shape[0]
    columns = 1 + len(result.snapshots)
    figure, axes = plt.subplots(views, columns, figsize=(2.1 * columns, 2.1 * views + 0.4),
                                squeeze=False)
    for view in range(views):
        target = result.targets[view].float()
        axes[view, 0].imshow(target.numpy(), cmap="gray", vmin=0, vmax=1)
        axes[view, 0].set_title(f"view {view}: mask", fontsize=8)
        for column, (step, coverage) in enumerate(result.snapshots, start=1):
            silhouette = coverage[view].float()
            overlay = torch.stack([silhouette, target, torch.zeros_like(target)], dim=-1)
            iou = float(mask_iou(silhouette, target))
            axes[view, column].imshow(overlay.clamp(0, 1).numpy())
            axes[view, column].set_title(f"step {step}: IoU {iou:.3f}", fontsize=8)
    for axis in axes.flat:
        axis.set_xticks([])
        axis.set_yticks([])
    figure.suptitle(title or f"fit: mean IoU {result.mean_iou:.3f} (red fit, green mask)",
                    fontsize=9)
    figure.tight_layout()
    return save_figure(figure, path)
