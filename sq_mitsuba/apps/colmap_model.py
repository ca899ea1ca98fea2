"""A pass's poses as a COLMAP sparse model (text format), to start structure from motion.

``predict --sequence`` writes one into ``colmap/`` beside its other files: ``cameras.txt``
(one PINHOLE camera, the frames' intrinsics), ``images.txt`` (each frame's pose, no
keypoints) and ``points3D.txt`` (empty: the shared assembly is ``sequence.glb``). COLMAP reads
such a folder as a model (``colmap model_converter``, the GUI's import), and with a database of
the same images, features extracted and matched, ``colmap point_triangulator`` triangulates
the frames' points at these poses and ``colmap bundle_adjuster`` refines them: the assembly's
poses as the start of the multi-view reconstruction the paper's method is meant to kick-start.

Convention: COLMAP's image pose is world -> camera, ``x_cam = R(q) x_world + t``, its
quaternion ``(QW, QX, QY, QZ)`` Hamilton's, its camera frame x right, y down, z forward, and
the centre of the top-left pixel at (0.5, 0.5): the project's own conventions for the body ->
camera pose (``q_vbs2tango``, ``r_Vo2To_vbs``; :mod:`sq_mitsuba.geometry.camera`), so the
target's body frame is the model's world frame and the files hold the poses unchanged.
Lengths are the pose files' (unit size, or metres with ``--target-size``).

The image identifiers are 1 to N in the frames' order. ``point_triangulator`` matches the
model's images to the database's by identifier: extract the features of the frames in that
order (file names that sort in it do) or renumber the model to the database's identifiers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["COLMAP_FILES", "read_colmap_model", "write_colmap_model"]

COLMAP_FILES = ("cameras.txt", "images.txt", "points3D.txt")
"""The files of a COLMAP text model, as :func:`write_colmap_model` writes them."""


def write_colmap_model(folder: str | Path, camera: Any, names: Sequence[str],
                       quaternions: Any, translations: Any) -> list[Path]:
    """Write the COLMAP text model of N frames seen by one pinhole camera (each file
    atomically); returns the files.

    Args:
        camera: a :class:`~sq_mitsuba.geometry.camera.Camera` (the frames' own size).
        names: the N image file names (COLMAP's ``NAME``: relative to its image folder).
        quaternions: (N, 4) body -> camera rotations as (w, x, y, z), Hamilton's.
        translations: (N, 3) the body's origin in the camera frame.

    Raises:
        ValueError: one line: shapes that differ from (N, 4) and (N, 3), a value that is not
            finite, a quaternion far from unit length, a name empty, twice or with white
            space (COLMAP's text lines are split at spaces).
    """
    from sq_mitsuba.io import atomic_write_text

    q = np.asarray(quaternions, dtype=np.float64)
    t = np.asarray(translations, dtype=np.float64)
    count = len(names)
    if q.shape != (count, 4) or t.shape != (count, 3):
        raise ValueError(f"quaternions, translations: expected ({count}, 4) and ({count}, 3) "
                         f"for {count} names, got {q.shape} and {t.shape}")
    if not (np.isfinite(q).all() and np.isfinite(t).all()):
        raise ValueError("quaternions, translations: every value must be finite")
    norms = np.linalg.norm(q, axis=1)
    if count and np.abs(norms - 1).max() > 1e-3:
        k = int(np.abs(norms - 1).argmax())
        raise ValueError(f"quaternions: quaternion {k} has length {norms[k]:.6g}, not 1")
    for k, name in enumerate(names):
        if not name or any(c.isspace() for c in name) or name in names[:k]:
            raise ValueError(f"names: {name!r} (image {k}) must be non-empty, without white "
                             "space and given once")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cameras = ("# Camera list with one line of data per camera:\n"
               "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
               "# Number of cameras: 1\n"
               f"1 PINHOLE {camera.width} {camera.height} {camera.fx!r} {camera.fy!r} "
               f"{camera.cx!r} {camera.cy!r}\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {count}, mean observations per image: 0"]
    for k, name in enumerate(names):
        unit = q[k] / norms[k]
        lines.append(" ".join([str(k + 1), *(repr(float(v)) for v in unit),
                               *(repr(float(v)) for v in t[k]), "1", name]))
        lines.append("")  # no keypoints
    points = ("# 3D point list with one line of data per point:\n"
              "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
              "# Number of points: 0, mean track length: 0\n")
    files = []
    for file_name, text in zip(COLMAP_FILES, (cameras, "\n".join(lines) + "\n", points),
                               strict=True):
        atomic_write_text(folder / file_name, text)
        files.append(folder / file_name)
    return files


def read_colmap_model(folder: str | Path) -> tuple[Any, list[tuple[str, np.ndarray,
                                                                    np.ndarray]]]:
    """Read a COLMAP text model of one PINHOLE camera (as :func:`write_colmap_model` writes
    it): the :class:`~sq_mitsuba.geometry.camera.Camera` and, per image in the file's
    order, (name, quaternion (4,) w first, translation (3,)).

    Raises:
        ValueError: one line naming the file and line: a file missing, another camera model
            or more than one camera, a line that is not a camera's or an image's.
    """
    from sq_mitsuba.geometry.camera import Camera

    folder = Path(folder)
    rows: dict[str, list[list[str]]] = {}
    for file_name in COLMAP_FILES[:2]:
        path = folder / file_name
        if not path.is_file():
            raise ValueError(f"{path}: no such file (a COLMAP text model has {file_name})")
        lines = path.read_text(encoding="utf-8").splitlines()
        rows[file_name] = [line.split() for line in lines if not line.startswith("#")]
    cameras = [row for row in rows["cameras.txt"] if row]
    if len(cameras) != 1 or len(cameras[0]) != 8 or cameras[0][1] != "PINHOLE":
        raise ValueError(f"{folder / 'cameras.txt'}: expected one PINHOLE camera (CAMERA_ID "
                         f"PINHOLE W H fx fy cx cy), got {cameras}")
    _, _, width, height, fx, fy, cx, cy = cameras[0]
    camera = Camera(float(fx), float(fy), float(cx), float(cy), int(width), int(height))
    images = []
    lines = rows["images.txt"]
    for k in range(0, len(lines), 2):  # a pose line, then its keypoints' line
        row = lines[k]
        if len(row) != 10:
            raise ValueError(f"{folder / 'images.txt'}: image line {k // 2 + 1} has "
                             f"{len(row)} fields, not 10 (IMAGE_ID QW QX QY QZ TX TY TZ "
                             "CAMERA_ID NAME)")
        values = np.array([float(v) for v in row[1:8]])
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"{folder / 'images.txt'}: image {row[9]}: a pose value is not "
                             "finite")
        images.append((row[9], values[:4], values[4:]))
    return camera, images
