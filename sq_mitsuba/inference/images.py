"""Images as the network takes them: checked, as float (B, C, H, W) in [0, 1], resized to the
network's square input; and the camera of images of a given size.

Convention:
    - Images are resized to the network's S x S input: ``area`` (box average) when both sides
      shrink, bilinear (``align_corners=False``) when both grow, antialiased bilinear
      otherwise. Pixel edges scale with the image, so the intrinsics follow by
      :meth:`~sq_mitsuba.geometry.camera.Camera.rescaled`.
    - A camera for another image size with the same aspect ratio is taken to have the same
      field of view and is rescaled to the images' size.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from sq_mitsuba.geometry.camera import Camera

__all__ = ["camera_for", "prepare_images", "resize_images"]

# Relative aspect-ratio difference below which a camera of another size is rescaled.
_ASPECT_TOLERANCE = 1e-3


def prepare_images(images: Tensor | np.ndarray, channels: int = 1) -> Tensor:
    """Check images and return them as float (B, C, H, W) in [0, 1].

    Args:
        images: (B, H, W) (when ``channels`` is 1) or (B, C, H, W); uint8 (0..255) or floating
            point in [0, 1]; a torch tensor or a numpy array.
        channels: the C the network expects.

    Raises:
        ValueError: naming ``images``: wrong type, shape or dtype, NaN or values outside [0, 1].
    """
    if isinstance(images, np.ndarray):
        images = torch.from_numpy(images)
    if not isinstance(images, Tensor):
        raise ValueError(f"images: expected a torch.Tensor or numpy array, "
                         f"got {type(images).__name__}")
    if images.dim() == 3 and channels == 1:
        images = images[:, None]
    expected = "(B, H, W) or (B, 1, H, W)" if channels == 1 else f"(B, {channels}, H, W)"
    if images.dim() != 4 or images.shape[1] != channels or images.numel() == 0:
        raise ValueError(f"images: expected shape {expected}, got {tuple(images.shape)}")
    if images.dtype == torch.uint8:
        return images.float() / 255.0
    if not images.is_floating_point():
        raise ValueError(f"images: expected uint8 or floating point, got {images.dtype}")
    if not bool(torch.isfinite(images).all()):
        raise ValueError("images: contains NaN or infinite values")
    low, high = float(images.amin()), float(images.amax())
    if low < 0.0 or high > 1.0:
        raise ValueError(f"images: float values must lie in [0, 1], got [{low:.4g}, {high:.4g}]"
                         " (divide uint8-range floats by 255)")
    return images


def resize_images(images: Tensor, size: int) -> Tensor:
    """(B, C, H, W) -> (B, C, size, size), resampled as the module docstring says."""
    height, width = images.shape[-2:]
    if (height, width) == (size, size):
        return images
    if height >= size and width >= size:
        return F.interpolate(images, size=(size, size), mode="area")
    grow = height <= size and width <= size
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False,
                         antialias=not grow)


def camera_for(camera: Camera, width: int, height: int) -> Camera:
    """``camera`` for ``width`` x ``height`` images: itself, or rescaled (same aspect ratio).

    Raises:
        ValueError: naming ``camera`` when its aspect ratio differs from the images'.
    """
    if not isinstance(camera, Camera):
        raise ValueError(f"camera: expected a Camera, got {type(camera).__name__}")
    if (camera.width, camera.height) == (width, height):
        return camera
    if abs(camera.width * height / (camera.height * width) - 1.0) > _ASPECT_TOLERANCE:
        raise ValueError(f"camera: is for {camera.width} x {camera.height} images, the images are "
                         f"{width} x {height} (another aspect ratio); pass their camera")
    return camera.rescaled(width, height)
