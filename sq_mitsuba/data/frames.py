"""What each dataset image shows: target pose, sun, Earth and stars, sampled per image.

Pure numpy and torch; the renderer (:mod:`sq_mitsuba.render.space`) turns a :class:`Frame`
into pixels. Every frame is drawn from its own seed, derived from the dataset seed, the model
name and the image index, so any image can be re-rendered alone and a resumed run draws
exactly what an uninterrupted one draws.

Convention: camera frame OpenCV (x right, y down, z forward); a pose maps body to camera,
``x_cam = R x_body + t``, with R = quaternion_to_matrix(q), q = (w, x, y, z). Directions
(sun, Earth) are unit vectors in the camera frame pointing *from the target towards* the
body. The phase angle is the angle at the target between the sun and the camera: 0 deg lights
the visible side fully, 180 deg back-lights it.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sq_mitsuba.camera import Camera
from sq_mitsuba.io import read_json
from sq_mitsuba.rotation import quaternion_to_matrix, random_quaternions

SCENES_DIR = Path(__file__).resolve().parents[2] / "scenes"


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
        path = Path(path) if path is not None else SCENES_DIR / "space.json"
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


def frame_seed(dataset_seed: int, model: str, index: int) -> int:
    """A 63-bit seed for one image, independent of the order images are rendered in."""
    sequence = np.random.SeedSequence([dataset_seed, zlib.crc32(model.encode()), index])
    return int(sequence.generate_state(1, dtype=np.uint64)[0] >> 1)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def orthonormal_basis(direction: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) with columns (e1, e2, d): d = unit ``direction``, right-handed."""
    axis = _unit(np.asarray(direction, dtype=np.float64))
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = _unit(np.cross(axis, helper))
    return np.stack([e1, np.cross(axis, e1), axis], axis=1)


def _direction_at_angle(rng: np.random.Generator, axis: np.ndarray, cos_low: float,
                        cos_high: float) -> np.ndarray:
    """Unit vector uniform on the zone cos(angle to ``axis``) in [cos_low, cos_high]."""
    cos_theta = rng.uniform(cos_low, cos_high)
    sin_theta = math.sqrt(max(0.0, 1 - cos_theta**2))
    e1, e2, _ = orthonormal_basis(axis).T
    phi = rng.uniform(0, 2 * math.pi)
    return cos_theta * axis + sin_theta * (math.cos(phi) * e1 + math.sin(phi) * e2)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    gen = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
    return quaternion_to_matrix(random_quaternions(1, gen, torch.float64))[0].numpy()


def place_target(vertices_cam: np.ndarray, camera: Camera, config: PoseConfig,
                 rng: np.random.Generator) -> np.ndarray:
    """Translation t that keeps the rotated target (vertices R x, (V, 3)) wholly in view.

    Depth is drawn from ``distance_scale`` times 0.5 / tan(hfov / 2) and pushed back only if
    the target would not fit; lateral offsets use up to ``max_lateral_fraction`` of the free
    margin and are halved until every vertex projects inside the image.
    """
    base = 0.5 / math.tan(math.radians(camera.fov_x_deg) / 2)
    depth = base * rng.uniform(*config.distance_scale)
    lateral_draw = rng.uniform(-1.0, 1.0, size=2)
    margin = config.margin_px

    def bounds(t: np.ndarray) -> tuple[float, float, float, float]:
        p = vertices_cam + t
        u = camera.fx * p[:, 0] / p[:, 2] + camera.cx
        v = camera.fy * p[:, 1] / p[:, 2] + camera.cy
        return u.min(), u.max(), v.min(), v.max()

    def fits(t: np.ndarray) -> bool:
        if (vertices_cam[:, 2] + t[2]).min() <= 1e-3:
            return False
        u0, u1, v0, v1 = bounds(t)
        return u0 >= margin and v0 >= margin and u1 <= camera.width - margin and \
            v1 <= camera.height - margin

    t = np.array([0.0, 0.0, depth])
    for _ in range(200):
        if fits(t):
            break
        t[2] *= 1.05
    else:
        raise ValueError("target cannot be placed in view (is the model unit size?)")
    u0, u1, v0, v1 = bounds(t)
    near = (vertices_cam[:, 2] + t[2]).min()
    # Free margin in pixels on each side, converted to metres at the nearest depth.
    room_x = min(u0 - margin, camera.width - margin - u1) * near / camera.fx
    room_y = min(v0 - margin, camera.height - margin - v1) * near / camera.fy
    offset = lateral_draw * config.max_lateral_fraction * np.array([room_x, room_y])
    for _ in range(30):
        candidate = np.array([offset[0], offset[1], t[2]])
        if fits(candidate):
            return candidate
        offset = offset / 2
    return t


