"""Half-turn symmetry detection on shapes built with a known symmetry group, a generated
spacecraft of each kind, and the cached per-model record."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from sq_mitsuba.data.mesh_io import TaggedMesh, obj_text
from sq_mitsuba.data.mesh_processing import process_mesh
from sq_mitsuba.data.solids import sample_triangles
from sq_mitsuba.data.spacecraft import generate_spacecraft
from sq_mitsuba.data.symmetry import (
    DEFAULT_THRESHOLD,
    HALF_TURNS,
    SYMMETRIES_FILE,
    detect_symmetries,
    model_symmetries,
    stack_symmetries,
    symmetry_distances,
)


def boxes_points(boxes, count=20_000, seed=0):
    """Surface points of a union of boxes given as (extents, centre) pairs."""
    meshes = []
    for extents, centre in boxes:
        transform = np.eye(4)
        transform[:3, 3] = centre
        meshes.append(trimesh.creation.box(extents=extents, transform=transform))
    mesh = trimesh.util.concatenate(meshes)
    points, _ = sample_triangles(np.asarray(mesh.vertices), np.asarray(mesh.faces), count,
                                 np.random.default_rng(seed))
    return points


BUS = ((0.3, 0.25, 0.35), (0.0, 0.0, 0.0))
MAST = ((0.05, 0.05, 0.15), (0.0, 0.0, 0.25))  # on top: no half turn about x or y keeps it
#: Bus, top mast, and two wings at +-x offset to +-y: only the half turn about z maps the
#: wings onto each other (about x or y the wings land 0.2 off, and the mast below the bus).
ONLY_Z = [BUS, MAST, ((0.35, 0.15, 0.01), (0.325, 0.1, 0.0)),
          ((0.35, 0.15, 0.01), (-0.325, -0.1, 0.0))]
#: One wing only: no half turn maps it onto anything.
ASYMMETRIC = [BUS, MAST, ((0.35, 0.15, 0.01), (0.325, 0.1, 0.0))]
#: A centred box alone: every half turn is a symmetry.
BOX = [((0.6, 0.4, 0.2), (0.0, 0.0, 0.0))]


def as_axes(matrices):
    """Which half turns a list of matrices holds, checking the identity comes first."""
    assert np.array_equal(matrices[0], np.eye(3))
    return [a for a, turn in HALF_TURNS.items() for m in matrices[1:] if np.array_equal(m, turn)]


def test_half_turn_about_z_only():
    points = boxes_points(ONLY_Z)
    distances = symmetry_distances(points)
    assert distances["z"] < 0.1 * DEFAULT_THRESHOLD
    assert min(distances["x"], distances["y"]) > 2 * DEFAULT_THRESHOLD
    assert as_axes(detect_symmetries(points)) == ["z"]


def test_asymmetric_model_has_identity_only():
    matrices = detect_symmetries(boxes_points(ASYMMETRIC))
    assert len(matrices) == 1 and as_axes(matrices) == []


def test_box_has_every_half_turn_and_the_distance_is_scale_free():
    points = boxes_points(BOX)
    assert as_axes(detect_symmetries(points)) == ["x", "y", "z"]
    # The distance is relative to the longest side: the same shape at 10x is the same.
    small, large = symmetry_distances(boxes_points(ONLY_Z)), symmetry_distances(
        10 * boxes_points(ONLY_Z))
    assert all(small[k] == pytest.approx(large[k], rel=1e-9, abs=1e-12) for k in small)


def test_distance_is_the_floor_corrected_chamfer():
    """The definition, checked by brute force on a small cloud."""
    points = boxes_points(ONLY_Z, count=2_000, seed=3)
    order = np.random.default_rng(0).permutation(len(points))
    first, second = points[order[:1000]], points[order[1000:]]

    def chamfer(a, b):
        d = np.linalg.norm(a[:, None] - b[None], axis=-1)
        return 0.5 * (d.min(1).mean() + d.min(0).mean())

    size = np.ptp(points, axis=0).max()
    floor = chamfer(first, second)
    distances = symmetry_distances(points)
    assert distances["floor"] == pytest.approx(floor / size, rel=1e-9)
    for axis, turn in HALF_TURNS.items():
        expected = (chamfer(first, second @ turn.T) - floor) / size
        assert distances[axis] == pytest.approx(expected, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize(("seed", "archetype", "axes"), [
    (4253401181, "sunshade_observatory", ["z"]),  # mirror-symmetric shade and telescope
    (549907821, "single_wing", []),
])
def test_generated_spacecraft(seed, archetype, axes):
    spacecraft = generate_spacecraft(seed, archetype)
    model = process_mesh(spacecraft.union(), method="solid")
    points, _ = sample_triangles(model.mesh.vertices, model.mesh.faces, 20_000,
                                 np.random.default_rng(0))
    distances = symmetry_distances(points)
    assert as_axes(detect_symmetries(points)) == axes
    # Far from the threshold either way: the decision does not hinge on sampling noise.
    assert all(distances[a] < 0.3 * DEFAULT_THRESHOLD or distances[a] > 3 * DEFAULT_THRESHOLD
               for a in HALF_TURNS)


def write_samples(model_dir, points):
    (model_dir / "models").mkdir(parents=True)
    np.savez_compressed(model_dir / "models" / "samples.npz",
                        surface_points=points.astype(np.float32))


def test_model_symmetries_computes_writes_and_reads(tmp_path):
    write_samples(tmp_path / "m", boxes_points(ONLY_Z))
    matrices = model_symmetries(tmp_path / "m")  # reading a model writes nothing beside it
    assert not (tmp_path / "m" / "models" / SYMMETRIES_FILE).exists()
    assert np.array_equal(model_symmetries(tmp_path / "m", write=True), matrices)
    assert matrices.shape == (2, 3, 3)
    assert np.array_equal(matrices[0], np.eye(3)) and np.array_equal(matrices[1], HALF_TURNS["z"])
    path = tmp_path / "m" / "models" / SYMMETRIES_FILE
    record = json.loads(path.read_text())
    assert record["axes"] == ["z"] and record["threshold"] == DEFAULT_THRESHOLD
    assert set(record["distances"]) == {"x", "y", "z"}
    assert record["distances"]["z"] < DEFAULT_THRESHOLD < record["distances"]["x"]
    # The file is the record: it is read back, not recomputed.
    record["matrices"] = [np.eye(3).tolist(), HALF_TURNS["x"].tolist()]
    path.write_text(json.dumps(record))
    assert np.array_equal(model_symmetries(tmp_path / "m")[1], HALF_TURNS["x"])


def test_model_symmetries_from_the_mesh_without_samples(tmp_path):
    mesh = trimesh.creation.box(extents=(0.6, 0.4, 0.2))
    tagged = TaggedMesh(np.asarray(mesh.vertices), np.asarray(mesh.faces),
                        np.zeros(len(mesh.faces), dtype=np.int16))
    (tmp_path / "m" / "models").mkdir(parents=True)
    (tmp_path / "m" / "models" / "model_normalized.obj").write_text(obj_text(tagged))
    assert model_symmetries(tmp_path / "m", write=True).shape == (4, 3, 3)
    assert (tmp_path / "m" / "models" / SYMMETRIES_FILE).is_file()


@pytest.mark.parametrize(("content", "message"), [
    ("{", "not valid JSON"),
    ('{"format": "other"}', "not a symmetries file"),
    ('{"format": "sq_mitsuba.data.symmetry", "matrices": [[1, 0, 0]]}', "matrices"),
    ('{"format": "sq_mitsuba.data.symmetry", "matrices": [[[2, 0, 0], [0, 1, 0], [0, 0, 1]]]}',
     "rotation"),
    ('{"format": "sq_mitsuba.data.symmetry", '
     '"matrices": [[[-1, 0, 0], [0, -1, 0], [0, 0, 1]]]}', "identity"),
])
def test_model_symmetries_bad_file(tmp_path, content, message):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / SYMMETRIES_FILE).write_text(content)
    with pytest.raises(ValueError, match=message):
        model_symmetries(tmp_path)


def test_model_symmetries_missing_folder_and_bad_points(tmp_path):
    with pytest.raises(FileNotFoundError, match="models"):
        model_symmetries(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="surface_points"):
        detect_symmetries(np.zeros((50, 3)))
    with pytest.raises(ValueError, match="surface_points"):
        detect_symmetries(np.zeros((5000, 2)))
    with pytest.raises(ValueError, match="threshold"):
        detect_symmetries(boxes_points(BOX, 2000), threshold=-1)
    write_samples(tmp_path / "few", boxes_points(BOX, 200))
    with pytest.raises(ValueError, match="surface_points"):
        model_symmetries(tmp_path / "few", write=True)
    assert not (tmp_path / "few" / "models" / SYMMETRIES_FILE).exists()
    points = boxes_points(BOX, 2000)
    points[3] = np.nan
    write_samples(tmp_path / "nan", points)
    with pytest.raises(ValueError, match=r"samples\.npz: surface_points: 1 of 2000 points"):
        model_symmetries(tmp_path / "nan")


def test_stack_symmetries_pads_with_identity():
    stacked = stack_symmetries([np.eye(3)[None], np.stack([np.eye(3), HALF_TURNS["z"],
                                                           HALF_TURNS["x"]])])
    assert stacked.shape == (2, 3, 3, 3)
    assert np.array_equal(stacked[0], np.tile(np.eye(3), (3, 1, 1)))
    assert np.array_equal(stacked[1, 2], HALF_TURNS["x"])
    with pytest.raises(ValueError, match=r"sets\[0\]"):
        stack_symmetries([np.ones((1, 3, 3))])


def test_symmetry_table_in_worker_processes_matches_one_process(tmp_path):
    """The training table of many models, analysed in two worker processes, holds each
    model's own group (padded with identities), the same as one process gives; a model that
    cannot be analysed gets the identity alone, and every analysis is kept in the cache."""
    from sq_mitsuba.training.data_stream import symmetry_table

    shapes = [ONLY_Z, ASYMMETRIC, BOX, ONLY_Z, BOX, ASYMMETRIC, ONLY_Z, BOX]
    names = [f"m{i}" for i in range(len(shapes))] + ["broken"]
    for name, shape in zip(names, shapes, strict=False):
        write_samples(tmp_path / "data" / name, boxes_points(shape, count=4_000, seed=1))
    (tmp_path / "data" / "broken" / "models").mkdir(parents=True)  # no samples, no mesh
    pooled = symmetry_table(tmp_path / "data", names, tmp_path / "pool", workers=2)
    serial = symmetry_table(tmp_path / "data", names, tmp_path / "serial", workers=1)
    assert torch.equal(pooled, serial) and pooled.shape == (len(names), 4, 3, 3)
    expected = {id(ONLY_Z): ["z"], id(ASYMMETRIC): [], id(BOX): ["x", "y", "z"]}
    for row, shape in zip(pooled, [*shapes, None], strict=True):
        axes = expected.get(id(shape), [])
        assert as_axes(row.numpy()[:1 + len(axes)]) == axes
        assert all(np.array_equal(m, np.eye(3)) for m in row.numpy()[1 + len(axes):])
    assert len(list((tmp_path / "pool").glob("*.json"))) == len(shapes)


def test_two_passing_half_turns_bring_the_third():
    """Half turns about x and y compose to the one about z: a set with two of them alone is no
    group, and a symmetry-aware loss would count the implied pose as an error."""
    from sq_mitsuba.data.symmetry import passing_axes

    threshold = 0.01
    assert passing_axes({"x": 0.0095, "y": 0.0098, "z": 0.0103}, threshold) == ["x", "y", "z"]
    assert passing_axes({"x": 0.0095, "y": 0.02, "z": 0.0103}, threshold) == ["x"]
    assert passing_axes({"x": 0.02, "y": 0.03, "z": 0.04}, threshold) == []
    turns = [HALF_TURNS[a] for a in "xyz"]
    np.testing.assert_allclose(turns[0] @ turns[1], turns[2], atol=1e-12)  # why: the product
