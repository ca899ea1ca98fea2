"""Training losses against independent references: dense pairwise Chamfer, brute-force
occupancy through the per-primitive superquadric functions, the silhouette renderer's own
images, finite differences, quaternion angles and hand-computed values.

The tests that take ``device`` run on ``pytest --device`` (conftest.py): inputs are drawn on
the CPU from the same seeds, then moved. The reprojection loss renders with Mitsuba's LLVM
variant and stays on the CPU."""

from __future__ import annotations

import math
from itertools import combinations

import pytest
import torch

from sq_mitsuba.config import ConfigError, from_dict
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import (
    matrix_to_quaternion,
    quaternion_angle,
    random_rotations,
    rotation_6d_to_matrix,
)
from sq_mitsuba.geometry.superquadric import inside_outside_dual
from sq_mitsuba.model.losses import (
    chamfer_loss,
    mask_loss,
    occupancy_loss,
    pose_loss,
    reprojection_loss,
    rotation_6d_loss,
    surface_chamfer_loss,
    taper_loss,
)
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly
from sq_mitsuba.training.loss_terms import PUBLISHED_WEIGHTS, LossConfig, total_loss

# ------------------------------------------------------------------------------- Chamfer


def dense_chamfer(pred: torch.Tensor, keep: torch.Tensor | None, target: torch.Tensor):
    """Reference: every pairwise squared distance, min per row and per column."""
    squared = ((pred[:, :, None] - target[:, None]) ** 2).sum(-1)  # (B, N, K)
    if keep is None:
        keep = torch.ones(pred.shape[:2], dtype=torch.bool, device=pred.device)
    forward = squared.min(dim=2).values
    forward = (forward * keep).sum(1) / keep.sum(1)
    backward = squared.masked_fill(~keep[:, :, None], math.inf).min(dim=1).values.mean(1)
    return (forward + backward).mean()


def clouds(batch=3, count=40, targets=30, seed=0, device="cpu"):
    generator = torch.Generator().manual_seed(seed)
    pred = torch.rand(batch, count, 3, generator=generator, dtype=torch.float64)
    target = torch.rand(batch, targets, 3, generator=generator, dtype=torch.float64)
    keep = torch.rand(batch, count, generator=generator) > 0.3
    return pred.to(device), keep.to(device), target.to(device)


@pytest.mark.parametrize("masked", [False, True])
def test_chamfer_matches_dense_reference_value_and_gradient(masked, device):
    pred, keep, target = clouds(device=device)
    keep = keep if masked else None
    pred_a, target_a = pred.clone().requires_grad_(), target.clone().requires_grad_()
    pred_b, target_b = pred.clone().requires_grad_(), target.clone().requires_grad_()
    ours = chamfer_loss(pred_a, keep, target_a)
    reference = dense_chamfer(pred_b, keep, target_b)
    ours.backward()
    reference.backward()
    assert ours.dtype == torch.float64 and ours.dim() == 0
    assert ours.item() == pytest.approx(reference.item(), rel=1e-12)
    assert torch.allclose(pred_a.grad, pred_b.grad, rtol=1e-10, atol=1e-14)
    assert torch.allclose(target_a.grad, target_b.grad, rtol=1e-10, atol=1e-14)
    if masked:  # points that do not count get no gradient
        assert float(pred_a.grad[~keep].abs().max()) == 0.0
        assert float(pred_a.grad[keep].abs().max()) > 0.0


def test_chamfer_gradcheck(device):
    pred, keep, target = clouds(batch=2, count=12, targets=9, seed=1, device=device)
    pred.requires_grad_()
    target.requires_grad_()
    assert torch.autograd.gradcheck(lambda p, t: chamfer_loss(p, keep, t), (pred, target),
                                    eps=1e-7, atol=1e-6)


def test_chamfer_ignores_masked_points_and_keeps_all_of_an_empty_item(device):
    pred, keep, target = clouds(batch=2, device=device)
    moved = pred.clone()
    moved[~keep] += 100.0  # points that do not count can go anywhere
    assert float(chamfer_loss(moved, keep, target)) == pytest.approx(
        float(chamfer_loss(pred, keep, target)), rel=1e-12)
    keep[1] = False  # convention: an item where no point counts uses all its points
    expected = dense_chamfer(pred, torch.stack([keep[0], torch.ones_like(keep[1])]), target)
    assert float(chamfer_loss(pred, keep, target)) == pytest.approx(float(expected), rel=1e-12)


