"""A target mask segmented from a space image, for refinement when no mask is given.

Rule (documented, deterministic, numpy and scipy only): space is dark, so a pixel belongs to
the target when it is brighter than ``max(floor, fraction * p)``, with ``p`` the 99.5th
percentile of the image (robust to a few hot pixels) and the defaults ``floor = 8/255`` and
``fraction = 0.12``. The bright set is closed (fills gaps between lit panels), its holes are
filled (shadowed parts inside the outline), and connected pieces smaller than
``min_piece`` of the largest are dropped (stars are single pixels). A bright background (the
Earth) breaks the rule: when the mask covers more than ``earth_fraction`` of the image border,
the result carries a warning.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Segmentation:
    """A segmented mask (H, W) bool, the threshold used (in image units), and a warning
    (None when the rule's assumptions hold)."""

    mask: np.ndarray
    threshold: float
    warning: str | None


def segment_target(image: np.ndarray, floor: float = 8 / 255, fraction: float = 0.12,
                   min_piece: float = 0.05, earth_fraction: float = 0.25) -> Segmentation:
    """Segment the target of a grayscale space image (H, W) with values in [0, 1].

    Raises:
        ValueError: for a non-2D, non-finite or empty-of-target image.
    """
    from scipy import ndimage

    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 2 or min(image.shape) < 2:
        raise ValueError(f"image: expected a 2D grayscale array, got shape {image.shape}")
    if not np.isfinite(image).all():
        raise ValueError("image: contains NaN or infinite values")
    threshold = max(floor, fraction * float(np.percentile(image, 99.5)))
    bright = image > threshold
    if not bright.any():
        raise ValueError(f"image: nothing brighter than the threshold {threshold:.4f}; no "
                         "target to segment (too dark, or an eclipse)")
    structure = np.ones((3, 3), dtype=bool)
    closed = ndimage.binary_closing(np.pad(bright, 2), structure, iterations=2)[2:-2, 2:-2]
    filled = ndimage.binary_fill_holes(closed | bright)
    labels, count = ndimage.label(filled, structure)
    areas = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    keep = np.flatnonzero(areas >= min_piece * areas.max()) + 1
    mask = np.isin(labels, keep)
    border = np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]])
    warning = None
    if border.mean() > earth_fraction:
        warning = (f"the segmented mask covers {100 * border.mean():.0f} % of the image border: "
                   "a bright background (the Earth?) is probably merged with the target; "
                   "pass a mask instead")
    return Segmentation(mask, threshold, warning)
