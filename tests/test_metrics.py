"""Evaluation metrics against their definitions: brute force in float64, hand-made examples.

The tests that take ``device`` run on ``pytest --device`` (conftest.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sq_mitsuba.geometry.metrics import (
    camera_frame_chamfer,
    chamfer_l1,
    chamfer_l2,
    mask_iou,
    rotation_error_deg,
    translation_error,
    volumetric_iou,
)
from sq_mitsuba.geometry.rotation import random_rotations


def brute_force(a: torch.Tensor, b: torch.Tensor, p: float) -> tuple[torch.Tensor, torch.Tensor]:
    """All pairwise L``p`` distances, then the minima both ways: (|a|,), (|b|,)."""
    pairwise = (a[:, None, :] - b[None, :, :]).abs().pow(p).sum(-1).pow(1 / p)
    return pairwise.min(dim=1).values, pairwise.min(dim=0).values


@pytest.fixture(scope="module")
def clouds():
    generator = torch.Generator().manual_seed(0)
    pred = torch.rand(3, 200, 3, generator=generator, dtype=torch.float64)
    gt = torch.rand(3, 150, 3, generator=generator, dtype=torch.float64) * 1.3 - 0.1
    return pred, gt


def test_chamfer_conventions_match_brute_force(clouds):
    pred, gt = clouds
    paper = chamfer_l1(pred, gt, "paper")
    occnet = chamfer_l1(pred, gt, "occnet")
    l2 = chamfer_l2(pred, gt)
    for b in range(pred.shape[0]):
        f1, b1 = brute_force(pred[b], gt[b], 1)
        f2, b2 = brute_force(pred[b], gt[b], 2)
        assert float(paper[b]) == pytest.approx(float(f1.mean() + b1.mean()), rel=1e-12)
        assert float(occnet[b]) == pytest.approx(float(0.5 * (f2.mean() + b2.mean())), rel=1e-12)
        assert float(l2[b]) == pytest.approx(float((f2**2).mean() + (b2**2).mean()), rel=1e-12)


def test_chamfer_three_point_example_by_hand():
    # pred {(0,0,0), (1,0,0)}, gt {(0,1,1)}.
    pred = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0]]])
    gt = torch.tensor([[[0.0, 1, 1]]])
    # L1: pred->gt distances 2 and 3 (mean 2.5); gt->pred nearest is (0,0,0) at 2. Sum 4.5.
    assert float(chamfer_l1(pred, gt, "paper")) == pytest.approx(4.5)
    # L2: pred->gt sqrt(2), sqrt(3); gt->pred sqrt(2). 0.5 ((sqrt2 + sqrt3)/2 + sqrt2).
    expected = 0.5 * ((math.sqrt(2) + math.sqrt(3)) / 2 + math.sqrt(2))
    assert float(chamfer_l1(pred, gt, "occnet")) == pytest.approx(expected)
    # Squared L2: (2 + 3) / 2 + 2 = 4.5 as well, by coincidence of this example.
    assert float(chamfer_l2(pred, gt)) == pytest.approx(4.5)


def test_l1_nearest_neighbour_is_taken_under_the_l1_norm():
    # gt point A is nearer in L2, B nearer in L1: the paper convention must pick B.
    pred = torch.tensor([[[0.0, 0, 0]]])
    gt = torch.tensor([[[0.9, 0.9, 0.0], [1.5, 0.0, 0.0]]])  # L1: 1.8 vs 1.5; L2: 1.27 vs 1.5
    forward_paper = chamfer_l1(pred, gt, "paper") - 1.5  # gt->pred: mean(1.8, 1.5) = 1.65
    assert float(forward_paper) == pytest.approx(1.65)


def test_perfect_prediction_scores_zero_and_one():
    generator = torch.Generator().manual_seed(1)
    points = torch.rand(2, 100, 3, generator=generator)
    rotation = random_rotations(2, generator)
    translation = torch.tensor([[0.1, -0.2, 2.0], [0.0, 0.3, 1.7]])
    assert torch.all(chamfer_l1(points, points, "paper") == 0)
    assert torch.all(chamfer_l1(points, points, "occnet") == 0)
    assert torch.all(camera_frame_chamfer(points, rotation, translation,
                                          points, rotation, translation) == 0)
    assert torch.allclose(rotation_error_deg(rotation, rotation), torch.zeros(2), atol=1e-3)
    masks = torch.rand(2, 16, 16, generator=generator) > 0.5
    assert torch.all(mask_iou(masks.float(), masks.float()) == 1)
    assert torch.all(volumetric_iou(masks.flatten(1), masks.flatten(1)) == 1)
    # Shapes that would broadcast into a wrong answer are refused, not scored.
    with pytest.raises(ValueError, match="expected equal shapes"):
        mask_iou(masks.float(), masks.float()[:, None])
    with pytest.raises(ValueError, match="batch sizes differ"):
        camera_frame_chamfer(points, rotation[:1], translation, points, rotation, translation)


def test_masks_select_points():
    pred = torch.tensor([[[0.0, 0, 0], [5.0, 5, 5]]])
    gt = torch.tensor([[[0.0, 0, 0]]])
    keep = torch.tensor([[True, False]])
    assert float(chamfer_l1(pred, gt, "paper", pred_mask=keep)) == 0
    with pytest.raises(ValueError, match="pred: item 0 has no points"):
        chamfer_l1(pred, gt, pred_mask=torch.zeros(1, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="pred_mask: expected shape"):
        chamfer_l1(pred, gt, pred_mask=torch.ones(2, 2, dtype=torch.bool))


def test_symmetry_aware_rotation_error_of_r_s_is_zero(device):
    on = {"dtype": torch.float64, "device": device}
    generator = torch.Generator().manual_seed(2)
    rotation = random_rotations(4, generator, torch.float64, device)
    half_turn_z = torch.diag(torch.tensor([-1.0, -1.0, 1.0], **on))
    symmetries = torch.stack([torch.eye(3, **on), half_turn_z])
    flipped = rotation @ half_turn_z
    raw = rotation_error_deg(flipped, rotation)
    assert torch.allclose(raw, torch.full((4,), 180.0, **on), atol=1e-6)
    aware = rotation_error_deg(flipped, rotation, symmetries)
    assert torch.allclose(aware, torch.zeros(4, **on), atol=1e-5)
    # Per-model symmetry sets (B, S, 3, 3): a model without the symmetry keeps the raw error.
    per_model = torch.stack([symmetries, torch.stack([torch.eye(3, **on)] * 2)] * 2)
    mixed = rotation_error_deg(flipped, rotation, per_model)
    assert mixed[0] < 1e-5 and mixed[1] == pytest.approx(180.0, abs=1e-6)


def test_camera_frame_chamfer_sees_pose_errors_and_is_blind_to_symmetries():
    # A box symmetric under a half turn about z: R S places it exactly where R does.
    corners = torch.cartesian_prod(*[torch.tensor([-0.5, 0.5], dtype=torch.float64)] * 3)
    box = (corners * torch.tensor([1.0, 0.6, 0.3], dtype=torch.float64))[None]
    rotation = random_rotations(1, torch.Generator().manual_seed(3), torch.float64)
    translation = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
    half_turn_z = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))
    same = camera_frame_chamfer(box, rotation @ half_turn_z, translation, box, rotation,
                                translation)
    assert float(same) == pytest.approx(0.0, abs=1e-12)
    moved = translation + torch.tensor([0.2, 0, 0], dtype=torch.float64)
    shifted = camera_frame_chamfer(box, rotation, moved, box, rotation, translation)
    # Every point moves by 0.2 m: occnet Chamfer 0.2 at most, divided by the 2 m distance.
    assert 0.0 < float(shifted) <= 0.1 + 1e-12
    # Against numpy by brute force: two clouds and two poses, placed and scored by hand.
    generator = np.random.default_rng(5)
    pred_points, gt_points = generator.normal(size=(1, 40, 3)), generator.normal(size=(1, 30, 3))
    poses = random_rotations(2, torch.Generator().manual_seed(4), torch.float64).numpy()
    t_pred, t_gt = np.array([[0.3, -0.2, 3.1]]), np.array([[0.1, 0.4, 2.7]])
    placed_pred = pred_points[0] @ poses[0].T + t_pred[0]
    placed_gt = gt_points[0] @ poses[1].T + t_gt[0]
    distances = np.linalg.norm(placed_pred[:, None] - placed_gt[None], axis=-1)
    expected = 0.5 * (distances.min(1).mean() + distances.min(0).mean()) / np.linalg.norm(t_gt)
    got = camera_frame_chamfer(*map(torch.from_numpy, (pred_points, poses[:1], t_pred,
                                                        gt_points, poses[1:], t_gt)))
    assert float(got) == pytest.approx(expected, rel=1e-12)


def test_volumetric_iou_and_translation_error_by_hand(device):
    pred = torch.tensor([[True, True, False, False]], device=device)
    gt = torch.tensor([[True, False, True, False]], device=device)
    assert float(volumetric_iou(pred, gt)) == pytest.approx(1 / 3)
    assert float(volumetric_iou(torch.zeros(1, 3, dtype=torch.bool, device=device),
                                torch.zeros(1, 3, dtype=torch.bool, device=device))) == 1.0
    t_true = torch.tensor([[0.0, 0.0, 2.0]], device=device)
    t_pred = torch.tensor([[0.3, 0.0, 2.4]], device=device)
    assert float(translation_error(t_pred, t_true)) == pytest.approx(0.5)
    assert float(translation_error(t_pred, t_true, relative=True)) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="convention"):
        chamfer_l1(t_pred[:, None], t_true[:, None], "l3")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="pred_inside, gt_inside"):
        volumetric_iou(pred, gt[:, :3])


def test_a_zero_quaternion_or_true_distance_is_an_error_not_nan():
    """A zero quaternion has no rotation and a zero true translation no distance to divide by:
    both gave NaN (or 180 deg) in the metrics; now one line naming the argument and item."""
    from sq_mitsuba.checks import value_checks
    from sq_mitsuba.geometry.metrics import speed_score
    from sq_mitsuba.geometry.rotation import quaternion_angle, quaternion_to_matrix

    q = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    t = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^quaternion: zero vector at 1 "):
        quaternion_to_matrix(q)
    with pytest.raises(ValueError, match=r"^quaternion_b: zero vector at 1 "):
        quaternion_angle(q[:1].expand(2, 4), q)
    with pytest.raises(ValueError, match=r"^translation_true: zero vector at 1 "):
        speed_score(q[:1].expand(2, 4), q[:1].expand(2, 4), t, t)
    with pytest.raises(ValueError, match=r"^gt_translation: zero vector at 1 "):
        translation_error(t, t, relative=True)
    points = torch.rand(2, 10, 3, dtype=torch.float64)
    rotation = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    with pytest.raises(ValueError, match=r"^gt_translation: zero vector at 1 "):
        camera_frame_chamfer(points, rotation, t, points, rotation, t)
    # The absolute translation error of a target at the camera is defined: no error there.
    assert translation_error(t, t).tolist() == [0.0, 0.0]
    # Value checks switched off (a hot loop): no check, the arithmetic's own result.
    with value_checks(False):
        assert bool(torch.isnan(quaternion_to_matrix(q)[1]).all())


def test_a_prediction_and_truth_of_different_batches_are_refused_not_broadcast():
    """(1, 3, 3) against (B, 3, 3) broadcast to B errors of one prediction against every
    truth: a silent mistake in a metric, now one line naming both arguments."""
    from sq_mitsuba.geometry.metrics import rotation_error_deg, speed_score

    rotations = torch.eye(3, dtype=torch.float64).expand(3, 3, 3)
    with pytest.raises(ValueError, match=r"^pred_rotation, gt_rotation: expected the same "
                                         r"shape, got pred_rotation=\(1, 3, 3\)"):
        rotation_error_deg(rotations[:1], rotations)
    t = torch.tensor([[0.0, 0.0, 2.0]] * 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^pred_translation, gt_translation"):
        translation_error(t[:1], t)
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^quaternion_pred, quaternion_true"):
        speed_score(q[:1], q, t, t)
    with pytest.raises(ValueError, match=r"^translation_pred, translation_true"):
        speed_score(q, q, t, t[:2])
    assert rotation_error_deg(rotations, rotations).shape == (3,)


def test_symmetries_take_one_rotation_an_item_and_speed_pairs_one_batch():
    """(B, T, 3, 3) with symmetries paired T with S (180 deg where 0 was right); a quaternion
    batch of 1 against translations of 4 mixed a (1,) and a (4,) score."""
    from sq_mitsuba.geometry.metrics import rotation_error_deg, speed_score
    from sq_mitsuba.geometry.rotation import random_rotations
    from sq_mitsuba.geometry.so3_grid import half_turns

    truth = random_rotations(8, torch.Generator().manual_seed(3), dtype=torch.float64)
    turns = half_turns(torch.float64)
    assert float(rotation_error_deg(truth @ turns[1], truth, turns).max()) < 1e-6
    with pytest.raises(ValueError, match=r"^pred_rotation: expected \(B, 3, 3\) with symmetries"):
        rotation_error_deg(truth.reshape(2, 4, 3, 3), truth.reshape(2, 4, 3, 3), turns)
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    t = torch.tensor([[0.0, 0.0, 2.0]] * 4, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^quaternion_pred, translation_pred"):
        speed_score(q, q, t, t + 0.1)


def test_camera_frame_chamfer_refuses_an_unbatched_rotation():
    """A (3, 3) rotation passed the batch-size check for B = 3 (its first dim is 3)."""
    points = torch.rand(3, 10, 3, dtype=torch.float64)
    rotations = torch.eye(3, dtype=torch.float64).expand(3, 3, 3)
    t = torch.tensor([[0.0, 0.0, 2.0]] * 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^pred_rotation: expected \(B, 3, 3\), got \(3, 3\)"):
        camera_frame_chamfer(points, rotations[0], t, points, rotations, t)
    assert camera_frame_chamfer(points, rotations, t, points, rotations, t).abs().max() == 0
