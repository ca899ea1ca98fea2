"""Label-preserving augmentation: rotated masks match renders at the rotated pose; photometric
kinds leave masks and poses alone; per-item determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sq_mitsuba.config import ConfigError, from_dict
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.image_turns import check_rotation_exact, rotate_batch, z_rotation
from sq_mitsuba.geometry.metrics import mask_iou
from sq_mitsuba.geometry.rotation import quaternion_to_matrix, random_quaternions
from sq_mitsuba.render.silhouette.renderer import render_assembly
from sq_mitsuba.training.augment import AugmentConfig, augment_batch

SIZE = 64


def _rngs(count: int, seed: int = 0) -> list[np.random.Generator]:
    return [np.random.default_rng([seed, i]) for i in range(count)]


@pytest.fixture(scope="module")
def scene(renderer64):
    """An asymmetric two-primitive assembly seen at 4 random poses: masks (4, 1, 64, 64)."""
    assembly = Assembly.from_values(
        size=torch.tensor([[[0.35, 0.12, 0.08], [0.08, 0.2, 0.06]]], dtype=torch.float64),
        shape=torch.tensor([[[0.2, 0.6], [0.5, 0.3]]], dtype=torch.float64),
        translation=torch.tensor([[[0.05, 0.0, 0.0], [-0.25, 0.12, 0.0]]], dtype=torch.float64))
    gen = torch.Generator().manual_seed(3)
    rotations = quaternion_to_matrix(random_quaternions(4, gen, torch.float64))
    # Off-centre targets, so that a wrong rotation centre would show.
    translations = torch.tensor([[0.15, -0.1, 2.2], [-0.2, 0.05, 2.4], [0.0, 0.2, 2.0],
                                 [0.1, 0.1, 2.6]], dtype=torch.float64)
    with torch.no_grad():
        masks = render_assembly(assembly, rotations, translations, renderer64, level=4)
    return assembly, rotations, translations, masks[:, None]


def test_rotated_mask_matches_render_at_rotated_pose(scene, renderer64):
    """After in-plane rotation, the assembly rendered at (Rz R, Rz t) covers the rotated mask."""
    assembly, rotations, translations, masks = scene
    config = AugmentConfig(rotation=True, probability=1.0)
    images = masks.clone()
    out_images, out_masks, out_r, out_t = augment_batch(
        images, masks, rotations, translations, config, _rngs(4), renderer64.camera)
    with torch.no_grad():
        rendered = render_assembly(assembly, out_r, out_t, renderer64, level=4)
    iou = mask_iou(rendered, out_masks[:, 0])
    assert bool((iou > 0.95).all()), iou
    # The rotation was not the identity: the original masks no longer fit.
    assert bool((mask_iou(masks[:, 0], out_masks[:, 0]) < 0.9).all())
    # Poses stay rotations, distances are kept, and the image was turned like the mask.
    eye = torch.eye(3, dtype=torch.float64).expand(4, 3, 3)
    assert torch.allclose(out_r @ out_r.transpose(1, 2), eye, atol=1e-10)
    assert torch.allclose(out_t.norm(dim=-1), translations.norm(dim=-1), atol=1e-10)
    assert torch.allclose(out_t[:, 2], translations[:, 2], atol=1e-10)
    assert torch.equal(out_images, out_masks)


def test_rotation_sign_and_centre():
    """A bright pixel right of the centre moves to the angle's side (clockwise on screen)."""
    image = torch.zeros(1, 1, 33, 33, dtype=torch.float64)
    image[0, 0, 16, 26] = 1.0  # 10 px right of the centre pixel (16, 16)
    turned = rotate_batch(image, torch.tensor([math.pi / 2], dtype=torch.float64))
    row, col = divmod(int(turned[0, 0].argmax()), 33)
    assert (row, col) == (26, 16)  # y down: +90 deg takes +x to +y
    rz = z_rotation(torch.tensor([math.pi / 2], dtype=torch.float64))[0]
    assert torch.allclose(rz @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
                          torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), atol=1e-12)
    assert torch.isclose(torch.linalg.det(rz), torch.tensor(1.0, dtype=torch.float64))


