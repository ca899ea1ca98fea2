"""Material tags carried by every spacecraft part, for the dataset renderer.

Convention: a material is referred to by its index in :data:`MATERIALS`; per-face material
arrays store these indices (``int16``). The order is fixed: appending is safe, reordering
breaks files already written.
"""

from __future__ import annotations

MATERIALS: tuple[str, ...] = (
    "gold_mli",
    "silver_mli",
    "solar_cell",
    "white_paint",
    "aluminium",
    "dark_composite",
    "antenna_white",
)

# Grey-level diffuse reflectance used by previews
# (a rough visual cue only; the dataset renderer assigns its own physically based materials).
PREVIEW_ALBEDO: dict[str, float] = {
    "gold_mli": 0.55,
    "silver_mli": 0.75,
    "solar_cell": 0.08,
    "white_paint": 0.85,
    "aluminium": 0.6,
    "dark_composite": 0.15,
    "antenna_white": 0.9,
}

# sRGB viewer colours of the GLB written beside each OBJ (viewers and Blender only).
MTL_COLOUR: dict[str, tuple[float, float, float]] = {
    "gold_mli": (0.83, 0.62, 0.21),
    "silver_mli": (0.78, 0.78, 0.80),
    "solar_cell": (0.06, 0.08, 0.25),
    "white_paint": (0.90, 0.90, 0.90),
    "aluminium": (0.60, 0.61, 0.63),
    "dark_composite": (0.12, 0.12, 0.13),
    "antenna_white": (0.95, 0.95, 0.93),
}


def material_index(name: str) -> int:
    """Index of material ``name`` in :data:`MATERIALS` (``ValueError`` naming it if unknown)."""
    try:
        return MATERIALS.index(name)
    except ValueError:
        raise ValueError(f"material: unknown tag {name!r}; choose from {MATERIALS}") from None