def test_chamfer_of_identical_clouds_is_zero_and_known_for_a_shift():
    pred, _, _ = clouds(batch=2, count=20)
    assert float(chamfer_loss(pred, None, pred.clone())) == 0.0
    # Two single points 0.3 apart: 0.09 each way.
    a = torch.zeros(1, 1, 3, dtype=torch.float64)
    b = torch.tensor([[[0.0, 0.3, 0.0]]], dtype=torch.float64)
    assert float(chamfer_loss(a, None, b)) == pytest.approx(0.18, rel=1e-12)


@pytest.mark.parametrize("masked", [False, True])
def test_euclidean_chamfer_is_twice_the_metrics_l2_chamfer_l1(masked, device):
    """``squared=False``: the mean nearest Euclidean distances, directions summed, i.e. twice
    the evaluation's Chamfer-L1 of the "occnet" convention (its own implementation)."""
    from sq_mitsuba.geometry.metrics import chamfer_l1

    pred, keep, target = clouds(seed=5, device=device)
    keep = keep if masked else None
    expected = 2 * chamfer_l1(pred, target, "occnet", pred_mask=keep).mean()
    assert float(chamfer_loss(pred, keep, target, squared=False)) == pytest.approx(
        float(expected), rel=1e-9)
    # Two single points 0.3 apart: 0.3 each way (0.09 squared).
    a = torch.zeros(1, 1, 3, dtype=torch.float64)
    b = torch.tensor([[[0.0, 0.3, 0.0]]], dtype=torch.float64)
    assert float(chamfer_loss(a, None, b, squared=False)) == pytest.approx(0.6, rel=1e-9)


def test_euclidean_chamfer_gradcheck(device):
    pred, keep, target = clouds(batch=2, count=12, targets=9, seed=6, device=device)
    pred.requires_grad_()
    target.requires_grad_()
    assert torch.autograd.gradcheck(lambda p, t: chamfer_loss(p, keep, t, squared=False),
                                    (pred, target), eps=1e-7, atol=1e-6)


def test_surface_chamfer_matches_metrics_chamfer_l2(device):
    from sq_mitsuba.geometry.metrics import chamfer_l2

    generator = torch.Generator().manual_seed(4)
    raw = 0.8 * torch.randn(2, 3, 16, generator=generator, dtype=torch.float64)
    assembly = Assembly.from_raw(raw.to(device))
    target = (0.4 * torch.rand(2, 500, 3, generator=generator, dtype=torch.float64) - 0.2
              ).to(device)
    points, inside = assembly.surface_points_with_mask(level=2)
    assert bool(inside.any())  # the test exercises the mask
    expected = chamfer_l2(points.flatten(1, 2), target,
                          pred_mask=~inside.flatten(1, 2)).mean()
    assert float(surface_chamfer_loss(assembly, target, level=2)) == pytest.approx(
        float(expected), rel=1e-10)


@pytest.mark.parametrize(("args", "message"), [
    ((torch.zeros(2, 5, 3), None, torch.zeros(3, 4, 3)), "pred_points, target"),
    ((torch.zeros(2, 5, 2), None, torch.zeros(2, 4, 3)), "pred_points"),
    ((torch.zeros(2, 5, 3), torch.ones(2, 5), torch.zeros(2, 4, 3)), "pred_mask"),
    ((torch.zeros(2, 5, 3), None, torch.zeros(2, 4, 3, dtype=torch.float64)), "target"),
    ((torch.full((1, 5, 3), math.nan), None, torch.zeros(1, 4, 3)), "pred_points"),
])
def test_chamfer_bad_input(args, message):
    with pytest.raises(ValueError, match=message):
        chamfer_loss(*args)


# ----------------------------------------------------------------------------- occupancy


