"""Procedural spacecraft: parts library, archetype families, seeded generator, materials."""

from sq_mitsuba.data.spacecraft.archetypes import ARCHETYPES
from sq_mitsuba.data.spacecraft.generator import (
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
from sq_mitsuba.data.spacecraft.parts import Part
from sq_mitsuba.render.materials import MATERIALS, material_index

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
