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
    # float32 and in place: a large image's picture is the largest array predict holds.
    rgb = np.repeat(np.asarray(image, dtype=np.float32)[..., None], 3, axis=-1)
    rgb *= 0.8
    for coverage, colour in silhouettes:
        alpha = np.clip(np.asarray(coverage, dtype=np.float32), 0, 1)
        alpha *= 0.45
        for channel, value in enumerate(colour):  # rgb = rgb (1 - alpha) + alpha colour
            rgb[..., channel] += alpha * (np.float32(value) - rgb[..., channel])
    if outline is not None:
        from scipy import ndimage

        edge = outline & ~ndimage.binary_erosion(outline)
        rgb[edge] = MASK_COLOUR
    np.clip(rgb, 0, 1, out=rgb)
    rgb *= 255
    rgb += 0.5
    return rgb.astype(np.uint8)
