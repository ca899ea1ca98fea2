"""Procedural spacecraft: parts library, archetype recipes, the compositional generator
(attachment grammar and families, with a fixed leave-family-out set), free-form part
graphs, seeded generator, materials."""

from sq_mitsuba.data.spacecraft.archetypes import ARCHETYPES
from sq_mitsuba.data.spacecraft.families import FAMILIES, HELD_OUT_FAMILIES, TRAINING_FAMILIES
from sq_mitsuba.data.spacecraft.generator import (
    DEFAULT_CATALOGUE_COUNT,
    DEFAULT_CATALOGUE_SEED,
    RECIPES,
    THIN_FRACTION,
    CatalogueEntry,
    Spacecraft,
    TaggedMesh,
    catalogue,
    composed_catalogue,
    generate_spacecraft,
    graph_catalogue,
    is_held_out,
    union_parts,
)
from sq_mitsuba.data.spacecraft.part_graph import PART_GRAPH
from sq_mitsuba.data.spacecraft.parts import Part
from sq_mitsuba.render.materials import MATERIALS, material_index

__all__ = [
    "ARCHETYPES",
    "DEFAULT_CATALOGUE_COUNT",
    "DEFAULT_CATALOGUE_SEED",
    "FAMILIES",
    "HELD_OUT_FAMILIES",
    "MATERIALS",
    "PART_GRAPH",
    "RECIPES",
    "THIN_FRACTION",
    "TRAINING_FAMILIES",
    "CatalogueEntry",
    "Part",
    "Spacecraft",
    "TaggedMesh",
    "catalogue",
    "composed_catalogue",
    "generate_spacecraft",
    "graph_catalogue",
    "is_held_out",
    "material_index",
    "union_parts",
]
