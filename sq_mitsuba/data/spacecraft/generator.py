"""Seeded spacecraft generator: archetype recipe -> parts -> exact boolean union.

Convention: thin parts (solar panels, sunshields, dish shells, body cells) are
:data:`THIN_FRACTION` of the spacecraft's longest side thick, i.e. 0.01 after the model is
scaled to unit size. The recipe runs twice from the same seed: once to measure the longest
side, once with the thickness set from it (the second run draws the same random numbers, so
the layout is identical).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import manifold3d
import numpy as np

from sq_mitsuba.data.mesh_io import TaggedMesh
from sq_mitsuba.data.mesh_processing import union_solids
from sq_mitsuba.data.spacecraft.archetypes import ARCHETYPES
from sq_mitsuba.data.spacecraft.parts import Part
from sq_mitsuba.render.materials import MATERIALS, material_index

THIN_FRACTION = 0.01
DEFAULT_CATALOGUE_COUNT = 64  # the paper's dataset size (57 train / 7 test)
DEFAULT_CATALOGUE_SEED = 0  # ``sq-mitsuba models generate`` without --seed


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
    """Exact union (manifold3d) of closed parts; per-face materials follow each part's tag."""
    for part in parts:
        if part.solid.is_empty() or part.solid.status() != manifold3d.Error.NoError:
            raise ValueError(f"part {part.kind!r}: not a valid closed solid")
    return union_solids([p.solid for p in parts], [material_index(p.material) for p in parts])


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
