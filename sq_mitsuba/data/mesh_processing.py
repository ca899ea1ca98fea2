"""The paper's model processing (Section V.A): watertight, unit size, centred, aligned.

Pipeline: :func:`load_mesh` (OBJ, PLY, STL, GLB/GLTF, OFF; scenes flattened) ->
:func:`sq_mitsuba.data.solids.make_solid` (a closed, outward-oriented surface without internal
structures, by an exact boolean union or by depth fusion) -> :func:`normalise` (unit size,
centre of mass at the origin, extents sorted) -> :func:`sample_model` (surface points with
normals, occupancy points) -> :func:`write_model`; :func:`process_mesh` runs the first three
and checks the invariants.

Convention: point arrays are float32 in files, float64 in memory.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sq_mitsuba.data.mesh_io import SAMPLES_FILE, TaggedMesh, glb_bytes, obj_text
from sq_mitsuba.data.solids import (
    FUSION_RESOLUTION,
    MIN_FUSION_RESOLUTION,
    MeshError,
    as_manifold,
    center_of_mass,
    edge_manifold,
    make_solid,
    sample_triangles,
    signed_volume,
)
from sq_mitsuba.io import atomic_path, atomic_write_bytes, atomic_write_json, atomic_write_text
from sq_mitsuba.machine import available_memory, too_much_memory
from sq_mitsuba.render.materials import MATERIALS, material_index

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
IMPORT_MATERIAL = "aluminium"  # imported meshes carry no tags we can trust
UNIFORM_CUBE_SIDE = 1.0
NEAR_SIGMAS = (0.003, 0.01)  # half of the near-surface points at each scale

INVARIANT_TOLERANCE = 1e-3
#: Memory an import takes per face of the file's mesh, all steps (load, solid, normalise,
#: sample, write) at their peak: measured 2026-12-02, 5.2 M faces took 5.15 GB and 1.3 M faces
#: 1.3 GB, about 1 KB a face.
IMPORT_BYTES_PER_FACE = 1024
_COUNT_CHUNK = 16 << 20  # bytes read at a time when counting a text file's faces


# ------------------------------------------------------------------------------------- load

def check_import_memory(path: str | Path, faces: int) -> None:
    """Refuse (one-line :class:`MeshError` naming the file and its face count) importing a mesh
    of ``faces`` faces when it would need more memory than this process may use (about
    :data:`IMPORT_BYTES_PER_FACE` a face): such a file was killed, or crashed silently, minutes
    into the import. Nothing is checked where the memory is unknown."""
    memory = available_memory()
    need = faces * IMPORT_BYTES_PER_FACE
    if memory is not None and need > memory:
        raise MeshError(too_much_memory(
            f"{path} ({faces:,} faces)", need, memory,
            f"at most about {memory // IMPORT_BYTES_PER_FACE:,} faces fit; simplify "
            "(decimate) the mesh first"))


def _count_in_file(path: Path, token: bytes) -> int:
    """Occurrences of ``token`` in the file, read in chunks (a large file is never whole in
    memory; a token cut between two chunks is counted once)."""
    count, tail = 0, b""
    with open(path, "rb") as file:
        while chunk := file.read(_COUNT_CHUNK):
            data = tail + chunk
            count += data.count(token)
            tail = data[-(len(token) - 1):]  # too short to hold a whole token: none counted twice
    return count


def file_face_count(path: str | Path) -> int | None:
    """The faces a mesh file holds, found without parsing it: binary STL's count (its header),
    PLY's ``element face N``, OFF's counts line, and by counting the lines of OBJ (``f ...``)
    and ASCII STL (``endfacet``). A polygon counts once (trimesh makes it several triangles).
    None for other formats (GLB, GLTF) and for files whose header does not say."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        with open(path, "rb") as file:
            head = file.read(65536)
        if suffix == ".stl":
            size = path.stat().st_size
            if len(head) >= 84 and size == 84 + 50 * int.from_bytes(head[80:84], "little"):
                return int.from_bytes(head[80:84], "little")  # binary: the size agrees
            return _count_in_file(path, b"endfacet")
        if suffix == ".obj":
            return _count_in_file(path, b"\nf ") + head.startswith(b"f ")
        lines = head.decode("latin-1").splitlines()
        if suffix == ".ply":
            for line in lines:
                words = line.split()
                if words[:2] == ["element", "face"] and len(words) == 3:
                    return int(words[2])
                if words[:1] == ["end_header"]:
                    return None
        if suffix == ".off":
            words = [w for line in lines for w in line.split("#")[0].split()]
            if words and words[0].upper().endswith("OFF"):
                return int(words[2])  # OFF, then the vertex, face and edge counts
    except (OSError, ValueError, IndexError):  # unreadable or odd: the loader says why
        return None
    return None


