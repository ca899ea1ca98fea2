"""Free-form part graphs: one connected solid per seed, structure that varies, own catalogue.

The part-graph recipe is a training family outside ``FAMILIES``, so the catalogues made
before it (the held-out set and the broad library among them) must not move: they are
pinned to the digests they had before the recipe was added.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import trimesh

from sq_mitsuba.data.mesh_io import TaggedMesh
from sq_mitsuba.data.mesh_processing import process_mesh
from sq_mitsuba.data.spacecraft import (
    ARCHETYPES,
    FAMILIES,
    PART_GRAPH,
    RECIPES,
    composed_catalogue,
    generate_spacecraft,
    graph_catalogue,
    is_held_out,
)
from sq_mitsuba.data.spacecraft.generator import catalogue_split

QUICK_SEEDS = 12  # the quick connectedness check; the slow sweep takes 120


def _pieces(mesh: TaggedMesh) -> int:
    """Edge-connected pieces of a triangle mesh (trimesh)."""
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    labels = trimesh.graph.connected_component_labels(tm.face_adjacency,
                                                      node_count=len(tm.faces))
    return int(labels.max()) + 1


def test_part_graph_is_a_recipe_outside_the_families() -> None:
    assert PART_GRAPH in RECIPES
    assert PART_GRAPH not in FAMILIES and PART_GRAPH not in ARCHETYPES
    assert set(RECIPES) == set(FAMILIES) | set(ARCHETYPES) | {PART_GRAPH}
    assert not is_held_out(PART_GRAPH)


def test_same_seed_same_mesh() -> None:
    first = generate_spacecraft(3, PART_GRAPH).union()
    assert first.digest() == generate_spacecraft(3, PART_GRAPH).union().digest()
    assert first.digest() != generate_spacecraft(4, PART_GRAPH).union().digest()
    assert len(first.face_material) == len(first.faces)


def test_every_seed_is_one_watertight_piece() -> None:
    """Every attachment reaches into its host: the exact union is one piece, and the
    processed model (what ``models generate`` writes) is watertight and outward."""
    for seed in range(QUICK_SEEDS):
        mesh = generate_spacecraft(seed, PART_GRAPH).union()
        assert _pieces(mesh) == 1, seed
        if seed < 2:
            model = process_mesh(mesh, method="solid")
            assert model.checks["watertight"] and model.checks["outward"], seed


@pytest.mark.slow
def test_one_piece_across_many_seeds() -> None:
    bad = [seed for seed in range(QUICK_SEEDS, 120)
           if _pieces(generate_spacecraft(seed, PART_GRAPH).union()) != 1]
    assert bad == []


def _rod_axes(parts) -> list[np.ndarray]:
    axes = []
    for p in parts:
        if p.kind in {"boom", "strut"}:
            v = np.asarray(p.solid.to_mesh64().vert_properties)[:, :3]
            centred = v - v.mean(axis=0)
            axes.append(np.linalg.svd(centred, full_matrices=False)[2][0])
    return axes


def test_structure_varies_not_a_template() -> None:
    """Across 24 seeds: the number of bodies, of parts and of attachment kinds all vary;
    some graphs chain bodies (more than one bus body), some carry several dishes or arrays,
    and some boom leaves the core at more than 20 degrees from every body axis."""
    bodies, counts, dishes, wings, oblique = [], [], [], [], []
    for seed in range(24):
        parts = generate_spacecraft(seed, PART_GRAPH).parts
        kinds = [p.kind for p in parts]
        bodies.append(sum(k.startswith("bus_") for k in kinds))
        counts.append(len(parts))
        dishes.append(kinds.count("dish"))
        wings.append(kinds.count("solar_panel"))
        angles = [np.degrees(np.arccos(min(1.0, np.abs(a).max()))) for a in _rod_axes(parts)]
        oblique.append(max(angles, default=0.0))
    assert len(set(bodies)) >= 4 and max(bodies) >= 3 and min(bodies) == 1
    assert len(set(counts)) >= 12
    assert max(wings) >= 4 and min(wings) == 0 and max(dishes) >= 2
    assert max(oblique) > 20.0


def test_extent_spreads_over_the_real_range() -> None:
    """Longest over shortest side of the bounding box spreads from compact to long (booms
    and arrays several times the body)."""
    from sq_mitsuba.data.spacecraft.generator import parts_extent

    ratios = []
    for seed in range(24):
        extent = np.sort(parts_extent(generate_spacecraft(seed, PART_GRAPH).parts))
        ratios.append(extent[2] / extent[0])
    assert min(ratios) < 2.0 and max(ratios) > 5.0


# --------------------------------------------------------------------------- the catalogue

def test_graph_catalogue_names_seeds_and_splits() -> None:
    entries = graph_catalogue(130, 5)
    assert [e.name for e in entries[:2]] == ["pg00000_part_graph", "pg00001_part_graph"]
    assert len({e.name for e in entries}) == 130
    assert all(e.archetype == PART_GRAPH and e.catalogue_seed == 5 for e in entries)
    assert [e.split for e in entries] == [catalogue_split(5, i) for i in range(130)]
    assert sum(e.split == "test" for e in entries[:128]) == 14  # 7 in every 64
    assert graph_catalogue(40, 5) == entries[:40]
    assert [e.seed for e in graph_catalogue(40, 6)] != [e.seed for e in entries[:40]]
    assert len({e.seed for e in entries}) == 130
    with pytest.raises(ValueError, match="count"):
        graph_catalogue(0, 0)
    with pytest.raises(ValueError, match="seed"):
        graph_catalogue(3, -1)


def _digest(entries) -> str:
    rows = "".join(f"{e.name},{e.archetype},{e.seed},{e.split}\n" for e in entries)
    return hashlib.sha256(rows.encode()).hexdigest()


def test_earlier_composed_catalogues_unchanged() -> None:
    """Values computed before the part graphs were added: the held-out set (seed 7) and the
    broad training library (seed 1) reproduce, and so does a held-out family's mesh."""
    assert _digest(composed_catalogue(200, 7)) == (
        "cc16eeed8032c042549bf3d6adbbfe62b915968e2de539cd383efaf167111247")
    assert _digest(composed_catalogue(400, 1)) == (
        "417d7166f0d59a5007a54286a4b55c131a2a1b395994dbfa5d73fdfa14cef064")
    assert generate_spacecraft(5, "module_stack").union().digest() == (
        "882932aef4e3a3b11f62b39f0aa71bd8baa2a76f85b3bcc0d1d4d025bccb3274")


def test_part_graph_library_pinned() -> None:
    """The recipe and catalogue that the recorded part-graph runs trained on (seed 0, 1,000
    models): a change to either makes a different library, so it must be deliberate."""
    assert _digest(graph_catalogue(1000, 0)) == (
        "58d33324ca982d820813fc30b57490896ebb9e91c28c95dc6293ff4327e12e7d")
    assert generate_spacecraft(3, PART_GRAPH).union().digest() == (
        "13cd3841dc2d7b2a9424e2359d3607f6479f59d21a7bde3e4ce71fb27ec4f8b5")