def brute_force_occupancy_loss(assembly, points, labels, sharpness, balance):
    """Per-primitive dual inside-outside via the plain superquadric function, sigmoid, max,
    the textbook BCE, balanced by a loop over items."""
    local = assembly.to_primitive_frames(points)  # (B, M, N, 3)
    f = inside_outside_dual(local, assembly.size, assembly.shape)  # (B, M, N)
    g = torch.sigmoid(sharpness * (1 - f)).amax(dim=1)  # (B, N)
    y = labels.to(g.dtype)
    bce = -(y * torch.log(g) + (1 - y) * torch.log(1 - g))
    if not balance:
        return bce.mean()
    per_item = []
    for item in range(len(bce)):
        inside, outside = labels[item].bool(), ~labels[item].bool()
        means = [bce[item][m].mean() for m in (inside, outside) if bool(m.any())]
        per_item.append(sum(means) / len(means))
    return torch.stack(per_item).mean()


def occupancy_setup(seed=2, device="cpu"):
    generator = torch.Generator().manual_seed(seed)
    raw = 0.8 * torch.randn(3, 4, 16, generator=generator, dtype=torch.float64)
    points = torch.rand(3, 400, 3, generator=generator, dtype=torch.float64) - 0.5
    labels = torch.rand(3, 400, generator=generator) < 0.35  # unbalanced on purpose
    labels[2] = False  # an item with outside points only
    return raw.to(device), points.to(device), labels.to(device)


@pytest.mark.parametrize("balance", [True, False])
def test_occupancy_loss_matches_brute_force(balance, device):
    raw, points, labels = occupancy_setup(device=device)
    raw_a, raw_b = raw.clone().requires_grad_(), raw.clone().requires_grad_()
    ours = occupancy_loss(Assembly.from_raw(raw_a), points, labels, 10.0, balance)
    reference = brute_force_occupancy_loss(Assembly.from_raw(raw_b), points, labels, 10.0,
                                           balance)
    ours.backward()
    reference.backward()
    assert ours.item() == pytest.approx(reference.item(), rel=1e-9)
    assert torch.allclose(raw_a.grad, raw_b.grad, rtol=1e-7, atol=1e-12)
    assert float(raw_a.grad.abs().sum()) > 0


def test_occupancy_balance_equals_plain_mean_for_balanced_labels(device):
    raw, points, _ = occupancy_setup(seed=5, device=device)
    labels = torch.zeros(3, 400, dtype=torch.bool, device=device)
    labels[:, ::2] = True
    assembly = Assembly.from_raw(raw)
    balanced = occupancy_loss(assembly, points, labels, balance=True)
    plain = occupancy_loss(assembly, points, labels, balance=False)
    assert float(balanced) == pytest.approx(float(plain), rel=1e-12)
    # And with float labels: the same as bool ones.
    assert float(occupancy_loss(assembly, points, labels.double())) == pytest.approx(
        float(balanced), rel=1e-12)


def test_occupancy_loss_prefers_the_right_labels(device):
    on = {"dtype": torch.float64, "device": device}
    sphere = Assembly.from_values(torch.full((1, 1, 3), 0.3, **on), torch.ones(1, 1, 2, **on))
    points = torch.tensor([[[0.0, 0, 0], [0.1, 0.1, 0], [0.45, 0, 0], [0, 0.4, 0.3]]], **on)
    right = torch.tensor([[True, True, False, False]], device=device)
    assert float(occupancy_loss(sphere, points, right)) < 0.1
    assert float(occupancy_loss(sphere, points, ~right)) > 2.0


def test_occupancy_bad_input():
    raw, points, labels = occupancy_setup()
    assembly = Assembly.from_raw(raw)
    with pytest.raises(ValueError, match="labels"):
        occupancy_loss(assembly, points, labels[:, :10])
    with pytest.raises(ValueError, match="labels"):
        occupancy_loss(assembly, points, labels.double() * 2)
    with pytest.raises(ValueError, match="sharpness"):
        occupancy_loss(assembly, points, labels, sharpness=0.0)


# -------------------------------------------------------------------------- reprojection


def spheres(radii, dtype=torch.float64):
    """Single-primitive assemblies: spheres of the given radii (B, 1, 16)."""
    radii = torch.as_tensor(radii, dtype=dtype)
    return Assembly.from_values(radii[:, None, None].expand(-1, 1, 3).contiguous(),
                                torch.ones(len(radii), 1, 2, dtype=dtype))


def poses(count, dtype=torch.float64):
    rotation = random_rotations(count, torch.Generator().manual_seed(7), dtype=dtype)
    translation = torch.tensor([[0.0, 0.0, 2.5]], dtype=dtype).expand(count, 3).contiguous()
    return rotation, translation


