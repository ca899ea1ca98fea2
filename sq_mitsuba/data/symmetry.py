"""Half-turn symmetries of a model: which body-frame rotations map its surface onto itself.

A rotation S with ``S(model) = model`` makes the poses R and R S show the same image, so a pose
loss or error must not tell them apart (:func:`sq_mitsuba.model.losses.pose_loss`,
:func:`sq_mitsuba.geometry.metrics.rotation_error_deg`). Processed models keep the axes they
were built along, ordered by extent (x >= y >= z, centre of mass at the origin), so the
candidates are the half turns about the body axes x, y and z (a symmetry about an axis the
model was not built along is not looked for); each is tested by the Chamfer distance between
the surface and its turned copy.

Convention: the distance is the occnet Chamfer distance, ``0.5 (mean_a min_b |a - b| +
mean_b min_a |a - b|)`` (Euclidean, nearest neighbours from KD-trees), between two disjoint
random halves A and B of the surface points, one of them turned, minus the same distance with
neither turned: ``d(S) = chamfer(A, S B) - chamfer(A, B)``, in units of the longest side of
the points' bounding box (1 for processed models). The subtracted term is what sampling alone
costs (two samples of one surface never coincide point for point): 0.002 to 0.011 at 20,000
points on generated spacecraft, 0.001 to 0.005 at 100,000, so without it the decision would
depend on the point count and the surface area.

Threshold (:data:`DEFAULT_THRESHOLD` = 0.01), measured on 56 generated spacecraft (catalogue
seeds 0 and 1, all 14 archetypes, 20,000 points each, 168 half turns): the values form a
continuum from 0.0000 (symmetric by construction, e.g. sunshade observatories about z) up to
0.0074 (layouts symmetric apart from small appendages), then 0.0091 (a twin-wing spacecraft
about x and z), then a gap to 0.0112 (a truss science craft), 0.0123 (a cubesat), 0.0157 and
on up to 0.21 (single wings, tri-wings, dish probes). 0.01 sits in that gap: near-symmetric
models count as symmetric, since their turned surface lies on average within 1 % of the
model's size of the original. 69 half turns pass; 24 models have one, 15 all three, 17
none, and none has exactly two. Two half turns about perpendicular axes compose to the third,
so where two pass the third is counted too (:func:`passing_axes`): the symmetries are a group.
Distances at 20,000 points are within about 0.001 of those at 100,000.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sq_mitsuba.io import atomic_write_json, read_json

__all__ = [
    "DEFAULT_THRESHOLD",
    "HALF_TURNS",
    "SYMMETRIES_FILE",
    "detect_symmetries",
    "model_symmetries",
    "passing_axes",
    "stack_symmetries",
    "symmetry_distances",
]

#: Largest floor-corrected Chamfer distance (in units of the model's longest side) of a
#: half turn that counts as a symmetry; see the module docstring for the measurements.
DEFAULT_THRESHOLD = 0.01
#: Half turns about the body axes, the candidate symmetries.
HALF_TURNS: dict[str, np.ndarray] = {
    "x": np.diag([1.0, -1.0, -1.0]),
    "y": np.diag([-1.0, 1.0, -1.0]),
    "z": np.diag([-1.0, -1.0, 1.0]),
}
#: Points used at most (a seeded random subset of larger clouds; samples.npz holds 100,000).
#: The floor-corrected distances at 20,000 points match those at 100,000 to about 0.001, and
#: a half turn far from a symmetry makes the KD-tree searches long: 0.1 to 1 s per model here
#: against 12 to 40 s at 100,000.
DEFAULT_MAX_POINTS = 20_000
#: Fewer points than this make the floor correction itself too noisy to trust.
MIN_POINTS = 1_000
SYMMETRIES_FILE = "symmetries.json"
JSON_FORMAT = "sq_mitsuba.data.symmetry"
JSON_VERSION = 1


def _check_points(surface_points: Any) -> np.ndarray:
    points = np.asarray(surface_points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"surface_points: expected shape (N, 3), got {points.shape}")
    if len(points) < MIN_POINTS:
        raise ValueError(f"surface_points: need at least {MIN_POINTS} points, got {len(points)}")
    if not np.isfinite(points).all():
        raise ValueError("surface_points: contains NaN or infinite values")
    return points


def _chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """occnet Chamfer distance 0.5 (mean_a min_b |a - b| + mean_b min_a |a - b|)."""
    from scipy.spatial import cKDTree

    forward, _ = cKDTree(b).query(a, k=1)
    backward, _ = cKDTree(a).query(b, k=1)
    return 0.5 * (float(forward.mean()) + float(backward.mean()))


def symmetry_distances(surface_points: np.ndarray, max_points: int = DEFAULT_MAX_POINTS,
                       seed: int = 0) -> dict[str, float]:
    """Floor-corrected Chamfer distance of each half turn, relative to the model's size.

    Args:
        surface_points: (N, 3) points on the surface in the body frame, N >= 1,000.
        max_points: use a random subset of this many points when there are more.
        seed: seed of the subset and of the split into halves.

    Returns:
        ``{"x": d, "y": d, "z": d, "floor": f}``: d(S) = (chamfer(A, S B) - chamfer(A, B)) /
        size and f = chamfer(A, B) / size, with A, B disjoint random halves and size the
        longest side of the points' bounding box.
    """
    points = _check_points(surface_points)
    if isinstance(max_points, bool) or not isinstance(max_points, int) or \
            max_points < MIN_POINTS:
        raise ValueError(f"max_points: expected an integer >= {MIN_POINTS}, got {max_points!r}")
    size = float(np.ptp(points, axis=0).max())
    if size <= 0:
        raise ValueError("surface_points: all points coincide")
    order = np.random.default_rng(seed).permutation(len(points))[:max_points]
    half = len(order) // 2
    first, second = points[order[:half]], points[order[half:2 * half]]
    floor = _chamfer(first, second)
    distances = {axis: (_chamfer(first, second @ turn.T) - floor) / size
                 for axis, turn in HALF_TURNS.items()}
    return {**distances, "floor": floor / size}


def detect_symmetries(surface_points: np.ndarray, threshold: float = DEFAULT_THRESHOLD,
                      max_points: int = DEFAULT_MAX_POINTS) -> list[np.ndarray]:
    """The model's symmetries among the half turns about its body axes.

    Args:
        surface_points: (N, 3) surface points in the model's body frame
            (docs/conventions.md).
        threshold: largest :func:`symmetry_distances` value of a symmetry (default
            :data:`DEFAULT_THRESHOLD`, in units of the model's longest side).
        max_points: see :func:`symmetry_distances`.

    Returns:
        3 x 3 rotation matrices, the identity first, then the half turns about x, y, z that
        pass, in that order.
    """
    if isinstance(threshold, bool) or not isinstance(threshold, int | float) or \
            not math.isfinite(threshold) or threshold < 0:
        raise ValueError(f"threshold: expected a non-negative number, got {threshold!r}")
    distances = symmetry_distances(surface_points, max_points)
    return [np.eye(3)] + [HALF_TURNS[axis].copy()
                          for axis in passing_axes(distances, threshold)]


def passing_axes(distances: dict[str, float], threshold: float) -> list[str]:
    """The axes (of "x", "y", "z", in that order) whose half turn is a symmetry: distance
    within ``threshold``, and the third where two pass (their product: a group)."""
    axes = [axis for axis in HALF_TURNS if distances[axis] <= threshold]
    return list(HALF_TURNS) if len(axes) == 2 else axes


def _check_matrices(matrices: Any, where: str) -> np.ndarray:
    """(S, 3, 3) rotations with the identity first, or ValueError naming ``where``."""
    try:
        array = np.asarray(matrices, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected a list of 3 x 3 matrices") from None
    if array.ndim != 3 or array.shape[1:] != (3, 3) or len(array) < 1:
        raise ValueError(f"{where}: expected a list of 3 x 3 matrices, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{where}: contains NaN or infinite values")
    identity = np.eye(3)
    orthogonal = np.abs(array @ array.transpose(0, 2, 1) - identity).max() <= 1e-6
    if not orthogonal or not np.allclose(np.linalg.det(array), 1.0, atol=1e-6):
        raise ValueError(f"{where}: every matrix must be a rotation")
    if not np.allclose(array[0], identity, atol=1e-9):
        raise ValueError(f"{where}: the first matrix must be the identity")
    return array


def _source_of(model_dir: Path) -> Path:
    """The file a model's surface points come from: samples.npz, else the mesh."""
    from sq_mitsuba.data.spe3r.layout import MESH_FILE, MODELS, SAMPLES_FILE

    samples_path = model_dir / MODELS / SAMPLES_FILE
    return samples_path if samples_path.is_file() else model_dir / MODELS / MESH_FILE


def _surface_points_of(model_dir: Path) -> np.ndarray:
    """The model's surface points: samples.npz, or 100,000 samples of its mesh."""
    from sq_mitsuba.data.solids import sample_triangles
    from sq_mitsuba.data.spe3r.layout import MODELS, SAMPLES_FILE, load_model, read_samples

    samples_path = model_dir / MODELS / SAMPLES_FILE
    if samples_path.is_file():
        points = read_samples(samples_path, ("surface_points",))["surface_points"]
        return np.asarray(points, dtype=np.float64)
    vertices, faces, _ = load_model(model_dir)
    points, _ = sample_triangles(vertices, faces, DEFAULT_MAX_POINTS, np.random.default_rng(0))
    return points


def _read_record(path: Path) -> np.ndarray:
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != JSON_FORMAT:
        raise ValueError(f"{path}: not a symmetries file (format != {JSON_FORMAT!r})")
    return _check_matrices(data.get("matrices"), f"{path}: matrices")


def _cache_file(cache_dir: Path, model_dir: Path, source: Path) -> Path:
    """The cache file of a model's symmetries: named by the model and a digest of the file
    its points come from (and of the threshold), so an edited model gets a new one."""
    import hashlib

    digest = hashlib.sha256(f"{JSON_VERSION}:{DEFAULT_THRESHOLD}:{source.name}:".encode())
    with open(source, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return Path(cache_dir) / f"{model_dir.name}-{digest.hexdigest()[:16]}.json"


def model_symmetries(model_dir: str | Path, cache_dir: str | Path | None = None,
                     write: bool = False) -> np.ndarray:
    """Symmetries (S, 3, 3) of the model in ``model_dir`` (a folder of the SPE3R layout).

    Reads ``<model_dir>/models/symmetries.json`` when present (a record that came with the
    model: delete it to recompute), else ``cache_dir``'s record of the model when there is
    one. Otherwise detects them (:func:`detect_symmetries`, default threshold) from the
    surface points of ``models/samples.npz``, or from points sampled on
    ``models/model_normalized.obj`` when there is none, and writes the record atomically:
    ``{"matrices": [...], "threshold": t, "distances": {"x": d, "y": d, "z": d},
    "floor": f, "points": n, ...}``.

    Convention: reading a model never changes its folder. The record goes to ``cache_dir``
    (e.g. a training run's cache), as ``<model>-<digest>.json`` with the digest of the file
    the points come from, so an edited model is analysed again; into the model folder only
    with ``write`` (for whoever owns that folder, e.g. a library being built); nowhere
    without either. A record that cannot be written is skipped (with a warning): the
    symmetries are returned all the same.

    Raises:
        FileNotFoundError: no ``models`` folder.
        ValueError: a malformed symmetries file in the model folder, unreadable samples (a
            missing array, NaN), a missing or unusable mesh where there are no samples, or
            too few points (the message names the file or the points).
    """
    from sq_mitsuba.data.spe3r.layout import MODELS

    model_dir = Path(model_dir)
    path = model_dir / MODELS / SYMMETRIES_FILE
    if path.is_file():
        return _read_record(path)
    if not (model_dir / MODELS).is_dir():
        raise FileNotFoundError(f"{model_dir / MODELS}: missing")
    cached = None
    if cache_dir is not None and _source_of(model_dir).is_file():
        cached = _cache_file(Path(cache_dir), model_dir, _source_of(model_dir))
        if cached.is_file():
            try:
                return _read_record(cached)
            except ValueError:  # a damaged cache file: analyse again and replace it
                pass
    points = _surface_points_of(model_dir)
    distances = symmetry_distances(points)
    axes = passing_axes(distances, DEFAULT_THRESHOLD)
    matrices = [np.eye(3)] + [HALF_TURNS[a] for a in axes]
    record = {
        "format": JSON_FORMAT,
        "version": JSON_VERSION,
        "matrices": [m.tolist() for m in matrices],
        "axes": axes,
        "threshold": DEFAULT_THRESHOLD,
        "distances": {a: round(distances[a], 6) for a in HALF_TURNS},
        "floor": round(distances["floor"], 6),
        "points": min(len(points), DEFAULT_MAX_POINTS),
        "metric": "occnet Chamfer between halves A and S B minus that of A and B, "
                  "over the longest side",
    }
    for target in ([path] if write else []) + ([cached] if cached is not None else []):
        try:
            atomic_write_json(target, record)
        except OSError as error:
            warnings.warn(f"{target}: not written ({error})", stacklevel=2)
    return np.stack(matrices)


def stack_symmetries(sets: Sequence[Any]) -> np.ndarray:
    """Per-model symmetry sets (S_i, 3, 3) -> one (B, S_max, 3, 3) array.

    Shorter sets are padded with identities, which change no minimum over the set (the
    identity is always a member), so :func:`sq_mitsuba.model.losses.pose_loss` can take
    a batch of models with different symmetries.
    """
    arrays = [_check_matrices(s, f"sets[{i}]") for i, s in enumerate(sets)]
    if not arrays:
        raise ValueError("sets: expected at least one symmetry set")
    longest = max(len(a) for a in arrays)
    padded = np.tile(np.eye(3), (len(arrays), longest, 1, 1))
    for index, array in enumerate(arrays):
        padded[index, :len(array)] = array
    return padded
