"""The own-mesh ranking (sq_mitsuba/evaluation/mesh_ranking.py) against brute force."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sq_mitsuba.evaluation.mesh_ranking import MeshRanking, assembly_clouds, median_rank
from sq_mitsuba.geometry.assembly import Assembly


def brute_force_chamfer_l1(a: np.ndarray, b: np.ndarray) -> float:
    """Paper convention: L1 nearest neighbours, the two directions' means summed."""
    distances = np.abs(a[:, None, :] - b[None, :, :]).sum(-1)
    return float(distances.min(1).mean() + distances.min(0).mean())


@pytest.fixture(scope="module")
def candidates() -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    # Four boxes of different proportions, surface-ish random points.
    extents = [(0.5, 0.2, 0.1), (0.2, 0.5, 0.3), (0.4, 0.4, 0.4), (0.1, 0.1, 0.6)]
    return [rng.uniform(-1, 1, (300 + 50 * k, 3)) * np.asarray(e) for k, e in enumerate(extents)]


def test_chamfer_matches_brute_force(candidates):
    cloud = np.random.default_rng(4).normal(size=(211, 3)) * 0.3
    got = MeshRanking(candidates).chamfer(cloud)
    want = [brute_force_chamfer_l1(cloud, c) for c in candidates]
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_own_mesh_is_first_when_the_prediction_is_that_mesh(candidates):
    ranking = MeshRanking(candidates)
    for own, cloud in enumerate(candidates):
        rank = ranking.rank(cloud, own)
        assert rank.rank == 1 and rank.beaten == 1.0 and rank.own_chamfer == 0.0
        assert rank.nearest_other > 0.0


def test_rank_counts_the_other_candidates_that_are_closer(candidates):
    ranking = MeshRanking(candidates)
    cloud = candidates[2] * 1.05  # nearest is candidate 2; ask where candidate 0 ranks
    distances = [brute_force_chamfer_l1(cloud, c) for c in candidates]
    closer = sum(d < distances[0] for k, d in enumerate(distances) if k != 0)
    rank = ranking.rank(cloud, 0)
    assert rank.rank == 1 + closer and closer >= 1
    assert rank.beaten == pytest.approx(1 - closer / 3)
    summary = median_rank([rank, ranking.rank(cloud, 2), ranking.rank(cloud, 2)])
    assert summary["median_rank"] == 1.0 and summary["top1"] == pytest.approx(2 / 3)


def test_assembly_clouds_drop_points_inside_other_primitives():
    # Two overlapping boxes: points of each inside the other do not count.
    assembly = Assembly.from_values(
        size=torch.tensor([[[0.3, 0.1, 0.1], [0.1, 0.3, 0.1]]], dtype=torch.float64),
        shape=torch.tensor([[[0.1, 0.1], [0.1, 0.1]]], dtype=torch.float64),
        translation=torch.zeros(1, 2, 3, dtype=torch.float64))
    (cloud,) = assembly_clouds(assembly, level=2)
    points, inside = assembly.surface_points_with_mask(2)
    assert len(cloud) == int((~inside).sum()) < points[0].reshape(-1, 3).shape[0]
    assert np.all(Assembly(assembly.params).union_occupancy(
        torch.from_numpy(cloud)[None] * 0.98)[0].numpy() > 0.5)


def test_bad_input_is_one_line(candidates):
    with pytest.raises(ValueError, match="at least 2 candidate"):
        MeshRanking(candidates[:1])
    with pytest.raises(ValueError, match=r"clouds\[1\]"):
        MeshRanking([candidates[0], np.zeros((0, 3))])
    with pytest.raises(ValueError, match="own: expected"):
        MeshRanking(candidates).rank(candidates[0], 4)
    with pytest.raises(ValueError, match="cloud: expected"):
        MeshRanking(candidates).chamfer(np.zeros((5, 2)))
