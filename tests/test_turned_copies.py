"""The turned copies the predictor reads (inference/turned_copies.py), against torch's exact
quarter turns."""

import math

import torch

from sq_mitsuba.inference.turned_copies import turn_angles, turned_images


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
