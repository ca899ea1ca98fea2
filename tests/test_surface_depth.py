"""The visible surface's depth (``model.surface_depth``): the target map against a brute-force
projection, a flat plate facing the camera against its analytic depth, the loss against its
definition; the depth head and its term in a training step."""

from __future__ import annotations

import math

import pytest
import torch

from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import random_rotations
from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet
from sq_mitsuba.model.surface_depth import surface_depth_loss, visible_depth_map

K = torch.tensor([[60.0, 0.0, 31.0], [0.0, 64.0, 33.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_the_map_is_the_nearest_point_of_each_cell_by_brute_force() -> None:
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(2, 300, 3, generator=generator, dtype=torch.float64) - 0.5
    rotation = random_rotations(2, generator, dtype=torch.float64)
    translation = torch.tensor([[0.1, -0.2, 2.0], [-0.3, 0.0, 2.5]], dtype=torch.float64)
    depth, valid = visible_depth_map(points, rotation, translation, K, 64, stride=8,
                                     min_points=2)
    assert depth.shape == valid.shape == (2, 1, 8, 8)
    for b in range(2):
        nearest: dict[tuple[int, int], list[float]] = {}
        for point in points[b]:
            camera = rotation[b] @ point + translation[b]
            u, v, w = (K @ camera).tolist()
            column, row = math.floor(u / w / 8), math.floor(v / w / 8)
            if 0 <= column < 8 and 0 <= row < 8:
                nearest.setdefault((row, column), []).append(camera[2].item())
        expected_valid = torch.zeros(8, 8, dtype=torch.bool)
        for (row, column), zs in nearest.items():
            if len(zs) >= 2:
                expected_valid[row, column] = True
                assert depth[b, 0, row, column].item() == pytest.approx(
                    min(zs) - translation[b, 2].item(), abs=1e-12)
        assert torch.equal(valid[b, 0], expected_valid)
        assert bool((depth[b, 0][~expected_valid] == 0).all())


def test_a_plate_facing_the_camera_has_its_own_depth() -> None:
    """A square plate at z = -0.2 in the body frame, a camera looking along +z from 2 m: every
    cell the plate fills reads -0.2 (its points all lie there), the others do not count."""
    grid = torch.linspace(-0.3, 0.3, 61, dtype=torch.float64)
    x, y = torch.meshgrid(grid, grid, indexing="ij")
    plate = torch.stack([x.flatten(), y.flatten(), torch.full_like(x.flatten(), -0.2)], -1)
    depth, valid = visible_depth_map(plate[None], torch.eye(3, dtype=torch.float64)[None],
                                     torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64), K,
                                     64, stride=4)
    assert int(valid.sum()) > 20
    torch.testing.assert_close(depth[valid], torch.full_like(depth[valid], -0.2))


def test_the_loss_is_the_mean_error_over_valid_cells() -> None:
    target = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]], [[[0.0, 0.0], [0.0, 0.0]]]])
    valid = torch.tensor([[[[True, True], [False, False]]], [[[False, False], [False, False]]]])
    predicted = target + torch.tensor([[[[0.5, -1.5], [9.0, 9.0]]], [[[9.0, 9.0], [9.0, 9.0]]]])
    # Item 0: mean of 0.5 and 1.5; item 1: no valid cell, 0.
    assert surface_depth_loss(predicted, target, valid).item() == pytest.approx(0.5)
    with pytest.raises(ValueError, match="one shape"):
        surface_depth_loss(predicted[:, :, :1], target, valid)


def test_the_depth_head_trains_through_its_term() -> None:
    """A network with a depth head: its map has the mask head's stride-4 shape and starts near
    depth 0; the term reads it against the batch's points and its gradient reaches the head."""
    from sq_mitsuba.training.batch import TrainingBatch
    from sq_mitsuba.training.loss_terms import LossConfig, LossContext, compute_terms

    torch.manual_seed(1)
    net = SuperquadricNet(NetworkConfig(encoder="efficientnet_lite0", latent="spatial",
                                        image_size=64, num_primitives=2, latent_dim=16,
                                        hidden_dim=16, spatial_channels=8, depth_head=True))
    k = Camera.default(64).matrix(torch.float32)
    images = torch.rand(2, 1, 64, 64, generator=torch.Generator().manual_seed(2))
    out = net(images, k)
    assert out.surface_depth is not None and out.surface_depth.shape == (2, 1, 16, 16)
    generator = torch.Generator().manual_seed(3)
    batch = TrainingBatch(
        image=images, mask=torch.zeros(2, 1, 64, 64),
        rotation=random_rotations(2, generator), translation=torch.tensor([[0.0, 0.0, 2.0]] * 2),
        model_index=torch.zeros(2, dtype=torch.long),
        surface_points=torch.rand(2, 500, 3, generator=generator) - 0.5,
        occupancy_points=torch.zeros(2, 4, 3), occupancy_labels=torch.zeros(2, 4),
        symmetries=torch.eye(3).expand(2, 1, 3, 3))
    context = LossContext(LossConfig(weights={"surface_depth": 1.0}), camera_matrix=k)
    term = compute_terms(out, batch, context)["surface_depth"]
    assert 0 < term.item() < 1.0  # points within 0.87 of the origin, the map near 0
    term.backward()
    assert net.depth_head.to_logit.weight.grad.abs().sum() > 0
