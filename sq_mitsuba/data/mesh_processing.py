"""The paper's model processing (Section V.A): watertight, unit size, centred, aligned.

Pipeline: :func:`load_mesh` (OBJ, PLY, STL, GLB/GLTF, scenes flattened) ->
:func:`make_solid` (a closed, outward-oriented surface without internal structures) ->
:func:`normalise` (unit size, centre of mass at the origin, extents sorted) ->
:func:`sample_model` (surface points with normals, occupancy points) -> :func:`write_model`.

Two routes to a solid, chosen by :func:`make_solid`:

* ``"boolean"``: when every connected piece of the input is a closed oriented 2-manifold (all
  generated spacecraft; clean imported parts), the pieces (turned outward where inverted) are
  united exactly with manifold3d. Overlaps, nested parts and internal faces disappear; thin
  panels are kept exactly.
* ``"fusion"``: anything else (holes, stray internal faces, non-manifold edges). Depth maps
  rendered with Mitsuba from many directions carve the space seen from outside, as in Stutz
  and Geiger's depth fusion; a voxel is solid unless it is seen from at least
  ``FUSION_VOTES`` directions, which closes holes that are only seen through from a few
  directions. The surface is extracted by marching cubes on a signed field whose magnitude is
  the exact distance to the input triangles near the boundary, so it lies on the input
  surface to well below a voxel. Zero-thickness sheets (faces with free space on both sides)
  are thickened to ``SHEET_HALF_THICKNESS`` voxels on each side so they survive.

Convention: point arrays are float32 in files, float64 in memory.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sq_mitsuba.data.mesh_io import SAMPLES_FILE, TaggedMesh, glb_bytes, obj_text
from sq_mitsuba.io import atomic_path, atomic_write_bytes, atomic_write_json, atomic_write_text
from sq_mitsuba.render.materials import MATERIALS, material_index

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
IMPORT_MATERIAL = "aluminium"  # imported meshes carry no tags we can trust
FUSION_RESOLUTION = 128  # voxels along the longest side
MIN_FUSION_RESOLUTION = 16
FUSION_PAD = 3  # voxels of free space around the model
FUSION_BASE_BYTES = 2 * 2**30
"""Memory of depth fusion beyond its voxel arrays (Mitsuba, surface samples, distance
queries), an upper bound from measurements (about 1.3 GiB with Mitsuba loaded)."""
FUSION_BYTES_PER_VOXEL = 128
"""Memory per voxel of the fusion grid, an upper bound: the voxel-testing step holds about a
hundred bytes per voxel (coordinates, indices, projections) when most voxels are tested."""
FUSION_VIEWS = 64
FUSION_VOTES = 2
SHEET_HALF_THICKNESS = 0.75  # voxels
UNIFORM_CUBE_SIDE = 1.0
NEAR_SIGMAS = (0.003, 0.01)  # half of the near-surface points at each scale

INVARIANT_TOLERANCE = 1e-3


class MeshError(ValueError):
    """A mesh that cannot be processed; the message names the file."""


# ------------------------------------------------------------------------------------- load

def load_mesh(path: str | Path) -> TaggedMesh:
    """Read a mesh file (scenes flattened with their node transforms) as a tagged mesh.

    Every face gets :data:`IMPORT_MATERIAL`. Raises :class:`MeshError` naming the file when it
    cannot be read, holds no triangles, or has NaN/infinite or out-of-range data.
    """
    import trimesh

    path = Path(path)
    if path.is_dir():
        raise MeshError(f"{path}: is a folder, not a mesh file")
    if not path.is_file():
        raise MeshError(f"{path}: no such file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise MeshError(f"{path}: unsupported format {path.suffix!r}; "
                        f"expected one of {', '.join(MESH_SUFFIXES)}")
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as error:  # trimesh raises many types on garbage input
        raise MeshError(f"{path}: cannot read as a mesh ({type(error).__name__}: "
                        f"{str(error).splitlines()[0] if str(error) else 'no detail'})") from None
    if isinstance(loaded, trimesh.Scene):
        geometries = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geometries) if geometries else None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError(f"{path}: no triangles found")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if not np.isfinite(vertices).all():
        raise MeshError(f"{path}: vertex coordinates contain NaN or infinity")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{path}: face indices out of range")
    material = np.full(len(faces), material_index(IMPORT_MATERIAL), dtype=np.int16)
    return TaggedMesh(vertices, faces, material)


# ------------------------------------------------------------------------------- helpers

def _merge_vertices(mesh: TaggedMesh, tolerance: float) -> TaggedMesh:
    """Weld vertices closer than ``tolerance``; drop degenerate and duplicate faces."""
    key = np.round(mesh.vertices / tolerance).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[mesh.faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (
        faces[:, 0] != faces[:, 2])
    faces, material = faces[keep], mesh.face_material[keep]
    # Identical triangles (same vertex set) are duplicates, whatever their winding.
    _, unique_rows = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    unique_rows.sort()
    vertices = mesh.vertices[first]
    return TaggedMesh(vertices, faces[unique_rows], material[unique_rows])


def _compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used, inverse = np.unique(faces, return_inverse=True)
    return vertices[used], inverse.reshape(-1, 3)


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by a closed triangle mesh (negative when it faces inwards)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def center_of_mass(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centre of mass of the solid bounded by a closed mesh, uniform density."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    six_vol = np.einsum("ij,ij->i", a, np.cross(b, c))
    return (six_vol[:, None] * (a + b + c)).sum(axis=0) / (4.0 * six_vol.sum())


def edge_manifold(faces: np.ndarray) -> tuple[bool, bool]:
    """(every edge has exactly two faces, the two traverse it in opposite directions)."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    n = int(faces.max()) + 1
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    closed = bool((counts == 2).all())
    _, directed_counts = np.unique(directed[:, 0] * n + directed[:, 1], return_counts=True)
    return closed, closed and bool((directed_counts == 1).all())


