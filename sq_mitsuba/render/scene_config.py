"""Configuration of the space scene (``scenes/space.json``) and the per-image :class:`Frame`.

The scene renderer (:mod:`sq_mitsuba.render.space`) reads these types; the frame sampler
(:mod:`sq_mitsuba.data.frames`) draws a :class:`Frame` per image from a :class:`SceneConfig`.

:class:`SceneConfig` follows the project's configuration style (:mod:`sq_mitsuba.config`):
frozen dataclasses, every field documented and bounded, loaded strictly. A scene file holds
only the fields it changes (the rest keep the defaults below, which ``scenes/space.json``
repeats); keys starting with ``_`` are comments. A :class:`SceneConfig` checks itself when
built, in code too, so an invalid one cannot reach the renderer: NaN, an irradiance of 0 or a
``max_depth`` that leaves the target black are :class:`~sq_mitsuba.config.ConfigError` s naming
the field before any image is rendered.

Convention: camera frame OpenCV (x right, y down, z forward); a pose maps body to camera,
``x_cam = R x_body + t``, with R = quaternion_to_matrix(q), q = (w, x, y, z). Directions
(sun, Earth) are unit vectors in the camera frame pointing from the target towards the sun
and towards the Earth's centre (the Earth is far enough that the camera sees it in the same
direction). The phase angle is the angle at the target between the directions to the sun and to the
camera: 0 deg lights the visible side fully, 90 deg half of it, 180 deg back-lights it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from sq_mitsuba.config import (
    ConfigError,
    from_dict,
    in_range,
    load,
    positive,
    to_dict,
    validate,
)
from sq_mitsuba.geometry.rotation import quaternion_to_matrix
from sq_mitsuba.io import read_json


def scenes_dir() -> Path:
    """The folder of the shipped scene files (``scenes/`` in a checkout, package data in a
    wheel)."""
    try:
        return Path(str(resources.files("sq_mitsuba.scenes")))
    except ModuleNotFoundError:
        # A checkout on PYTHONPATH, not installed: sq_mitsuba.scenes is only a mapping of
        # the installed package, so read the checkout's top-level scenes/ folder.
        return Path(__file__).resolve().parents[2] / "scenes"


EARTH_CLEARANCE_M = 5.0
"""Least distance in metres between the camera and the drawn Earth sphere: beyond the target,
which lies about 2 m away for the default camera and poses."""


def _ordered(name: str, pair: tuple[float, float]) -> None:
    """Raise ``ValueError`` unless a (low, high) range has low <= high."""
    if pair[0] > pair[1]:
        raise ValueError(f"{name}: low {pair[0]} is above high {pair[1]}")


def _strip_comments(data: Any) -> Any:
    """``data`` without the keys starting with ``_`` (comments), at every level."""
    if isinstance(data, dict):
        return {key: _strip_comments(value) for key, value in data.items()
                if not (isinstance(key, str) and key.startswith("_"))}
    return data


# ------------------------------------------------------------------------ configuration


@dataclass(frozen=True)
class IntegratorConfig:
    """Mitsuba's path tracer for the image."""

    max_depth: int = in_range(2, 64, default=4)
    """Longest light path in segments. 2 is direct light only (1 would show emitters alone: a
    black target); 3 adds earthshine and one bounce between parts; 4 a second bounce."""
    reconstruction_filter: Literal["box", "tent", "gaussian", "mitchell", "catmullrom",
                                   "lanczos"] = "box"
    """Mitsuba pixel reconstruction filter. ``box`` keeps each sample in its own pixel, as the
    mask pass does."""


@dataclass(frozen=True)
class SunConfig:
    """The sun: a distant point source, placed per image by its phase angle."""

    irradiance: float = positive(1361.0)
    """Solar irradiance at the target in W/m^2 (the solar constant at 1 AU)."""
    phase_deg: tuple[float, float] = in_range(0, 180, default=(0.0, 120.0))
    """Range of the phase angle in degrees (at the target, between the directions to the sun
    and to the camera). [0, 120] keeps at least a quarter of a sphere's visible disk
    lit; [0, 180] allows every sun direction, back-lighting included."""
    phase_distribution: Literal["uniform_angle", "uniform_sphere"] = "uniform_angle"
    """How the phase angle is drawn within ``phase_deg``: ``uniform_angle``, uniform in the
    angle (every phase as likely); ``uniform_sphere``, the sun direction uniform on the sphere
    (zone) the range allows, so phases near 90 deg are the most likely, as for a sun at a
    random place in the sky (with ``phase_deg = [0, 180]``). The sun's azimuth about the
    direction to the camera is uniform either way."""

    def __post_init__(self) -> None:
        _ordered("phase_deg", self.phase_deg)


