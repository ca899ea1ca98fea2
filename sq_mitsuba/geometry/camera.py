"""Pinhole camera intrinsics in the OpenCV frame (x right, y down, z forward): pure torch.

Convention: pixel coordinates (u, v) are continuous; the pixel of row i and column j covers
[j, j + 1) x [i, i + 1), so its centre is (u, v) = (j + 0.5, i + 0.5) and the centre of a
W x H image is (W / 2, H / 2), as in Mitsuba's film and SPEED's ``camera.json`` (``ccx =
Nu / 2``). ``u`` runs right along x, ``v`` down along y: ``u = fx x / z + cx``, ``v = fy y /
z + cy``.

The conversion to a Mitsuba sensor lives in the rendering layer
(:mod:`sq_mitsuba.render.silhouette.renderer`); nothing here imports Mitsuba.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from sq_mitsuba.checks import check_int, check_tensor
from sq_mitsuba.inputs import check_camera_intrinsics
from sq_mitsuba.io import read_json

# SPEED camera (Sharma et al.): focal length 17.6 mm, pixel pitch 5.86 um, 1920 x 1200 px.
SPEED_FOCAL_LENGTH_M = 0.0176
SPEED_PIXEL_PITCH_M = 5.86e-6
SPEED_WIDTH_PX = 1920
DEFAULT_RESOLUTION = 256


def _check_beside_matrix(data: dict[str, Any], matrix: list[list[float]], where: str) -> None:
    """A one-line ``ValueError`` where the metric intrinsics a SPEED file holds beside its
    ``cameraMatrix`` disagree with it: the matrix is the one read, so an edit of ``fx`` (say)
    alone would otherwise be ignored without a word. Focal lengths agree to 0.1 %, principal
    points to a pixel (conventions of the pixel centre differ by half of one)."""
    for focal, pitch, (i, j) in (("fx", "ppx", (0, 0)), ("fy", "ppy", (1, 1))):
        if focal in data and pitch in data and data[pitch] != 0:
            pixels = float(data[focal]) / float(data[pitch])
            if not math.isclose(pixels, matrix[i][j], rel_tol=1e-3):
                raise ValueError(f"{where}: {focal} / {pitch} = {pixels:.6g} px, but "
                                 f"cameraMatrix[{i}][{j}] = {matrix[i][j]:.6g} px; the matrix "
                                 f"is what is read: make the two agree, or remove {focal}")
    for centre, (i, j) in (("ccx", (0, 2)), ("ccy", (1, 2))):
        if centre in data and abs(float(data[centre]) - matrix[i][j]) > 1.0:
            raise ValueError(f"{where}: {centre} = {float(data[centre]):g} px, but "
                             f"cameraMatrix[{i}][{j}] = {matrix[i][j]:g} px; the matrix is "
                             f"what is read: make the two agree, or remove {centre}")


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics of a ``width`` x ``height`` image, focal lengths and principal point
    in pixels. Immutable; :meth:`rescaled` returns a new camera."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(
                    value):
                raise ValueError(f"{name}: expected a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"fx, fy: focal lengths must be > 0, got {self.fx}, {self.fy}")
        for name in ("width", "height"):  # a numpy integer stored as Python's
            object.__setattr__(self, name, check_int(name, getattr(self, name)))

    # ------------------------------------------------------------------ construction

    @classmethod
    def default(cls, resolution: int = DEFAULT_RESOLUTION) -> Camera:
        """The project's default camera: square image with the SPEED camera's horizontal field
        of view (35.45 deg), principal point at the image centre; fx = fy = 400.45 at 256 px.

        Raises:
            ValueError: naming ``resolution`` unless a positive integer (pixels a side).
        """
        resolution = check_int("resolution (pixels a side)", resolution)  # np.int64(256): 256
        focal = SPEED_FOCAL_LENGTH_M / SPEED_PIXEL_PITCH_M * resolution / SPEED_WIDTH_PX
        return cls(focal, focal, resolution / 2, resolution / 2, resolution, resolution)

    @classmethod
    def from_fov(cls, fov_x_deg: float, width: int, height: int) -> Camera:
        """Square pixels, horizontal field of view ``fov_x_deg``, centred principal point."""
        if isinstance(fov_x_deg, bool) or not isinstance(fov_x_deg, numbers.Real) \
                or not 0 < fov_x_deg < 180:  # '30' failed comparing a str with 0
            raise ValueError(f"fov_x_deg: expected a value in (0, 180), got {fov_x_deg!r}")
        focal = width / (2 * math.tan(math.radians(fov_x_deg) / 2))
        return cls(focal, focal, width / 2, height / 2, width, height)

    @classmethod
    def from_speed_dict(cls, data: dict[str, Any], where: str = "camera") -> Camera:
        """From a SPEED-style camera dictionary: ``Nu``, ``Nv`` and ``cameraMatrix`` (pixels),
        or, without a matrix, ``fx``, ``fy`` in metres with the pixel pitch ``ppx``, ``ppy``
        and principal point ``ccx``, ``ccy``.

        The description must be one this pinhole camera is: JSON numbers (not strings), whole
        ``Nu`` and ``Nv``, a matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (no skew, a last
        row of ``[0, 0, 1]``), ``distCoeffs``, if given, all zero (SPEED's are; a lens
        distortion is not modelled: undistort such images first), and consistent
        (:func:`sq_mitsuba.inputs.check_camera_intrinsics`: images of at least 8 x 8 px, a
        matrix that fits ``Nu`` x ``Nv``); ``where`` (the file) starts the one-line
        ``ValueError`` otherwise."""
        if not isinstance(data, dict):
            raise ValueError(f"{where}: not a SPEED-style camera description (expected a JSON "
                             f"object, got {type(data).__name__})")
        missing = [key for key in ("Nu", "Nv") if key not in data]
        if "cameraMatrix" not in data:
            missing += [key for key in ("fx", "fy", "ppx", "ppy") if key not in data]
        if missing:
            raise ValueError(f"{where}: not a SPEED-style camera description (no "
                             f"{', '.join(map(repr, missing))})")
        width = _whole(data["Nu"], f"{where}: Nu")
        height = _whole(data["Nv"], f"{where}: Nv")
        for key, value in (("Nu", width), ("Nv", height)):  # named as the file names them
            if value < 1:
                raise ValueError(f"{where}: {key}: expected a positive integer, got {value}")
        if "cameraMatrix" in data:
            matrix = data["cameraMatrix"]
            if not isinstance(matrix, list | tuple) or len(matrix) != 3 or not all(
                    isinstance(row, list | tuple) and len(row) == 3 for row in matrix):
                raise ValueError(f"{where}: cameraMatrix must be 3 rows of 3 numbers, got "
                                 f"{_shown(matrix)}")
            values = [[_number(v, f"{where}: cameraMatrix[{i}][{j}]") for j, v in
                       enumerate(row)] for i, row in enumerate(matrix)]
            for (i, j), what in (((0, 1), "the skew"), ((1, 0), "an entry below fx")):
                if values[i][j] != 0.0:
                    raise ValueError(f"{where}: cameraMatrix[{i}][{j}] ({what}) is "
                                     f"{values[i][j]:g}; a pinhole camera without skew has 0")
            if values[2] != [0.0, 0.0, 1.0]:
                raise ValueError(f"{where}: cameraMatrix's last row is {_shown(matrix[2])}; "
                                 "an intrinsic matrix's is [0, 0, 1] (divide the matrix by "
                                 "its [2][2] entry)")
            fx, fy, cx, cy = values[0][0], values[1][1], values[0][2], values[1][2]
            for key in ("fx", "fy", "ppx", "ppy", "ccx", "ccy"):  # unused beside the matrix,
                if key in data:  # but a NaN or a string there is a broken file all the same
                    _number(data[key], f"{where}: {key}")
            _check_beside_matrix(data, values, where)
        else:
            for key in ("ppx", "ppy"):
                if _number(data[key], f"{where}: {key}") <= 0:
                    raise ValueError(f"{where}: {key} (the pixel pitch, metres) must be > 0, "
                                     f"got {data[key]!r}")
            fx = _number(data["fx"], f"{where}: fx") / _number(data["ppx"], f"{where}: ppx")
            fy = _number(data["fy"], f"{where}: fy") / _number(data["ppy"], f"{where}: ppy")
            cx = _number(data.get("ccx", width / 2), f"{where}: ccx")
            cy = _number(data.get("ccy", height / 2), f"{where}: ccy")
        if "distCoeffs" in data:
            coefficients = data["distCoeffs"]
            if not isinstance(coefficients, list | tuple):
                raise ValueError(f"{where}: distCoeffs must be a list of numbers, got "
                                 f"{_shown(coefficients)}")
            numbers = [_number(v, f"{where}: distCoeffs[{k}]")
                       for k, v in enumerate(coefficients)]
            if any(v != 0.0 for v in numbers):
                raise ValueError(f"{where}: distCoeffs {_shown(coefficients)} describe a lens "
                                 "distortion, which sq_mitsuba does not model; undistort the "
                                 "images first (e.g. cv2.undistort) and give zeros")
        try:
            camera = cls(fx, fy, cx, cy, width, height)
        except ValueError as error:
            raise ValueError(f"{where}: {error}") from None
        check_camera_intrinsics(width, height, camera.fx, camera.fy, cx, cy, where)
        return camera

    @classmethod
    def load(cls, path: str | Path) -> Camera:
        """From a SPEED-style ``camera.json``."""
        path = Path(path)
        data = read_json(path)
        if not isinstance(data, dict):
            raise ValueError(f"camera: {path} must hold a JSON object")
        return cls.from_speed_dict(data, str(path))

    def to_speed_dict(self, pixel_pitch_m: float | None = None) -> dict[str, Any]:
        """SPEED-style dictionary: ``cameraMatrix`` in pixels; focal lengths in metres with the
        pixel pitch ``pixel_pitch_m`` (default: the SPEED sensor's physical width spread over
        ``width`` pixels; a crop of a larger picture passes the picture's, so the lens in
        metres stays the picture's), so that ``fx / ppx`` is pixels either way."""
        pitch_x = pixel_pitch_m if pixel_pitch_m is not None else \
            SPEED_PIXEL_PITCH_M * SPEED_WIDTH_PX / self.width
        return {
            "Nu": self.width, "Nv": self.height,
            "ppx": pitch_x, "ppy": pitch_x,
            "fx": self.fx * pitch_x, "fy": self.fy * pitch_x,
            "ccx": self.cx, "ccy": self.cy,
            "cameraMatrix": [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
            "distCoeffs": [0.0, 0.0, 0.0, 0.0, 0.0],
        }

    def rescaled(self, width: int, height: int | None = None) -> Camera:
        """The same camera imaging onto ``width`` x ``height`` pixels (default: keep the aspect
        ratio). Pixel edges scale, so the principal point scales with them."""
        if height is None:
            height = max(1, round(self.height * width / self.width))
        width, height = check_int("width", width), check_int("height", height)
        sx, sy = width / self.width, height / self.height
        return Camera(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    # ------------------------------------------------------------------ geometry

    @property
    def fov_x_deg(self) -> float:
        """Horizontal field of view in degrees (of a centred principal point)."""
        return math.degrees(2 * math.atan(self.width / (2 * self.fx)))

    def matrix(self, dtype: torch.dtype = torch.float32,
               device: str | torch.device = "cpu") -> Tensor:
        """Intrinsic matrix K (3, 3)."""
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
                            dtype=dtype, device=device)

    def project(self, points: Tensor) -> Tensor:
        """Pixel coordinates (..., 2) of camera-frame points (..., 3).

        Points at or behind the camera (z <= 0) give non-finite or mirrored pixels, as the
        pinhole model does; callers decide what to do with them.
        """
        check_tensor("points", points, (3,), finite=False)
        x, y, z = points.unbind(-1)
        return torch.stack((self.fx * x / z + self.cx, self.fy * y / z + self.cy), dim=-1)

    def unproject(self, pixels: Tensor, depth: Tensor | float) -> Tensor:
        """Camera-frame points (..., 3) at depth ``z = depth`` (broadcast to (...)) seen at
        ``pixels`` (..., 2)."""
        check_tensor("pixels", pixels, (2,))
        try:  # a string or a bool is no depth, though torch would make one of each
            if isinstance(depth, str | bytes | bool):
                raise TypeError
            depth = torch.as_tensor(depth, dtype=pixels.dtype, device=pixels.device)
        except (TypeError, ValueError, RuntimeError):
            raise ValueError("depth: expected a number or a tensor, got "
                             f"{_shown(depth)}") from None
        if not bool(torch.isfinite(depth).all()):
            raise ValueError("depth: contains NaN or infinite values")
        u, v = pixels.unbind(-1)
        try:
            z = torch.broadcast_to(depth, u.shape)
        except RuntimeError:
            raise ValueError(f"depth: shape {tuple(depth.shape)} does not broadcast to the "
                             f"pixels' {tuple(u.shape)} (pixels (..., 2), depth (...))") from None
        return torch.stack(((u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z), dim=-1)

    def pixel_centers(self, dtype: torch.dtype = torch.float32,
                      device: str | torch.device = "cpu") -> Tensor:
        """Pixel centres (H, W, 2) as (u, v) = (j + 0.5, i + 0.5)."""
        v, u = torch.meshgrid(torch.arange(self.height, dtype=dtype, device=device) + 0.5,
                              torch.arange(self.width, dtype=dtype, device=device) + 0.5,
                              indexing="ij")
        return torch.stack((u, v), dim=-1)


def _shown(value: Any) -> str:
    """``repr(value)``, cut to 60 characters."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _number(value: Any, where: str) -> float:
    """A JSON number as a finite float, or a one-line ``ValueError`` starting with ``where``
    (a string such as ``"400"`` is refused, not converted)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        kind = " (a string: write the number without quotes)" if isinstance(value, str) else ""
        raise ValueError(f"{where} must be a number, got {_shown(value)}{kind}")
    if not math.isfinite(value):
        raise ValueError(f"{where} must be finite, got {value!r}")
    return float(value)


def _whole(value: Any, where: str) -> int:
    """A JSON number that is a whole count of pixels (``256`` or ``256.0``, not ``256.5``)."""
    number = _number(value, where)
    if number != int(number):
        raise ValueError(f"{where} must be a whole number of pixels, got {value!r}")
    return int(number)