def _components(faces: np.ndarray, n_vertices: int) -> list[np.ndarray]:
    """Face indices of each edge-connected piece (vertex connectivity)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_vertices, n_vertices))
    _, label = connected_components(graph, directed=False)
    face_label = label[faces[:, 0]]
    order = np.argsort(face_label, kind="stable")
    splits = np.flatnonzero(np.diff(face_label[order])) + 1
    return np.split(order, splits)


def connected_pieces(mesh: TaggedMesh) -> int:
    """How many vertex-connected pieces the mesh has (1 for a single connected body)."""
    if len(mesh.faces) == 0:
        return 0
    return len(_components(mesh.faces, len(mesh.vertices)))


def transfer_face_material(source: TaggedMesh, vertices: np.ndarray, faces: np.ndarray
                           ) -> np.ndarray:
    """Material of each new face = material of the nearest source face (by face centre)."""
    if np.all(source.face_material == source.face_material[0]):
        return np.full(len(faces), source.face_material[0], dtype=np.int16)
    from scipy.spatial import cKDTree

    src_centres = source.vertices[source.faces].mean(axis=1)
    _, nearest = cKDTree(src_centres).query(vertices[faces].mean(axis=1))
    return source.face_material[nearest].astype(np.int16)


# ------------------------------------------------------------------------- boolean route

def _to_manifold(vertices: np.ndarray, faces: np.ndarray):
    import manifold3d

    mesh = manifold3d.Mesh(vert_properties=np.ascontiguousarray(vertices, np.float32),
                           tri_verts=np.ascontiguousarray(faces, np.uint32))
    solid = manifold3d.Manifold(mesh)
    return solid if solid.status() == manifold3d.Error.NoError and not solid.is_empty() else None


def solid_by_boolean(mesh: TaggedMesh) -> TaggedMesh | None:
    """Exact union of the input's pieces, or None when a piece is not a closed 2-manifold."""
    pieces, tags = [], []
    for face_ids in _components(mesh.faces, len(mesh.vertices)):
        faces = mesh.faces[face_ids]
        closed, oriented = edge_manifold(faces)
        if not (closed and oriented):
            return None
        volume = signed_volume(mesh.vertices, faces)
        if abs(volume) < 1e-12 * np.ptp(mesh.vertices, axis=0).max() ** 3:
            return None
        if volume < 0:  # inverted piece: turn it outward
            faces = faces[:, ::-1]
        vertices, local = _compact(mesh.vertices, faces)
        solid = _to_manifold(vertices, local)
        if solid is None:
            return None
        pieces.append(solid)
        tags.append(int(np.bincount(mesh.face_material[face_ids]).argmax()))
    result = union_solids(pieces, tags)
    if len(np.unique(mesh.face_material)) > 1:
        result = TaggedMesh(result.vertices, result.faces,
                            transfer_face_material(mesh, result.vertices, result.faces))
    return result


