"""Procedural spacecraft: determinism, variety, parts and materials, thin panels."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from sq_mitsuba.data.mesh_processing import normalise, process_mesh
from sq_mitsuba.data.solids import sample_triangles
from sq_mitsuba.data.spacecraft import (
    ARCHETYPES,
    DEFAULT_CATALOGUE_COUNT,
    DEFAULT_CATALOGUE_SEED,
    MATERIALS,
    catalogue,
    generate_spacecraft,
)
from sq_mitsuba.data.spacecraft.generator import MAX_CATALOGUE_COUNT, TEST_STRATA, catalogue_split
from sq_mitsuba.data.spacecraft.parts import CUBESAT_UNITS, cubesat_bus
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
    # near[i, j]: mean distance from 500 of model i's points to model j's 2,000 (one query per
    # tree). A quarter of the points (drawn at random) moves the mean by about 0.0005, far
    # inside the screen's margin over DISTINCT_CHAMFER.
    queries = np.concatenate([c[:500] for c in clouds])
    near = np.stack([cKDTree(c).query(queries, workers=-1)[0].reshape(64, -1).mean(axis=1)
                     for c in clouds], axis=1)
    candidates = [(i, j) for i, j in itertools.combinations(range(64), 2)
                  if 0.5 * (near[i, j] + near[j, i]) < SCREEN_CHAMFER]
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


def test_catalogue_splits_do_not_move_with_count() -> None:
    """A model's split is a function of its name and the catalogue seed: the first models of a
    small catalogue are those of a large one, splits included (the old rule drew the test
    models among ``count``, so ``--count 3`` and ``--count 64`` disagreed)."""
    for seed in (0, 5, 7, 123_456, 2**32 - 1):
        big = catalogue(200, seed)
        for count in (1, 2, 3, 6, 64, 65):
            assert catalogue(count, seed) == big[:count], (seed, count)
        by_name = {e.name: e.split for e in big}
        assert all(by_name[e.name] == e.split for e in catalogue(6, seed))
        assert all(e.split == catalogue_split(seed, i) for i, e in enumerate(big))
        assert all(e.catalogue_seed == seed for e in big)


def test_every_block_of_64_has_7_test_models_and_small_catalogues_one() -> None:
    for seed in range(40):
        entries = catalogue(192, seed)
        for block in range(3):
            assert sum(e.split == "test" for e in entries[64 * block:64 * block + 64]) == 7
        assert sum(e.split == "test" for e in entries[:2]) == 1, seed
        # The test models are spread: none of the 7 strata of a block goes without one.
        tests = [i for i, e in enumerate(entries[:64]) if e.split == "test"]
        assert len({next(k for k in range(7) if i < TEST_STRATA[k + 1]) for i in tests}) == 7
    assert catalogue(1, 0)[0].split == catalogue(64, 0)[0].split


def test_catalogue_seed_and_count_ranges() -> None:
    with pytest.raises(ValueError, match=r"seed: expected an integer in \[0, 4294967295\]"):
        catalogue(3, -1)
    with pytest.raises(ValueError, match="seed"):
        catalogue(3, 2**32)
    with pytest.raises(ValueError, match="count"):
        catalogue(0, 0)
    with pytest.raises(ValueError, match="count"):
        catalogue(MAX_CATALOGUE_COUNT + 1, 0)
    assert len(catalogue(3, 2**32 - 1)) == 3


@pytest.mark.parametrize("units", sorted(CUBESAT_UNITS))
def test_cubesat_rails_at_the_corners_and_proud_of_the_ends(units: int) -> None:
    """Four 8.5 mm square rails along z at the corners of the U envelope (their outer faces
    on it), standing 7 mm proud of each end of the body; a 1U is then the CubeSat Design
    Specification's 100 x 100 x 113.5 mm to 0.5 mm."""
    parts = cubesat_bus(units, thin=0.002)
    body = [np.array(p.solid.bounding_box()) for p in parts if p.kind == "cubesat_body"]
    rails = [np.array(p.solid.bounding_box()) for p in parts if p.kind == "cubesat_rail"]
    assert len(body) == 1 and len(rails) == 4
    envelope = np.array(CUBESAT_UNITS[units], float) * 0.1
    corners = set()
    for low, high in ((r[:3], r[3:]) for r in rails):
        np.testing.assert_allclose(high[:2] - low[:2], [0.0085, 0.0085], atol=1e-9)
        outer = np.where(low[:2] < 0, low[:2], high[:2])
        np.testing.assert_allclose(np.abs(outer), envelope[:2] / 2, atol=1e-9)
        corners.add(tuple(np.sign(outer)))
        np.testing.assert_allclose([body[0][2] - low[2], high[2] - body[0][5]], [0.007, 0.007],
                                   atol=1e-9)
    assert len(corners) == 4
    np.testing.assert_allclose(body[0][5] - body[0][2], envelope[2], atol=1e-9)
    if units == 1:
        whole = np.array([min(r[k] for r in rails) for k in range(3)]
                         + [max(r[k] for r in rails) for k in range(3, 6)])
        np.testing.assert_allclose(whole[3:] - whole[:3], [0.100, 0.100, 0.1135], atol=5e-4)
