"""Contact sheets of a model library, rendered with Mitsuba (grey levels per material).

Lighting: a sun (directional), a weaker fill light from the opposite side and a uniform
ambient sky. The ambient emitter is hidden from camera rays (``hide_emitters``), so it lights
the models but the background stays black (alpha 0 there).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sq_mitsuba.io import atomic_path
from sq_mitsuba.spacecraft.materials import MATERIALS, PREVIEW_ALBEDO

PREVIEW_FOV_DEG = 35.45  # the project's default camera (SPEED's horizontal field of view)
VIEW_DIRECTION = np.array([1.0, -1.4, 0.9])  # camera position direction: an oblique 3/4 view
SUN_DIRECTION = np.array([-0.5, 0.8, -0.6])  # direction the light travels
FILL_DIRECTION = np.array([0.6, 0.3, 0.5])  # a weak fill from below the far side
SUN_IRRADIANCE, FILL_IRRADIANCE, AMBIENT_RADIANCE = 2.4, 0.35, 0.18


def read_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, triangles (polygons fanned) and per-face material indices of an OBJ.

    ``usemtl`` names that are material tags are kept; anything else reads as aluminium.
    """
    path = Path(path)
    vertices, faces, tags = [], [], []
    current = MATERIALS.index("aluminium")
    with open(path, encoding="utf-8", errors="replace") as handle:
        for line in handle:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v" and len(parts) >= 4:
                vertices.append([float(x) for x in parts[1:4]])
            elif parts[0] == "usemtl" and len(parts) > 1:
                name = parts[1]
                current = MATERIALS.index(name) if name in MATERIALS else MATERIALS.index(
                    "aluminium")
            elif parts[0] == "f" and len(parts) >= 4:
                idx = [int(p.split("/")[0]) for p in parts[1:]]
                idx = [i - 1 if i > 0 else len(vertices) + i for i in idx]
                for k in range(1, len(idx) - 1):
                    faces.append([idx[0], idx[k], idx[k + 1]])
                    tags.append(current)
    if not vertices or not faces:
        raise ValueError(f"{path}: no triangles")
    return (np.asarray(vertices, float), np.asarray(faces, np.int64),
            np.asarray(tags, np.int16))


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


def library_models(root: str | Path) -> list[Path]:
    """``<root>/<model>/models/model_normalized.obj`` files, sorted by model name."""
    return sorted(Path(root).glob("*/models/model_normalized.obj"))


def contact_sheet(root: str | Path, out: str | Path, tile: int = 160, spp: int = 64,
                  columns: int | None = None, limit: int | None = None) -> int:
    """Render the models of a library into one labelled PNG grid; return the model count.

    Args:
        root: library root holding ``<model>/models/model_normalized.obj``.
        out: PNG path (written atomically).
        tile: tile side in pixels.
        spp: samples per pixel.
        columns: tiles per row (default: a square-ish grid).
        limit: render only the first ``limit`` models by name (default all).
    """
    from PIL import Image, ImageDraw

    if limit is not None and limit < 1:
        raise ValueError(f"limit: expected >= 1, got {limit}")
    files = library_models(root)[:limit]
    if not files:
        raise ValueError(f"{root}: no <model>/models/model_normalized.obj found")
    columns = columns or math.ceil(math.sqrt(len(files)))
    rows = math.ceil(len(files) / columns)
    label_h = 14
    sheet = Image.new("L", (columns * tile, rows * (tile + label_h)), color=0)
    draw = ImageDraw.Draw(sheet)
    for k, obj in enumerate(files):
        vertices, faces, tags = read_obj(obj)
        image = render_model(vertices, faces, tags, tile, spp)
        x, y = (k % columns) * tile, (k // columns) * (tile + label_h)
        sheet.paste(Image.fromarray((image * 255 + 0.5).astype(np.uint8), "L"), (x, y))
        draw.text((x + 3, y + tile + 1), obj.parent.parent.name[:28], fill=220)
    with atomic_path(out) as tmp:
        sheet.save(tmp)
    return len(files)
