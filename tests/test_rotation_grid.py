"""The rotation distribution head: training targets over the grid, local refinement below the
grid's spacing, distinct hypotheses."""

from __future__ import annotations

import math

import pytest
import torch

from sq_mitsuba.geometry.rotation import random_rotations, rotation_angle
from sq_mitsuba.geometry.so3_grid import (
    covering_angle_deg,
    half_turns,
    nearest_grid_index,
    so3_grid,
)
from sq_mitsuba.model.network import NetworkConfig
from sq_mitsuba.model.rotation_grid import (
    RotationGridPoseHead,
    rotation_hypotheses,
    soft_rotation_targets,
)


def _head(cells: int = 576) -> RotationGridPoseHead:
    return RotationGridPoseHead(NetworkConfig(rotation_cells=cells, latent_dim=8,
                                              hidden_dim=8, image_size=64))


def test_targets_sum_to_one_and_peak_at_every_equivalent() -> None:
    head = _head()
    grid = head.grid_rotations().double()
    truth = random_rotations(4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    identity_only = torch.eye(3, dtype=torch.float64).expand(4, 1, 3, 3)
    targets = soft_rotation_targets(truth, identity_only, head.quaternions.double())
    torch.testing.assert_close(targets.sum(-1), torch.ones(4, dtype=torch.float64))
    assert torch.equal(targets.argmax(-1), nearest_grid_index(truth, grid))
    # Two-fold symmetric models: half the mass near R, half near R @ S.
    turns = half_turns().expand(4, 4, 3, 3)[:, :2]
    targets = soft_rotation_targets(truth, turns, head.quaternions.double())
    near_r = nearest_grid_index(truth, grid)
    near_rs = nearest_grid_index(truth @ turns[:, 1], grid)
    for item in range(4):
        assert float(targets[item, near_r[item]]) == pytest.approx(
            float(targets[item, near_rs[item]]), rel=0.6)
        # Each mode is a Gaussian of sigma = the covering angle (18.4 deg here) in 3 dimensions:
        # 97 % of a chi distribution with 3 degrees of freedom lies within 3 sigma.
        near = rotation_angle(grid, truth[item].expand_as(grid)) < math.radians(55)
        near |= rotation_angle(grid, (truth[item] @ turns[0, 1]).expand_as(grid)) < math.radians(55)
        assert float(targets[item, near].sum()) > 0.93
    # Padding a model's symmetries with identities (to a batch's S) leaves its targets as
    # they are: the padded identities do not add weight to the identity's mode.
    identity = torch.eye(3, dtype=torch.float64).expand(4, 2, 3, 3)
    padded = soft_rotation_targets(truth, torch.cat([turns, identity], dim=1),
                                   head.quaternions.double())
    torch.testing.assert_close(padded, targets, rtol=0, atol=1e-12)
    with pytest.raises(ValueError):
        soft_rotation_targets(truth, turns[:2], head.quaternions)


def test_refined_rotation_is_finer_than_the_grid() -> None:
    """Logits equal to the log of a target distribution around R: the head's rotation (the
    argmax cell refined by its neighbours) lies nearer R than the nearest cell does."""
    head = _head()
    truth = random_rotations(32, generator=torch.Generator().manual_seed(1))
    targets = soft_rotation_targets(truth, torch.eye(3).expand(32, 1, 3, 3), head.quaternions)
    logits = targets.clamp_min(1e-12).log()
    head.to_logits.weight.data.zero_()
    # Feed the logits through the head's last layer as biases, item by item.
    errors_cell, errors_refined = [], []
    grid = head.grid_rotations()
    for item in range(32):
        head.to_logits.bias.data.copy_(logits[item])
        with torch.no_grad():
            out = head(torch.zeros(1, 8))
        cell = grid[logits[item].argmax()]
        errors_cell.append(float(rotation_angle(cell, truth[item])))
        errors_refined.append(float(rotation_angle(out.rotation[0], truth[item])))
    assert sum(errors_refined) < 0.7 * sum(errors_cell)


def test_hypotheses_are_distinct_modes_best_first() -> None:
    grid = so3_grid(576).float()
    truth = random_rotations(3, generator=torch.Generator().manual_seed(2))
    modes = torch.stack([truth, truth @ half_turns(torch.float32)[1]], dim=1)  # (3, 2, 3, 3)
    cells = _head().quaternions
    one = torch.eye(3).expand(3, 1, 3, 3)
    targets = (0.7 * soft_rotation_targets(truth, one, cells, sigma_deg=8.0)
               + 0.3 * soft_rotation_targets(modes[:, 1], one, cells, sigma_deg=8.0))
    rotations, scores = rotation_hypotheses(targets.log(), grid, count=4, separation_deg=30.0)
    cell = 1.5 * covering_angle_deg(576)
    assert rotations.shape == (3, 4, 3, 3) and scores.shape == (3, 4)
    assert bool((scores[:, :-1] >= scores[:, 1:]).all())
    for item in range(3):
        # Each mode is found to within its nearest cell (at most ~1.5 covering angles).
        assert math.degrees(float(rotation_angle(rotations[item, 0], truth[item]))) < cell
        assert math.degrees(float(rotation_angle(rotations[item, 1], modes[item, 1]))) < cell
        pairwise = rotation_angle(rotations[item][:, None], rotations[item][None])
        off_diagonal = pairwise[~torch.eye(4, dtype=torch.bool)]
        assert float(off_diagonal.min()) > math.radians(30.0) - 1e-4
    with pytest.raises(ValueError, match="K >= 1"):
        rotation_hypotheses(targets.log(), grid, count=0)
    with pytest.raises(ValueError, match="grid"):
        rotation_hypotheses(targets.log(), grid[:10], count=2)


def test_distribution_loss_is_the_cross_entropy_to_the_targets() -> None:
    """Its value against an independent computation; a peak on the truth scores lower than
    one a half turn away on an asymmetric model and the same on a two-fold symmetric one."""
    from sq_mitsuba.model.losses import rotation_distribution_loss
    from sq_mitsuba.model.rotation_grid import grid_quaternions

    cells = grid_quaternions(576)
    truth = random_rotations(2, generator=torch.Generator().manual_seed(4))
    logits = torch.randn(2, 576, generator=torch.Generator().manual_seed(5))
    one = torch.eye(3).expand(2, 1, 3, 3)
    targets = soft_rotation_targets(truth, one, cells)
    expected = -(targets * torch.log_softmax(logits, -1)).sum(-1)
    torch.testing.assert_close(rotation_distribution_loss(logits, truth, one), expected)
    grid = so3_grid(576).float()
    peak_true = torch.full((2, 576), -10.0)
    peak_true[torch.arange(2), nearest_grid_index(truth, grid)] = 10.0
    flipped = truth @ half_turns(torch.float32)[3]
    peak_flip = torch.full((2, 576), -10.0)
    peak_flip[torch.arange(2), nearest_grid_index(flipped, grid)] = 10.0
    asymmetric = rotation_distribution_loss(peak_true, truth, one)
    assert bool((asymmetric < rotation_distribution_loss(peak_flip, truth, one)).all())
    two_fold = torch.stack([torch.eye(3), half_turns(torch.float32)[3]]).expand(2, 2, 3, 3)
    torch.testing.assert_close(rotation_distribution_loss(peak_true, truth, two_fold),
                               rotation_distribution_loss(peak_flip, truth, two_fold),
                               rtol=0.05, atol=0.0)


def test_turned_cells_are_the_nearest_cells_of_the_rolled_grid() -> None:
    """Against brute force: each cell's image under a camera roll is the grid cell at the
    smallest angle from Rz @ G; no roll maps every cell to itself."""
    from sq_mitsuba.geometry.image_turns import z_rotation
    from sq_mitsuba.model.rotation_grid import turned_cells

    grid = so3_grid(576)
    angles = torch.tensor([0.0, 0.7, math.pi], dtype=torch.float64)
    cells = turned_cells(grid, z_rotation(angles))
    assert torch.equal(cells[0], torch.arange(576))
    for k, angle in enumerate(angles):
        moved = z_rotation(angle[None])[0] @ grid
        angle_to = rotation_angle(moved[:, None], grid[None])  # (G, G)
        brute = angle_to.argmin(dim=1)
        assert torch.equal(cells[k], brute)
    for bad_grid, bad_turns in ((grid, z_rotation(angles)[0]), (grid[:, :2], z_rotation(angles))):
        with pytest.raises(ValueError, match=r"expected rotations grid \(G, 3, 3\) and turns"):
            turned_cells(bad_grid, bad_turns)


def test_turned_distributions_multiply_back_in_the_unturned_frame() -> None:
    """Copies peaked where the roll moves one cell combine to a distribution peaked at that
    cell; one copy gives its own log-softmax; mismatched shapes are refused."""
    from sq_mitsuba.geometry.image_turns import z_rotation
    from sq_mitsuba.model.rotation_grid import turned_cells, turned_log_probabilities

    grid = so3_grid(576)
    turns = 4
    cells = turned_cells(grid, z_rotation(torch.arange(turns) * (2 * math.pi / turns)))
    generator = torch.Generator().manual_seed(3)
    noise = torch.randn(turns, 2, 576, generator=generator)
    truth = torch.tensor([17, 300])
    logits = noise.clone()
    for k in range(turns):
        logits[k, torch.arange(2), cells[k, truth]] += 6.0  # each copy sees the turned pose
    combined = turned_log_probabilities(logits, cells)
    assert torch.equal(combined.argmax(dim=-1), truth)
    torch.testing.assert_close(combined.exp().sum(-1), torch.ones(2))
    single = turned_log_probabilities(noise[:1], cells[:1])
    torch.testing.assert_close(single, noise[0].log_softmax(-1))
    with pytest.raises(ValueError, match="expected logits"):
        turned_log_probabilities(noise[0], cells)


def test_a_grid_too_small_for_a_cell_and_its_neighbours_is_a_config_error() -> None:
    """Each cell's reading is refined over its 8 nearest: 8 cells built a network that failed
    with torch's "selected index k out of range"."""
    from sq_mitsuba.config import ConfigError, validate

    with pytest.raises(ConfigError, match="rotation_cells"):
        validate(NetworkConfig(rotation_cells=8))
    validate(NetworkConfig(rotation_cells=9))
