"""Batched assemblies of superquadric primitives: occupancy, surface samples, meshes, files.

Convention:
    A batch of B assemblies of M primitives is a tensor ``params`` of shape (B, M, 16); per
    primitive, in this order:

    ====================  =======  ================================================
    field                 columns  meaning
    ====================  =======  ================================================
    ``size``              0:3      semi-axes (a1, a2, a3) > 0
    ``shape``             3:5      (e1, e2) in [0, 1] (dual superquadric exponents)
    ``translation``       5:8      primitive origin in the assembly frame
    ``rotation_6d``       8:14     first two rows of R (see :mod:`sq_mitsuba.geometry.rotation`)
    ``taper``             14:16    (k1, k2), |k| < 1
    ====================  =======  ================================================

    A primitive point maps to the assembly frame as ``x = R @ taper(x_primitive) + t``; query
    points go the other way (``untaper(R^T (x - t))``) before the inside-outside function.
    The assembly is the union of its primitives: its occupancy is the max over primitives.
"""

from __future__ import annotations

import json
import math
import numbers
import operator
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from sq_mitsuba.checks import check_rotations, check_tensor, value_checks, value_checks_enabled
from sq_mitsuba.geometry.icosphere import icosphere_angles, icosphere_faces
from sq_mitsuba.geometry.rotation import (
    degenerate_6d,
    matrix_to_rotation_6d,
    rotation_6d_to_matrix,
)
from sq_mitsuba.geometry.superquadric import (
    dual_field,
    dual_scales,
    first_derivatives_only,
    surface_points_dual,
    taper,
    untaper,
)
from sq_mitsuba.io import atomic_path, atomic_write_text, read_json

__all__ = ["FIELDS", "NUM_PARAMS", "Assembly", "ParameterRanges"]

NUM_PARAMS = 16
#: Column slices of the 16 numbers per primitive, in order.
FIELDS: dict[str, slice] = {
    "size": slice(0, 3),
    "shape": slice(3, 5),
    "translation": slice(5, 8),
    "rotation_6d": slice(8, 14),
    "taper": slice(14, 16),
}
JSON_FORMAT = "sq_mitsuba.geometry.assembly"
JSON_VERSION = 1
MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl")
#: The dtypes a description names (load refused the float16 files save wrote); exact in JSON.
_DTYPES = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32,
           "float64": torch.float64}


@dataclass(frozen=True)
class ParameterRanges:
    """How raw network outputs are squashed into valid parameters (authors' implementation).

    size = size_min + size_span * sigmoid, shape = sigmoid, translation = translation_scale *
    tanh, taper = taper_scale * tanh (0.9 rather than the paper's 1 keeps the cross-section
    from collapsing to a point), rotation = the raw 6D vector.
    """

    size_min: float = 0.01
    size_span: float = 0.49
    translation_scale: float = 0.5
    taper_scale: float = 0.9


