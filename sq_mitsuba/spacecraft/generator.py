"""Seeded spacecraft generator: archetype recipe -> parts -> exact boolean union.

Convention: thin parts (solar panels, sunshields, dish shells, body cells) are
:data:`THIN_FRACTION` of the spacecraft's longest side thick, i.e. 0.01 after the model is
scaled to unit size. The recipe runs twice from the same seed: once to measure the longest
side, once with the thickness set from it (the second run draws the same random numbers, so
the layout is identical).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field

import manifold3d
import numpy as np

from sq_mitsuba.spacecraft.archetypes import ARCHETYPES
from sq_mitsuba.spacecraft.materials import MATERIALS, material_index
from sq_mitsuba.spacecraft.parts import Part

THIN_FRACTION = 0.01
DEFAULT_CATALOGUE_COUNT = 64  # the paper's dataset size (57 train / 7 test)
DEFAULT_CATALOGUE_SEED = 0  # ``sq-mitsuba models generate`` without --seed


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


@dataclass
class Spacecraft:
    """A generated spacecraft: its recipe, seed and parts (in metres, body frame)."""

    name: str
    archetype: str
    seed: int
    thin: float
    parts: list[Part] = field(repr=False)

    def part_summary(self) -> dict[str, int]:
        """How many parts of each kind."""
        counts: dict[str, int] = {}
        for p in self.parts:
            counts[p.kind] = counts.get(p.kind, 0) + 1
        return dict(sorted(counts.items()))

    def materials(self) -> list[str]:
        """The material tags used, in :data:`MATERIALS` order."""
        used = {p.material for p in self.parts}
        return [m for m in MATERIALS if m in used]

    def union(self) -> TaggedMesh:
        """The exact boolean union of the parts, each face tagged with its part's material."""
        return union_parts(self.parts)


def union_parts(parts: Sequence[Part]) -> TaggedMesh:
    """Exact union (manifold3d) of closed parts; internal faces and overlaps disappear.

    Per-face materials follow manifold3d's provenance runs: each part gets its own original
    ID, and every output triangle records which input it came from.
    """
    if not parts:
        raise ValueError("parts: empty list, nothing to union")
    solids, id_to_material = [], {}
    for part in parts:
        if part.solid.is_empty() or part.solid.status() != manifold3d.Error.NoError:
            raise ValueError(f"part {part.kind!r}: not a valid closed solid")
        tagged = part.solid.as_original()
        id_to_material[tagged.original_id()] = material_index(part.material)
        solids.append(tagged)
    result = manifold3d.Manifold.batch_boolean(solids, manifold3d.OpType.Add)
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


def parts_extent(parts: Sequence[Part]) -> np.ndarray:
    """Side lengths (3,) of the axis-aligned box around all parts."""
    boxes = np.array([p.solid.bounding_box() for p in parts])
    return boxes[:, 3:].max(axis=0) - boxes[:, :3].min(axis=0)


def generate_spacecraft(seed: int, archetype: str, name: str | None = None) -> Spacecraft:
    """Build spacecraft ``archetype`` from ``seed`` (same arguments, same spacecraft).

    Args:
        seed: non-negative integer seed of the recipe's random numbers.
        archetype: one of :data:`ARCHETYPES`.
        name: model name (default ``"<archetype>_<seed>"``).
    """
    if archetype not in ARCHETYPES:
        raise ValueError(f"archetype: unknown {archetype!r}; choose from {sorted(ARCHETYPES)}")
    if int(seed) < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed}")
    recipe = ARCHETYPES[archetype]
    probe = recipe(np.random.default_rng(int(seed)), 0.02)
    thin = THIN_FRACTION * float(parts_extent(probe).max())
    parts = recipe(np.random.default_rng(int(seed)), thin)
    return Spacecraft(name or f"{archetype}_{seed}", archetype, int(seed), thin, parts)


@dataclass(frozen=True)
class CatalogueEntry:
    """One model of a generated catalogue."""

    name: str
    archetype: str
    seed: int
    split: str


def catalogue(count: int, seed: int, test_fraction: float = 7 / 64) -> list[CatalogueEntry]:
    """Names, archetypes, per-model seeds and train/test split of ``count`` models.

    Archetypes cycle through seeded permutations of all families, so every family appears once
    ``count >= len(ARCHETYPES)``. Convention: the test split has ``round(count *
    test_fraction)`` models (7 of the default 64, as in the paper), at least one when
    ``count >= 2``.
    """
    if count < 1:
        raise ValueError(f"count: expected >= 1, got {count}")
    rng = np.random.default_rng([int(seed), 0x5C])
    names = sorted(ARCHETYPES)
    order: list[str] = []
    while len(order) < count:
        order += [names[i] for i in rng.permutation(len(names))]
    model_seeds = np.random.SeedSequence(int(seed)).generate_state(count, dtype=np.uint32)
    n_test = max(1 if count >= 2 else 0, round(count * test_fraction))
    test = set(rng.choice(count, size=n_test, replace=False).tolist()) if n_test else set()
    return [CatalogueEntry(f"sc{i:03d}_{order[i]}", order[i], int(model_seeds[i]),
                           "test" if i in test else "train") for i in range(count)]