def test_reprojection_value_is_the_mse_of_the_rendered_silhouettes():
    # Two renderers with the same seed draw the same samples on their first call: the
    # images, and so the losses, are identical (not just close).
    generator = torch.Generator().manual_seed(0)
    raw = 0.6 * torch.randn(3, 2, 16, generator=generator, dtype=torch.float64)
    rotation, translation = poses(3)
    masks = (torch.rand(3, 32, 32, generator=generator) < 0.3).double()
    camera = Camera.default(32)
    images = render_assembly(Assembly.from_raw(raw), rotation, translation,
                             SilhouetteRenderer(camera, spp=8, seed=5), level=2)
    expected = ((images - masks) ** 2).mean((1, 2)).mean()
    with_grad = reprojection_loss(Assembly.from_raw(raw.clone().requires_grad_()), rotation,
                                  translation, masks, SilhouetteRenderer(camera, spp=8, seed=5),
                                  level=2)
    assert with_grad.requires_grad and with_grad.dtype == torch.float64
    assert with_grad.item() == pytest.approx(float(expected), rel=1e-6)
    with torch.no_grad():  # the forward-only path
        without = reprojection_loss(Assembly.from_raw(raw), rotation, translation, masks,
                                    SilhouetteRenderer(camera, spp=8, seed=5), level=2)
    assert float(without) == pytest.approx(float(expected), rel=1e-6)


def test_reprojection_gradient_agrees_with_finite_differences(renderer64):
    # A 0.2 sphere against the mask of a 0.28 sphere: growing the primitive lowers the loss.
    rotation, translation = torch.eye(3, dtype=torch.float64)[None], poses(1)[1]
    with torch.no_grad():
        mask = (render_assembly(spheres([0.28]), rotation, translation, renderer64) > 0.5)
    mask = mask.double()
    raw = torch.zeros(1, 1, 16, dtype=torch.float64)
    raw[..., 3:5] = 8.0  # shape -> 1: an ellipsoid
    raw[..., 8:14] = torch.tensor([1.0, 0, 0, 0, 1, 0], dtype=torch.float64)
    raw[..., 0:3] = math.log(0.19 / 0.30)  # size 0.01 + 0.49 sigmoid(raw) = 0.2
    direction = torch.zeros_like(raw)
    direction[..., 0:3] = 1 / math.sqrt(3)  # grow all three semi-axes

    def loss_at(values):
        return reprojection_loss(Assembly.from_raw(values), rotation, translation, mask,
                                 renderer64)

    grads = []
    for _ in range(3):  # average three independent backward passes
        leaf = raw.clone().requires_grad_()
        loss_at(leaf).backward()
        grads.append(float((leaf.grad * direction).sum()))
    gradient = sum(grads) / len(grads)
    step = 0.1  # small enough for the curvature, large enough for the forward noise
    with torch.no_grad():
        plus = sum(float(loss_at(raw + step * direction)) for _ in range(3)) / 3
        minus = sum(float(loss_at(raw - step * direction)) for _ in range(3)) / 3
    finite_difference = (plus - minus) / (2 * step)
    assert gradient < 0 and finite_difference < 0
    assert gradient == pytest.approx(finite_difference, rel=0.2)