class Assembly:
    """A batch of B superquadric assemblies with M primitives each.

    Build one with :meth:`from_raw` (network outputs), :meth:`from_values` (explicit fields) or
    the constructor (a ready (B, M, 16) tensor). Gradients flow from every output back to
    ``params``. The constructor refuses sizes not positive, shape exponents outside [0, 1],
    tapers of magnitude 1 or more and degenerate 6D rotations, unless value checks are off
    (:func:`sq_mitsuba.checks.value_checks`: the training step's, as these read the values).
    """

    def __init__(self, params: Tensor):
        check_tensor("params", params, (None, NUM_PARAMS), min_dims=3)
        if params.dim() != 3 or params.shape[1] == 0:  # M = 0 failed later, inside torch
            raise ValueError(f"params: expected shape (B, M, 16) with M >= 1 primitives, got "
                             f"{tuple(params.shape)}")
        self.params = params
        if not value_checks_enabled():  # each check below waits for a GPU: hot loops skip them
            return
        with torch.no_grad():
            if bool((self.size <= 0).any()):
                raise ValueError("params: size must be positive")
            if bool(((self.shape < 0) | (self.shape > 1)).any()):
                raise ValueError("params: shape must lie in [0, 1]")
            if bool((self.taper.abs() >= 1).any()):
                raise ValueError("params: taper must satisfy |k| < 1")
            if bool(degenerate_6d(self.rotation_6d).any()):
                raise ValueError("params: degenerate 6D rotation (zero or parallel rows)")

    # ---------------------------------------------------------------- construction

    @classmethod
    def from_raw(cls, raw: Tensor, ranges: ParameterRanges | None = None) -> Assembly:
        """Squash unconstrained outputs (B, M, 16) into valid parameters (see ParameterRanges).

        The 6D rotation (columns 8-13) is kept as it is, so raw zeros there are a degenerate
        rotation and refused: a head starts its 6D outputs at
        :data:`~sq_mitsuba.geometry.rotation.IDENTITY_6D` (as the network's bias does)."""
        ranges = ranges or ParameterRanges()
        check_tensor("raw", raw, (None, NUM_PARAMS), min_dims=3)
        size = ranges.size_min + ranges.size_span * torch.sigmoid(raw[..., FIELDS["size"]])
        shape = torch.sigmoid(raw[..., FIELDS["shape"]])
        translation = ranges.translation_scale * torch.tanh(raw[..., FIELDS["translation"]])
        taper_ = ranges.taper_scale * torch.tanh(raw[..., FIELDS["taper"]])
        return cls(torch.cat([size, shape, translation, raw[..., FIELDS["rotation_6d"]], taper_],
                             dim=-1))

    @classmethod
    def from_values(
        cls,
        size: Tensor,
        shape: Tensor,
        translation: Tensor | None = None,
        rotation: Tensor | None = None,
        taper: Tensor | None = None,
    ) -> Assembly:
        """Assemble explicit fields (leading dims (B, M)); missing ones default to identity.

        Args:
            size: (B, M, 3).
            shape: (B, M, 2).
            translation: (B, M, 3), default 0.
            rotation: (B, M, 3, 3) matrices or (B, M, 6) 6D vectors, default identity.
            taper: (B, M, 2), default 0.
        """
        check_tensor("size", size, (None, 3), min_dims=3)
        check_tensor("shape", shape, (None, 2), min_dims=3)
        batch = size.shape[:-1]
        zeros = size.new_zeros
        if translation is None:
            translation = zeros(*batch, 3)
        if taper is None:
            taper = zeros(*batch, 2)
        if rotation is None:
            rotation = torch.eye(3, dtype=size.dtype, device=size.device).expand(*batch, 3, 3)
        check_tensor("rotation", rotation, (None,), min_dims=3)
        if rotation.shape[-2:] == (3, 3):
            check_rotations("rotation", rotation)  # a reflection would come back as another
            rotation = matrix_to_rotation_6d(rotation)
        fields = {"size": size, "shape": shape, "translation": translation,
                  "rotation": rotation, "taper": taper}
        for name, value in fields.items():
            check_tensor(name, value)
            if value.shape[:-1] != batch:
                raise ValueError(f"{name}: expected leading dims {tuple(batch)}, "
                                 f"got {tuple(value.shape)}")
        if rotation.shape[-1] != 6:
            raise ValueError(f"rotation: expected (B, M, 3, 3) or (B, M, 6), "
                             f"got {tuple(rotation.shape)}")
        try:
            return cls(torch.cat([size, shape, translation, rotation, taper], dim=-1))
        except ValueError as error:  # named as given, not as the params built from it
            message = str(error)
            for name in ("size", "shape", "taper"):
                if message.startswith(f"params: {name} "):
                    raise ValueError(f"{name}: {message.removeprefix(f'params: {name} ')}") \
                        from None
            raise

    # ---------------------------------------------------------------- named views

    @property
    def batch_size(self) -> int:
        return self.params.shape[0]

    @property
    def num_primitives(self) -> int:
        return self.params.shape[1]

    @property
    def size(self) -> Tensor:
        """(B, M, 3)."""
        return self.params[..., FIELDS["size"]]

    @property
    def shape(self) -> Tensor:
        """(B, M, 2)."""
        return self.params[..., FIELDS["shape"]]

    @property
    def translation(self) -> Tensor:
        """(B, M, 3)."""
        return self.params[..., FIELDS["translation"]]

    @property
    def rotation_6d(self) -> Tensor:
        """(B, M, 6)."""
        return self.params[..., FIELDS["rotation_6d"]]

    @property
    def rotation(self) -> Tensor:
        """Rotation matrices (B, M, 3, 3), primitive frame -> assembly frame."""
        return rotation_6d_to_matrix(self.rotation_6d)

    @property
    def taper(self) -> Tensor:
        """(B, M, 2)."""
        return self.params[..., FIELDS["taper"]]

    def __getitem__(self, index: int | slice) -> Assembly:
        """The sub-batch ``params[index]`` (an int keeps the batch dim).

        Raises:
            IndexError: an int index outside the batch, naming it and the batch size.
        """
        if not isinstance(index, slice):
            try:
                index = operator.index(index)
            except TypeError:
                raise TypeError(f"index: expected an int or a slice, got "
                                f"{type(index).__name__}") from None
            position = self._item(index, "index")
            index = slice(position, position + 1)
        return Assembly(self.params[index])

    def rotated(self, rotation: Tensor) -> Assembly:
        """The assembly turned about its origin: ``x -> rotation[b] @ x`` for item b.

        Each primitive's centre turns and its frame with it (``t -> Q t``, ``R -> Q R``);
        sizes, shapes and tapers live in the primitive frame and stay. Differentiable in both
        the parameters and ``rotation``.

        Args:
            rotation: (B, 3, 3) rotation matrices (det 1) of the assembly's dtype.
        """
        check_tensor("rotation", rotation, (self.batch_size, 3, 3))
        if rotation.dim() != 3 or rotation.dtype != self.params.dtype:
            raise ValueError(f"rotation: expected ({self.batch_size}, 3, 3) of "
                             f"{self.params.dtype}, got {tuple(rotation.shape)} {rotation.dtype}")
        check_rotations("rotation", rotation)  # frames are rebuilt as rotations, t is not
        params = self.params
        translation = (rotation[:, None] @ self.translation[..., None])[..., 0]
        frames = matrix_to_rotation_6d(rotation[:, None] @ self.rotation)
        return Assembly(torch.cat([params[..., FIELDS["size"]], params[..., FIELDS["shape"]],
                                   translation, frames, params[..., FIELDS["taper"]]], dim=-1))

    def scaled(self, factor: float | Tensor) -> Assembly:
        """The assembly scaled about its origin: ``x -> factor[b] x`` for item b.

        Sizes and centres scale; shapes, frames and tapers (relative to the size) stay, so the
        union's inside-outside function at ``factor x`` is the original's at ``x``.
        Differentiable in the parameters and in a tensor ``factor``.

        Args:
            factor: a finite real number > 0, or (B,) of them in the assembly's dtype.

        Raises:
            ValueError: one line naming ``factor`` when it is not finite and positive, has
                another shape or dtype, or scales a length past the dtype's range.
        """
        if isinstance(factor, Tensor):
            if tuple(factor.shape) != (self.batch_size,) or factor.dtype != self.params.dtype:
                raise ValueError(f"factor: expected a ({self.batch_size},) tensor of "
                                 f"{self.params.dtype} (one per item), got "
                                 f"{tuple(factor.shape)} {factor.dtype}")
            scale = factor.to(self.params.device)[:, None, None]
            bad = not bool(torch.isfinite(scale).all() and (scale > 0).all())
        elif isinstance(factor, bool) or not isinstance(factor, numbers.Real):
            raise ValueError(f"factor: expected a number or a ({self.batch_size},) tensor, got "
                             f"{type(factor).__name__}")
        else:
            scale, bad = float(factor), not (math.isfinite(factor) and factor > 0)
        if bad:
            raise ValueError(f"factor: expected finite numbers > 0, got {factor!r}")
        params = self.params
        size, translation = params[..., FIELDS["size"]] * scale, \
            params[..., FIELDS["translation"]] * scale
        with torch.no_grad():
            if not bool(torch.isfinite(size).all() and torch.isfinite(translation).all()
                        and (size > 0).all()):
                raise ValueError(f"factor: {factor!r} scales a length of the assembly past "
                                 f"{params.dtype}'s range")
        return Assembly(torch.cat([size, params[..., FIELDS["shape"]], translation,
                                   params[..., FIELDS["rotation_6d"]],
                                   params[..., FIELDS["taper"]]], dim=-1))

    def _item(self, item: int, name: str = "item") -> int:
        """Batch item ``item`` (negative counts from the end) as an index in [0, B), or a
        one-line ``IndexError`` naming ``name``, the item and the batch size."""
        if isinstance(item, bool):
            raise TypeError(f"{name}: expected an int, got {item!r}")
        try:
            item = operator.index(item)
        except TypeError:
            raise TypeError(f"{name}: expected an int, got {type(item).__name__}") from None
        if not -self.batch_size <= item < self.batch_size:
            raise IndexError(f"{name}: {item} is out of range for an assembly batch of "
                             f"{self.batch_size}")
        return item % self.batch_size

    def __repr__(self) -> str:
        return (f"Assembly(batch_size={self.batch_size}, num_primitives={self.num_primitives}, "
                f"dtype={self.params.dtype}, device={self.params.device})")

    # ---------------------------------------------------------------- occupancy

    def _check_query_points(self, points: Tensor) -> None:
        """Query points must be (B, N, 3) of the assembly's batch size and dtype."""
        check_tensor("points", points, (None, 3), min_dims=3)
        if points.shape[0] != self.batch_size or points.dim() != 3:
            raise ValueError(f"points: expected shape ({self.batch_size}, N, 3), "
                             f"got {tuple(points.shape)}")
        if points.dtype != self.params.dtype:
            raise ValueError(f"points: dtype {points.dtype} differs from the assembly's "
                             f"{self.params.dtype}")

    def to_primitive_frames(self, points: Tensor) -> Tensor:
        """Query points (B, N, 3), assembly frame -> (B, M, N, 3) in untapered primitive frames."""
        self._check_query_points(points)
        # Row-vector form of R^T (x - t).
        local = (points[:, None] - self.translation[:, :, None]) @ self.rotation
        return untaper(local, self.taper, self.size)

    def inside_outside(self, points: Tensor) -> Tensor:
        """Dual inside-outside value of each primitive at each point: (B, N, 3) -> (B, M, N).

        Equal to ``inside_outside_dual(self.to_primitive_frames(points), size, shape)``, fused:
        rotation, scaling and the taper's inverse run as one batched matrix product and a few
        elementwise passes, and the backward reuses the forward's powers.
        """
        self._check_query_points(points)
        g, alpha = dual_scales(self.shape)
        g1 = g[..., 0]
        g12 = g1 * g[..., 1]
        # Scaled primitive coordinates (xb, yb, zb before untapering) = linear @ x - offset.
        scale = self.size * torch.stack([g12, g12, g1], dim=-1)
        linear = self.rotation.transpose(-1, -2) / scale[..., None]
        offset = (linear @ self.translation[..., None]).squeeze(-1)
        return _AssemblyInsideOutside.apply(points, linear, offset, self.taper, g1, alpha)

    def occupancy(self, points: Tensor, sharpness: float | Tensor = 10.0) -> Tensor:
        """Per-primitive soft occupancy g = sigmoid(s (1 - f)) (paper Eq. 14): (B, M, N).

        ``sharpness`` s: a finite number > 0 or a 0-d floating tensor of one (its value a
        value check); NaN gave NaN and a negative s swapped inside and outside."""
        if isinstance(sharpness, Tensor):
            if sharpness.dim() != 0 or not sharpness.is_floating_point():
                raise ValueError(f"sharpness: expected a finite number > 0, got a tensor of "
                                 f"shape {tuple(sharpness.shape)} {sharpness.dtype}")
            bad = value_checks_enabled() and not bool(torch.isfinite(sharpness) & (sharpness > 0))
        else:
            bad = isinstance(sharpness, bool) or not isinstance(sharpness, numbers.Real) \
                or not (math.isfinite(sharpness) and sharpness > 0)
        if bad:
            raise ValueError(f"sharpness: expected a finite number > 0, got {sharpness!r}")
        return torch.sigmoid(sharpness * (1.0 - self.inside_outside(points)))

    def union_occupancy(self, points: Tensor, sharpness: float | Tensor = 10.0) -> Tensor:
        """Occupancy of the union: max over primitives of :meth:`occupancy`, (B, N)."""
        return self.occupancy(points, sharpness).amax(dim=1)

    # ---------------------------------------------------------------- surface samples

    def surface_points(self, level: int = 3) -> Tensor:
        """Dual-sampled surface points on icosphere angles in the assembly frame, (B, M, V, 3).

        V = 642 at level 3.
        """
        eta, omega = icosphere_angles(level, self.params.dtype, self.params.device)
        local = surface_points_dual(eta, omega, self.size, self.shape)
        local = taper(local, self.taper, self.size)
        return local @ self.rotation.transpose(-1, -2) + self.translation[:, :, None]

    def inside_others(self, points: Tensor) -> Tensor:
        """Which other primitive each primitive's surface points lie strictly inside.

        Args:
            points: (B, M, V, 3), e.g. from :meth:`surface_points`.

        Returns:
            (B, M, M, V) bool, computed without gradient: ``[b, j, m, v]`` says that point v
            of primitive m lies strictly inside primitive j (never for j = m).
        """
        check_tensor("points", points, (None, None, 3), min_dims=4)
        if points.dim() != 4 or points.shape[:2] != self.params.shape[:2]:
            raise ValueError(f"points: expected (B, M, V, 3) = ({self.batch_size}, "
                             f"{self.num_primitives}, V, 3), got {tuple(points.shape)}")
        batch, count, per, _ = points.shape
        with torch.no_grad():
            values = self.inside_outside(points.reshape(batch, count * per, 3))
            values = values.reshape(batch, count, count, per)  # (B, other, owner, V)
            own = torch.eye(count, dtype=torch.bool, device=points.device)[None, :, :, None]
            return (values < 1.0) & ~own

    def inside_other_mask(self, points: Tensor) -> Tensor:
        """Which of each primitive's surface points (B, M, V, 3) lie strictly inside another
        primitive: (B, M, V) bool, without gradient (:meth:`inside_others`, any other)."""
        return self.inside_others(points).any(dim=1)

    def surface_points_with_mask(self, level: int = 3) -> tuple[Tensor, Tensor]:
        """:meth:`surface_points` and :meth:`inside_other_mask` of them: (B, M, V, 3), (B, M, V)."""
        points = self.surface_points(level)
        return points, self.inside_other_mask(points)

    # ---------------------------------------------------------------- meshes and files

    def meshes(self, level: int = 3) -> tuple[Tensor, Tensor]:
        """One closed triangle mesh per primitive: vertices (B, M, V, 3), faces (F, 3) int64."""
        return self.surface_points(level), icosphere_faces(level, self.params.device)

    def merged_mesh(self, level: int = 3) -> tuple[Tensor, Tensor]:
        """All primitives as one mesh: vertices (B, M * V, 3), faces (M * F, 3) int64."""
        vertices, faces = self.meshes(level)
        batch, count, per, _ = vertices.shape
        offsets = torch.arange(count, device=faces.device)[:, None, None] * per
        return vertices.reshape(batch, count * per, 3), (faces[None] + offsets).reshape(-1, 3)

    def to_trimesh_scene(self, item: int = 0, level: int = 3) -> Any:
        """A ``trimesh.Scene`` with one watertight mesh per primitive of batch item ``item``."""
        import trimesh

        item = self._item(item)
        vertices, faces = self[item].meshes(level)
        item = 0
        vertices = vertices[item].detach().cpu().double().numpy()
        faces = faces.cpu().numpy()
        scene = trimesh.Scene()
        for index, primitive_vertices in enumerate(vertices):
            mesh = trimesh.Trimesh(primitive_vertices, faces, process=False)
            scene.add_geometry(mesh, node_name=f"primitive_{index}",
                               geom_name=f"primitive_{index}")
        return scene

    def export(self, path: str | Path, item: int = 0, level: int = 3) -> Path:
        """Write batch item ``item`` as a mesh file (.obj, .ply, .stl, .glb, .gltf), atomically.

        GLB/glTF keep one mesh per primitive; OBJ, PLY and STL hold the merged mesh.

        Raises:
            ValueError: ``path: ...`` for another suffix; OSError: ``<path>: ...`` when the
                file cannot be written (naming ``path``, not the temporary file).
            IndexError: naming ``item`` outside the batch.
        """
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in MESH_SUFFIXES:
            raise ValueError(f"path: unsupported mesh format {suffix!r} "
                             f"(choose one of {', '.join(MESH_SUFFIXES)})")
        scene = self.to_trimesh_scene(item, level)
        target = scene if suffix in (".glb", ".gltf") else scene.to_geometry()
        with _naming(path), atomic_path(path) as tmp:
            target.export(tmp, file_type=suffix[1:])
        return path

    def to_dict(self, item: int = 0) -> dict[str, Any]:
        """Human-readable form of batch item ``item``: named fields per primitive.

        Values are stored as exact decimal forms of the tensor's floats, so
        :meth:`from_dict` rebuilds the identical tensor.

        Raises:
            IndexError: naming ``item`` outside the batch.
            ValueError: ``params: ...`` for what :meth:`from_dict` would refuse (NaN, a size
                not positive, ...: possible under value_checks(False)), checked either way.
        """
        index, dtype = self._item(item), self.params.dtype
        values = self.params[index].detach().cpu()
        # What from_dict refuses is refused here, before save writes a file (checks on or off).
        if dtype not in _DTYPES.values():
            raise ValueError(f"params: {dtype} cannot be saved (one of {', '.join(_DTYPES)})")
        if not bool(torch.isfinite(values).all()):
            raise ValueError(f"params: item {index} contains NaN or infinite values")
        with value_checks(True):
            Assembly(values[None])  # the constructor's range checks
        primitives = [
            {name: [float(v) for v in row[columns]] for name, columns in FIELDS.items()}
            for row in values
        ]
        return {
            "format": JSON_FORMAT,
            "version": JSON_VERSION,
            "dtype": str(dtype).removeprefix("torch."),
            "conventions": {
                "size": "semi-axes (a1, a2, a3) of the primitive, in its own frame",
                "rotation_6d": "the first two rows r1, r2 of the primitive-to-assembly rotation "
                               "as read, not normalised: R has rows b1 = r1 / |r1|, b2 = the "
                               "part of r2 orthogonal to b1, normalised, b3 = b1 x b2",
                "transform": "x_assembly = R @ taper(x_primitive) + translation",
                "taper": "taper(x, y, z) = ((1 - k1 z / a3) x, (1 - k2 z / a3) y, z)",
                "shape": "dual superquadric exponents (e1, e2) in [0, 1]",
                "units": "the lengths of the poses it was read or fitted with (predict: "
                         "metres for its pose file's target_size, 1 = the dataset's unit "
                         "size; fit: those of the poses given)",
            },
            "primitives": primitives,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any], device: str | torch.device = "cpu") -> Assembly:
        """Inverse of :meth:`to_dict`: an assembly with batch size 1.

        Raises:
            ValueError: another format, a version other than :data:`JSON_VERSION` (one line
                naming ``version``), or fields that are not numbers of a valid assembly.
        """
        if not isinstance(data, dict) or data.get("format") != JSON_FORMAT:
            raise ValueError(f"not an assembly description (format != {JSON_FORMAT!r})")
        version = data.get("version")
        if isinstance(version, bool) or version != JSON_VERSION:
            raise ValueError(f"version: {version!r} is not an assembly format version this "
                             f"sq_mitsuba reads ({JSON_VERSION})")
        dtype = _DTYPES.get(data.get("dtype", "float32"))
        if dtype is None:
            raise ValueError(f"dtype: unsupported {data.get('dtype')!r}")
        primitives = data.get("primitives")
        if not isinstance(primitives, list) or not primitives:
            raise ValueError("primitives: expected a non-empty list")
        rows = []
        for index, primitive in enumerate(primitives):
            row = []
            for name, columns in FIELDS.items():
                value = primitive.get(name) if isinstance(primitive, dict) else None
                width = columns.stop - columns.start
                if (not isinstance(value, list) or len(value) != width
                        or not all(isinstance(v, int | float) and not isinstance(v, bool)
                                   and math.isfinite(v)
                                   for v in value)):
                    raise ValueError(f"primitives[{index}].{name}: expected {width} finite numbers")
                row += value
            rows.append(row)
        params = torch.tensor([rows], dtype=torch.float64)
        try:  # a device this torch cannot use failed inside torch (an AssertionError on CPU)
            params = params.to(dtype=dtype, device=device)
        except (AssertionError, RuntimeError, TypeError, ValueError) as error:
            reason = " ".join(str(error).split())[:160] or type(error).__name__
            raise ValueError(f"device: {device!r} cannot hold the assembly ({reason})") from None
        return cls(params)

    def save(self, path: str | Path, item: int = 0) -> Path:
        """Write :meth:`to_dict` of batch item ``item`` as JSON, atomically.

        Raises:
            ValueError: ``path: ...`` unless it ends in ``.json`` (a mesh is written by
                :meth:`export`); OSError: ``<path>: ...`` when it cannot be written.
            IndexError: naming ``item`` outside the batch.
        """
        path = Path(path)
        if path.suffix.lower() != ".json":
            hint = (f"; {path.suffix} is a mesh format: use export()"
                    if path.suffix.lower() in MESH_SUFFIXES else "")
            raise ValueError(f"path: {path} is not a .json file (save writes the assembly's "
                             f"JSON description{hint})")
        text = json.dumps(self.to_dict(item), indent=2) + "\n"
        with _naming(path):
            atomic_write_text(path, text)
        return path

    @classmethod
    def load(cls, path: str | Path, device: str | torch.device = "cpu") -> Assembly:
        """Read an assembly JSON written by :meth:`save`."""
        path = Path(path)
        data = read_json(path)
        try:
            return cls.from_dict(data, device)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None


