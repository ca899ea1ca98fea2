"""The turned copies the predictor reads (inference/turned_copies.py), against torch's exact
quarter turns; the hypotheses of a head without a distribution."""

import math

import torch

from sq_mitsuba.geometry.rotation import random_rotations
from sq_mitsuba.inference.turned_copies import hypotheses_from_logits, turn_angles, turned_images
from sq_mitsuba.model.heads import Rotation6dPoseHead
from sq_mitsuba.model.network import NetworkConfig


def test_the_angles_are_equal_turns_from_the_unturned_image() -> None:
    angles = turn_angles(8)
    assert angles.dtype == torch.float64 and angles[0] == 0.0
    assert torch.allclose(angles.diff(), torch.full((7,), math.pi / 4, dtype=torch.float64))


def test_quarter_turns_are_exact_and_copy_major() -> None:
    # A point right of the centre lies below it after a quarter turn (x right, y down):
    # torch.rot90 by -1 (clockwise on the screen), then a half and three quarters.
    generator = torch.Generator().manual_seed(0)
    images = torch.rand(3, 1, 16, 16, generator=generator)
    turned = turned_images(images, turn_angles(4))
    assert turned.shape == (9, 1, 16, 16)
    for copy, k in enumerate((-1, -2, -3)):
        expected = torch.rot90(images, k=k, dims=(-2, -1))
        assert torch.allclose(turned[3 * copy:3 * copy + 3], expected, atol=1e-5), copy


def test_a_regressing_heads_hypotheses_are_a_copy_of_its_rotation() -> None:
    """Without a distribution, the one hypothesis is the rotation, in storage of its own: an
    in-place edit of ``rotation_hypotheses`` leaves ``rotation`` as it was."""
    head = Rotation6dPoseHead(NetworkConfig(image_size=64))
    rotation = random_rotations(2, torch.Generator().manual_seed(0))
    kept = rotation.clone()
    hypotheses, scores = hypotheses_from_logits(head, None, rotation, 8)
    assert hypotheses.shape == (2, 1, 3, 3) and torch.equal(hypotheses[:, 0], rotation)
    assert torch.equal(scores, torch.ones(2, 1))
    hypotheses.zero_()
    assert torch.equal(rotation, kept)
