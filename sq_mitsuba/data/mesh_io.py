"""The project's one mesh type, its OBJ reader and writer, and a glTF writer for viewers.

Convention: a :class:`TaggedMesh` carries one material index per face (into
:data:`sq_mitsuba.render.materials.MATERIALS`). A processed model's OBJ is one object with
shared vertices and no ``usemtl`` groups, so a reader that keeps its vertices
(``trimesh.load(path, force="mesh", process=False)``) gets the one closed surface (merging
vertices by position can pinch it where two parts touch at a point, where the union keeps two
vertices); its per-face tags live beside it, as
``face_material`` in ``samples.npz`` (in OBJ face order), and ``model_normalized.glb`` carries
them as glTF materials for viewers and Blender. :func:`read_obj` still reads the ``usemtl``
groups of older files and of other tools.
"""

from __future__ import annotations

import hashlib
import json
import math
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sq_mitsuba.render.materials import MATERIALS, MTL_COLOUR

SAMPLES_FILE = "samples.npz"
"""File beside a processed model's OBJ holding its samples and ``face_material`` tags."""


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
        """SHA-256 of the geometry and materials (vertices rounded to 1e-9): an identity of
        the mesh as made, not of its OBJ (written to 7 decimals, read back it digests
        otherwise)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(np.round(self.vertices, 9), dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.faces, dtype="<i8").tobytes())
        h.update(np.ascontiguousarray(self.face_material, dtype="<i2").tobytes())
        return h.hexdigest()


def read_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, triangles (polygons fanned) and per-face material indices of an OBJ.

    ``usemtl`` names that are material tags are kept; anything else reads as aluminium.

    Raises:
        FileNotFoundError: no such file; IsADirectoryError: ``<path>: is a folder, not a
            mesh file``; ValueError: no triangles, a face index out of range or a vertex not
            finite.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a folder, not a mesh file")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    vertices, faces, tags = [], [], []
    current = MATERIALS.index("aluminium")
    with open(path, encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, 1):
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                # A short vertex line dropped would shift every later face onto other vertices.
                if len(parts) < 4:
                    raise ValueError(f"{path}:{number}: a vertex needs 3 coordinates, got "
                                     f"{len(parts) - 1}")
                vertices.append([_number(float, x, path, number) for x in parts[1:4]])
            elif parts[0] == "usemtl" and len(parts) > 1:
                name = parts[1]
                current = MATERIALS.index(name) if name in MATERIALS else MATERIALS.index(
                    "aluminium")
            elif parts[0] == "f" and len(parts) >= 4:
                idx = [_number(int, p.split("/")[0], path, number) for p in parts[1:]]
                if 0 in idx:  # OBJ counts from 1 (negative: back from the last vertex read)
                    raise ValueError(f"{path}:{number}: face index 0 (OBJ indices start at 1)")
                idx = [i - 1 if i > 0 else len(vertices) + i for i in idx]
                if min(idx) < 0:
                    raise ValueError(f"{path}:{number}: a relative face index reaches before "
                                     "the first vertex")
                for k in range(1, len(idx) - 1):
                    faces.append([idx[0], idx[k], idx[k + 1]])
                    tags.append(current)
    if not vertices or not faces:
        raise ValueError(f"{path}: no triangles")
    points, triangles = np.asarray(vertices, float), np.asarray(faces, np.int64)
    outside = (triangles < 0) | (triangles >= len(points))
    if outside.any():
        face = int(np.argwhere(outside)[0, 0])
        raise ValueError(f"{path}: triangle {face} refers to a vertex it does not have (the "
                         f"file has {len(points)} vertices)")
    if not np.isfinite(points).all():
        raise ValueError(f"{path}: a vertex is not finite (NaN or infinite)")
    return points, triangles, np.asarray(tags, np.int16)


def _number(kind: type, text: str, path: Path, line: int) -> float | int:
    """``kind(text)`` (float or int) or a ValueError naming the file and line."""
    try:
        return kind(text)
    except ValueError:
        raise ValueError(f"{path}:{line}: {text!r} is not a number") from None


def check_face_material(face_material: np.ndarray, faces: int, where: Path | str,
                        mesh: Path | str) -> np.ndarray:
    """``face_material`` (F,) as int16 indices into :data:`MATERIALS`, or a ValueError naming
    ``where``: another length than the mesh's ``faces``, not integers, or an index outside
    0 .. len(MATERIALS) - 1 (an index past the end would stop a render, a negative one would
    silently pick another material)."""
    values = np.asarray(face_material)
    if values.ndim != 1:
        raise ValueError(f"{where}: face_material has shape {values.shape}, expected "
                         f"({faces},): one index per face of {mesh}")
    if len(values) != faces:
        raise ValueError(f"{where}: face_material has {len(values)} entries for the {faces} "
                         f"faces of {mesh} (one of the two files cut short or from another "
                         "model)")
    if len(values) and (values.dtype.kind not in "iu" or values.min() < 0
                        or values.max() >= len(MATERIALS)):
        raise ValueError(f"{where}: face_material holds {values.dtype} values outside the "
                         f"material indices 0..{len(MATERIALS) - 1}")
    return values.astype(np.int16)


NOT_AN_NPZ = "corrupt or truncated: not a valid .npz file"
"""What a ``.npz`` file numpy cannot read is said to be (not numpy's own words)."""

MAX_SAMPLE_POINTS = 10_000_000
"""Most points of one point set of a ``samples.npz`` that readers decode: five times the
largest set ``models generate --points`` writes (2,000,000 each), so no model of the tool's is
near it, while a member that a small compressed archive expands to gigabytes is refused."""
MAX_NPZ_VALUES = 3 * MAX_SAMPLE_POINTS
"""Most values of one ``.npz`` array that the readers decode (MAX_SAMPLE_POINTS points of 3
coordinates: 240 MB as float64); each member's ``.npy`` header is read first."""
MAX_NPZ_ITEMSIZE = 16
"""Widest value (bytes) of an ``.npz`` array that the readers decode (the tool's are at most
8: float64, int64)."""


class NpzArrayTooLarge(ValueError):
    """An ``.npz`` member larger than a reader's bound, refused from its header alone."""


def npz_array_header(archive: Any, key: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of array ``key`` of an open ``np.load`` archive, from its ``.npy``
    header: the member's first bytes only are decompressed. A member that is no ``.npy``
    array (which numpy would return as its raw bytes, read whole) is a ValueError."""
    name = key if key in archive.zip.namelist() else f"{key}.npy"  # NpzFile's own lookup
    with archive.zip.open(name) as member:
        version = np.lib.format.read_magic(member)  # ValueError for another file
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(member)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(member)
        else:  # 3.0 holds non-Latin-1 field names: never an array of the tool's
            raise ValueError(f"{key}: .npy format version {version} not read")
    return tuple(int(n) for n in shape), np.dtype(dtype)


def check_npz_array(archive: Any, key: str, path: str | Path,
                    limit: int = MAX_NPZ_VALUES) -> tuple[int, ...]:
    """The shape of array ``key`` of an open ``np.load`` archive, read from its header, where
    it holds at most ``limit`` values of at most :data:`MAX_NPZ_ITEMSIZE` bytes; else a
    one-line :class:`NpzArrayTooLarge` naming ``path`` and the array, before any of its data
    is decompressed (a 1 MB archive of zeros can expand to gigabytes)."""
    shape, dtype = npz_array_header(archive, key)
    count = math.prod(shape)
    if count > limit:
        raise NpzArrayTooLarge(f"{path}: {key}: {count:,} values (shape {shape}), more than "
                               f"the {limit:,} this tool reads; refused before reading it")
    if dtype.itemsize > MAX_NPZ_ITEMSIZE:
        raise NpzArrayTooLarge(f"{path}: {key}: values of {dtype.itemsize:,} bytes ({dtype}), "
                               f"wider than the {MAX_NPZ_ITEMSIZE} this tool reads; refused "
                               "before reading it")
    return shape


def read_npz(path: str | Path, keys: Iterable[str] | None = None,
             limits: Mapping[str, int] | None = None) -> dict[str, np.ndarray]:
    """The arrays ``keys`` (default: all) of the ``.npz`` archive ``path``; a key the archive
    lacks is left out (what a missing array means is the caller's to say). Each array's size
    is checked from its header before it is read: at most ``limits[key]`` values (default
    :data:`MAX_NPZ_VALUES`), see :func:`check_npz_array`.

    Raises:
        FileNotFoundError: no such file.
        NpzArrayTooLarge: an array beyond its bound (a ValueError naming file and array).
        ValueError: ``"<path>: corrupt or truncated: not a valid .npz file"`` for anything
            numpy cannot read: not numpy's own message, which for a file that is no archive
            advises loading it "unsafely" with ``allow_pickle``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    limits = limits or {}
    try:
        with np.load(path) as archive:  # allow_pickle stays False: a library is not trusted
            wanted = archive.files if keys is None else [k for k in keys if k in archive.files]
            for key in wanted:
                check_npz_array(archive, key, path, limits.get(key, MAX_NPZ_VALUES))
            return {key: np.asarray(archive[key]) for key in wanted}
    except NpzArrayTooLarge:
        raise
    except Exception:  # numpy, zipfile and zlib raise many kinds for damaged archives
        raise ValueError(f"{path}: {NOT_AN_NPZ}") from None


def read_tagged_obj(path: str | Path) -> TaggedMesh:
    """A processed model's OBJ with its per-face material tags.

    Tags come from ``face_material`` in the ``samples.npz`` beside the OBJ (how processed
    models store them); without that file (or that array) they are the OBJ's own ``usemtl``
    tags, as :func:`read_obj` reads them. Raises ``ValueError`` naming the file when the tag
    count does not match the face count.
    """
    path = Path(path)
    vertices, faces, tags = read_obj(path)
    samples = path.parent / SAMPLES_FILE
    if samples.is_file():  # one tag per face: a longer array is refused before it is read
        face_material = read_npz(samples, ["face_material"],
                                 {"face_material": len(faces)}).get("face_material")
        if face_material is not None:
            tags = check_face_material(face_material, len(faces), samples, path)
    return TaggedMesh(vertices, faces, tags)


def obj_text(mesh: TaggedMesh) -> str:
    """Wavefront OBJ: one object, shared vertices, faces in the mesh's order, no materials.

    Convention: no ``usemtl`` groups, because readers split an OBJ at them (duplicating the
    seam vertices, so the surface is no longer closed); the tags are stored elsewhere (see the
    module docstring).
    """
    lines = ["# sq_mitsuba processed model: unit size, centre of mass at origin",
             f"# per-face material tags: face_material in {SAMPLES_FILE}; "
             "colours: model_normalized.glb"]
    lines += [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in mesh.vertices]
    lines += [f"f {a} {b} {c}" for a, b, c in mesh.faces + 1]
    return "\n".join(lines) + "\n"


def _srgb_to_linear(c: float) -> float:
    """glTF colour factors are linear; the viewer colours of MTL_COLOUR are sRGB."""
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def glb_bytes(mesh: TaggedMesh, name: str = "model") -> bytes:
    """Binary glTF 2.0 of a tagged mesh: one node, one mesh, one primitive per material.

    All primitives index the same vertex array, so the surface stays connected; each gets a
    material named after its tag, coloured with :data:`MTL_COLOUR` (viewer colours only).
    No normals are stored: glTF viewers then shade each triangle flat, as the model is.
    Coordinates are the model frame as is (the OBJ's), not re-oriented to glTF's +Y up.
    """
    positions = np.ascontiguousarray(mesh.vertices, dtype="<f4")
    tags = np.asarray(mesh.face_material)
    used = [int(t) for t in np.unique(tags)]
    blobs = [positions.tobytes()]
    offset = len(blobs[0])
    accessors: list[dict] = [{
        "bufferView": 0, "componentType": 5126, "count": len(positions), "type": "VEC3",
        "min": positions.min(axis=0).tolist(), "max": positions.max(axis=0).tolist()}]
    buffer_views: list[dict] = [{"buffer": 0, "byteOffset": 0, "byteLength": offset,
                                 "target": 34962}]
    primitives, materials = [], []
    for k, tag in enumerate(used):
        indices = np.ascontiguousarray(mesh.faces[tags == tag].reshape(-1), dtype="<u4")
        blob = indices.tobytes()
        buffer_views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob),
                             "target": 34963})
        accessors.append({"bufferView": k + 1, "componentType": 5125, "count": len(indices),
                          "type": "SCALAR"})
        primitives.append({"attributes": {"POSITION": 0}, "indices": k + 1, "material": k,
                           "mode": 4})
        colour = [round(_srgb_to_linear(c), 6) for c in MTL_COLOUR[MATERIALS[tag]]]
        materials.append({"name": MATERIALS[tag], "pbrMetallicRoughness": {
            "baseColorFactor": [*colour, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.8}})
        blobs.append(blob)
        offset += len(blob)
    document = {
        "asset": {"version": "2.0", "generator": "sq_mitsuba"},
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": name}],
        "meshes": [{"name": name, "primitives": primitives}], "materials": materials,
        "accessors": accessors, "bufferViews": buffer_views, "buffers": [{"byteLength": offset}],
    }
    # Chunks are padded to 4 bytes: JSON with spaces, binary with zeros (glTF 2.0 rule).
    text = json.dumps(document, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    binary = b"".join(blobs)  # every blob is a multiple of 4 bytes long
    total = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join([struct.pack("<4sII", b"glTF", 2, total),
                     struct.pack("<I4s", len(text), b"JSON"), text,
                     struct.pack("<I4s", len(binary), b"BIN\x00"), binary])
