"""Procedural spacecraft: determinism, variety, parts and materials, thin panels."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from sq_mitsuba.data.mesh_processing import normalise, process_mesh, sample_triangles
from sq_mitsuba.data.spacecraft import (
    ARCHETYPES,
    DEFAULT_CATALOGUE_COUNT,
    DEFAULT_CATALOGUE_SEED,
    MATERIALS,
    catalogue,
    generate_spacecraft,
)
from sq_mitsuba.render.depth import RayCaster

# Distinctness threshold: occnet Chamfer-L1 between two unit-size models at 20,000 surface
# points each. Two draws of the same model differ by up to about 0.0025 there (sampling noise), so
# 0.005 (2x that) means "a different shape". A 2,000-point screen finds the candidate pairs.
DISTINCT_CHAMFER = 0.005
SCREEN_CHAMFER = 0.02


def _chamfer_l1(a: np.ndarray, b: np.ndarray) -> float:
    da, _ = cKDTree(b).query(a)
    db, _ = cKDTree(a).query(b)
    return 0.5 * (da.mean() + db.mean())


def test_at_least_twelve_archetypes_and_required_part_kinds() -> None:
    assert len(ARCHETYPES) >= 12
    kinds, materials = set(), set()
    for archetype in ARCHETYPES:
        for seed in range(4):
            sc = generate_spacecraft(seed, archetype)
            kinds |= {p.kind for p in sc.parts}
            materials |= {p.material for p in sc.parts}
            for part in sc.parts:
                assert part.material in MATERIALS
                assert not part.solid.is_empty()
    required = {"bus_box", "bus_cylinder", "bus_hexagonal", "bus_octagonal", "cubesat_body",
                "solar_panel", "yoke", "body_cells", "dish", "horn_antenna", "boom",
                "magnetometer_mast", "instrument", "telescope_tube", "sunshield",
                "heat_shield", "thruster_nozzle", "star_tracker"}
    assert required <= kinds, required - kinds
    assert materials == set(MATERIALS)


@pytest.mark.parametrize("archetype", sorted(ARCHETYPES))
def test_same_seed_same_mesh_hash(archetype: str) -> None:
    first = generate_spacecraft(11, archetype).union()
    second = generate_spacecraft(11, archetype).union()
    other = generate_spacecraft(12, archetype).union()
    assert first.digest() == second.digest()
    assert first.digest() != other.digest()
    assert len(first.face_material) == len(first.faces)


def test_default_catalogue_split_and_every_archetype() -> None:
    entries = catalogue(64, 0)
    assert len({e.name for e in entries}) == 64
    assert {e.archetype for e in entries} == set(ARCHETYPES)
    assert sum(e.split == "test" for e in entries) == 7
    assert [e.seed for e in catalogue(64, 0)] == [e.seed for e in entries]
    assert [e.seed for e in catalogue(64, 1)] != [e.seed for e in entries]


def test_default_64_models_pairwise_distinct() -> None:
    """Generator output of the default catalogue (union + normalisation, no sampling files)."""
    rng = np.random.default_rng(0)
    meshes = [normalise(generate_spacecraft(e.seed, e.archetype).union())[0]
              for e in catalogue(64, 0)]
    clouds = [sample_triangles(m.vertices, m.faces, 2000, rng)[0] for m in meshes]
    trees = [cKDTree(c) for c in clouds]
    candidates = []
    for i, j in itertools.combinations(range(64), 2):
        d = 0.5 * (trees[j].query(clouds[i])[0].mean() + trees[i].query(clouds[j])[0].mean())
        if d < SCREEN_CHAMFER:
            candidates.append((i, j))
    dense = {}
    for k in {k for pair in candidates for k in pair}:
        dense[k] = sample_triangles(meshes[k].vertices, meshes[k].faces, 20000, rng)[0]
    # Sampling-noise floor, measured: the same model drawn twice.
    noise = _chamfer_l1(dense[candidates[0][0]], sample_triangles(
        meshes[candidates[0][0]].vertices, meshes[candidates[0][0]].faces, 20000, rng)[0])
    assert noise < 0.6 * DISTINCT_CHAMFER, noise
    closest, pair = min((_chamfer_l1(dense[i], dense[j]), (i, j)) for i, j in candidates)
    print(f"closest pair {pair}: Chamfer-L1 {closest:.4f}, noise floor {noise:.4f}")
    assert closest > DISTINCT_CHAMFER, closest


def _edge_connected_pieces(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Pieces of a triangle mesh whose faces are joined through shared edges (trimesh)."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency,
                                                      node_count=len(mesh.faces))
    return int(labels.max()) + 1


def test_default_catalogue_models_are_one_connected_piece() -> None:
    """Every appendage is attached: each processed model of the default catalogue (the one
    ``sq-mitsuba models generate`` writes) is a single edge-connected watertight surface."""
    entries = catalogue(DEFAULT_CATALOGUE_COUNT, DEFAULT_CATALOGUE_SEED)
    pieces = {}
    for entry in entries:
        model = process_mesh(generate_spacecraft(entry.seed, entry.archetype).union(),
                             method="solid")
        assert model.checks["watertight"], entry.name
        pieces[entry.name] = _edge_connected_pieces(model.mesh.vertices, model.mesh.faces)
    assert {name: n for name, n in pieces.items() if n != 1} == {}


@pytest.mark.parametrize("archetype", sorted(ARCHETYPES))
def test_every_archetype_is_one_piece_across_seeds(archetype: str) -> None:
    """Attachment holds beyond the default catalogue: seeds 0-9 of every family, raw union."""
    for seed in range(10):
        mesh = generate_spacecraft(seed, archetype).union()
        assert _edge_connected_pieces(mesh.vertices, mesh.faces) == 1, (archetype, seed)


def _thin_frame(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre, unit normal and thickness of a thin box given by its vertices."""
    centre = vertices.mean(axis=0)
    _, _, vt = np.linalg.svd(vertices - centre)
    normal = vt[2]
    thickness = float(np.ptp((vertices - centre) @ normal))
    return centre, normal, thickness


def test_thin_panels_survive_processing() -> None:
    sc = generate_spacecraft(5, "twin_wing")
    model = process_mesh(sc.union(), method="solid")
    matrix = model.normalisation.matrix()
    caster = RayCaster(model.mesh.vertices, model.mesh.faces)
    panels = [p for p in sc.parts if p.kind == "solar_panel"]
    assert panels
    for panel in panels:
        mesh = panel.solid.to_mesh64()
        v = np.asarray(mesh.vert_properties)[:, :3] @ matrix[:3, :3].T + matrix[:3, 3]
        centre, normal, thickness = _thin_frame(v)
        assert thickness == pytest.approx(0.01, rel=0.05)
        # Occupancy: the panel's mid-plane is inside, 0.01 off either face is outside.
        probes = np.array([centre, centre + 0.015 * normal, centre - 0.015 * normal])
        assert caster.inside(probes).tolist() == [True, False, False]
        # Mesh: rays from both sides meet faces 0.01 apart.
        t_top, _ = caster.first_hit((centre + 0.1 * normal)[None], -normal)
        t_bottom, _ = caster.first_hit((centre - 0.1 * normal)[None], normal)
        measured = 0.2 - t_top[0] - t_bottom[0]
        assert measured == pytest.approx(thickness, abs=2e-4)
    assert model.checks["watertight"] and model.checks["outward"]
