"""A model library on disk in the SPE3R layout: generate or import, process, write.

Each model lands in ``<root>/<model>/models/`` (see
:func:`sq_mitsuba.data.mesh_processing.write_model`); ``<root>/splits.csv`` lists generated
models as ``model,train`` / ``model,test`` rows without a header.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from sq_mitsuba.data.mesh_processing import (
    FUSION_RESOLUTION,
    MeshError,
    connected_pieces,
    load_mesh,
    model_card,
    process_mesh,
    sample_model,
    write_model,
)
from sq_mitsuba.data.spacecraft import THIN_FRACTION, CatalogueEntry, generate_spacecraft


def generate_model(entry: CatalogueEntry, out_root: str | Path, points: int = 100_000) -> Path:
    """Generate, process, sample and write one catalogue entry; return its models folder.

    Raises :class:`MeshError` (nothing written) when the spacecraft is not one connected body.
    """
    spacecraft = generate_spacecraft(entry.seed, entry.archetype, entry.name)
    raw = spacecraft.union()
    model = process_mesh(raw, method="solid")
    pieces = connected_pieces(model.mesh)
    if pieces != 1:
        raise MeshError(f"{entry.name}: the union of its parts has {pieces} disconnected "
                        "pieces; every appendage must overlap the part it is mounted on")
    model.checks["one_piece"] = True
    samples = sample_model(model.mesh, points, points, points, seed=entry.seed)
    card = model_card(entry.name, model, samples, source="procedural",
                      archetype=entry.archetype, seed=entry.seed, split=entry.split,
                      generator_mesh_sha256=raw.digest(),
                      thin_part_thickness=round(spacecraft.thin * model.normalisation.scale, 6),
                      thin_fraction=THIN_FRACTION, parts=spacecraft.part_summary(),
                      part_materials=spacecraft.materials())
    return write_model(out_root, entry.name, model, samples, card)


def model_name_for(path: Path) -> str:
    """A folder-safe model name from a file name."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", path.stem).strip("._") or "model"


def import_model(path: str | Path, out_root: str | Path, method: str = "auto",
                 align: str = "axes", resolution: int = FUSION_RESOLUTION,
                 points: int = 100_000, name: str | None = None) -> Path:
    """Load, process, sample and write one mesh file; errors name the file."""
    path = Path(path)
    mesh = load_mesh(path)
    try:
        model = process_mesh(mesh, method=method, align=align, resolution=resolution)
    except MeshError as error:
        raise MeshError(f"{path}: {error}") from None
    name = name or model_name_for(path)
    seed = int(np.frombuffer(model.mesh.digest().encode()[:8], dtype=np.uint64)[0] % 2**32)
    samples = sample_model(model.mesh, points, points, points, seed=seed)
    card = model_card(name, model, samples, source=str(path), archetype="imported",
                      seed=None, parts={"imported_mesh": 1})
    return write_model(out_root, name, model, samples, card)
