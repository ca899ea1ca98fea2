"""The overlay ``predict`` and the demo draw: the image dimmed, each silhouette blended in its
colour, the outline of the fitted mask on top."""

from __future__ import annotations

import numpy as np

__all__ = ["MASK_COLOUR", "NETWORK_COLOUR", "REFINED_COLOUR", "overlay_image"]

#: Colours (RGB in [0, 1]) of the overlay: network silhouette, refined silhouette, mask edge.
NETWORK_COLOUR = (1.0, 0.15, 0.1)
REFINED_COLOUR = (0.1, 0.9, 0.2)
MASK_COLOUR = (1.0, 0.85, 0.0)


def overlay_image(image: np.ndarray, silhouettes: list[tuple[np.ndarray, tuple[float, ...]]],
                  outline: np.ndarray | None) -> np.ndarray:
    """RGB (H, W, 3) uint8: the grey image (H, W) in [0, 1], dimmed, with each coverage
    (H, W) blended in its colour (45 %) and the edge of ``outline`` (H, W) bool on top."""
    rgb = np.repeat(image[..., None], 3, axis=-1) * 0.8
    for coverage, colour in silhouettes:
        alpha = 0.45 * np.clip(coverage, 0, 1)[..., None]
        rgb = rgb * (1 - alpha) + alpha * np.asarray(colour)
    if outline is not None:
        from scipy import ndimage

        edge = outline & ~ndimage.binary_erosion(outline)
        rgb[edge] = MASK_COLOUR
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
