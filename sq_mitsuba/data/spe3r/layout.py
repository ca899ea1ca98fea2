"""The SPE3R dataset layout: paths, splits, labels and model files, shared by every role.

Layout (our datasets and the SPE3R release alike)::

    <root>/camera.json                    SPEED-style intrinsics
    <root>/splits.csv                     "model,train" / "model,test", no header
    <root>/<model>/labels.json            [{filename, q_vbs2tango_true, r_Vo2To_vbs_true, ...}]
    <root>/<model>/images/<index>.png     8-bit grayscale (.jpg accepted on read)
    <root>/<model>/masks/<index>.png      binary mask of the target alone
    <root>/<model>/models/                model_normalized.obj (+ samples.npz, model_card.json)

Convention: a label's pose maps body to camera (OpenCV frame: x right, y down, z forward),
``x_cam = R x_body + t`` with R the Hamilton matrix of the scalar-first quaternion
``q_vbs2tango_true`` and t = ``r_Vo2To_vbs_true`` in metres. Extra keys (lighting record, seed)
are ignored by SPE3R readers.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image

from sq_mitsuba.io import atomic_path, atomic_write_text

IMAGES, MASKS, MODELS, PROGRESS = "images", "masks", "models", ".progress"
MESH_FILE = "model_normalized.obj"
SAMPLES_FILE = "samples.npz"
#: SPE3R v1.1 validation images of each training model.
VALIDATION_INDICES = frozenset(range(400, 500)) | frozenset(range(900, 1000))


class DatasetError(ValueError):
    """A dataset or model folder that cannot be used; the message names the file."""


# ------------------------------------------------------------------------ small helpers


def read_splits(path: Path) -> dict[str, str]:
    """``splits.csv`` as {model: "train" | "test"}."""
    splits: dict[str, str] = {}
    with open(path, newline="", encoding="utf-8") as handle:
        for line_number, row in enumerate(csv.reader(handle), start=1):
            if not row:
                continue
            if len(row) != 2 or row[1].strip() not in ("train", "test"):
                raise DatasetError(f"{path}:{line_number}: expected 'model,train|test', "
                                   f"got {','.join(row)!r}")
            splits[row[0].strip()] = row[1].strip()
    return splits


def write_splits(out_root: str | Path, rows: Iterable[tuple[str, str]]) -> Path:
    """Write ``splits.csv`` (``model,train|test`` rows, no header) atomically."""
    path = Path(out_root) / "splits.csv"
    atomic_write_text(path, "".join(f"{name},{split}\n" for name, split in rows))
    return path


def write_png(path: Path, array: np.ndarray) -> None:
    """8-bit grayscale PNG, written atomically (deterministic bytes for the same array)."""
    with atomic_path(path) as tmp:
        Image.fromarray(array, mode="L").save(tmp, format="PNG", optimize=False)


def write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    """Float32 channels (H, W) into one OpenEXR file, atomically."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    data = {name: np.ascontiguousarray(array, dtype=np.float32)
            for name, array in channels.items()}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, data) as exr:
            exr.write(str(tmp))


def load_model(model_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertices (V, 3), faces (F, 3) and per-face material tags (F,) or None of a model.

    The OBJ is read in file order (trimesh regroups the faces of multi-material OBJs, which
    would detach them from the per-face tags of ``samples.npz``).
    """
    from sq_mitsuba.data.mesh_io import read_obj
    from sq_mitsuba.render.materials import MATERIALS

    mesh_path = model_dir / MODELS / MESH_FILE
    if not mesh_path.is_file():
        raise DatasetError(f"{mesh_path}: missing")
    try:
        vertices, faces, _ = read_obj(mesh_path)
    except (OSError, ValueError, IndexError) as error:
        raise DatasetError(f"{mesh_path}: cannot read mesh ({error})") from None
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(vertices) < 4 or len(faces) < 4 or not np.isfinite(vertices).all() or \
            faces.min() < 0 or faces.max() >= len(vertices):
        raise DatasetError(f"{mesh_path}: not a usable mesh ({len(vertices)} vertices, "
                           f"{len(faces)} faces)")
    tags = None
    samples_path = model_dir / MODELS / SAMPLES_FILE
    if samples_path.is_file():
        try:
            with np.load(samples_path) as samples:
                face_material = samples["face_material"] if "face_material" in samples else None
        except Exception as error:  # numpy raises several kinds on corrupt archives
            raise DatasetError(f"{samples_path}: cannot read ({error})") from None
        if face_material is not None:
            if len(face_material) != len(faces):
                raise DatasetError(f"{samples_path}: face_material has {len(face_material)} "
                                   f"entries for {len(faces)} faces")
            tags = np.asarray(MATERIALS)[np.asarray(face_material, dtype=np.int64)]
    return vertices, faces, tags



def read_gray(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as image:
            return np.asarray(image.convert("L"))
    except (OSError, ValueError) as error:
        raise DatasetError(f"{path}: cannot read image ({error})") from None


def _resize(array: np.ndarray, size: int, resample: int) -> np.ndarray:
    if array.shape == (size, size):
        return array
    return np.asarray(Image.fromarray(array).resize((size, size), resample))


def balanced_occupancy(points: np.ndarray, inside: np.ndarray, count: int,
                        rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    inside_idx, outside_idx = np.flatnonzero(inside), np.flatnonzero(~inside)
    want_in = min(count // 2, len(inside_idx))
    want_out = count - want_in
    chosen = np.concatenate([
        rng.choice(inside_idx, want_in, replace=False) if want_in else np.empty(0, int),
        rng.choice(outside_idx, want_out, replace=len(outside_idx) < want_out),
    ])
    return points[chosen], inside[chosen]


def model_points(model_dir: Path) -> dict[str, np.ndarray]:
    samples_path = model_dir / MODELS / SAMPLES_FILE
    if samples_path.is_file():
        with np.load(samples_path) as samples:
            return {
                "surface": samples["surface_points"],
                "points": np.concatenate([samples["uniform_points"], samples["near_points"]]),
                "inside": np.concatenate([samples["uniform_inside"],
                                          samples["near_inside"]]).astype(bool),
            }
    # SPE3R release or imported data without our samples: sample the mesh once.
    import trimesh

    from sq_mitsuba.render.depth import RayCaster

    vertices, faces, _ = load_model(model_dir)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    rng = np.random.default_rng(0)
    surface, _ = trimesh.sample.sample_surface(mesh, 100_000, seed=0)
    uniform = rng.uniform(-0.5, 0.5, (50_000, 3))
    near = surface[:50_000] + rng.normal(scale=0.01, size=(50_000, 3))
    points = np.concatenate([uniform, near])
    inside = RayCaster(vertices, faces).inside(points)
    return {"surface": np.asarray(surface), "points": points, "inside": np.asarray(inside)}


def dataset_models(root: Path) -> list[str]:
    """The models named in ``root/splits.csv``, sorted."""
    return sorted(read_splits(root / "splits.csv"))
