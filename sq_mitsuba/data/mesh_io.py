"""The project's one mesh type and its one OBJ reader and writer.

Convention: a :class:`TaggedMesh` carries one material index per face (into
:data:`sq_mitsuba.render.materials.MATERIALS`); OBJ files keep shared vertices and group faces
by material with ``usemtl``, in face order, so per-face arrays stay aligned with the file.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sq_mitsuba.render.materials import MATERIALS, MTL_COLOUR


@dataclass(frozen=True)
class TaggedMesh:
    """A triangle mesh with one material index per face (into ``MATERIALS``).

    Attributes:
        vertices: (V, 3) float64.
        faces: (F, 3) int64, counter-clockwise seen from outside.
        face_material: (F,) int16 indices into :data:`MATERIALS`.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_material: np.ndarray

    def digest(self) -> str:
        """SHA-256 of the geometry and materials (vertices rounded to 1e-9)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(np.round(self.vertices, 9), dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.faces, dtype="<i8").tobytes())
        h.update(np.ascontiguousarray(self.face_material, dtype="<i2").tobytes())
        return h.hexdigest()


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


def obj_text(mesh: TaggedMesh, mtl_name: str | None = "model_normalized.mtl") -> str:
    """Wavefront OBJ: shared vertices, faces grouped by material with ``usemtl``."""
    lines = ["# sq_mitsuba processed model: unit size, centre of mass at origin"]
    if mtl_name:
        lines.append(f"mtllib {mtl_name}")
    lines += [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in mesh.vertices]
    current = -1
    for (a, b, c), tag in zip(mesh.faces + 1, mesh.face_material, strict=True):
        if tag != current:
            lines.append(f"usemtl {MATERIALS[tag]}")
            current = tag
        lines.append(f"f {a} {b} {c}")
    return "\n".join(lines) + "\n"


def mtl_text() -> str:
    """Viewer colours of all material tags."""
    out = []
    for name in MATERIALS:
        r, g, b = MTL_COLOUR[name]
        out += [f"newmtl {name}", f"Kd {r:.3f} {g:.3f} {b:.3f}", ""]
    return "\n".join(out)
