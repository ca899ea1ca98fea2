"""The visible surface's normals (``model.surface_normals``): the target map against a
brute-force projection, a box's faces against their analytic normals, the loss against its
definition; the normal head and its term in a training step."""

from __future__ import annotations

import math

import pytest
import torch

from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import random_rotations
from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet
from sq_mitsuba.model.surface_normals import surface_normal_loss, visible_normal_map

SMALL = dict(encoder="efficientnet_lite0", latent="spatial", image_size=64, num_primitives=2,
             latent_dim=16, hidden_dim=16, spatial_channels=8, normal_head=True)
"A small network with a normal head, cheap to run on 64 px images."
K = torch.tensor([[60.0, 0.0, 31.0], [0.0, 64.0, 33.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_the_map_is_the_front_facing_normals_mean_by_brute_force() -> None:
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(2, 300, 3, generator=generator, dtype=torch.float64) - 0.5
    normals = torch.nn.functional.normalize(
        torch.randn(2, 300, 3, generator=generator, dtype=torch.float64), dim=-1)
    normals[1, :20] = 0.0  # unknown normals count for nothing
    rotation = random_rotations(2, generator, dtype=torch.float64)
    translation = torch.tensor([[0.1, -0.2, 2.0], [-0.3, 0.0, 2.5]], dtype=torch.float64)
    band = 0.1
    normal, valid = visible_normal_map(points, normals, rotation, translation, K, 64, stride=8,
                                       band=band)
    assert normal.shape == (2, 3, 8, 8) and valid.shape == (2, 1, 8, 8)
    for b in range(2):
        facing: dict[tuple[int, int], list[tuple[float, torch.Tensor]]] = {}
        for i, point in enumerate(points[b]):
            camera = rotation[b] @ point + translation[b]
            turned = rotation[b] @ normals[b, i]
            u, v, w = (K @ camera).tolist()
            cell = (math.floor(v / w / 8), math.floor(u / w / 8))
            if 0 <= cell[0] < 8 and 0 <= cell[1] < 8 and float(turned @ camera) < 0:
                facing.setdefault(cell, []).append((camera[2].item(), turned))
        expected_valid = torch.zeros(8, 8, dtype=torch.bool)
        for (row, column), seen in facing.items():
            front = min(z for z, _ in seen) + band
            counted = [n for z, n in seen if z <= front and float(n.norm()) > 0.5]
            if counted:
                expected_valid[row, column] = True
                torch.testing.assert_close(normal[b, :, row, column],
                                           sum(counted) / len(counted))
        assert torch.equal(valid[b, 0], expected_valid)
        assert bool((normal[b].permute(1, 2, 0)[~expected_valid] == 0).all())


def test_a_box_turned_towards_the_camera_shows_its_faces_normals() -> None:
    """A unit cube's surface, turned so three faces face the camera: the cells read those
    three faces' normals, turned into the camera frame, and each of them is seen (a cell
    where two faces meet reads their mean: 90 % of the cells at least)."""
    generator = torch.Generator().manual_seed(4)
    face_points, face_normals = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = torch.rand(4000, 3, generator=generator, dtype=torch.float64) - 0.5
            p[:, axis] = 0.5 * sign
            n = torch.zeros(4000, 3, dtype=torch.float64)
            n[:, axis] = sign
            face_points.append(p)
            face_normals.append(n)
    points, normals = torch.cat(face_points)[None], torch.cat(face_normals)[None]
    # Turned 35 deg about y, then 25 about x: the camera sees the -x, -y and -z faces.
    a, b = math.radians(35), math.radians(25)
    about_y = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0],
                            [-math.sin(a), 0, math.cos(a)]], dtype=torch.float64)
    about_x = torch.tensor([[1, 0, 0], [0, math.cos(b), -math.sin(b)],
                            [0, math.sin(b), math.cos(b)]], dtype=torch.float64)
    rotation = (about_x @ about_y)[None]
    normal, valid = visible_normal_map(points, normals, rotation,
                                       torch.tensor([[0.0, 0.0, 2.5]], dtype=torch.float64), K,
                                       64, stride=4, band=0.005)
    seen = normal[0].permute(1, 2, 0)[valid[0, 0]]  # (cells, 3)
    assert float(seen.norm(dim=1).max()) <= 1 + 1e-12  # a mean of unit normals
    faces = (torch.eye(3, dtype=torch.float64) @ rotation[0].T)  # +x, +y, +z turned
    facing = torch.cat([faces, -faces])
    facing = facing[facing[:, 2] < 0]  # the three faces whose normals point at the camera
    assert len(facing) == 3 and len(seen) > 30
    match = (seen @ facing.T)  # cosine to each facing face's normal
    assert float((match.amax(1) > 1 - 1e-9).double().mean()) > 0.9
    assert set(match.argmax(1).tolist()) == {0, 1, 2}


def test_the_loss_is_the_mean_squared_distance_over_valid_cells() -> None:
    target = torch.zeros(2, 3, 1, 2)
    target[0, 2] = -1.0  # both cells of item 0 face the camera
    valid = torch.tensor([[[[True, False]]], [[[False, False]]]])
    predicted = torch.zeros(2, 3, 1, 2)
    predicted[0, :, 0, 0] = torch.tensor([0.6, 0.0, -0.2])  # 0.36 + 0.64 away
    predicted[0, :, 0, 1] = torch.tensor([0.0, 0.0, 5.0])  # not counted
    predicted[1] = 1.0
    # Item 0: 1.0 on its one valid cell; item 1: none valid, 0.
    assert surface_normal_loss(predicted, target, valid).item() == pytest.approx(0.5)
    with pytest.raises(ValueError, match="expected"):
        surface_normal_loss(predicted[:, :1], target, valid)


