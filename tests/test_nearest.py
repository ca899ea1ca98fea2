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
