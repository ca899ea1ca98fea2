"""What each dataset image shows: target pose, sun, Earth and stars, sampled per image.

Pure numpy and torch; the renderer (:mod:`sq_mitsuba.render.space`) turns a :class:`Frame`
into pixels. Every frame is drawn from its own seed, derived from the dataset seed, the model
name and the image index, so any image can be re-rendered alone and a resumed run draws
exactly what an uninterrupted one draws.

Convention: camera frame OpenCV (x right, y down, z forward); a pose maps body to camera,
``x_cam = R x_body + t``, with R = quaternion_to_matrix(q), q = (w, x, y, z). Directions
(sun, Earth) are unit vectors in the camera frame pointing *from the target towards* the
body. The phase angle is the angle at the target between the directions to the sun and to the
camera: 0 deg lights the visible side fully, 180 deg back-lights it.

Lighting: the sun is placed by its phase angle, drawn from ``sun.phase_deg`` with
``sun.phase_distribution`` (default uniform in [0, 120] deg), then the Earth where it does not
hide that sun, in view of the camera with probability ``earth.probability_in_view``. With
probability ``eclipse.probability`` (default 0) the sun is put behind the Earth instead.
"""

from __future__ import annotations

import math
import zlib

import numpy as np
import torch

from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.frames import orthonormal_basis
from sq_mitsuba.geometry.rotation import (
    axis_angle_to_matrix,
    matrix_to_quaternion,
    quaternion_to_matrix,
    random_quaternions,
)
from sq_mitsuba.render.scene_config import Frame, PoseConfig, SceneConfig, SunConfig

_SUN_TRIES, _EARTH_TRIES = 5, 100
"""Draws of the sun, and of the Earth per sun, before a frame is kept in the Earth's shadow.
For the default camera and scene one draw of the Earth clears the sun with probability about
0.2 at worst (sun behind the camera, Earth out of view, lowest altitude)."""


def frame_seed(dataset_seed: int, model: str, index: int) -> int:
    """A 63-bit seed for one image, independent of the order images are rendered in."""
    sequence = np.random.SeedSequence([dataset_seed, zlib.crc32(model.encode()), index])
    return int(sequence.generate_state(1, dtype=np.uint64)[0] >> 1)


def _direction_around(rng: np.random.Generator, axis: np.ndarray,
                      cos_theta: float) -> np.ndarray:
    """Unit vector at angle acos(``cos_theta``) from ``axis``, azimuth uniform about it."""
    sin_theta = math.sqrt(max(0.0, 1 - cos_theta**2))
    e1, e2, _ = orthonormal_basis(axis).T
    phi = rng.uniform(0, 2 * math.pi)
    return cos_theta * axis + sin_theta * (math.cos(phi) * e1 + math.sin(phi) * e2)


def _direction_at_angle(rng: np.random.Generator, axis: np.ndarray, cos_low: float,
                        cos_high: float) -> np.ndarray:
    """Unit vector uniform on the zone cos(angle to ``axis``) in [cos_low, cos_high]."""
    return _direction_around(rng, axis, rng.uniform(cos_low, cos_high))


def sun_at_phase(rng: np.random.Generator, to_camera: np.ndarray, config: SunConfig,
                 ) -> np.ndarray:
    """A sun direction (3,) whose phase angle (to ``to_camera``, a unit vector) is drawn from
    ``config.phase_deg`` with ``config.phase_distribution``; its azimuth about ``to_camera``
    is uniform."""
    low, high = (math.radians(a) for a in config.phase_deg)
    if config.phase_distribution == "uniform_angle":
        cos_phase = math.cos(rng.uniform(low, high))
    else:  # uniform_sphere: the cosine is uniform on a zone of the sphere
        cos_phase = rng.uniform(math.cos(high), math.cos(low))
    return _direction_around(rng, to_camera, cos_phase)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    gen = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
    return quaternion_to_matrix(random_quaternions(1, gen, torch.float64))[0].numpy()


def _image_bounds(points_cam: np.ndarray, camera: Camera) -> tuple[float, float, float, float]:
    """Pixel extent (u_min, u_max, v_min, v_max) of camera-frame points (V, 3) in front."""
    u = camera.fx * points_cam[:, 0] / points_cam[:, 2] + camera.cx
    v = camera.fy * points_cam[:, 1] / points_cam[:, 2] + camera.cy
    return float(u.min()), float(u.max()), float(v.min()), float(v.max())


