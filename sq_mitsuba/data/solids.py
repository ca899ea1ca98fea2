"""Closed solids from any triangle mesh: the first step of the paper's model processing.

:func:`make_solid` returns a closed, outward-oriented surface without internal structures,
by one of two routes:

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

Also here: a closed mesh's own measures (:func:`signed_volume`, :func:`center_of_mass`,
:func:`edge_manifold`, :func:`connected_pieces`) and area-uniform surface samples
(:func:`sample_triangles`). :mod:`sq_mitsuba.data.mesh_processing` runs the whole pipeline.

Convention: vertices float64 and faces int64, in the input's units (the fusion route works at
unit size inside and scales back).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sq_mitsuba.data.mesh_io import TaggedMesh

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


class MeshError(ValueError):
    """A mesh that cannot be processed; the message names the file."""


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

def as_manifold(vertices: np.ndarray, faces: np.ndarray):
    """The mesh as a ``manifold3d.Manifold``, or None where manifold3d does not accept it as a
    closed oriented 2-manifold (or it is empty)."""
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
        solid = as_manifold(vertices, local)
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
    solid_mesh = as_manifold(verts, tri)
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