@contextmanager
def _naming(path: Path) -> Iterator[None]:
    """Turn an ``OSError`` of writing ``path`` (which names the temporary file, or nothing)
    into one line naming ``path``."""
    try:
        yield
    except OSError as error:
        reason = error.strerror or " ".join(str(error).split()) or type(error).__name__
        raise type(error)(f"{path}: cannot write ({reason})") from None


class _AssemblyInsideOutside(torch.autograd.Function):
    """Dual inside-outside values of M primitives at N shared query points, fused.

    Inputs: points (B, N, 3); linear (B, M, 3, 3) = diag(1 / scale) R^T; offset (B, M, 3) =
    linear @ t; taper (B, M, 2); g1 (B, M); alpha (B, M, 2). Output f (B, M, N).
    Coordinates are laid out (B, M, 3, N) so every elementwise pass runs over contiguous rows.
    """

    @staticmethod
    def forward(ctx, points: Tensor, linear: Tensor, offset: Tensor, taper_: Tensor,
                g1: Tensor, alpha: Tensor) -> Tensor:
        batch, count = linear.shape[:2]
        num_points = points.shape[1]
        with_grad = any(ctx.needs_input_grad)
        rotated = torch.baddbmm(-offset.reshape(batch, 3 * count, 1),
                                linear.reshape(batch, 3 * count, 3), points.transpose(1, 2))
        x_rot, y_rot, zb = rotated.view(batch, count, 3, num_points).unbind(2)
        # z / a3 = zb g1, frozen beyond the slab |z| <= a3 (see superquadric.untaper).
        z_rel = (zb * g1[..., None]).clamp_(-1.0, 1.0)
        factor_x = (z_rel * -taper_[..., 0, None]).add_(1.0)
        factor_y = (z_rel * -taper_[..., 1, None]).add_(1.0)
        xb, yb = x_rot / factor_x, y_rot / factor_y
        f, grads = dual_field(xb, yb, zb, alpha[..., 0, None], alpha[..., 1, None], with_grad)
        if with_grad:
            ctx.save_for_backward(points, linear, taper_, g1, z_rel, factor_x, factor_y,
                                  xb, yb, zb, *grads)
        return f

    @staticmethod
    @first_derivatives_only
    @once_differentiable
    def backward(ctx, grad_f: Tensor):
        (points, linear, taper_, g1, z_rel, factor_x, factor_y, xb, yb, zb,
         d_x, d_y, d_z, d_alpha1, d_alpha2) = ctx.saved_tensors
        batch, count = linear.shape[:2]
        grad_x_rot = (grad_f * d_x).div_(factor_x)
        grad_y_rot = (grad_f * d_y).div_(factor_y)
        # xb = x_rot / factor with factor = 1 - k z_rel: d xb/d k = xb z_rel / factor.
        weighted_x, weighted_y = grad_x_rot * xb, grad_y_rot * yb
        grad_taper = torch.stack([(weighted_x * z_rel).sum(-1), (weighted_y * z_rel).sum(-1)],
                                 dim=-1)
        grad_z_rel = (weighted_x.mul_(taper_[..., 0, None])
                      .add_(weighted_y.mul_(taper_[..., 1, None])))
        grad_z_rel.mul_(z_rel.abs() < 1.0)  # the clamp passes no gradient outside the slab
        grad_g1 = (grad_z_rel * zb).sum(-1)
        grad_zb = (grad_f * d_z).addcmul_(grad_z_rel, g1[..., None])
        grad_rotated = torch.stack([grad_x_rot, grad_y_rot, grad_zb], dim=2)
        grad_rotated = grad_rotated.view(batch, 3 * count, -1)
        grad_points = grad_linear = grad_offset = grad_alpha = None
        if ctx.needs_input_grad[0]:
            grad_points = torch.bmm(linear.reshape(batch, 3 * count, 3).transpose(1, 2),
                                    grad_rotated).transpose(1, 2)
        if ctx.needs_input_grad[1]:
            grad_linear = torch.bmm(grad_rotated, points).view(batch, count, 3, 3)
        if ctx.needs_input_grad[2]:
            grad_offset = -grad_rotated.sum(-1).view(batch, count, 3)
        if ctx.needs_input_grad[5]:
            grad_alpha = torch.stack([(grad_f * d_alpha1).sum(-1), (grad_f * d_alpha2).sum(-1)],
                                     dim=-1)
        return grad_points, grad_linear, grad_offset, grad_taper, grad_g1, grad_alpha