def in_view(points_cam: np.ndarray, camera: Camera, margin_px: float) -> bool:
    """Whether every camera-frame point (V, 3) is in front of the camera and projects at
    least ``margin_px`` pixels inside the image."""
    if points_cam[:, 2].min() <= 1e-3:
        return False
    u0, u1, v0, v1 = _image_bounds(points_cam, camera)
    return u0 >= margin_px and v0 >= margin_px and u1 <= camera.width - margin_px and \
        v1 <= camera.height - margin_px


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
        return _image_bounds(vertices_cam + t, camera)

    def fits(t: np.ndarray) -> bool:
        return in_view(vertices_cam + t, camera, margin)

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
    wants_earth_in_view = rng.random() < earth.probability_in_view
    wants_eclipse = rng.random() < config.eclipse.probability
    to_camera = -translation / np.linalg.norm(translation)

    def draw_earth() -> np.ndarray:
        if wants_earth_in_view:
            # Centre angle such that the limb crosses the field of view.
            low = max(0.0, angular_radius - 0.6 * half_diagonal)
            high = angular_radius + 0.6 * half_diagonal
            return _direction_at_angle(rng, axis, math.cos(high), math.cos(low))
        clear = min(math.pi, angular_radius + half_diagonal + math.radians(5))
        return _direction_at_angle(rng, axis, -1.0, math.cos(clear))

    def hidden(sun: np.ndarray, earth_direction: np.ndarray) -> bool:
        return float(sun @ earth_direction) > math.cos(angular_radius)

    if wants_eclipse:
        # Sun behind the Earth's disk as seen from the target (the phase follows from it).
        earth_direction = draw_earth()
        sun = _direction_at_angle(rng, earth_direction, math.cos(0.9 * angular_radius), 1.0)
    else:
        # The phase angle is drawn first, so that it follows the configured distribution
        # exactly; then the Earth is placed (in view or not, as drawn above) where it does not
        # hide that sun. When no such place turns up (possible only for wide fields of view
        # with the sun near the camera and the Earth out of view), another sun is drawn, and
        # after that the frame is kept as an eclipse, recorded so in its label.
        for attempt in range(_SUN_TRIES * _EARTH_TRIES):
            if attempt % _EARTH_TRIES == 0:
                sun = sun_at_phase(rng, to_camera, config.sun)
            earth_direction = draw_earth()
            if not hidden(sun, earth_direction):
                break
    angle_to_axis = math.acos(float(np.clip(earth_direction @ axis, -1, 1)))
    earth_in_view = angle_to_axis < angular_radius + half_diagonal
    eclipse = hidden(sun, earth_direction)
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


#: How :func:`sample_pass_frame` places a pass, recorded in a pass dataset's manifest so that
#: one rendered by an earlier placement is not resumed with this one: 1, the first frame framed
#: as a single image (a turned frame could cut the target at the image's edge); 2, the whole
#: pass moved back until every frame holds the target.
PASS_FRAMING = 2


def sample_pass_frame(vertices: np.ndarray, camera: Camera, config: SceneConfig,
                      dataset_seed: int, model: str, index: int, frames_per_pass: int,
                      tumble_deg: tuple[float, float] = (3.0, 15.0),
                      approach: tuple[float, float] = (0.0, 0.2)) -> Frame:
    """Image ``index`` of ``model`` when its images are passes of ``frames_per_pass`` frames:
    frame ``k = index % frames_per_pass`` of pass ``p = index // frames_per_pass``.

    A pass starts from the frame :func:`sample_frame` draws for image ``p * frames_per_pass``
    (pose, sun, Earth and stars). Along the pass the target tumbles about an axis drawn
    uniformly on the sphere at a rate drawn from ``tumble_deg`` (degrees per frame), and the
    camera approaches along its line of sight from ``1 + a`` times the start distance to the
    start distance (``a`` drawn from ``approach``), so the last frame is framed as the start
    frame was, unless a frame would then cut the turned target at the image's edge: the whole
    pass is moved back (by factors of 1.05) until every frame holds it; the sun, the Earth
    and the stars keep their directions in the camera frame (an inertially pointed camera),
    and the phase angle follows the target's direction.

    Convention: ``R_k = Rot(axis, k * rate) R_0``, the tumble about an axis fixed in the camera
    frame; so the relative rotation between frames i and j is ``R_j R_i^T = Rot(axis,
    (j - i) * rate)``.
    """
    if frames_per_pass < 1:
        raise ValueError(f"frames_per_pass: expected >= 1, got {frames_per_pass}")
    first = (index // frames_per_pass) * frames_per_pass
    step = index - first
    start = sample_frame(vertices, camera, config, dataset_seed, model, first)
    rng = np.random.default_rng([frame_seed(dataset_seed, model, first), 0x9A55])
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rate = math.radians(rng.uniform(*tumble_deg))
    closing = rng.uniform(*approach)

    def pose(k: int) -> tuple[np.ndarray, np.ndarray]:
        turn = axis_angle_to_matrix(torch.from_numpy(axis * (k * rate))).numpy()
        remaining = (frames_per_pass - 1 - k) / max(frames_per_pass - 1, 1)
        return turn @ start.rotation, np.asarray(start.translation) * (1.0 + closing * remaining)

    # The start frame holds the whole target, but turned it may not: the whole pass is then
    # moved back along the start's line of sight (every frame's image position of the body
    # origin kept) until every frame holds it, as any single image does.
    poses = [pose(k) for k in range(frames_per_pass)]
    turned = [(vertices @ r.T, t) for r, t in poses]  # each frame's target, turned once
    distance = 1.0
    for _ in range(200):
        if all(in_view(points + t * distance, camera, config.pose.margin_px)
               for points, t in turned):
            break
        distance *= 1.05
    else:  # the body origin's image lies inside the margin, so moving back always ends
        raise ValueError(f"{model}: pass {index // frames_per_pass} cannot be framed in view "
                         "(is the model unit size and centred?)")
    rotation, translation = poses[step]
    translation = translation * distance
    quaternion = matrix_to_quaternion(torch.from_numpy(rotation))
    to_camera = -translation / np.linalg.norm(translation)
    phase = math.degrees(math.acos(float(np.clip(np.asarray(start.sun_direction) @ to_camera,
                                                 -1, 1))))
    return Frame(
        index=index, seed=frame_seed(dataset_seed, model, index),  # its own noise, as any image
        quaternion=tuple(float(v) for v in quaternion),
        translation=tuple(float(v) for v in translation),
        sun_direction=start.sun_direction, phase_angle_deg=phase,
        earth_direction=start.earth_direction,
        earth_angular_radius_deg=start.earth_angular_radius_deg,
        earth_altitude_km=start.earth_altitude_km, earth_in_view=start.earth_in_view,
        earth_rotation=start.earth_rotation, star_rotation=start.star_rotation,
        eclipse=start.eclipse)
