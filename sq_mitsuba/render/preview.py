"""Preview renders of a model, with Mitsuba (grey levels per material).

Lighting: a sun (directional), a weaker fill light from the opposite side and a uniform
ambient sky. The ambient emitter is hidden from camera rays (``hide_emitters``), so it lights
the models but the background stays black (alpha 0 there).
"""

from __future__ import annotations

import math

import numpy as np

from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.render.materials import MATERIALS, PREVIEW_ALBEDO

PREVIEW_FOV_DEG = 35.45  # the project's default camera (SPEED's horizontal field of view)
VIEW_DIRECTION = np.array([1.0, -1.4, 0.9])  # camera position direction: an oblique 3/4 view
SUN_DIRECTION = np.array([-0.5, 0.8, -0.6])  # direction the light travels
FILL_DIRECTION = np.array([0.6, 0.3, 0.5])  # a weak fill from below the far side
SUN_IRRADIANCE, FILL_IRRADIANCE, AMBIENT_RADIANCE = 2.4, 0.35, 0.18


def render_model(vertices: np.ndarray, faces: np.ndarray, face_material: np.ndarray,
                 size: int = 160, spp: int = 64) -> np.ndarray:
    """A (size, size) grey image in [0, 1] (sRGB-like gamma) of a unit-size model.

    The background is black: the ambient light is hidden from the camera.
    """
    from sq_mitsuba.render.backend import mitsuba

    mi = mitsuba()
    centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    radius = float(np.linalg.norm(np.ptp(vertices, axis=0))) / 2
    distance = 1.05 * radius / math.sin(math.radians(PREVIEW_FOV_DEG / 2))
    eye = centre + distance * VIEW_DIRECTION / np.linalg.norm(VIEW_DIRECTION)
    # Stratified samples converge faster; multijitter needs a square count.
    sampler = "multijitter" if math.isqrt(spp) ** 2 == spp else "independent"
    scene: dict = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3, "hide_emitters": True},
        "sensor": {
            "type": "perspective", "fov": PREVIEW_FOV_DEG, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(),
                                                       target=centre.tolist(), up=[0, 0, 1]),
            "film": {"type": "hdrfilm", "width": size, "height": size,
                     "pixel_format": "luminance_alpha", "rfilter": {"type": "gaussian"}},
            "sampler": {"type": sampler, "sample_count": spp},
        },
        "sun": {"type": "directional", "direction": SUN_DIRECTION.tolist(),
                "irradiance": SUN_IRRADIANCE},
        "fill": {"type": "directional", "direction": FILL_DIRECTION.tolist(),
                 "irradiance": FILL_IRRADIANCE},
        "ambient": {"type": "constant", "radiance": AMBIENT_RADIANCE},
    }
    for tag in np.unique(face_material):
        sub = faces[face_material == tag]
        used, local = np.unique(sub, return_inverse=True)
        props = mi.Properties()
        props["bsdf"] = mi.load_dict({"type": "diffuse",
                                      "reflectance": PREVIEW_ALBEDO[MATERIALS[int(tag)]]})
        mesh = mi.Mesh(f"part_{int(tag)}", len(used), len(sub), props=props,
                       has_vertex_normals=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(vertices[used].astype(np.float32).ravel())
        params["faces"] = mi.UInt32(local.reshape(-1).astype(np.uint32))
        params.update()
        scene[f"part_{int(tag)}"] = mesh
    rendered = np.asarray(mi.render(mi.load_dict(scene), spp=spp))
    # Hidden emitters: background pixels carry zero radiance, and edge pixels already hold
    # the film's coverage-weighted average, so the luminance channel is the final image.
    return np.clip(rendered[..., 0], 0.0, 1.0) ** (1 / 2.2)


def render_face_ids(vertices: np.ndarray, faces: np.ndarray, camera: Camera,
                    light: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """First-hit face index and Lambert shading per pixel of camera-frame meshes.

    Mitsuba casts one ray through each pixel centre of ``camera`` (a
    :class:`~sq_mitsuba.geometry.camera.Camera`, OpenCV frame at the origin); the shading is
    ``0.25 + 0.75 |n . l|`` with ``l`` the unit direction to the light (default: from the camera,
    up and to the left). The variant is mono, so callers colour the face indices themselves
    (one colour per primitive, say).

    Args:
        vertices: (V, 3) camera-frame vertices; faces: (F, 3).

    Returns:
        face index (H, W) int64 (-1 on background) and shading (H, W) float in [0, 1].
    """
    from sq_mitsuba.render.depth import RayCaster

    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    directions = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy,
                           np.ones_like(u)], axis=-1).reshape(-1, 3)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    caster = RayCaster(vertices, faces)
    _, face = caster.first_hit(np.zeros_like(directions), directions)
    light = np.array([-0.4, -0.5, -1.0]) if light is None else np.asarray(light, float)
    light = light / np.linalg.norm(light)
    normals = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                       vertices[faces[:, 2]] - vertices[faces[:, 0]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    shade = np.zeros(len(face))
    hit = face >= 0
    shade[hit] = 0.25 + 0.75 * np.abs(normals[face[hit]] @ light)
    shape = (camera.height, camera.width)
    return face.reshape(shape), shade.reshape(shape)
