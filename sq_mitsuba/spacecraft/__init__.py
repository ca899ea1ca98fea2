"""Procedural spacecraft: parts library, archetype families, seeded generator, materials."""

from sq_mitsuba.spacecraft.archetypes import ARCHETYPES
from sq_mitsuba.spacecraft.generator import (
    DEFAULT_CATALOGUE_COUNT,
    DEFAULT_CATALOGUE_SEED,
    THIN_FRACTION,
    CatalogueEntry,
    Spacecraft,
    TaggedMesh,
    catalogue,
    generate_spacecraft,
    union_parts,
)
from sq_mitsuba.spacecraft.materials import MATERIALS, material_index
from sq_mitsuba.spacecraft.parts import Part

__all__ = [
    "ARCHETYPES",
    "DEFAULT_CATALOGUE_COUNT",
    "DEFAULT_CATALOGUE_SEED",
    "MATERIALS",
    "THIN_FRACTION",
    "CatalogueEntry",
    "Part",
    "Spacecraft",
    "TaggedMesh",
    "catalogue",
    "generate_spacecraft",
    "material_index",
    "union_parts",
]