def union_solids(solids: Sequence, materials: Sequence[int]) -> TaggedMesh:
    """Exact union (manifold3d) of closed solids, face ``i`` of solid ``k`` tagged
    ``materials[k]``; internal faces and overlaps disappear.

    Per-face materials follow manifold3d's provenance runs: each solid gets its own original
    ID, and every output triangle records which input it came from.
    """
    import manifold3d

    if not solids:
        raise ValueError("solids: empty list, nothing to union")
    tagged_solids, id_to_material = [], {}
    for solid, material in zip(solids, materials, strict=True):
        tagged = solid.as_original()
        id_to_material[tagged.original_id()] = int(material)
        tagged_solids.append(tagged)
    result = manifold3d.Manifold.batch_boolean(tagged_solids, manifold3d.OpType.Add)
    if result.status() != manifold3d.Error.NoError or result.is_empty():
        raise ValueError(f"union of parts failed: {result.status()}")
    mesh = result.to_mesh64()
    vertices = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    faces = np.asarray(mesh.tri_verts, dtype=np.int64).reshape(-1, 3)
    run_index = np.asarray(mesh.run_index, dtype=np.int64) // 3
    run_ids = np.asarray(mesh.run_original_id, dtype=np.int64)
    face_material = np.zeros(len(faces), dtype=np.int16)
    for start, stop, original in zip(run_index[:-1], run_index[1:], run_ids, strict=True):
        face_material[start:stop] = id_to_material[int(original)]
    # Drop unreferenced vertices so the OBJ holds only what the faces use.
    used, inverse = np.unique(faces, return_inverse=True)
    return TaggedMesh(vertices[used], inverse.reshape(-1, 3).astype(np.int64), face_material)


# -------------------------------------------------------------------------- fusion route

def _unsigned_distance(points: np.ndarray, triangles: np.ndarray, tree, sample_face: np.ndarray,
                       candidates: int = 12) -> np.ndarray:
    """Distance from each point to the nearest of the triangles (exact among candidates).

    Candidates are the faces of the ``candidates`` nearest surface samples (``tree``), dense
    enough that the true nearest face is among them.
    """
    import trimesh

    out = np.empty(len(points))
    for start in range(0, len(points), 200_000):
        p = points[start:start + 200_000]
        _, idx = tree.query(p, k=candidates)
        faces = sample_face[idx]  # (n, k)
        flat_p = np.repeat(p, candidates, axis=0)
        closest = trimesh.triangles.closest_point(triangles[faces.ravel()], flat_p)
        dist = np.linalg.norm(closest - flat_p, axis=1).reshape(len(p), candidates)
        out[start:start + len(p)] = dist.min(axis=1)
    return out


def _surface_samples(vertices: np.ndarray, faces: np.ndarray, spacing: float,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points on the triangles, about ``spacing`` apart, plus every face's centre."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    count = int(min(3_000_000, max(10_000, area.sum() / spacing**2)))
    points, face = sample_triangles(vertices, faces, count, rng)
    centres = tri.mean(axis=1)
    return (np.concatenate([points, centres]),
            np.concatenate([face, np.arange(len(faces))]))


def _grid_points(axes: list[np.ndarray]) -> np.ndarray:
    """(3, N) float32 coordinates of a grid's nodes, x slowest ("ij" order)."""
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh]).astype(np.float32)


def _unseen(points: np.ndarray, maps: list, votes: int, h: float) -> np.ndarray:
    """Boolean (N,): seen in front of the first surface by fewer than ``votes`` depth maps.

    ``points`` is (3, N). A point stops being tested once it has the votes to be outside,
    which after a few views is most of empty space.
    """
    from scipy import ndimage

    undecided = np.arange(points.shape[1])
    seen = np.zeros(points.shape[1], dtype=np.int16)
    for dm in maps:
        if len(undecided) == 0:
            break
        # Conservative: a pixel's depth is the nearest surface in its 3x3 neighbourhood, so
        # thin parts seen edge-on are not carved between pixel rays.
        depth = ndimage.minimum_filter(dm.depth, size=3, mode="nearest")
        p = points[:, undecided] - dm.origin.astype(np.float32)[:, None]
        frame = np.stack([dm.right, dm.up, dm.direction]).astype(np.float32)
        uvw = frame @ p  # (3, n): the layout numpy multiplies fast
        j = np.clip(((uvw[0] - dm.u0) / dm.pixel).astype(np.int32), 0, depth.shape[1] - 1)
        i = np.clip(((uvw[1] - dm.v0) / dm.pixel).astype(np.int32), 0, depth.shape[0] - 1)
        seen[undecided] += uvw[2] < depth[i, j] - 0.25 * h
        undecided = undecided[seen[undecided] < votes]
    return seen < votes