@dataclass(frozen=True)
class EarthTextureConfig:
    """Procedural albedo map of the Earth (equirectangular), seeded by the dataset seed."""

    width: int = in_range(16, 16384, default=1024)
    """Texture width in texels (longitude)."""
    height: int = in_range(8, 8192, default=512)
    """Texture height in texels (latitude)."""
    ocean_albedo: float = in_range(0, 1, default=0.06)
    """Albedo of the oceans."""
    land_albedo: tuple[float, float] = in_range(0, 1, default=(0.12, 0.32))
    """Albedo range of land, from low to high relief."""
    cloud_albedo: float = in_range(0, 1, default=0.75)
    """Albedo of clouds."""
    land_fraction: float = in_range(0, 1, default=0.3)
    """Share of the surface that is land."""
    cloud_cover: float = in_range(0, 1, default=0.45)
    """Share of the surface under cloud (soft-edged)."""

    def __post_init__(self) -> None:
        _ordered("land_albedo", self.land_albedo)


@dataclass(frozen=True)
class EarthConfig:
    """The Earth: a textured sphere of its true angular size, lit by the sun."""

    probability_in_view: float = in_range(0, 1, default=0.3)
    """Probability that the Earth's limb crosses the field of view behind the target."""
    altitude_km: tuple[float, float] = positive(default=(400.0, 1200.0))
    """Range of the target's altitude in km (uniform); sets the Earth's angular size."""
    radius_km: float = positive(6371.0)
    """Radius of the Earth in km."""
    render_distance: float = in_range(10, 1e5, default=200.0)
    """Distance in metres at which the Earth sphere is drawn, scaled to keep its true angular
    size. The sphere's nearest point is then ``render_distance * h / (radius + h)`` away at
    altitude h (12 m at 400 km by default); it must stay at least
    ``EARTH_CLEARANCE_M`` away, beyond the target."""
    texture: EarthTextureConfig = field(default_factory=EarthTextureConfig)
    """The Earth's albedo map."""

    def __post_init__(self) -> None:
        _ordered("altitude_km", self.altitude_km)
        low = self.altitude_km[0]
        clearance = self.render_distance * low / (self.radius_km + low)
        if clearance < EARTH_CLEARANCE_M:
            raise ValueError(
                f"render_distance: at altitude {low:g} km the Earth sphere drawn "
                f"{self.render_distance:g} m away comes within {clearance:.2f} m of the camera "
                f"(needs >= {EARTH_CLEARANCE_M:g} m, beyond the target); raise render_distance "
                f"to {EARTH_CLEARANCE_M * (self.radius_km + low) / low:.0f} or more")


@dataclass(frozen=True)
class StarsConfig:
    """The star field: point stars on an environment map, seeded by the dataset seed."""

    count: int = in_range(0, 10_000_000, default=4000)
    """Number of stars (0: a black sky)."""
    radiance: tuple[float, float] = positive(default=(0.5, 60.0))
    """Range of a star's radiance in W/(m^2 sr), log-uniform per star; with the default fixed
    exposure the brightest reach mid grey."""
    envmap_width: int = in_range(64, 16384, default=2048)
    """Width of the equirectangular star map in texels (height: half of it)."""

    def __post_init__(self) -> None:
        _ordered("radiance", self.radiance)


@dataclass(frozen=True)
class EclipseConfig:
    """Frames whose sun lies behind the Earth, lit only by earthshine, if any."""

    probability: float = in_range(0, 1, default=0.0)
    """Probability of an eclipse frame. Such a target is black inside a full mask (unless
    earthshine reaches it), so the default is 0; the phase angle of an eclipse frame is not
    drawn from ``sun.phase_deg``."""


@dataclass(frozen=True)
class PoseConfig:
    """Where the target is placed in the field of view."""

    distance_scale: tuple[float, float] = in_range(0.5, 50, default=(1.0, 4.0 / 3.0))
    """Range of the target's distance in units of 0.5 / tan(hfov / 2) (the distance at which a
    unit-size target spans the image width): 1.56 to 2.09 m for the default camera. The target
    is pushed back further when it would not fit in the image."""
    max_lateral_fraction: float = in_range(0, 1, default=0.8)
    """Share of the free margin around the target used by random lateral offsets."""
    margin_px: float = in_range(0, 1000, default=2.0)
    """Smallest distance in pixels between the target and the image border."""

    def __post_init__(self) -> None:
        _ordered("distance_scale", self.distance_scale)