def test_reprojection_subset_is_unbiased_and_reproducible():
    camera = Camera.default(24)
    renderer = SilhouetteRenderer(camera, spp=64, seed=3)
    radii = [0.05, 0.15, 0.3, 0.45]
    assembly = spheres(radii)
    rotation, translation = poses(4)
    masks = torch.zeros(4, 24, 24, dtype=torch.float64)
    masks[:, 8:16, 8:16] = 1.0
    with torch.no_grad():
        per_item = ((render_assembly(assembly, rotation, translation, renderer, level=2)
                     - masks) ** 2).mean((1, 2))
        full = float(reprojection_loss(assembly, rotation, translation, masks, renderer, 2))
        assert full == pytest.approx(float(per_item.mean()), rel=0.02)
        subsets = {pair: float(per_item[list(pair)].mean()) for pair in combinations(range(4), 2)}
        gaps = sorted(abs(a - b) for a, b in combinations(subsets.values(), 2))
        assert gaps[0] > 0.01  # every subset has a recognisably different value

        def draws(seed, count):
            generator = torch.Generator().manual_seed(seed)
            values = [float(reprojection_loss(assembly, rotation, translation, masks,
                                              renderer, 2, items=2, generator=generator))
                      for _ in range(count)]
            chosen = [min(subsets, key=lambda pair, v=v: abs(subsets[pair] - v)) for v in values]
            for pair, value in zip(chosen, values, strict=True):
                assert value == pytest.approx(subsets[pair], abs=0.002)
            return values, chosen

        values, chosen = draws(11, 48)
        _, chosen_again = draws(11, 10)
    assert chosen_again == chosen[:10]  # same generator seed, same subsets
    assert len(set(chosen)) >= 5
    # Subset means of 2 of 4 items: variance sigma^2 / 2 * (4 - 2) / (4 - 1) per draw.
    sigma = float(per_item.std(unbiased=False))
    tolerance = 4 * sigma * math.sqrt(1 / 3 / len(values)) + 0.002
    assert sum(values) / len(values) == pytest.approx(full, abs=tolerance)


def test_reprojection_bad_input(renderer64):
    rotation, translation = poses(2)
    masks = torch.zeros(2, 64, 64, dtype=torch.float64)
    assembly = spheres([0.2, 0.3])
    with pytest.raises(ValueError, match="masks"):
        reprojection_loss(assembly, rotation, translation, masks[:, :32], renderer64)
    with pytest.raises(ValueError, match="items"):
        reprojection_loss(assembly, rotation, translation, masks, renderer64, items=3)
    with pytest.raises(ValueError, match="assembly"):
        reprojection_loss(spheres([0.2, 0.3, 0.4]), rotation, translation, masks, renderer64)
    with pytest.raises(ValueError, match="rotations, translations, masks"):
        reprojection_loss(assembly, rotation, translation[:1], masks, renderer64)


# ---------------------------------------------------------------------------------- pose


def half_turn(axis, device="cpu"):
    matrix = -torch.eye(3, dtype=torch.float64)
    matrix[axis, axis] = 1.0
    return matrix.to(device)


def test_pose_loss_without_symmetries_is_the_speed_error(device):
    generator = torch.Generator().manual_seed(8)
    pred, true = random_rotations(5, generator, torch.float64), random_rotations(
        5, generator, torch.float64)
    t_true = torch.randn(5, 3, generator=generator, dtype=torch.float64) + 5
    t_pred = t_true + 0.3 * torch.randn(5, 3, generator=generator, dtype=torch.float64)
    pred, true, t_true, t_pred = (t.to(device) for t in (pred, true, t_true, t_pred))
    rotation_term, translation_term = pose_loss(pred, t_pred, true, t_true)
    expected = quaternion_angle(matrix_to_quaternion(pred), matrix_to_quaternion(true))
    assert torch.allclose(rotation_term, expected, atol=1e-9)
    assert torch.allclose(translation_term, (t_true - t_pred).norm(dim=1) / t_true.norm(dim=1))
    identity_only = torch.eye(3, dtype=torch.float64, device=device).expand(5, 1, 3, 3)
    assert torch.allclose(pose_loss(pred, t_pred, true, t_true, identity_only)[0],
                          rotation_term, atol=1e-12)


@pytest.mark.parametrize("group", ["z", "xyz"])
def test_pose_loss_is_invariant_under_the_model_symmetries(group, device):
    members = [torch.eye(3, dtype=torch.float64)] + [half_turn("xyz".index(a)) for a in group]
    symmetries = torch.stack(members).to(device)  # a group: {I, Rz} or {I, Rx, Ry, Rz}
    generator = torch.Generator().manual_seed(9)
    pred, true = random_rotations(4, generator, torch.float64, device), random_rotations(
        4, generator, torch.float64, device)
    t = torch.tensor([[0.0, 0.0, 8.0]], dtype=torch.float64, device=device).expand(4, 3)
    reference, _ = pose_loss(pred, t, true, t, symmetries[None].expand(4, -1, -1, -1))
    raw, _ = pose_loss(pred, t, true, t)
    assert bool((reference <= raw + 1e-12).all())
    for member in symmetries:
        moved, _ = pose_loss(pred, t, true @ member, t, symmetries)  # (S, 3, 3) broadcasts
        assert torch.allclose(moved, reference, atol=1e-10)
        # A prediction off by a symmetry costs nothing; without the symmetries it costs.
        zero, _ = pose_loss(true @ member, t, true, t, symmetries)
        assert float(zero.abs().max()) < 1e-6
    if group == "z":  # a half turn that is not a symmetry of the model is still an error
        off, _ = pose_loss(true @ half_turn(0, device), t, true, t, symmetries)
        assert torch.allclose(off, torch.full_like(off, math.pi), atol=1e-6)


