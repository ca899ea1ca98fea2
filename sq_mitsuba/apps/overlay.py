"""The overlay ``predict`` and the demo draw: the image dimmed, each silhouette blended in its
colour, the outline of the fitted mask on top; the silhouettes rendered for it
(:func:`overlay_silhouettes`, at most :data:`OVERLAY_MAX_SIDE` pixels a side)."""

from __future__ import annotations

from typing import Any

import numpy as np

from sq_mitsuba.geometry.camera import Camera

__all__ = ["MASK_COLOUR", "NETWORK_COLOUR", "OVERLAY_MAX_SIDE", "REFINED_COLOUR",
           "overlay_camera", "overlay_image", "overlay_silhouettes", "resized_coverage"]

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


#: Longest side (pixels) at which the overlay's silhouettes are rendered; a larger image's
#: are rendered at this size and resized to it. The overlay is a picture: at 16 samples a
#: pixel, a 4,000 px image's silhouettes took most of `predict`'s time and memory.
OVERLAY_MAX_SIDE = 1024


def overlay_camera(camera: Camera) -> Camera:
    """The camera the overlay's silhouettes are rendered with: ``camera``, or for an image
    whose longer side exceeds :data:`OVERLAY_MAX_SIDE` the same camera on that many pixels."""
    side = max(camera.width, camera.height)
    if side <= OVERLAY_MAX_SIDE:
        return camera
    scale = OVERLAY_MAX_SIDE / side
    return camera.rescaled(max(1, round(camera.width * scale)),
                           max(1, round(camera.height * scale)))


def overlay_silhouettes(assembly: Any, rotation: Any, translation: Any, renderer: Any,
                        level: int, shape: tuple[int, ...]) -> list[np.ndarray]:
    """The coverages (H, W) = ``shape[:2]`` of B assemblies at their poses (rotation (B, 3, 3),
    translation (B, 3)), rendered in one launch by ``renderer`` (its camera from
    :func:`overlay_camera`) and each resized to the picture."""
    import torch

    from sq_mitsuba.render.silhouette.renderer import render_assembly

    with torch.no_grad():
        coverage = render_assembly(assembly, rotation, translation, renderer, level).cpu().numpy()
    return [resized_coverage(item, shape[1], shape[0]) for item in coverage]


def resized_coverage(coverage: np.ndarray, width: int, height: int) -> np.ndarray:
    """A coverage (h, w) in [0, 1] resized bilinearly to (height, width), float32."""
    from PIL import Image

    if coverage.shape == (height, width):
        return coverage.astype(np.float32, copy=False)
    picture = Image.fromarray(np.ascontiguousarray(coverage, dtype=np.float32), "F")
    return np.asarray(picture.resize((width, height), Image.BILINEAR))
