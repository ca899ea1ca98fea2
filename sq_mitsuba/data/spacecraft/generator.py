"""Seeded spacecraft generator: archetype recipe -> parts -> exact boolean union.

Convention: thin parts (solar panels, sunshields, dish shells, body cells) are
:data:`THIN_FRACTION` of the spacecraft's longest side thick, i.e. 0.01 after the model is
scaled to unit size. The recipe runs twice from the same seed: once to measure the longest
side, once with the thickness set from it (the second run draws the same random numbers, so
the layout is identical).

Catalogue splits are stable: a model's train/test split is a function of its number (in its
name) and the catalogue seed only, so ``--count 6`` and ``--count 64`` agree on the first six
models (see :func:`catalogue_split` for the rule).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field

import manifold3d
import numpy as np

from sq_mitsuba.data.mesh_io import TaggedMesh
from sq_mitsuba.data.solids import union_solids
from sq_mitsuba.data.spacecraft.archetypes import ARCHETYPES, Recipe
from sq_mitsuba.data.spacecraft.families import FAMILIES, HELD_OUT_FAMILIES
from sq_mitsuba.data.spacecraft.part_graph import PART_GRAPH, part_graph
from sq_mitsuba.data.spacecraft.parts import Part
from sq_mitsuba.render.materials import MATERIALS, material_index

THIN_FRACTION = 0.01
DEFAULT_CATALOGUE_COUNT = 64  # the paper's dataset size (57 train / 7 test)
DEFAULT_CATALOGUE_SEED = 0  # ``sq-mitsuba models generate`` without --seed
MAX_CATALOGUE_COUNT = 10_000
"""Most models one catalogue holds (a generous ceiling: 64 is the paper's library)."""
MAX_CATALOGUE_SEED = 2**32 - 1
"""Largest catalogue seed (seeds are 32-bit unsigned integers, 0 included)."""
SPLIT_BLOCK = 64
"""Model numbers are split in blocks of this many; each holds 7 test models."""
TEST_STRATA = (0, 2, 12, 23, 33, 43, 54, 64)
"""Stratum boundaries within a block: one test model in each of the 7 strata."""


RECIPES: dict[str, Recipe] = {**ARCHETYPES, **FAMILIES, PART_GRAPH: part_graph}
"""Every recipe :func:`generate_spacecraft` builds: the 14 archetypes of :func:`catalogue`,
the families of the compositional generator (:func:`composed_catalogue`) and the free-form
part graphs (:func:`graph_catalogue`)."""
_RECIPE_NAMES = [*ARCHETYPES, *FAMILIES, PART_GRAPH]
if len(RECIPES) != len(_RECIPE_NAMES):  # pragma: no cover - a naming mistake
    raise ImportError("recipe names overlap: "
                      f"{sorted({n for n in _RECIPE_NAMES if _RECIPE_NAMES.count(n) > 1})}")


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
    mesh = union_solids([p.solid for p in parts], [material_index(p.material) for p in parts])
    return fill_cavities(mesh)


#: A closed shell of the union whose volume is at most this fraction of the largest shell's
#: is a sliver, not a part: a spacecraft fills about 1 % of its bounding cube, so this is a
#: cube of 2e-4 of its longest side (1 cm on a 50 m station), smaller than any part the
#: families make; the sliver seen (a station's truss, catalogue seed 77) was 1.6e-10.
SLIVER_VOLUME = 1e-9


def fill_cavities(mesh: TaggedMesh) -> TaggedMesh:
    """``mesh`` without enclosed cavities or slivers: the closed shells of negative signed
    volume (voids that several overlapping parts can close off inside the solid, invisible
    from outside) are dropped, so the solid is filled there, and so are shells of no volume
    (at most :data:`SLIVER_VOLUME` of the largest shell's: flat tetrahedra the exact union
    can leave where faces of several parts nearly meet, a few triangles that would otherwise
    count as a second piece of the spacecraft). A mesh of one shell is returned as it is."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = mesh.faces
    n = len(mesh.vertices)
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    if count == 1:
        return mesh
    tri = mesh.vertices[faces]
    six_volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
    shell = labels[faces[:, 0]]
    volumes = np.bincount(shell, weights=six_volume, minlength=count)
    keep = volumes[shell] > SLIVER_VOLUME * volumes.max()
    if keep.all():
        return mesh
    used, inverse = np.unique(faces[keep], return_inverse=True)
    return TaggedMesh(mesh.vertices[used], inverse.reshape(-1, 3).astype(np.int64),
                      mesh.face_material[keep])


def parts_extent(parts: Sequence[Part]) -> np.ndarray:
    """Side lengths (3,) of the axis-aligned box around all parts."""
    boxes = np.array([p.solid.bounding_box() for p in parts])
    return boxes[:, 3:].max(axis=0) - boxes[:, :3].min(axis=0)


def generate_spacecraft(seed: int, archetype: str, name: str | None = None) -> Spacecraft:
    """Build spacecraft ``archetype`` from ``seed`` (same arguments, same spacecraft).

    Args:
        seed: non-negative integer seed of the recipe's random numbers.
        archetype: one of :data:`ARCHETYPES`, a family of :data:`FAMILIES` (the
            compositional generator) or ``"part_graph"``, i.e. a key of :data:`RECIPES`.
        name: model name (default ``"<archetype>_<seed>"``).
    """
    if archetype not in RECIPES:
        raise ValueError(f"archetype: unknown {archetype!r}; choose from {sorted(RECIPES)}")
    if int(seed) < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed}")
    recipe = RECIPES[archetype]
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
    catalogue_seed: int | None = None
    """The seed of the catalogue the entry belongs to (it fixes name, seed and split)."""


def _check_catalogue_seed(seed: int) -> int:
    if isinstance(seed, bool) or int(seed) != seed or not 0 <= int(seed) <= MAX_CATALOGUE_SEED:
        raise ValueError(f"seed: expected an integer in [0, {MAX_CATALOGUE_SEED}], got {seed}")
    return int(seed)


def _check_catalogue_size(count: int, seed: int) -> tuple[int, int]:
    """``count`` and ``seed`` of a catalogue, checked (one-line errors naming them)."""
    if isinstance(count, bool) or int(count) != count or not 1 <= count <= MAX_CATALOGUE_COUNT:
        raise ValueError(f"count: expected an integer in [1, {MAX_CATALOGUE_COUNT}], got {count}")
    return int(count), _check_catalogue_seed(seed)


def _stratum_of(position: int) -> int:
    """Index into :data:`TEST_STRATA` of the stratum holding ``position`` (0 <= p < 64)."""
    return next(k for k in range(len(TEST_STRATA) - 1) if position < TEST_STRATA[k + 1])


def catalogue_split(seed: int, number: int) -> str:
    """``"test"`` or ``"train"``: the split of catalogue model ``number`` of catalogue ``seed``.

    Convention (the catalogue's split rule): model numbers are cut into blocks of
    :data:`SPLIT_BLOCK` = 64, each block into the :data:`TEST_STRATA` (numbers 0-1, 2-11,
    12-22, 23-32, 33-42, 43-53, 54-63 of the block); in every stratum exactly one model is a
    test model, the one at the position given by the SHA-256 of ``(seed, block, stratum)``.
    So a model's split depends only on its number (part of its name) and the catalogue seed,
    never on ``--count``, on other models or on earlier runs; every block of 64 holds 7 test
    models (the paper's 57/7 split of its 64 models), and any catalogue of two or more models
    holds at least one (the first stratum is models 0 and 1).
    """
    seed = _check_catalogue_seed(seed)
    if isinstance(number, bool) or int(number) != number or number < 0:
        raise ValueError(f"number: expected a non-negative integer, got {number}")
    block, position = divmod(int(number), SPLIT_BLOCK)
    k = _stratum_of(position)
    low, high = TEST_STRATA[k], TEST_STRATA[k + 1]
    digest = hashlib.sha256(f"sq_mitsuba catalogue split {seed} {block} {k}".encode()).digest()
    chosen = low + int.from_bytes(digest[:8], "little") % (high - low)
    return "test" if position == chosen else "train"


def catalogue(count: int, seed: int) -> list[CatalogueEntry]:
    """Names, archetypes, per-model seeds and train/test split of ``count`` models.

    Archetypes cycle through seeded permutations of all families, so every family appears once
    ``count >= len(ARCHETYPES)``. Model ``i`` is named ``sc<i:03d>_<archetype>``. Every entry
    is a function of ``(seed, i)`` alone: ``catalogue(n, seed)`` is the first ``n`` entries of
    ``catalogue(m, seed)`` for any ``m >= n``, splits included (see :func:`catalogue_split`).

    Args:
        count: number of models, ``1 <= count <= MAX_CATALOGUE_COUNT``.
        seed: catalogue seed, ``0 <= seed <= MAX_CATALOGUE_SEED`` (``2**32 - 1``).
    """
    count, seed = _check_catalogue_size(count, seed)
    rng = np.random.default_rng([seed, 0x5C])
    names = sorted(ARCHETYPES)
    order: list[str] = []
    # Permutations are drawn one after the other, so the first ``count`` archetypes do not
    # depend on ``count``; SeedSequence.generate_state is prefix-stable the same way.
    while len(order) < count:
        order += [names[i] for i in rng.permutation(len(names))]
    model_seeds = np.random.SeedSequence(seed).generate_state(count, dtype=np.uint32)
    return [CatalogueEntry(f"sc{i:03d}_{order[i]}", order[i], int(model_seeds[i]),
                           catalogue_split(seed, i), seed) for i in range(count)]


COMPOSED_PREFIX = "cs"
"""Name prefix of the compositional catalogue's models (``cs<i:05d>_<family>``), apart from
the archetype catalogue's ``sc<i:03d>_<archetype>``."""


def composed_catalogue(count: int, seed: int, families: Sequence[str] | None = None,
                       ) -> list[CatalogueEntry]:
    """``count`` models of the compositional generator (:data:`FAMILIES`), as catalogue entries.

    The catalogue is one stream of models per ``seed``: position ``i`` of the stream holds a
    family from seeded permutations of all :data:`FAMILIES` (each permutation shows every
    family once) and a model seed; its model is named ``cs<i:05d>_<family>``. ``families``
    keeps only the models of those families (default: all), in stream order, so a model's
    name, family, seed and split are a function of ``(seed, i)`` alone, whichever families
    are asked for and whatever ``count``: ``composed_catalogue(n, s, f)`` is the first ``n``
    entries of ``composed_catalogue(m, s, f)`` for ``m >= n``, and a training library
    (``families=TRAINING_FAMILIES``) and a held-out one (``HELD_OUT_FAMILIES``) generated
    from the same seed never give one name to two models.

    Split: models of the :data:`HELD_OUT_FAMILIES` are ``"test"`` (``splits.csv`` holds only
    ``train`` and ``test``; :func:`is_held_out` tells them from the in-family test models);
    the others follow :func:`catalogue_split` of their position (7 test positions in every
    block of 64).

    Args:
        count: number of models, ``1 <= count <= MAX_CATALOGUE_COUNT``.
        seed: catalogue seed, ``0 <= seed <= MAX_CATALOGUE_SEED``.
        families: names from :data:`FAMILIES` to keep (None: all).
    """
    count, seed = _check_catalogue_size(count, seed)
    names = sorted(FAMILIES)
    wanted = set(names) if families is None else set(families)
    unknown = wanted - set(names)
    if unknown or not wanted:
        raise ValueError(f"families: unknown {sorted(unknown)}; choose from {names}")
    rng = np.random.default_rng([seed, 0xC0, 0x5E])
    # Every permutation holds each wanted family once: this many positions hold ``count``.
    length = -(-int(count) // len(wanted)) * len(names)
    order: list[str] = []
    while len(order) < length:
        order += [names[i] for i in rng.permutation(len(names))]
    model_seeds = np.random.SeedSequence([seed, 0xC05E]).generate_state(length, dtype=np.uint32)
    entries = []
    for i in range(length):
        family = order[i]
        if family not in wanted:
            continue
        split = "test" if family in HELD_OUT_FAMILIES else catalogue_split(seed, i)
        entries.append(CatalogueEntry(f"{COMPOSED_PREFIX}{i:05d}_{family}", family,
                                      int(model_seeds[i]), split, seed))
        if len(entries) == count:
            break
    return entries


GRAPH_PREFIX = "pg"
"""Name prefix of the part-graph catalogue's models (``pg<i:05d>_part_graph``)."""


def graph_catalogue(count: int, seed: int) -> list[CatalogueEntry]:
    """``count`` free-form part graphs (:mod:`~sq_mitsuba.data.spacecraft.part_graph`), as
    catalogue entries named ``pg<i:05d>_part_graph``.

    Model ``i`` has a seed from the catalogue seed and the split :func:`catalogue_split`
    gives its number; as for the other catalogues, every entry is a function of
    ``(seed, i)`` alone. Part graphs belong to no held-out family: a network may train on
    them, and no catalogue made before them changes.

    Args:
        count: number of models, ``1 <= count <= MAX_CATALOGUE_COUNT``.
        seed: catalogue seed, ``0 <= seed <= MAX_CATALOGUE_SEED``.
    """
    count, seed = _check_catalogue_size(count, seed)
    model_seeds = np.random.SeedSequence([seed, 0x96A9]).generate_state(count, dtype=np.uint32)
    return [CatalogueEntry(f"{GRAPH_PREFIX}{i:05d}_{PART_GRAPH}", PART_GRAPH,
                           int(model_seeds[i]), catalogue_split(seed, i), seed)
            for i in range(count)]


def is_held_out(entry: CatalogueEntry | str) -> bool:
    """Whether a catalogue entry (or a family name) belongs to :data:`HELD_OUT_FAMILIES`."""
    family = entry if isinstance(entry, str) else entry.archetype
    return family in HELD_OUT_FAMILIES