def test_rotation_6d_loss_regresses_the_raw_output_onto_the_target_rows(device):
    """The 6D regression compares the raw network output with the first two rows of R_true S
    (the rows rotation_6d_to_matrix keeps), minimised over the symmetries, with its gradient
    on the raw output."""
    from sq_mitsuba.geometry.rotation import rotation_6d_to_matrix

    generator = torch.Generator().manual_seed(15)
    true = random_rotations(5, generator, torch.float64, device)
    raw = torch.randn(5, 6, generator=generator, dtype=torch.float64).to(device)
    raw.requires_grad_()
    value = rotation_6d_loss(raw, true)
    expected = (raw - true[:, :2].reshape(5, 6)).square().sum(-1)
    assert torch.allclose(value, expected, atol=1e-12)
    # The target rows are a fixed point: they map to the true rotation, at zero loss.
    rows = true[:, :2].reshape(5, 6)
    assert torch.allclose(rotation_6d_to_matrix(rows), true, atol=1e-12)
    assert float(rotation_6d_loss(rows, true).abs().max()) < 1e-24
    # Symmetries: the turned target is as good as the target itself.
    symmetries = torch.stack([torch.eye(3, dtype=torch.float64), half_turn(0)]).to(device)
    turned = rotation_6d_loss(rows, true @ half_turn(0, device), symmetries)
    assert float(turned.abs().max()) < 1e-24
    value.sum().backward()
    assert torch.allclose(raw.grad, 2 * (raw - rows).detach(), atol=1e-12)
    with pytest.raises(ValueError, match="pred_rotation_6d: expected shape"):
        rotation_6d_loss(raw[:3], true)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pose_loss_gradient_is_finite_at_zero_error(dtype, device):
    true = random_rotations(3, torch.Generator().manual_seed(10), dtype, device)
    d6 = true[:, :2, :].reshape(3, 6).clone().requires_grad_()
    t = torch.tensor([[0.1, -0.2, 6.0]], dtype=dtype, device=device).expand(3, 3).clone(
        ).requires_grad_()
    symmetries = torch.stack([torch.eye(3, dtype=dtype), half_turn(2).to(dtype)]).to(device)
    rotation_term, translation_term = pose_loss(rotation_6d_to_matrix(d6), t, true,
                                                t.detach(), symmetries)
    (rotation_term.sum() + translation_term.sum()).backward()
    assert rotation_term.max().item() < 1e-3
    assert bool(torch.isfinite(d6.grad).all()) and bool(torch.isfinite(t.grad).all())
    # Near zero the angle grows like the rotation's size: gradients stay bounded.
    d6.grad = None
    nudged = d6.detach() + 1e-4 * torch.randn(3, 6, generator=torch.Generator().manual_seed(1),
                                              dtype=dtype).to(device)
    nudged.requires_grad_()
    rotation_term, _ = pose_loss(rotation_6d_to_matrix(nudged), t.detach(), true, t.detach())
    rotation_term.sum().backward()
    assert bool(torch.isfinite(nudged.grad).all()) and float(nudged.grad.abs().max()) < 10


def test_pose_loss_bad_input():
    rotation = torch.eye(3).expand(2, 3, 3)
    t = torch.ones(2, 3)
    with pytest.raises(ValueError, match="gt_translation"):
        pose_loss(rotation, t, rotation, torch.zeros(2, 3))
    with pytest.raises(ValueError, match="symmetries"):
        pose_loss(rotation, t, rotation, t, torch.eye(3).expand(3, 2, 3, 3))
    with pytest.raises(ValueError, match="pose"):
        pose_loss(rotation, t[:1], rotation, t)


# ------------------------------------------------------------------- regularisers, total


