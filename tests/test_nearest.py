"""The nearest-neighbour core of the Chamfer distances against brute force, in float64.

The tests that take ``device`` run on ``pytest --device`` (conftest.py): the KD-tree search
runs on the CPU, its indices come back on the clouds' device."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sq_mitsuba.geometry.nearest import gathered_differences, matched_indices, nearest_neighbours


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_nearest_neighbours_match_brute_force(p):
    rng = np.random.default_rng(0)
    source, target = rng.normal(size=(200, 3)), rng.normal(size=(300, 3))
    distances, indices = nearest_neighbours(source, target, p)
    dense = (np.abs(source[:, None] - target[None]) ** p).sum(-1) ** (1 / p)
    np.testing.assert_array_equal(indices, dense.argmin(1))
    np.testing.assert_allclose(distances, dense.min(1), rtol=1e-12)
    assert distances.dtype == np.float64 and indices.dtype == np.int64


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_matched_indices_respect_the_mask_both_ways(p, device):
    gen = torch.Generator().manual_seed(1)
    a = torch.randn(3, 40, 3, generator=gen, dtype=torch.float64).to(device)
    b = torch.randn(3, 60, 3, generator=gen, dtype=torch.float64).to(device)
    keep = (torch.rand(3, 40, generator=gen) > 0.4).to(device)
    a_to_b, b_to_a = matched_indices(a, keep, b, p)
    for item in range(3):
        dense = torch.cdist(a[item], b[item], p=p)  # (40, 60)
        kept = keep[item]
        assert torch.equal(a_to_b[item][kept], dense[kept].argmin(1))
        assert torch.equal(a_to_b[item][~kept], torch.zeros_like(a_to_b[item][~kept]))
        masked = dense.masked_fill(~kept[:, None], float("inf"))
        assert torch.equal(b_to_a[item], masked.argmin(0))


def test_gathered_differences_value_and_gradient(device):
    gen = torch.Generator().manual_seed(2)
    source = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64).to(device)
    target = torch.randn(2, 7, 3, generator=gen, dtype=torch.float64).to(device)
    source.requires_grad_()
    target.requires_grad_()
    index = torch.randint(0, 7, (2, 5), generator=gen).to(device)
    differences = gathered_differences(source, target, index)
    expected = torch.stack([source[b] - target[b][index[b]] for b in range(2)])
    assert torch.equal(differences, expected)
    assert torch.autograd.gradcheck(lambda s, t: gathered_differences(s, t, index),
                                    (source, target))


def _matched_distances(a, b, a_to_b, b_to_a, p):
    """The L``p`` distance of every matched pair: (B, N) a -> b and (B, K) b -> a."""
    forward = torch.linalg.vector_norm(gathered_differences(a, b, a_to_b), ord=p, dim=-1)
    backward = torch.linalg.vector_norm(gathered_differences(b, a, b_to_a), ord=p, dim=-1)
    return forward, backward


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("p", [1.0, 2.0])
def test_dense_search_equals_the_kdtree_search(p, dtype, device):
    """The batched dense search (forced on any device) matches the KD-tree's pairs: equal
    matched distances (indices may differ only between tied neighbours), masks respected."""
    gen = torch.Generator().manual_seed(3)
    a = torch.randn(4, 300, 3, generator=gen, dtype=dtype).to(device)
    b = torch.randn(4, 500, 3, generator=gen, dtype=dtype).to(device)
    keep = (torch.rand(4, 300, generator=gen) > 0.3).to(device)
    keep[2] = False
    keep[2, 7] = True  # an item keeping one point
    kd = matched_indices(a, keep, b, p, method="kdtree")
    dense = matched_indices(a, keep, b, p, method="dense")
    assert all(i.device == a.device and i.dtype == torch.int64 for i in (*kd, *dense))
    assert torch.equal(dense[0][~keep], torch.zeros_like(dense[0][~keep]))
    assert bool(keep.gather(1, dense[1]).all())  # b's neighbours are kept points of a
    tolerance = 1e-12 if dtype == torch.float64 else 1e-5
    (dense_forward, dense_backward) = _matched_distances(a, b, *dense, p)
    (kd_forward, kd_backward) = _matched_distances(a, b, *kd, p)
    torch.testing.assert_close(dense_forward[keep], kd_forward[keep], rtol=0, atol=tolerance)
    torch.testing.assert_close(dense_backward, kd_backward, rtol=0, atol=tolerance)


def test_dense_search_in_small_chunks_equals_one_chunk(monkeypatch):
    """Chunks of items and of rows (b's running minimum over them) give one chunk's answer."""
    import sq_mitsuba.geometry.nearest as nearest

    gen = torch.Generator().manual_seed(4)
    a, b = torch.randn(5, 90, 3, generator=gen), torch.randn(5, 70, 3, generator=gen)
    keep = torch.rand(5, 90, generator=gen) > 0.5
    whole = matched_indices(a, keep, b, 2.0, method="dense")
    monkeypatch.setattr(nearest, "DENSE_CHUNK", 70 * 16)  # 16 rows of one item at a time
    chunked = matched_indices(a, keep, b, 2.0, method="dense")
    assert torch.equal(whole[0], chunked[0]) and torch.equal(whole[1], chunked[1])


def test_the_search_is_chosen_by_device():
    from sq_mitsuba.geometry.nearest import nearest_method

    assert nearest_method(torch.device("cpu")) == "kdtree"
    assert nearest_method(torch.device("cuda", 0)) == "dense"
    assert nearest_method(torch.device("cpu"), "dense") == "dense"
    with pytest.raises(ValueError, match="method"):
        nearest_method(torch.device("cpu"), "brute")
    with pytest.raises(ValueError, match="p: the dense search"):
        matched_indices(torch.zeros(1, 2, 3), torch.ones(1, 2, dtype=torch.bool),
                        torch.zeros(1, 2, 3), 3.0, method="dense")


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_chamfer_loss_value_and_gradient_equal_between_searches(dtype, device):
    from sq_mitsuba.model.losses import chamfer_loss

    gen = torch.Generator().manual_seed(5)
    points = torch.randn(3, 200, 3, generator=gen, dtype=dtype).to(device)
    target = torch.randn(3, 400, 3, generator=gen, dtype=dtype).to(device)
    keep = (torch.rand(3, 200, generator=gen) > 0.25).to(device)
    results = []
    for method in ("kdtree", "dense"):
        leaf = points.clone().requires_grad_(True)
        loss = chamfer_loss(leaf, keep, target, method=method)
        loss.backward()
        results.append((loss.detach(), leaf.grad))
    tolerance = {"rtol": 1e-12, "atol": 1e-12} if dtype == torch.float64 else \
        {"rtol": 1e-5, "atol": 1e-6}
    torch.testing.assert_close(results[1][0], results[0][0], **tolerance)
    torch.testing.assert_close(results[1][1], results[0][1], **tolerance)
