"""Configuration of the space scene (``scenes/space.json``) and the per-image :class:`Frame`.

The scene renderer (:mod:`sq_mitsuba.render.space`) reads these types; the frame sampler
(:mod:`sq_mitsuba.data.frames`) draws a :class:`Frame` per image from a :class:`SceneConfig`.

Convention: camera frame OpenCV (x right, y down, z forward); a pose maps body to camera,
``x_cam = R x_body + t``, with R = quaternion_to_matrix(q), q = (w, x, y, z). Directions
(sun, Earth) are unit vectors in the camera frame pointing *from the target towards* the
body. The phase angle is the angle at the target between the sun and the camera: 0 deg lights
the visible side fully, 180 deg back-lights it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sq_mitsuba.geometry.rotation import quaternion_to_matrix
from sq_mitsuba.io import read_json


def scenes_dir() -> Path:
    """The folder of the shipped scene files (``scenes/`` in a checkout, package data in a
    wheel)."""
    return Path(str(resources.files("sq_mitsuba.scenes")))


# ------------------------------------------------------------------------ configuration


@dataclass(frozen=True)
class IntegratorConfig:
    max_depth: int = 4
    reconstruction_filter: str = "box"


@dataclass(frozen=True)
class SunConfig:
    irradiance: float = 1361.0  # W/m^2, the solar constant


@dataclass(frozen=True)
class EarthTextureConfig:
    width: int = 1024
    height: int = 512
    ocean_albedo: float = 0.06
    land_albedo: tuple[float, float] = (0.12, 0.32)
    cloud_albedo: float = 0.75
    land_fraction: float = 0.3
    cloud_cover: float = 0.45


@dataclass(frozen=True)
class EarthConfig:
    probability_in_view: float = 0.3
    altitude_km: tuple[float, float] = (400.0, 1200.0)
    radius_km: float = 6371.0
    render_distance: float = 200.0
    texture: EarthTextureConfig = field(default_factory=EarthTextureConfig)


@dataclass(frozen=True)
class StarsConfig:
    count: int = 4000
    radiance: tuple[float, float] = (0.5, 60.0)
    envmap_width: int = 2048


@dataclass(frozen=True)
class EclipseConfig:
    probability: float = 0.05


@dataclass(frozen=True)
class PoseConfig:
    distance_scale: tuple[float, float] = (1.0, 4.0 / 3.0)
    max_lateral_fraction: float = 0.8
    margin_px: float = 2.0


@dataclass(frozen=True)
class ExposureConfig:
    reference_albedo: float = 0.9


@dataclass(frozen=True)
class MaskConfig:
    spp: int = 64


@dataclass(frozen=True)
class SceneConfig:
    """Everything about the space scene that is not per image (``scenes/space.json``)."""

    integrator: IntegratorConfig = field(default_factory=IntegratorConfig)
    sun: SunConfig = field(default_factory=SunConfig)
    earth: EarthConfig = field(default_factory=EarthConfig)
    stars: StarsConfig = field(default_factory=StarsConfig)
    eclipse: EclipseConfig = field(default_factory=EclipseConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    mask: MaskConfig = field(default_factory=MaskConfig)

    @classmethod
    def load(cls, path: str | Path | None = None) -> SceneConfig:
        """``scenes/space.json`` (or ``path``); keys starting with ``_`` are comments."""
        path = Path(path) if path is not None else scenes_dir() / "space.json"
        data = read_json(path)
        return _from_dict(cls, data, str(path))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _from_dict(kind: type, data: Any, where: str) -> Any:
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected an object")
    names = sorted(f.name for f in dataclasses.fields(kind))
    defaults = kind()
    values = {}
    for key, value in data.items():
        if key.startswith("_"):
            continue
        if key not in names:
            raise ValueError(f"{where}: unknown key {key!r} (expected one of {names})")
        default = getattr(defaults, key)
        if dataclasses.is_dataclass(default):
            values[key] = _from_dict(type(default), value, f"{where}.{key}")
        elif isinstance(default, tuple):
            if not isinstance(value, list) or len(value) != len(default):
                raise ValueError(f"{where}.{key}: expected a list of {len(default)} numbers")
            values[key] = tuple(float(v) for v in value)
        elif isinstance(default, bool | int | float | str):
            if isinstance(default, float) and isinstance(value, int | float):
                value = float(value)
            if type(value) is not type(default):
                raise ValueError(f"{where}.{key}: expected {type(default).__name__}, "
                                 f"got {value!r}")
            values[key] = value
    return kind(**values)


# ------------------------------------------------------------------------ frames


@dataclass(frozen=True)
class Frame:
    """One image's content: pose of the target and the lighting state, camera frame."""

    index: int
    seed: int
    quaternion: tuple[float, float, float, float]
    translation: tuple[float, float, float]
    sun_direction: tuple[float, float, float]
    phase_angle_deg: float
    earth_direction: tuple[float, float, float]
    earth_angular_radius_deg: float
    earth_altitude_km: float
    earth_in_view: bool
    earth_rotation: tuple[float, ...]  # 3 x 3 row-major, texture orientation
    star_rotation: tuple[float, ...]  # 3 x 3 row-major
    eclipse: bool

    @property
    def rotation(self) -> np.ndarray:
        """R (3, 3) body to camera."""
        q = torch.tensor(self.quaternion, dtype=torch.float64)
        return quaternion_to_matrix(q).numpy()

    def label_extras(self) -> dict[str, Any]:
        """The lighting record stored beside the SPE3R pose keys."""
        return {
            "sun_direction_cam": [round(v, 9) for v in self.sun_direction],
            "phase_angle_deg": round(self.phase_angle_deg, 6),
            "earth_in_view": self.earth_in_view,
            "earth_direction_cam": [round(v, 9) for v in self.earth_direction],
            "earth_altitude_km": round(self.earth_altitude_km, 3),
            "eclipse": self.eclipse,
            "seed": self.seed,
        }