def test_taper_loss_is_the_mean_squared_taper():
    taper = torch.tensor([[[0.5, -0.1], [0.0, 0.3]]], dtype=torch.float64)
    assembly = Assembly.from_values(torch.full((1, 2, 3), 0.2, dtype=torch.float64),
                                    torch.ones(1, 2, 2, dtype=torch.float64), taper=taper)
    assert float(taper_loss(assembly)) == pytest.approx((0.25 + 0.01 + 0 + 0.09) / 4)


def test_mask_loss_is_the_cross_entropy_against_the_area_averaged_mask():
    """By hand: each 2 x 2 block of the full mask averages to one target cell t, and the
    loss is the mean over cells of -(t log p + (1 - t) log(1 - p)), p = sigmoid(logit)."""
    mask = torch.tensor([[[[1, 1, 0, 0], [1, 0, 0, 0], [1, 1, 1, 1], [1, 1, 1, 1]]]],
                        dtype=torch.float64)
    logits = torch.tensor([[[[2.0, -1.0], [0.5, 3.0]]]], dtype=torch.float64)
    targets = [0.75, 0.0, 1.0, 1.0]  # the blocks' shares of the mask
    expected = 0.0
    for logit, target in zip(logits.flatten().tolist(), targets, strict=True):
        p = 1 / (1 + math.exp(-logit))
        expected -= target * math.log(p) + (1 - target) * math.log(1 - p)
    assert float(mask_loss(logits, mask)) == pytest.approx(expected / 4, rel=1e-12)


def test_loss_weights_defaults_and_config():
    weights = LossConfig().weights
    assert weights == PUBLISHED_WEIGHTS == {"chamfer": 10, "occupancy": 1, "reprojection": 1,
                                            "rotation": 0.1, "translation": 0.1,
                                            "overlap": 0.1, "taper": 0.01}
    assert LossConfig().enabled() == ("chamfer", "occupancy", "reprojection", "rotation",
                                      "translation", "overlap", "taper")  # registry order
    off = from_dict(LossConfig, {"weights": {**PUBLISHED_WEIGHTS, "reprojection": 0,
                                             "taper": 0.5}})
    assert "reprojection" not in off.enabled() and off.weights["taper"] == 0.5
    # A table lists the terms that train: one left out is off.
    assert from_dict(LossConfig, {"weights": {"chamfer": 1.0}}).enabled() == ("chamfer",)
    with pytest.raises(ConfigError, match="chamfer"):
        from_dict(LossConfig, {"weights": {"chamfer": -1}})
    with pytest.raises(ConfigError, match="unknown loss term 'oriented_chamfer'"):
        from_dict(LossConfig, {"weights": {"oriented_chamfer": 1.0}})
    assert LossConfig().chamfer_distance == "squared"  # the paper's Eq. 12
    with pytest.raises(ConfigError, match="chamfer_distance"):
        from_dict(LossConfig, {"chamfer_distance": "manhattan"})


def test_total_loss_sums_weighted_terms_and_skips_zero_weights():
    names = LossConfig().enabled()
    terms = {name: torch.tensor(float(i + 1), requires_grad=True)
             for i, name in enumerate(names)}
    total = total_loss(terms, PUBLISHED_WEIGHTS)
    expected = sum(PUBLISHED_WEIGHTS[name] * (i + 1) for i, name in enumerate(names))
    assert total.item() == pytest.approx(expected)
    total.backward()
    assert float(terms["chamfer"].grad) == pytest.approx(10.0)
    weights = {**PUBLISHED_WEIGHTS, "reprojection": 0.0, "taper": 0.0}
    partial = {k: v for k, v in terms.items() if k != "reprojection"}
    partial["taper"] = torch.tensor(math.nan)  # a switched-off term is never read
    assert total_loss(partial, weights).item() == pytest.approx(expected - 3 - 0.07)
    with pytest.raises(ValueError, match="reprojection"):
        total_loss(partial, PUBLISHED_WEIGHTS)
    with pytest.raises(ValueError, match="unknown term 'shape'"):
        total_loss({**terms, "shape": torch.tensor(1.0)}, PUBLISHED_WEIGHTS)
    with pytest.raises(ValueError, match="scalar"):
        total_loss({**terms, "rotation": torch.ones(3)}, PUBLISHED_WEIGHTS)
