"""Procedural spacecraft: parts library, archetype families, seeded generator, materials."""

from sq_mitsuba.spacecraft.archetypes import ARCHETYPES
from sq_mitsuba.spacecraft.generator import (
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