def load_mesh(path: str | Path) -> TaggedMesh:
    """Read a mesh file (scenes flattened with their node transforms) as a tagged mesh.

    Every face gets :data:`IMPORT_MATERIAL`. Raises :class:`MeshError` naming the file when it
    cannot be read, holds no triangles, has NaN/infinite or out-of-range data, or more faces
    than the import could process in this process's memory (:func:`check_import_memory`).
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
    check_import_memory(path, len(loaded.faces))  # before the import's costly steps
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if not np.isfinite(vertices).all():
        raise MeshError(f"{path}: vertex coordinates contain NaN or infinity")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{path}: face indices out of range")
    material = np.full(len(faces), material_index(IMPORT_MATERIAL), dtype=np.int16)
    return TaggedMesh(vertices, faces, material)


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
        "manifold": as_manifold(mesh.vertices, mesh.faces) is not None,
        "unit_size": abs(float(extents.max()) - 1.0) <= INVARIANT_TOLERANCE,
        "centred_on_center_of_mass": float(np.abs(com).max()) <= INVARIANT_TOLERANCE,
        # Within the tolerance: equal sides (a model symmetric under a quarter turn) come out
        # of the rotation and scaling with either one a rounding error longer.
        "extents_sorted": bool(extents[0] >= extents[1] - INVARIANT_TOLERANCE
                               and extents[1] >= extents[2] - INVARIANT_TOLERANCE),
    }


# ----------------------------------------------------------------------------- sampling

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
                 resolution: int = FUSION_RESOLUTION, recentre: bool = False) -> ProcessedModel:
    """Make ``mesh`` a processed model; :class:`MeshError` if an invariant fails.

    ``recentre``: move the mesh to its box's centre first (imported files). Volumes and
    centres of mass are sums over the faces about the origin, so a model far from it (CAD or
    assembly coordinates, a million of its sizes away) cancels them to rounding noise; the
    record of the normalisation keeps the source's coordinates all the same
    (``x_model = s R (x - c) + t = s R x + (t - s R c)``). Generated models, built about
    the origin, are processed as they are, bit for bit as before.
    """
    if isinstance(resolution, bool) or not isinstance(resolution, int | np.integer) \
            or resolution < MIN_FUSION_RESOLUTION:  # -5 failed as a reshape deep inside
        raise ValueError(f"resolution: expected an integer >= {MIN_FUSION_RESOLUTION}, got "
                         f"{resolution!r}")
    centre = np.zeros(3)
    if recentre and len(mesh.vertices):
        centre = (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2
        mesh = TaggedMesh(mesh.vertices - centre, mesh.faces, mesh.face_material)
    solid, route = make_solid(mesh, method, resolution)
    if signed_volume(solid.vertices, solid.faces) <= 0:
        raise MeshError("processed solid has zero volume")
    normalised, norm = normalise(solid, align)
    if recentre:
        norm = Normalisation(norm.rotation, norm.scale,
                             norm.translation - norm.scale * norm.rotation @ centre)
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
        # Ten significant digits, not decimals: a mesh in micrometres scales by about 1e-7,
        # which ten decimals cut to four digits (1e-100 units: to 0).
        "source_to_model": [[float(f"{float(x):.10g}") for x in row]
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