def sample_frame(vertices: np.ndarray, camera: Camera, config: SceneConfig, dataset_seed: int,
                 model: str, index: int) -> Frame:
    """Draw image ``index`` of ``model``: pose, sun, Earth and stars.

    Args:
        vertices: (V, 3) model vertices in the body frame (unit size, centred).
        camera: the dataset camera.
        config: scene configuration.
        dataset_seed, model, index: identify the image (see :func:`frame_seed`).
    """
    seed = frame_seed(dataset_seed, model, index)
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
    quaternion = random_quaternions(1, gen, torch.float64)[0]
    rotation = quaternion_to_matrix(quaternion).numpy()
    translation = place_target(vertices @ rotation.T, camera, config.pose, rng)

    earth = config.earth
    altitude = rng.uniform(*earth.altitude_km)
    angular_radius = math.asin(earth.radius_km / (earth.radius_km + altitude))
    half_diagonal = math.atan(math.hypot(camera.width, camera.height) / 2 / camera.fx)
    axis = np.array([0.0, 0.0, 1.0])
    if rng.random() < earth.probability_in_view:
        # Centre angle such that the limb crosses the field of view.
        low = max(0.0, angular_radius - 0.6 * half_diagonal)
        high = angular_radius + 0.6 * half_diagonal
        earth_direction = _direction_at_angle(rng, axis, math.cos(high), math.cos(low))
    else:
        clear = min(math.pi, angular_radius + half_diagonal + math.radians(5))
        earth_direction = _direction_at_angle(rng, axis, -1.0, math.cos(clear))
    angle_to_axis = math.acos(float(np.clip(earth_direction @ axis, -1, 1)))
    earth_in_view = angle_to_axis < angular_radius + half_diagonal

    if rng.random() < config.eclipse.probability:
        # Sun behind the Earth's disk as seen from the target.
        sun = _direction_at_angle(rng, earth_direction, math.cos(0.9 * angular_radius), 1.0)
    else:
        # Uniform over the sky not hidden by the Earth (its disk spans ~30 % of it in LEO).
        sun = _direction_at_angle(rng, earth_direction, -1.0, math.cos(angular_radius))
    eclipse = math.acos(float(np.clip(sun @ earth_direction, -1, 1))) < angular_radius
    to_camera = -translation / np.linalg.norm(translation)
    phase = math.degrees(math.acos(float(np.clip(sun @ to_camera, -1, 1))))

    return Frame(
        index=index, seed=seed,
        quaternion=tuple(float(v) for v in quaternion),
        translation=tuple(float(v) for v in translation),
        sun_direction=tuple(float(v) for v in sun),
        phase_angle_deg=phase,
        earth_direction=tuple(float(v) for v in earth_direction),
        earth_angular_radius_deg=math.degrees(angular_radius),
        earth_altitude_km=float(altitude),
        earth_in_view=bool(earth_in_view),
        earth_rotation=tuple(_random_rotation(rng).reshape(-1).tolist()),
        star_rotation=tuple(_random_rotation(rng).reshape(-1).tolist()),
        eclipse=bool(eclipse),
    )
