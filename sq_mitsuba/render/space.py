"""Physically based space scene: a spacecraft lit by the sun, the Earth and stars behind it.

One :class:`SpaceScene` per model: the target is one Mitsuba mesh per material tag (from the
per-face tags of the processed model), with the BSDFs of ``scenes/materials.json``, all
two-sided (any tag can belong to a thin part). The sun is a ``directional`` emitter with the
solar irradiance; the Earth a sphere with a procedural albedo texture, drawn at
``render_distance`` and scaled to keep its true angular size; the stars an environment map.
The camera is the dataset camera at the origin (OpenCV frame,
:func:`sq_mitsuba.render.silhouette.renderer.sensor_dict`); poses move the vertices.

A second, tiny scene renders the mask of the target alone: black meshes before a constant
white environment, seen by one visibility test per sample (the ``target_coverage`` integrator
of :mod:`sq_mitsuba.render.silhouette.integrator`, what ``path`` with ``max_depth=1`` renders,
three times faster), so the image is 1 - coverage; the mask is coverage >= 0.5, estimated
with stratified samples. With ``with_depth`` the same pass also gives the target's depth (for
EXR output).

Eclipses (the sun behind the Earth's disk, seen from the target) switch the sun off
analytically; everything else, earthshine included, is path traced.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.frames import orthonormal_basis
from sq_mitsuba.render.backend import mitsuba
from sq_mitsuba.render.scene_config import ExposureConfig, Frame, SceneConfig, scenes_dir
from sq_mitsuba.render.silhouette.integrator import COVERAGE_PLUGIN
from sq_mitsuba.render.silhouette.integrator import register as register_integrators
from sq_mitsuba.render.silhouette.renderer import sensor_dict

# Stratified samples estimate edge coverage with far less noise than independent ones.
MASK_SAMPLER = "stratified"


LIT_FLOOR = 10
"""8-bit grey level from which a pixel of the target counts as lit (clear of the dark noise of
shadowed parts) in :meth:`RenderedFrame.visibility`; a target whose mean grey is below it is
what the dataset statistics call a dark image."""


@dataclass
class RenderedFrame:
    """Linear radiance (H, W) in W/(m^2 sr), coverage of the target (H, W) in [0, 1], depth
    of the target (H, W) in metres (0 where it is absent; None unless the scene renders
    depth), and the exposure to tonemap with (fixed, or this image's auto exposure)."""

    radiance: np.ndarray
    coverage: np.ndarray
    depth: np.ndarray | None
    exposure: float

    @property
    def mask(self) -> np.ndarray:
        """Binary mask (H, W) uint8 in {0, 255}: coverage >= 0.5."""
        return np.where(self.coverage >= 0.5, 255, 0).astype(np.uint8)

    def image_8bit(self) -> np.ndarray:
        """Tonemapped (H, W) uint8: linear radiance times exposure, clipped, sRGB encoded."""
        return tonemap(self.radiance, self.exposure)

    def visibility(self) -> tuple[float, float]:
        """How well the target shows in the 8-bit image, over the pixels of its mask:

        - mean: the mean grey level / 255, in [0, 1] (``target_visibility`` in the labels);
        - lit fraction: the share of pixels at or above :data:`LIT_FLOOR` / 255
          (``target_lit_fraction``), i.e. how much of the silhouette has visible texture.

        Both are 0 for an empty mask.
        """
        inside = self.coverage >= 0.5
        if not inside.any():
            return 0.0, 0.0
        grey = self.image_8bit()[inside]
        return float(grey.mean() / 255.0), float(np.mean(grey >= LIT_FLOOR))

    def label_extras(self) -> dict[str, float]:
        """The exposure and visibility record stored in the image's label."""
        mean, lit = self.visibility()
        return {"exposure": self.exposure, "target_visibility": round(mean, 6),
                "target_lit_fraction": round(lit, 6)}


def tonemap(radiance: np.ndarray, exposure: float) -> np.ndarray:
    """Linear radiance -> 8-bit sRGB grey levels: ``srgb(clip(radiance * exposure, 0, 1))``."""
    x = np.clip(radiance * exposure, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def fixed_exposure(config: SceneConfig) -> float:
    """The fixed exposure: a Lambertian surface of albedo ``exposure.reference_albedo`` facing
    the sun (radiance albedo * E / pi) maps to 1, i.e. white."""
    return math.pi / (config.sun.irradiance * config.exposure.reference_albedo)


def auto_exposure(radiance: np.ndarray, inside: np.ndarray, fixed: float,
                  config: ExposureConfig) -> float:
    """Per-image exposure from the radiance already rendered (no second pass).

    The ``config.percentile`` percentile of ``radiance`` (H, W) over the pixels where ``inside``
    (H, W) bool is set maps to ``config.auto_white``, within ``config.auto_gain`` times
    ``fixed``. A target with no light on it gets the highest gain; an empty mask the fixed
    exposure (kept within the gain range).
    """
    low, high = (fixed * gain for gain in config.auto_gain)
    if not inside.any():
        return float(min(max(fixed, low), high))
    level = float(np.percentile(radiance[inside], config.percentile))
    if level <= 0.0:
        return float(high)
    return float(min(max(config.auto_white / level, low), high))


def mask_samples(spp_at_256: int, camera: Camera) -> int:
    """Mask samples per pixel: ``spp_at_256`` at 256 px, more for smaller images, rounded up
    to a square.

    A pixel of a smaller image covers more of the target's outline, so it gets proportionally
    more samples; the boundary noise per unit of image size then stays the same. The stratified
    sampler draws a square number of samples (a k x k grid) and warns when asked for another
    count, then takes the next square anyway: asking for that square renders the same images
    without the warning.
    """
    scale = (256.0 / min(camera.width, camera.height)) ** 2
    wanted = max(spp_at_256, math.ceil(spp_at_256 * scale))
    side = math.isqrt(wanted)
    return (side + (side * side < wanted)) ** 2


def load_materials(path: str | Path | None = None) -> dict[str, dict[str, Any]]:
    """BSDF dictionaries per material tag (comments, keys starting with ``_``, dropped), from
    ``path`` or the shipped ``scenes/materials.json``."""
    from sq_mitsuba.io import read_json

    path = Path(path) if path is not None else scenes_dir() / "materials.json"
    data = read_json(path)  # malformed, empty or nested too deep: one line naming it
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected an object of materials by tag, got "
                         f"{type(data).__name__}")
    if "default" not in data:
        raise ValueError(f"{path}: needs a 'default' material")
    return {k: v for k, v in data.items() if not k.startswith("_")}


def _bsdf_dict(spec: dict[str, Any]) -> dict[str, Any]:
    """A material of ``materials.json`` as a two-sided Mitsuba BSDF: every tag can belong to a
    thin part (panels, foils, dishes) seen from either side."""
    spec = dict(spec)
    for key in ("reflectance", "diffuse_reflectance"):
        if isinstance(spec.get(key), int | float):
            spec[key] = {"type": "rgb", "value": float(spec[key])}
    return {"type": "twosided", "bsdf": spec}


def _value_noise(rng: np.random.Generator, height: int, width: int, octaves: int) -> np.ndarray:
    """Fractal value noise in [0, 1], periodic in longitude (for an equirectangular map)."""
    from scipy.ndimage import zoom

    total = np.zeros((height, width))
    amplitude, weight = 1.0, 0.0
    for octave in range(octaves):
        cells = 4 * 2**octave
        grid = rng.random((max(2, cells // 2), cells))
        grid = np.concatenate([grid, grid[:, :1]], axis=1)  # wrap longitude
        layer = zoom(grid, ((height) / grid.shape[0], (width + width / cells) / grid.shape[1]),
                     order=3, mode="grid-wrap")[:height, :width]
        total += amplitude * layer
        weight += amplitude
        amplitude *= 0.5
    total /= weight
    return (total - total.min()) / (np.ptp(total) + 1e-12)


@cache
def earth_texture(seed: int, width: int, height: int, ocean: float, land: tuple[float, float],
                  cloud: float, land_fraction: float, cloud_cover: float) -> np.ndarray:
    """Procedural Earth albedo (height, width): oceans, land and clouds, seeded."""
    rng = np.random.default_rng(seed)
    relief = _value_noise(rng, height, width, 6)
    clouds = _value_noise(rng, height, width, 6)
    is_land = relief > np.quantile(relief, 1 - land_fraction)
    albedo = np.where(is_land, land[0] + (land[1] - land[0]) * relief, ocean)
    cloudiness = np.clip((clouds - (1 - cloud_cover)) / 0.15, 0.0, 1.0)
    return (albedo * (1 - cloudiness) + cloud * cloudiness).astype(np.float32)


@cache
def star_envmap(seed: int, count: int, radiance: tuple[float, float], width: int) -> np.ndarray:
    """Equirectangular star field (width / 2, width): black with point stars, log-uniform."""
    rng = np.random.default_rng(seed)
    height = width // 2
    env = np.zeros((height, width), dtype=np.float32)
    # Uniform on the sphere: uniform longitude, latitude by arcsine.
    lon = rng.integers(0, width, count)
    lat = np.arcsin(rng.uniform(-1, 1, count))
    row = np.clip(((0.5 - lat / math.pi) * height).astype(int), 0, height - 1)
    env[row, lon] = np.exp(rng.uniform(np.log(radiance[0]), np.log(radiance[1]), count))
    return env


def _transform(mi: Any, linear: np.ndarray, offset: np.ndarray | None = None) -> Any:
    matrix = np.eye(4)
    matrix[:3, :3] = linear
    if offset is not None:
        matrix[:3, 3] = offset
    return mi.ScalarTransform4f(matrix.tolist())


def _render_seed(frame: Frame) -> int:
    """Mitsuba's sampler seed of ``frame`` (its seed folded into 31 bits)."""
    return frame.seed % (1 << 31)


def _warm_up_frame() -> Frame:
    """A fixed frame: target 2 m ahead, sun behind the camera, Earth to the side."""
    identity = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    return Frame(index=-1, seed=0, quaternion=(1.0, 0.0, 0.0, 0.0),
                 translation=(0.0, 0.0, 2.0), sun_direction=(0.0, 0.0, -1.0),
                 phase_angle_deg=0.0, earth_direction=(1.0, 0.0, 0.0),
                 earth_angular_radius_deg=65.0, earth_altitude_km=700.0, earth_in_view=False,
                 earth_rotation=identity, star_rotation=identity, eclipse=False)


def _face_tags(face_material: np.ndarray | None, faces: int) -> np.ndarray:
    """(F,) material tags (strings) of ``face_material`` (tags, MATERIALS indices or None)."""
    if face_material is None:
        return np.full(faces, "default")
    values = np.asarray(face_material)
    if values.ndim != 1 or len(values) != faces:
        raise ValueError(f"face_material: expected one tag per face ({faces}), got shape "
                         f"{values.shape}")
    if values.dtype.kind not in "iu":
        return values.astype(str)
    from sq_mitsuba.render.materials import MATERIALS

    if len(values) and (values.min() < 0 or values.max() >= len(MATERIALS)):
        raise ValueError(f"face_material: indices outside the materials 0..{len(MATERIALS) - 1}")
    return np.asarray(MATERIALS)[values]


class SpaceScene:
    """Renders one model in the space scene, frame after frame (see the module docstring).

    Args:
        vertices: (V, 3) model vertices, body frame.
        faces: (F, 3) triangle indices.
        face_material: (F,) material per face: tags (strings, keys of the materials) or
            indices into :data:`sq_mitsuba.render.materials.MATERIALS`; None for the default.
            A tag the materials lack is refused (it would render grey, unnoticed).
        camera: dataset camera (fx must equal fy: Mitsuba has one field of view).
        config: scene configuration (``exposure.mode = "auto"`` sets each frame's exposure
            from its own radiance, see :func:`auto_exposure`).
        spp: path-tracing samples per pixel.
        dataset_seed: seeds the Earth texture and star field (shared by all images).
        materials: BSDFs per tag, default ``scenes/materials.json``.
        with_depth: also render the target's depth (an ``aov`` pass, twice the mask's cost).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, face_material: np.ndarray | None,
                 camera: Camera, config: SceneConfig, spp: int = 64, dataset_seed: int = 0,
                 materials: dict[str, dict[str, Any]] | None = None, with_depth: bool = False):
        if abs(camera.fx - camera.fy) > 1e-6 * camera.fx:
            raise ValueError(f"camera: the dataset renderer needs fx == fy, got {camera.fx}, "
                             f"{camera.fy}")
        if spp < 1:
            raise ValueError(f"spp: expected >= 1, got {spp}")
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3 or \
                not np.isfinite(vertices).all():
            raise ValueError("vertices: expected finite (V, 3) with V >= 3")
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0 or faces.min() < 0 or \
                faces.max() >= len(vertices):
            raise ValueError("faces: expected (F, 3) indices into vertices")
        self.mi = mi = mitsuba()
        self.camera, self.config, self.spp = camera, config, spp
        self.vertices = vertices
        materials = materials or load_materials()
        tags = _face_tags(face_material, len(faces))
        known = sorted(key for key in materials if not key.startswith("_"))
        unknown = sorted(set(tags.tolist()) - set(known))
        if unknown:
            raise ValueError(f"face_material: {', '.join(map(repr, unknown[:5]))}: no such "
                             f"material (known: {', '.join(known)})")
        self.parts: list[tuple[str, np.ndarray, np.ndarray]] = []  # (key, vertex ids, faces)
        for tag in sorted(set(tags.tolist())):
            part_faces = faces[tags == tag]
            used, local = np.unique(part_faces, return_inverse=True)
            self.parts.append((tag, used, local.reshape(-1, 3)))
        self.exposure = fixed_exposure(config)  # auto exposure starts from it, per frame

        sensor = sensor_dict(camera)
        sensor["sampler"] = {"type": "independent", "sample_count": spp}
        sensor["film"]["rfilter"] = {"type": config.integrator.reconstruction_filter}
        texture_cfg = config.earth.texture
        albedo = earth_texture(dataset_seed, texture_cfg.width, texture_cfg.height,
                               texture_cfg.ocean_albedo, tuple(texture_cfg.land_albedo),
                               texture_cfg.cloud_albedo, texture_cfg.land_fraction,
                               texture_cfg.cloud_cover)
        stars = star_envmap(dataset_seed, config.stars.count, tuple(config.stars.radiance),
                            config.stars.envmap_width)
        scene: dict[str, Any] = {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": config.integrator.max_depth},
            "sensor": sensor,
            "sun": {"type": "directional", "direction": [0.0, 0.0, 1.0],
                    "irradiance": config.sun.irradiance},
            "stars": {"type": "envmap", "bitmap": mi.Bitmap(stars[..., None])},
            "earth": {"type": "sphere", "bsdf": {"type": "diffuse", "reflectance": {
                "type": "bitmap", "bitmap": mi.Bitmap(albedo[..., None]), "raw": True}}},
        }
        for tag, used, local in self.parts:
            spec = materials.get(tag, materials["default"])
            scene[f"part_{tag}"] = self._mesh(f"part_{tag}", used, local, _bsdf_dict(spec))
        self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)

        mask_sensor = sensor_dict(camera)
        mask_sensor["sampler"] = {"type": MASK_SAMPLER,
                                  "sample_count": mask_samples(config.mask.spp, camera)}
        self.with_depth = with_depth
        register_integrators()
        coverage_integrator = {"type": COVERAGE_PLUGIN}
        mask_scene: dict[str, Any] = {
            "type": "scene", "sensor": mask_sensor,
            "integrator": ({"type": "aov", "aovs": "depth:depth",
                            "integrator": coverage_integrator}
                           if with_depth else coverage_integrator),
            "background": {"type": "constant", "radiance": 1.0},
        }
        for tag, used, local in self.parts:
            mask_scene[f"part_{tag}"] = self._mesh(f"part_{tag}", used, local, None)
        self.mask_scene = mi.load_dict(mask_scene)
        self.mask_params = mi.traverse(self.mask_scene)
        # A render before the scenes' parameters are first updated differs in the last bits
        # from every later one (measured; later renders are identical whatever came before).
        # Loading one frame's parameters (no render: a render's cost saved per scene) makes
        # each image independent of whether it was the first of its scene, so a resumed run
        # writes the same bytes as an uninterrupted one.
        self._load_frame(_warm_up_frame())

    def _mesh(self, name: str, used: np.ndarray, local: np.ndarray,
              bsdf: dict[str, Any] | None) -> Any:
        mi = self.mi
        props = mi.Properties()
        if bsdf is not None:
            props["bsdf"] = mi.load_dict(bsdf)
        mesh = mi.Mesh(name, len(used), len(local), props=props, has_vertex_normals=False,
                       has_vertex_texcoords=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(self.vertices[used].astype(np.float32).ravel())
        params["faces"] = mi.UInt32(local.astype(np.uint32).ravel())
        params.update()
        return mesh

    def _set_pose(self, params: Any, posed: np.ndarray) -> None:
        """Load the posed vertices (V, 3) float32 into the parts of one scene."""
        for tag, used, _ in self.parts:
            params[f"part_{tag}.vertex_positions"] = self.mi.Float(posed[used].ravel())

    def _posed(self, frame: Frame) -> np.ndarray:
        """The target's vertices (V, 3) float32 in the camera frame at ``frame``'s pose."""
        return (self.vertices @ frame.rotation.T + np.asarray(frame.translation)).astype(
            np.float32)

    def mask_pass(self, frame: Frame, integrator: Any = None) -> np.ndarray:
        """The raw mask pass of ``frame``: (H, W, 1) float64 of 1 - coverage, and the
        coverage-weighted depth as a second channel with ``with_depth``.

        Args:
            frame: the pose (and seed) to render.
            integrator: another Mitsuba integrator to render the mask scene with (the
                benchmark and the tests compare the lean one against ``path``); None: the
                scene's own.
        """
        return self._mask_pass(frame, self._posed(frame), integrator)

    def _mask_pass(self, frame: Frame, posed: np.ndarray, integrator: Any = None) -> np.ndarray:
        """:meth:`mask_pass` with the target's vertices posed already (``posed``, (V, 3))."""
        self._load_mask_pose(posed)
        return np.array(self.mi.render(self.mask_scene, integrator=integrator,
                                       seed=_render_seed(frame)), dtype=np.float64)

    def _ray_cosine(self) -> np.ndarray:
        """(H, W) the cosine between each pixel centre's ray and the optical axis: one over
        the length of the ray's point at depth 1."""
        camera = self.camera
        at_unit_depth = camera.unproject(camera.pixel_centers(torch.float64), 1.0)
        return (1.0 / torch.linalg.vector_norm(at_unit_depth, dim=-1)).numpy()

    def render(self, frame: Frame, radiance: bool = True) -> RenderedFrame:
        """Path-trace ``frame`` (and its mask). ``radiance=False`` renders the mask only."""
        mi = self.mi
        posed = self._posed(frame)
        seed = _render_seed(frame)
        channels = self._mask_pass(frame, posed)
        coverage = np.clip(1.0 - channels[..., 0], 0.0, 1.0)
        depth = None
        if self.with_depth:
            # Missed samples add depth 0 to the pixel average: divide by the coverage. The aov
            # is the distance along each ray; the depth is camera-frame z (the project's
            # convention), that distance times the cosine of the pixel's ray to the axis.
            distance = np.where(coverage > 1e-6, channels[..., 1] / np.maximum(coverage, 1e-6),
                                0.0)
            depth = distance * self._ray_cosine()
        if not radiance:
            return RenderedFrame(np.zeros_like(coverage), coverage, depth, self.exposure)

        self._load_lighting(frame, posed)
        image = np.array(mi.render(self.scene, seed=seed), dtype=np.float64)[..., 0]
        exposure = self.exposure
        if self.config.exposure.mode == "auto":
            exposure = auto_exposure(image, coverage >= 0.5, self.exposure,
                                     self.config.exposure)
        return RenderedFrame(image, coverage, depth, exposure)

    def _load_frame(self, frame: Frame) -> None:
        """Load ``frame``'s parameters into both scenes, as :meth:`render` does, without
        rendering."""
        posed = self._posed(frame)
        self._load_mask_pose(posed)
        self._load_lighting(frame, posed)

    def _load_mask_pose(self, posed: np.ndarray) -> None:
        self._set_pose(self.mask_params, posed)
        self.mask_params.update()

    def _load_lighting(self, frame: Frame, posed: np.ndarray) -> None:
        """The target at ``posed``, the sun, the Earth and the stars of ``frame`` into the
        path-traced scene."""
        mi = self.mi
        self._set_pose(self.params, posed)
        sun = np.asarray(frame.sun_direction)
        # The directional emitter shines along its local +z: from the sun towards the target.
        self.params["sun.to_world"] = _transform(mi, orthonormal_basis(-sun))
        # Eclipses are applied analytically: the directional emitter sizes its shadow rays
        # from the scene's bounds at load time, so the moving Earth cannot be relied on to
        # block it. A point sun is either wholly hidden or not (no penumbra).
        self.params["sun.irradiance.value"] = 0.0 if frame.eclipse else \
            self.config.sun.irradiance
        earth = self.config.earth
        distance = earth.render_distance
        radius = distance * math.sin(math.radians(frame.earth_angular_radius_deg))
        spin = np.asarray(frame.earth_rotation).reshape(3, 3)
        self.params["earth.to_world"] = _transform(
            mi, spin * radius, distance * np.asarray(frame.earth_direction))
        self.params["stars.to_world"] = _transform(mi, np.asarray(frame.star_rotation)
                                                   .reshape(3, 3))
        # The sphere checks its rotated, scaled transform in float32 and reports rounding
        # as shear; the transform is a similarity, so that one warning is muted here.
        logger = mi.logger()
        level = logger.log_level()
        logger.set_log_level(mi.LogLevel.Error)
        try:
            self.params.update()
        finally:
            logger.set_log_level(level)