def test_rotation_refuses_inexact_cameras():
    check_rotation_exact(Camera.default(64))
    with pytest.raises(ValueError, match="principal point"):
        check_rotation_exact(Camera(80.0, 80.0, 30.0, 32.0, 64, 64))
    with pytest.raises(ValueError, match="fx = fy"):
        check_rotation_exact(Camera(80.0, 90.0, 32.0, 32.0, 64, 64))
    images = torch.zeros(1, 1, 64, 64)
    with pytest.raises(ValueError, match="principal point"):
        augment_batch(images, images.clone(), torch.eye(3)[None], torch.tensor([[0, 0, 2.0]]),
                      AugmentConfig(rotation=True, probability=1.0), _rngs(1),
                      Camera(80.0, 80.0, 30.0, 32.0, 64, 64))


def test_photometric_kinds_keep_labels_and_act():
    gen = torch.Generator().manual_seed(0)
    images = 0.2 + 0.5 * torch.rand(6, 1, SIZE, SIZE, generator=gen)
    masks = (torch.rand(6, 1, SIZE, SIZE, generator=gen) > 0.5).float()
    rotations = quaternion_to_matrix(random_quaternions(6, gen, torch.float32))
    translations = torch.tensor([[0.0, 0.0, 2.0]]).repeat(6, 1)
    photometric = AugmentConfig(brightness=True, gamma=True, noise=True, blur=True,
                                probability=1.0)
    out_i, out_m, out_r, out_t = augment_batch(images, masks, rotations, translations,
                                               photometric, _rngs(6))
    assert torch.equal(out_m, masks) and torch.equal(out_r, rotations)
    assert torch.equal(out_t, translations)
    assert not torch.equal(out_i, images)
    assert float(out_i.min()) >= 0 and float(out_i.max()) <= 1

    # Each kind alone does what it says, checked against its definition.
    factor_only = AugmentConfig(brightness=True, brightness_range=(1.3, 1.3), probability=1.0)
    out = augment_batch(images, masks, rotations, translations, factor_only, _rngs(6))[0]
    assert torch.allclose(out, (images * 1.3).clamp(0, 1), atol=1e-6)
    gamma_only = AugmentConfig(gamma=True, gamma_range=(0.8, 0.8), probability=1.0)
    out = augment_batch(images, masks, rotations, translations, gamma_only, _rngs(6))[0]
    assert torch.allclose(out, images ** 0.8, atol=1e-6)
    flat = torch.full((2, 1, SIZE, SIZE), 0.5)
    noise_only = AugmentConfig(noise=True, noise_std=(0.02, 0.02), probability=1.0)
    out = augment_batch(flat, flat.clone(), rotations[:2], translations[:2], noise_only,
                        _rngs(2))[0]
    assert abs(float((out - 0.5).std()) - 0.02) < 0.002
    blur_only = AugmentConfig(blur=True, blur_sigma=(1.0, 1.0), probability=1.0)
    out = augment_batch(images, masks, rotations, translations, blur_only, _rngs(6))[0]
    assert abs(float(out.mean() - images.mean())) < 1e-3  # blur keeps the mean
    assert float(out.std()) < 0.6 * float(images.std())  # and removes pixel noise
    # On an impulse away from the borders the blur is the 2D Gaussian written out densely,
    # normalised over its window (radius 3 sigma): both axes, the right width.
    impulse = torch.zeros(1, 1, SIZE, SIZE, dtype=torch.float64)
    impulse[0, 0, SIZE // 2, SIZE // 2] = 1.0
    out = augment_batch(impulse, impulse.clone(), rotations[:1], translations[:1], blur_only,
                        _rngs(1))[0][0, 0]
    offsets = torch.arange(-3, 4, dtype=torch.float64)
    dense = torch.exp(-0.5 * (offsets[:, None] ** 2 + offsets[None] ** 2))  # sigma 1
    expected = torch.zeros(SIZE, SIZE, dtype=torch.float64)
    expected[SIZE // 2 - 3:SIZE // 2 + 4, SIZE // 2 - 3:SIZE // 2 + 4] = dense / dense.sum()
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-6)


def test_per_item_determinism_and_probability():
    """An item's augmentation depends on its own generator only, not on the batch."""
    gen = torch.Generator().manual_seed(1)
    images = torch.rand(5, 1, 32, 32, generator=gen)
    masks = (images > 0.5).float()
    rotations = torch.eye(3).repeat(5, 1, 1)
    translations = torch.tensor([[0.0, 0.0, 2.0]]).repeat(5, 1)
    config = AugmentConfig(rotation=True, brightness=True, gamma=True, noise=True, blur=True)
    full = augment_batch(images, masks, rotations, translations, config, _rngs(5, seed=9))
    rngs = _rngs(5, seed=9)
    alone = augment_batch(images[3:4], masks[3:4], rotations[3:4], translations[3:4], config,
                          [rngs[3]])
    for a, b in zip(full, alone, strict=True):
        assert torch.allclose(a[3:4], b, atol=1e-6)
    again = augment_batch(images, masks, rotations, translations, config, _rngs(5, seed=9))
    assert all(torch.equal(a, b) for a, b in zip(full, again, strict=True))
    off = AugmentConfig(rotation=True, probability=0.0)
    same = augment_batch(images, masks, rotations, translations, off, _rngs(5))
    assert all(torch.equal(a, b) for a, b in zip(same, (images, masks, rotations,
                                                        translations), strict=True))


def test_config_bounds():
    with pytest.raises(ConfigError, match="brightness_range"):
        from_dict(AugmentConfig, {"brightness_range": [1.5, 0.5]})
    with pytest.raises(ConfigError, match="probability"):
        from_dict(AugmentConfig, {"probability": 1.5})
    assert not AugmentConfig().enabled


def test_draw_and_apply_equal_augment_batch_and_refuse_bad_input():
    """The two halves the data stream uses (draws on the host, applied on the device) give
    augment_batch's batch bit for bit, and refuse mismatched input in one line each."""
    from sq_mitsuba.training.augment import apply_augmentation, draw_augmentation

    gen = torch.Generator().manual_seed(3)
    images = torch.rand(4, 1, SIZE, SIZE, generator=gen)
    masks = (images > 0.5).float()
    rotations = quaternion_to_matrix(random_quaternions(4, gen, torch.float32))
    translations = torch.tensor([[0.0, 0.0, 2.0]]).repeat(4, 1)
    config = AugmentConfig(rotation=True, brightness=True, gamma=True, noise=True, blur=True,
                           probability=0.7)
    whole = augment_batch(images, masks, rotations, translations, config, _rngs(4, seed=5))
    draws = draw_augmentation(config, _rngs(4, seed=5), tuple(images.shape))
    halves = apply_augmentation(images, masks, rotations, translations, draws)
    for a, b in zip(whole, halves, strict=True):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="generators: expected 4"):
        draw_augmentation(config, _rngs(3), tuple(images.shape))
    with pytest.raises(ValueError, match="draws: made for 4 items, the batch has 2"):
        apply_augmentation(images[:2], masks[:2], rotations[:2], translations[:2], draws)
    with pytest.raises(ValueError, match="masks: expected"):
        apply_augmentation(images, masks[:, :, :8], rotations, translations, draws)
    with pytest.raises(ValueError, match="principal point"):
        apply_augmentation(images, masks, rotations, translations,
                           draw_augmentation(AugmentConfig(rotation=True, probability=1.0),
                                             _rngs(4), tuple(images.shape)),
                           Camera(80.0, 80.0, 30.0, 32.0, SIZE, SIZE))
