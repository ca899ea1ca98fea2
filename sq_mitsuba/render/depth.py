"""Ray casting with Mitsuba for mesh processing: inside-outside labels and depth maps.

Two uses:

* :meth:`RayCaster.inside` labels points inside a closed, outward-oriented mesh: a point is
  inside when the first surface a ray meets from it is seen from the back. Three fixed,
  generic directions vote, so a ray grazing an edge cannot flip a label on its own.
* :func:`orthographic_depth_maps` renders first-hit depth maps along many view directions,
  the input of the depth-map fusion that makes imported meshes watertight
  (:mod:`sq_mitsuba.data.solids`).

Convention: ``numpy`` arrays in, ``numpy`` arrays out, float32 on the Mitsuba side.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sq_mitsuba.geometry.frames import orthonormal_basis

# Generic (irrational-looking) unit directions: no axis-aligned ray runs along a face or edge
# of the boxes and prisms the models are built from.
VOTE_DIRECTIONS = np.array([
    [0.2672612, 0.5345225, 0.8017837],
    [-0.7071068, 0.4082483, -0.5773503],
    [0.5570860, -0.8196442, 0.1335426],
])
VOTE_DIRECTIONS = VOTE_DIRECTIONS / np.linalg.norm(VOTE_DIRECTIONS, axis=1, keepdims=True)

_CHUNK = 1 << 21  # rays per Mitsuba call: bounds the memory of one wavefront


def _mitsuba():
    from sq_mitsuba.render.backend import mitsuba

    return mitsuba()


class RayCaster:
    """A Mitsuba scene holding one triangle mesh, for batched ray queries.

    Args:
        vertices: (V, 3) float array.
        faces: (F, 3) integer array of vertex indices.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        source = np.asarray(vertices, dtype=np.float64)
        vertices = source.astype(np.float32)
        faces = np.asarray(faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
            raise ValueError(f"vertices: expected shape (V>0, 3), got {vertices.shape}")
        if not np.isfinite(source).all():
            raise ValueError("vertices: not finite (NaN or infinite)")
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"faces: expected shape (F>0, 3), got {faces.shape}")
        # Checked before the cast: -1 would become 4294967295, a read past the vertices.
        if faces.dtype.kind not in "iu" or faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError(f"faces: expected integer indices in [0, {len(vertices)}), got "
                             f"{faces.dtype} in [{faces.min()}, {faces.max()}]")
        faces = faces.astype(np.uint32)
        mi = _mitsuba()
        self._mi = mi
        mesh = mi.Mesh("raycast_mesh", len(vertices), len(faces), has_vertex_normals=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(vertices.ravel())
        params["faces"] = mi.UInt32(faces.ravel())
        params.update()
        self._scene = mi.load_dict({"type": "scene", "mesh": mesh})
        # Geometric normals of the mesh Mitsuba intersects (its float32 vertices), computed in
        # float64, indexed by the hit's primitive index.
        v = vertices.astype(np.float64)
        self._normals = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])

    def first_hit(self, origins: np.ndarray, directions: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Distance to and face index of the first hit of each ray (inf and -1 on a miss).

        Args:
            origins: (N, 3) ray origins.
            directions: (N, 3) or (3,) unit directions.
        """
        mi = self._mi
        origins = np.asarray(origins, dtype=np.float32)
        directions = np.broadcast_to(np.asarray(directions, np.float32), origins.shape)
        t_out = np.full(len(origins), np.inf)
        f_out = np.full(len(origins), -1, dtype=np.int64)
        for start in range(0, len(origins), _CHUNK):
            o = origins[start:start + _CHUNK]
            d = directions[start:start + _CHUNK]
            ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]),
                           mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
            pi = self._scene.ray_intersect_preliminary(ray, coherent=False)
            valid = np.asarray(pi.is_valid(), dtype=bool)
            t = np.asarray(pi.t, dtype=np.float64)
            prim = np.asarray(pi.prim_index, dtype=np.int64)
            t_out[start:start + _CHUNK] = np.where(valid, t, np.inf)
            f_out[start:start + _CHUNK] = np.where(valid, prim, -1)
        return t_out, f_out

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Boolean (N,): is each point inside the (closed, outward-oriented) mesh?

        A ray's first hit seen from the back means the ray started inside. Majority of the
        three :data:`VOTE_DIRECTIONS`.
        """
        points = np.asarray(points, dtype=np.float64)
        votes = np.zeros(len(points), dtype=np.int8)
        for direction in VOTE_DIRECTIONS:
            _, face = self.first_hit(points, direction)
            hit = face >= 0
            backface = np.zeros(len(points), dtype=bool)
            backface[hit] = self._normals[face[hit]] @ direction > 0
            votes += backface
        return votes >= 2


@dataclass(frozen=True)
class DepthMap:
    """An orthographic first-hit depth map along ``direction``.

    Pixel (i, j) holds the distance from the image plane (through ``origin``, normal
    ``direction``) to the first surface along the ray through
    ``origin + (u0 + (j + 0.5) pixel) right + (v0 + (i + 0.5) pixel) up``; inf on a miss.
    """

    direction: np.ndarray
    right: np.ndarray
    up: np.ndarray
    origin: np.ndarray
    u0: float
    v0: float
    pixel: float
    depth: np.ndarray  # (H, W) float32


def view_basis(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (right, up) completing ``direction`` to a right-handed orthonormal
    frame: the negated first two columns of :func:`orthonormal_basis`."""
    e1, e2, _ = orthonormal_basis(direction).T
    return -e1, -e2


def fibonacci_directions(count: int) -> np.ndarray:
    """``count`` unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def orthographic_depth_maps(caster: RayCaster, directions: np.ndarray, box_min: np.ndarray,
                            box_max: np.ndarray, pixel: float) -> list[DepthMap]:
    """Depth maps of the mesh in ``caster`` along each direction, covering a box.

    Args:
        caster: the mesh.
        directions: (K, 3) viewing directions (rays travel along them).
        box_min, box_max: (3,) the region every map must cover.
        pixel: pixel size in scene units.
    """
    box_min, box_max = np.asarray(box_min, float), np.asarray(box_max, float)
    corners = np.array([[x, y, z] for x in (box_min[0], box_max[0])
                        for y in (box_min[1], box_max[1]) for z in (box_min[2], box_max[2])])
    center = (box_min + box_max) / 2
    radius = float(np.linalg.norm(box_max - box_min)) / 2 + pixel
    maps = []
    for direction in np.asarray(directions, float):
        d = direction / np.linalg.norm(direction)
        right, up = view_basis(d)
        u, v = (corners - center) @ right, (corners - center) @ up
        u0, v0 = float(u.min()) - pixel, float(v.min()) - pixel
        width = int(np.ceil((u.max() + pixel - u0) / pixel))
        height = int(np.ceil((v.max() + pixel - v0) / pixel))
        origin = center - radius * d
        jj, ii = np.meshgrid(u0 + (np.arange(width) + 0.5) * pixel,
                             v0 + (np.arange(height) + 0.5) * pixel)
        starts = origin + jj.reshape(-1, 1) * right + ii.reshape(-1, 1) * up
        t, _ = caster.first_hit(starts, d)
        maps.append(DepthMap(d, right, up, origin, u0, v0, pixel,
                             t.reshape(height, width).astype(np.float32)))
    return maps
