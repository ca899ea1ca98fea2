"""An image of another aspect ratio than the model's camera, padded with black to the camera's
aspect ratio (centred), and cut back afterwards: its pixels, its overlay and its camera."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["MAX_PADDING_GROWTH", "Padding", "padded_camera", "padding_to_aspect"]

#: Largest growth of the pixel count by padding to the camera's aspect ratio (a strip of 4:1
#: or worse is no picture of a spacecraft to pad into a square).
MAX_PADDING_GROWTH = 4


@dataclass(frozen=True)
class Padding:
    """Where an image sits in the black picture it was padded to (pixels)."""

    top: int
    left: int
    height: int
    "Height of the image (not of the padded picture)."
    width: int
    "Width of the image."
    padded_height: int
    padded_width: int

    def pad(self, array: np.ndarray) -> np.ndarray:
        """(height, width, ...) -> (padded_height, padded_width, ...), zeros around."""
        padded = np.zeros((self.padded_height, self.padded_width, *array.shape[2:]),
                          dtype=array.dtype)
        padded[self.top:self.top + self.height, self.left:self.left + self.width] = array
        return padded

    def crop(self, array: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`pad`: the image's part of a padded array."""
        return array[self.top:self.top + self.height, self.left:self.left + self.width]

    def crop_camera(self, camera: Any) -> Any:
        """The padded picture's camera -> the camera of the image's own pixels."""
        from dataclasses import replace

        return replace(camera, cx=camera.cx - self.left, cy=camera.cy - self.top,
                       width=self.width, height=self.height)

    def pixel_pitch_m(self) -> float:
        """The padded picture's pixel pitch in metres (the SPEED sensor's width over its
        width), which its crop keeps: ``crop_camera(c).to_speed_dict(pixel_pitch_m())``."""
        from sq_mitsuba.geometry.camera import SPEED_PIXEL_PITCH_M, SPEED_WIDTH_PX

        return SPEED_PIXEL_PITCH_M * SPEED_WIDTH_PX / self.padded_width

    def describe(self) -> str:
        return (f"{self.width} x {self.height} px, another aspect ratio than the model's camera: "
                f"padded with black to {self.padded_width} x {self.padded_height} px, the "
                "camera's field of view taken across the padded picture (pass --camera for "
                "the image's own)")


def padding_to_aspect(width: int, height: int, camera: Any) -> Padding | None:
    """The centred black padding that gives a ``width`` x ``height`` image ``camera``'s aspect
    ratio, or None when it has it already (within rounding to whole pixels)."""
    from sq_mitsuba.inference.images import camera_for

    try:
        camera_for(camera, width, height)
        return None
    except ValueError:
        pass
    if width * camera.height > height * camera.width:  # wider than the camera: pad rows
        padded_width, padded_height = width, max(height, round(width * camera.height
                                                               / camera.width))
    else:
        padded_width, padded_height = max(width, round(height * camera.width
                                                       / camera.height)), height
    return Padding((padded_height - height) // 2, (padded_width - width) // 2, height, width,
                   padded_height, padded_width)


def padded_camera(camera: Any, width: int, height: int) -> Any:
    """``camera`` for a ``width`` x ``height`` picture: rescaled when the aspect ratios agree,
    else (a picture padded to the camera's aspect ratio, off by the rounding to whole pixels)
    scaled by the width ratio with square pixels kept, principal point at the same fraction
    of the picture."""
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.inference.images import camera_for

    try:
        return camera_for(camera, width, height)
    except ValueError:
        scale = width / camera.width
        return Camera(camera.fx * scale, camera.fy * scale, camera.cx * scale,
                      camera.cy * height / camera.height, width, height)