def test_the_normal_head_trains_through_its_term() -> None:
    """A network with a normal head: its map has the stride-4 shape and starts facing the
    camera; the term reads it against the batch's points and normals and its gradient reaches
    the head; without normals in the batch the term names what is missing."""
    from sq_mitsuba.training.batch import TrainingBatch
    from sq_mitsuba.training.loss_terms import (
        LossConfig,
        LossContext,
        LossTermError,
        compute_terms,
    )

    torch.manual_seed(1)
    net = SuperquadricNet(NetworkConfig(**SMALL))
    k = Camera.default(64).matrix(torch.float32)
    images = torch.rand(2, 1, 64, 64, generator=torch.Generator().manual_seed(2))
    out = net(images, k)
    assert out.surface_normals is not None and out.surface_normals.shape == (2, 3, 16, 16)
    assert bool((out.surface_normals[:, 2] < 0).float().mean() > 0.9)
    generator = torch.Generator().manual_seed(3)
    points = torch.rand(2, 500, 3, generator=generator) - 0.5
    fields = dict(
        image=images, mask=torch.zeros(2, 1, 64, 64),
        rotation=random_rotations(2, generator), translation=torch.tensor([[0.0, 0.0, 2.0]] * 2),
        model_index=torch.zeros(2, dtype=torch.long), surface_points=points,
        occupancy_points=torch.zeros(2, 4, 3), occupancy_labels=torch.zeros(2, 4),
        symmetries=torch.eye(3).expand(2, 1, 3, 3))
    batch = TrainingBatch(**fields, surface_normals=torch.nn.functional.normalize(points, dim=-1))
    context = LossContext(LossConfig(weights={"surface_normal": 1.0}), camera_matrix=k)
    term = compute_terms(out, batch, context)["surface_normal"]
    assert 0 < term.item() < 4.0  # the distance between vectors of length <= 1
    term.backward()
    assert net.normal_head.to_logit.weight.grad.abs().sum() > 0
    with pytest.raises(LossTermError, match="no surface normals"):
        compute_terms(net(images, k), TrainingBatch(**fields), context)


def test_a_samples_file_without_good_normals_gives_zeros_and_no_cell(tmp_path) -> None:
    """Normals are optional: a samples.npz without them (an older release), or with them in
    another shape or holding NaN, reads as zeros, and no cell of the map counts."""
    import numpy as np

    from sq_mitsuba.data.spe3r.layout import read_samples, usable_normals

    points = np.random.default_rng(0).uniform(-0.5, 0.5, (50, 3))
    good = points / np.linalg.norm(points, axis=1, keepdims=True)
    cases = {"none": {}, "short": {"surface_normals": good[:10]},
             "nan": {"surface_normals": np.where(good > 0.9, np.nan, good)},
             "good": {"surface_normals": good}}
    for name, extra in cases.items():
        path = tmp_path / f"{name}.npz"
        np.savez(path, surface_points=points, **extra)
        samples = read_samples(path, ("surface_points",), optional=("surface_normals",))
        assert ("surface_normals" in samples) == (name != "none")
        read = usable_normals(samples.get("surface_normals"), len(points))
        assert read.shape == (50, 3)
        if name == "good":
            np.testing.assert_array_equal(read, good)
            continue
        assert not read.any(), name
        _, valid = visible_normal_map(torch.from_numpy(points)[None],
                                      torch.from_numpy(read).double()[None],
                                      torch.eye(3, dtype=torch.float64)[None],
                                      torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64), K,
                                      64)
        assert not bool(valid.any()), name


def test_normals_of_another_shape_than_the_points_are_refused() -> None:
    points = torch.zeros(2, 10, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="normals: expected the points' shape"):
        visible_normal_map(points, points[:, :5], torch.eye(3, dtype=torch.float64).expand(2, 3, 3),
                           torch.zeros(2, 3, dtype=torch.float64), K, 64)
    with pytest.raises(ValueError, match="points"):
        visible_normal_map(points[0], points[0], torch.eye(3, dtype=torch.float64)[None],
                           torch.zeros(1, 3, dtype=torch.float64), K, 64)


def test_a_deeper_wider_normal_head_counts_its_layers_and_loads_a_one_layer_head() -> None:
    """``normal_head_width`` and ``normal_head_layers``: the head's parameters against their
    count by hand (four 1 x 1 laterals, ``layers`` 3 x 3 convs, the 1 x 1 output), its map
    the stride-4 shape; a one-layer head's state (the default, as in older checkpoints) loads
    into the deeper one's first layers by name, the extra layers left as they are."""
    from sq_mitsuba.model.heads import MaskHead

    deep = SuperquadricNet(NetworkConfig(**SMALL, normal_head_width=24, normal_head_layers=3))
    channels = deep.encoder.pyramid_channels[:4]
    width = 24
    expected = sum(c * width + width for c in channels) + 3 * (9 * width * width + width) \
        + (3 * width + 3)
    assert sum(p.numel() for p in deep.normal_head.parameters()) == expected
    out = deep(torch.rand(1, 1, 64, 64), Camera.default(64).matrix(torch.float32))
    assert out.surface_normals.shape == (1, 3, 16, 16)
    one = MaskHead(deep.encoder.pyramid_channels, width=width, outputs=3)
    missing, unexpected = deep.normal_head.load_state_dict(one.state_dict(), strict=False)
    assert unexpected == [] and sorted(missing) == sorted(
        f"deeper.{i}.{p}" for i in (0, 1) for p in ("weight", "bias"))
    assert torch.equal(deep.normal_head.smooth.weight, one.smooth.weight)
    with pytest.raises(ValueError, match="layers"):
        MaskHead(deep.encoder.pyramid_channels, layers=0)