def _unseen_exact(caster, points: np.ndarray, directions: np.ndarray, votes: int
                  ) -> np.ndarray:
    """Like :func:`_unseen` with exact rays: a point is seen from view ``d`` when the ray
    from it towards the camera (along ``-d``) escapes."""
    undecided = np.arange(len(points))
    seen = np.zeros(len(points), dtype=np.int16)
    for d in directions:
        if len(undecided) == 0:
            break
        _, face = caster.first_hit(points[undecided], -d)
        seen[undecided] += face < 0
        undecided = undecided[seen[undecided] < votes]
    return seen < votes


def solid_by_fusion(mesh: TaggedMesh, resolution: int = FUSION_RESOLUTION,
                    views: int = FUSION_VIEWS, votes: int = FUSION_VOTES) -> TaggedMesh:
    """Watertight surface of anything by depth-map fusion (see the module docstring)."""
    from scipy import ndimage
    from scipy.spatial import cKDTree
    from skimage.measure import marching_cubes

    from sq_mitsuba.render.depth import RayCaster, fibonacci_directions, orthographic_depth_maps

    # Work at unit size so resolution and tolerances are relative to the model.
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    centre, scale = (lo + hi) / 2, float((hi - lo).max())
    vertices = (mesh.vertices - centre) / scale
    faces = mesh.faces
    h = 1.0 / resolution
    pad = FUSION_PAD
    box_min = vertices.min(axis=0) - pad * h
    dims = np.ceil((vertices.max(axis=0) + pad * h - box_min) / h).astype(int) + 1
    axes = [box_min[k] + h * np.arange(dims[k]) for k in range(3)]

    caster = RayCaster(vertices, faces)
    maps = orthographic_depth_maps(caster, fibonacci_directions(views), box_min,
                                   box_min + h * (dims - 1), pixel=h)
    # Coarse pass at twice the spacing: fine voxels deep inside coarse solid (every coarse
    # neighbour solid too) are solid without testing; the rest are tested at full resolution.
    coarse_axes = [a[::2] for a in axes]
    coarse = _unseen(_grid_points(coarse_axes), maps, votes, h).reshape(
        tuple(len(a) for a in coarse_axes))
    deep = ndimage.binary_erosion(coarse, structure=np.ones((3, 3, 3), bool), border_value=0)
    ii, jj, kk = (np.arange(d) // 2 for d in dims)
    deep_fine = deep[np.ix_(ii, jj, kk)]
    solid = deep_fine.copy()
    test = np.flatnonzero(~deep_fine.ravel())
    points_all = _grid_points(axes)
    solid.ravel()[test] = _unseen(points_all[:, test], maps, votes, h)

    # The depth-map test is conservative by up to a pixel (its 3x3 minimum filter), which
    # would thicken everything by about a voxel. Voxels at the solid's boundary are re-tested
    # with exact rays towards every view (no pixels), until the boundary stops moving.
    tested = np.zeros(solid.shape, dtype=bool)
    directions = fibonacci_directions(views)
    for _ in range(4):
        band = solid ^ ndimage.binary_erosion(solid, border_value=0)
        band |= ndimage.binary_dilation(solid, border_value=0) & ~solid
        band &= ~tested
        if not band.any():
            break
        idx = np.nonzero(band)
        points = np.stack([axes[k][idx[k]] for k in range(3)], axis=1)
        # More votes than the depth maps: a point near a hole sees out through it from a few
        # directions only, a point truly outside from at least an eighth of them.
        solid[idx] = _unseen_exact(caster, points, directions, max(votes, views // 16))
        tested |= band

    # Exact distance to the input triangles where the field changes sign (and near sheets).
    rng = np.random.default_rng(0)
    samples, sample_face = _surface_samples(vertices, faces, h / 2, rng)
    tree = cKDTree(samples)
    triangles = vertices[faces]
    boundary = solid ^ ndimage.binary_erosion(solid, border_value=0)
    boundary |= ndimage.binary_dilation(solid, border_value=0) & ~solid
    field = np.where(solid, -h, h).astype(np.float64)
    idx = np.nonzero(boundary)
    points = np.stack([axes[k][idx[k]] for k in range(3)], axis=1)
    dist = np.minimum(_unsigned_distance(points, triangles, tree, sample_face), h)
    field[idx] = np.where(solid[idx], -dist, dist)

    # Zero-thickness sheets: faces with free space on both sides get a thin slab.
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    good = norms > 0
    centres = triangles.mean(axis=1)
    unit = np.zeros_like(normals)
    unit[good] = normals[good] / norms[good, None]

    def solid_at(p: np.ndarray) -> np.ndarray:
        ijk = np.clip(np.rint((p - box_min) / h).astype(int), 0, dims - 1)
        return solid[ijk[:, 0], ijk[:, 1], ijk[:, 2]]

    sheet = good & ~solid_at(centres + 1.5 * h * unit) & ~solid_at(centres - 1.5 * h * unit)
    if sheet.any():
        sheet_samples = np.isin(sample_face, np.flatnonzero(sheet))
        sheet_tree = cKDTree(samples[sheet_samples])
        near = ~solid
        near_idx = np.nonzero(near)
        near_points = np.stack([axes[k][near_idx[k]] for k in range(3)], axis=1)
        d_near, _ = sheet_tree.query(near_points, distance_upper_bound=3 * h)
        close = np.isfinite(d_near)
        cp = near_points[close]
        d_exact = _unsigned_distance(cp, triangles, sheet_tree,
                                     sample_face[sheet_samples], candidates=8)
        sel = tuple(a[close] for a in near_idx)
        field[sel] = np.minimum(field[sel], d_exact - SHEET_HALF_THICKNESS * h)

    padded = np.pad(field, 1, constant_values=h)
    verts, tri, _, _ = marching_cubes(padded, level=0.0, spacing=(h, h, h),
                                      allow_degenerate=False)
    verts = verts + box_min - h
    if signed_volume(verts, tri) < 0:
        tri = tri[:, ::-1]
    solid_mesh = _to_manifold(verts, tri)
    if solid_mesh is None:
        raise MeshError("fusion produced a non-manifold surface")
    # Flat regions carry many marching-cubes triangles; merge them within a tenth of a voxel.
    solid_mesh = solid_mesh.simplify(0.1 * h)
    out = solid_mesh.to_mesh64()
    out_vertices = np.asarray(out.vert_properties, np.float64)[:, :3] * scale + centre
    out_faces = np.asarray(out.tri_verts, np.int64).reshape(-1, 3)
    return TaggedMesh(out_vertices, out_faces,
                      transfer_face_material(mesh, out_vertices, out_faces))


def fusion_memory_bytes(resolution: int) -> int:
    """Estimated peak memory (bytes) of :func:`solid_by_fusion` at ``resolution``.

    Convention: the worst case, a model as deep as it is long (a cube's grid of
    ``(resolution + 2 * FUSION_PAD + 2) ** 3`` voxels), at :data:`FUSION_BYTES_PER_VOXEL`,
    plus :data:`FUSION_BASE_BYTES`.
    """
    side = int(resolution) + 2 * FUSION_PAD + 2
    return FUSION_BASE_BYTES + FUSION_BYTES_PER_VOXEL * side**3


def max_fusion_resolution(memory_bytes: int) -> int:
    """The largest resolution whose :func:`fusion_memory_bytes` fits in ``memory_bytes``
    (``MIN_FUSION_RESOLUTION - 1`` when none does)."""
    voxels = max(memory_bytes - FUSION_BASE_BYTES, 0) / FUSION_BYTES_PER_VOXEL
    side = round(voxels ** (1 / 3)) + 1
    while side > 0 and FUSION_BYTES_PER_VOXEL * side**3 > memory_bytes - FUSION_BASE_BYTES:
        side -= 1
    return max(side - 2 * FUSION_PAD - 2, MIN_FUSION_RESOLUTION - 1)


def make_solid(mesh: TaggedMesh, method: str = "auto",
               resolution: int = FUSION_RESOLUTION) -> tuple[TaggedMesh, str]:
    """A closed outward surface without internal structures, and the route that made it.

    Args:
        mesh: any triangle soup.
        method: ``"auto"`` (boolean when every piece is closed, else fusion), ``"boolean"``,
            ``"fusion"``, or ``"solid"`` for a mesh that already is an exact union of closed
            parts (generated spacecraft): checked to be a closed oriented 2-manifold, kept.
        resolution: fusion voxels along the longest side.
    """
    if method not in ("auto", "boolean", "fusion", "solid"):
        raise ValueError(f"method: expected auto, boolean, fusion or solid, got {method!r}")
    if len(mesh.faces) == 0 or not np.isfinite(mesh.vertices).all():
        raise MeshError("mesh is empty or has NaN/infinite vertices")
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    if not np.isfinite(extent) or extent <= 0:
        raise MeshError("mesh has zero extent")
    if method == "solid":
        closed, oriented = edge_manifold(mesh.faces)
        if not (closed and oriented and signed_volume(mesh.vertices, mesh.faces) > 0):
            raise MeshError("mesh is not a closed outward 2-manifold")
        return mesh, "boolean"
    welded = _merge_vertices(mesh, tolerance=1e-7 * extent)
    if len(welded.faces) == 0:
        raise MeshError("mesh has only degenerate triangles")
    if np.sort(np.ptp(welded.vertices, axis=0))[0] <= 1e-6 * extent:
        raise MeshError("mesh is flat (zero volume)")
    if method in ("auto", "boolean"):
        solid = solid_by_boolean(welded)
        if solid is not None:
            return solid, "boolean"
        if method == "boolean":
            raise MeshError("boolean route needs closed oriented pieces; use fusion")
    return solid_by_fusion(welded, resolution=resolution), "fusion"


# --------------------------------------------------------------------------- normalise

@dataclass(frozen=True)
class Normalisation:
    """``x_model = scale * rotation @ x_source + translation``."""

    rotation: np.ndarray
    scale: float
    translation: np.ndarray

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous source-to-model transform."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m


def alignment_rotation(vertices: np.ndarray, faces: np.ndarray, align: str = "axes"
                       ) -> np.ndarray:
    """Rotation putting the largest extent on x, then y, then z.

    ``"axes"``: a signed permutation of the source axes (models built or modelled axis
    aligned, as the NASA and ESA models are). ``"obb"``: the minimum-volume oriented box's
    axes first. Convention: an odd permutation flips z so the result is a proper rotation.
    """
    if align not in ("axes", "obb"):
        raise ValueError(f"align: expected axes or obb, got {align!r}")
    base = np.eye(3)
    if align == "obb":
        import trimesh

        to_box, _ = trimesh.bounds.oriented_bounds(vertices)
        base = to_box[:3, :3]
    extents = np.ptp(vertices @ base.T, axis=0)
    order = np.argsort(-extents, kind="stable")
    rotation = base[order]
    if np.linalg.det(rotation) < 0:
        rotation[2] *= -1
    return rotation


def normalise(mesh: TaggedMesh, align: str = "axes") -> tuple[TaggedMesh, Normalisation]:
    """Unit size (longest aligned side 1), centre of mass at the origin, extents sorted."""
    rotation = alignment_rotation(mesh.vertices, mesh.faces, align)
    rotated = mesh.vertices @ rotation.T
    scale = 1.0 / float(np.ptp(rotated, axis=0).max())
    scaled = rotated * scale
    translation = -center_of_mass(scaled, mesh.faces)
    norm = Normalisation(rotation, scale, translation)
    return TaggedMesh(scaled + translation, mesh.faces, mesh.face_material), norm


def invariant_checks(mesh: TaggedMesh) -> dict[str, bool]:
    """The processed-model invariants, by name."""
    closed, oriented = edge_manifold(mesh.faces)
    extents = np.ptp(mesh.vertices, axis=0)
    volume = signed_volume(mesh.vertices, mesh.faces)
    com = center_of_mass(mesh.vertices, mesh.faces)
    return {
        "watertight": closed,
        "consistent_winding": oriented,
        "outward": volume > 0,
        "manifold": _to_manifold(mesh.vertices, mesh.faces) is not None,
        "unit_size": abs(float(extents.max()) - 1.0) <= INVARIANT_TOLERANCE,
        "centred_on_center_of_mass": float(np.abs(com).max()) <= INVARIANT_TOLERANCE,
        # Within the tolerance: equal sides (a model symmetric under a quarter turn) come out
        # of the rotation and scaling with either one a rounding error longer.
        "extents_sorted": bool(extents[0] >= extents[1] - INVARIANT_TOLERANCE
                               and extents[1] >= extents[2] - INVARIANT_TOLERANCE),
    }


# ----------------------------------------------------------------------------- sampling

def sample_triangles(vertices: np.ndarray, faces: np.ndarray, count: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points uniform on the surface (area-weighted) and their face indices."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(faces), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    w0, w1, w2 = 1 - s, s * (1 - r2), s * r2
    t = tri[face]
    return w0[:, None] * t[:, 0] + w1[:, None] * t[:, 1] + w2[:, None] * t[:, 2], face


def sample_model(mesh: TaggedMesh, n_surface: int = 100_000, n_uniform: int = 100_000,
                 n_near: int = 100_000, seed: int = 0) -> dict[str, np.ndarray]:
    """Surface points with normals, and uniform and near-surface points labelled inside.

    Convention: uniform points fill the cube of side 1 centred on the bounding-box centre
    (it holds the whole unit-size model); near-surface points are surface points plus
    isotropic Gaussian noise, half with each sigma in :data:`NEAR_SIGMAS`. Labels come from
    :class:`sq_mitsuba.render.depth.RayCaster` on the closed mesh.
    """
    from sq_mitsuba.render.depth import RayCaster

    rng = np.random.default_rng(seed)
    points, face = sample_triangles(mesh.vertices, mesh.faces, n_surface, rng)
    tri = mesh.vertices[mesh.faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    # Zero-area faces keep a zero normal: area-weighted sampling never picks them.
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals /= np.where(length > 0, length, 1.0)
    centre = (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2
    cube_min = centre - UNIFORM_CUBE_SIDE / 2
    uniform = cube_min + UNIFORM_CUBE_SIDE * rng.random((n_uniform, 3))
    near_base, _ = sample_triangles(mesh.vertices, mesh.faces, n_near, rng)
    sigma = np.where(np.arange(n_near) < n_near // 2, NEAR_SIGMAS[0], NEAR_SIGMAS[1])
    near = near_base + rng.normal(size=(n_near, 3)) * sigma[:, None]
    caster = RayCaster(mesh.vertices, mesh.faces)
    labels = caster.inside(np.concatenate([uniform, near]))
    return {
        "surface_points": points.astype(np.float32),
        "surface_normals": normals[face].astype(np.float32),
        "surface_face": face.astype(np.int32),
        "uniform_points": uniform.astype(np.float32),
        "uniform_inside": labels[:n_uniform],
        "near_points": near.astype(np.float32),
        "near_inside": labels[n_uniform:],
        "cube_min": cube_min.astype(np.float32),
        "cube_side": np.float32(UNIFORM_CUBE_SIDE),
        "face_material": mesh.face_material.astype(np.int16),
        "material_names": np.array(MATERIALS),
    }


# ------------------------------------------------------------------------------ process

@dataclass
class ProcessedModel:
    """A processed model: the normalised solid and what was done to it."""

    mesh: TaggedMesh
    route: str
    normalisation: Normalisation
    checks: dict[str, bool] = field(default_factory=dict)

    @property
    def volume(self) -> float:
        return signed_volume(self.mesh.vertices, self.mesh.faces)

    @property
    def extents(self) -> np.ndarray:
        return np.ptp(self.mesh.vertices, axis=0)


def process_mesh(mesh: TaggedMesh, method: str = "auto", align: str = "axes",
                 resolution: int = FUSION_RESOLUTION) -> ProcessedModel:
    """Make ``mesh`` a processed model; :class:`MeshError` if an invariant fails."""
    solid, route = make_solid(mesh, method, resolution)
    if signed_volume(solid.vertices, solid.faces) <= 0:
        raise MeshError("processed solid has zero volume")
    normalised, norm = normalise(solid, align)
    # Faces sorted by material: each material is one contiguous run of faces (one glTF
    # primitive); the per-face material array keeps the OBJ's face order.
    order = np.argsort(normalised.face_material, kind="stable")
    normalised = TaggedMesh(normalised.vertices, normalised.faces[order],
                            normalised.face_material[order])
    checks = invariant_checks(normalised)
    failed = [name for name, ok in checks.items() if not ok]
    if failed:
        raise MeshError(f"processed model fails checks: {', '.join(failed)}")
    return ProcessedModel(normalised, route, norm, checks)


# ------------------------------------------------------------------------------- writing

MODEL_FOLDER = "models"
"""The folder :func:`write_model` writes inside ``<out_root>/<name>/``."""
MODEL_FILES = ("model_normalized.obj", "model_normalized.glb", SAMPLES_FILE, "model_card.json")
"""What :func:`write_model` writes into it."""


def recover_cut_write(model_dir: Path) -> list[Path]:
    """Settle what a :func:`write_model` killed between its two renames left in ``model_dir``:
    the model it was replacing, set aside as ``.models.old.<pid>/``, comes back as ``models/``
    where none is there, and is removed beside one. Returns the folders it found."""
    final = model_dir / MODEL_FOLDER
    found = sorted(path for path in model_dir.glob(".models.old.*")
                   if path.is_dir() and not path.is_symlink())
    for stale in found:
        if final.exists():
            shutil.rmtree(stale, ignore_errors=True)
        else:
            os.replace(stale, final)
    return found


def write_model(out_root: str | Path, name: str, model: ProcessedModel,
                samples: dict[str, np.ndarray], card: dict) -> Path:
    """Write ``<out_root>/<name>/models/`` atomically; return that folder.

    Files: ``model_normalized.obj`` (one closed surface, no material groups: see
    :mod:`sq_mitsuba.data.mesh_io`), ``samples.npz`` (points, labels and the per-face material
    index array ``face_material`` in OBJ face order), ``model_normalized.glb`` (the same mesh
    with its materials, for viewers), ``model_card.json``. The folder is built beside its
    final place and renamed; a failure leaves nothing new.
    """
    model_dir = Path(out_root) / name
    created = not model_dir.exists()
    model_dir.mkdir(parents=True, exist_ok=True)
    final = model_dir / MODEL_FOLDER
    recover_cut_write(model_dir)  # an earlier write cut between its renames
    from sq_mitsuba.io import staging_folder  # mkdtemp with mkdir's permissions
    tmp = staging_folder(".models.", model_dir)
    old = None
    try:
        obj, glb, samples_file, card_file = MODEL_FILES
        atomic_write_text(tmp / obj, obj_text(model.mesh))
        atomic_write_bytes(tmp / glb, glb_bytes(model.mesh, name))
        with atomic_path(tmp / samples_file) as path:
            np.savez_compressed(path, **samples)
        atomic_write_json(tmp / card_file, card)
        if final.exists():
            old = model_dir / f".models.old.{os.getpid()}"
            os.replace(final, old)
        os.replace(tmp, final)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and old.exists() and not final.exists():
            os.replace(old, final)  # cut between the two renames: the old model comes back
        if created:
            with contextlib.suppress(OSError):
                model_dir.rmdir()
        raise
    return final


def model_card(name: str, model: ProcessedModel, samples: dict[str, np.ndarray],
               **extra: object) -> dict:
    """The model card: provenance, geometry figures, materials and checks passed."""
    counts = np.bincount(model.mesh.face_material, minlength=len(MATERIALS))
    card = {
        "name": name,
        **extra,
        "route": model.route,
        "volume": round(model.volume, 8),
        "extents": [round(float(e), 8) for e in model.extents],
        "vertices": len(model.mesh.vertices),
        "faces": len(model.mesh.faces),
        "mesh_sha256": model.mesh.digest(),
        "materials": {MATERIALS[i]: int(c) for i, c in enumerate(counts) if c},
        "source_to_model": [[round(float(x), 10) for x in row]
                            for row in model.normalisation.matrix()],
        "samples": {
            "file": "samples.npz",
            "surface": len(samples["surface_points"]),
            "uniform": len(samples["uniform_points"]),
            "near": len(samples["near_points"]),
            "near_sigmas": list(NEAR_SIGMAS),
            "uniform_cube_min": [float(x) for x in samples["cube_min"]],
            "uniform_cube_side": UNIFORM_CUBE_SIDE,
            "uniform_inside_fraction": round(float(samples["uniform_inside"].mean()), 6),
        },
        "checks": {k: bool(v) for k, v in model.checks.items()},
    }
    return card