@dataclass(frozen=True)
class ExposureConfig:
    """Linear radiance to 8-bit grey: ``srgb(clip(radiance * exposure, 0, 1))``.

    The exposure of each image is recorded in its label (radiance = linear grey / exposure).
    ``fixed``: every image shares one exposure, set by ``reference_albedo`` (brightness is
    physically comparable across images). ``auto`` (the default): per image, like a flight
    camera's auto-exposure, a high percentile of the target's radiance inside its mask maps to
    ``auto_white``, within ``auto_gain`` of the fixed exposure. Auto is the default because one
    fixed exposure leaves targets whose visible side is mostly solar cells or dark composite
    below 10/255 on average even at moderate phase angles.
    """

    mode: Literal["fixed", "auto"] = "auto"
    """``fixed``: one exposure for all images; ``auto``: one per image from the target's
    radiance (computed from the rendered image itself, no extra pass)."""
    reference_albedo: float = in_range(0, 1, default=0.9, low_inclusive=False)
    """Fixed exposure: a Lambertian surface of this albedo facing the sun maps to white. Also
    the reference that ``auto_gain`` is relative to."""
    percentile: float = in_range(50, 100, default=99.0)
    """Auto exposure: percentile of the target's radiance (pixels inside the mask) that maps to
    ``auto_white``."""
    auto_white: float = in_range(0.05, 1, default=1.0)
    """Auto exposure: linear level (before sRGB encoding, 1 = white) the percentile maps to."""
    auto_gain: tuple[float, float] = in_range(0.01, 1000, default=(0.25, 16.0))
    """Auto exposure: lowest and highest exposure as multiples of the fixed exposure, so that a
    target in shadow is not amplified into noise, nor a glint allowed to darken everything. A
    target with no light at all (an eclipse) gets the highest."""

    def __post_init__(self) -> None:
        _ordered("auto_gain", self.auto_gain)


@dataclass(frozen=True)
class MaskConfig:
    """The mask pass (target coverage, and depth for EXR output)."""

    spp: int = in_range(1, 4096, default=64)
    """Stratified samples per pixel at 256 px (more for smaller images, so that the boundary
    noise per unit of image size stays the same)."""


@dataclass(frozen=True)
class SceneConfig:
    """Everything about the space scene that is not per image (``scenes/space.json``).

    Checked when built (:func:`sq_mitsuba.config.validate`): a ``SceneConfig`` that exists is
    valid, whether loaded from a file or built in code.
    """

    integrator: IntegratorConfig = field(default_factory=IntegratorConfig)
    """Path tracer settings."""
    sun: SunConfig = field(default_factory=SunConfig)
    """Sun irradiance and phase-angle distribution."""
    earth: EarthConfig = field(default_factory=EarthConfig)
    """The Earth behind or beside the target."""
    stars: StarsConfig = field(default_factory=StarsConfig)
    """The star field."""
    eclipse: EclipseConfig = field(default_factory=EclipseConfig)
    """Frames in the Earth's shadow."""
    pose: PoseConfig = field(default_factory=PoseConfig)
    """Target placement."""
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    """Tone mapping of radiance to 8-bit grey."""
    mask: MaskConfig = field(default_factory=MaskConfig)
    """The mask pass."""

    def __post_init__(self) -> None:
        # Sub-configs built in code are not checked on their own; checking here means every
        # SceneConfig, however it was made (dataclasses.replace included), is valid.
        validate(self)

    @classmethod
    def load(cls, path: str | Path | None = None) -> SceneConfig:
        """The scene of ``path`` (JSON, or TOML by suffix), default the shipped
        ``scenes/space.json``. Fields the file leaves out keep their defaults; JSON keys
        starting with ``_`` are comments. Errors are :class:`ConfigError` s naming the file and
        the dotted field: ``space.json: sun.irradiance: expected a value > 0, got 0``."""
        path = Path(path) if path is not None else scenes_dir() / "space.json"
        if path.suffix.lower() == ".toml":
            return load(cls, path)  # TOML has comments of its own
        try:
            data = read_json(path)
        except FileNotFoundError:
            raise ConfigError(f"{path}: no such file") from None
        except IsADirectoryError:
            raise ConfigError(f"{path}: is a directory, not a scene file") from None
        except ValueError as error:  # malformed JSON, already one line naming the file
            raise ConfigError(str(error)) from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a JSON object at the top, got "
                              f"{type(data).__name__}")
        try:
            return from_dict(cls, _strip_comments(data))
        except ConfigError as error:
            raise ConfigError(f"{path}: {error}") from None

    def to_dict(self) -> dict[str, Any]:
        """The scene as JSON-able data (:func:`sq_mitsuba.config.to_dict`)."""
        return to_dict(self)


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
