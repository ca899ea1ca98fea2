"""Target masks segmented from space images: a shaded silhouette with stars and noise."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sq_mitsuba.data.segmentation import segment_target
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly


@pytest.fixture(scope="module")
def silhouette() -> np.ndarray:
    assembly = Assembly.from_values(size=torch.tensor([[[0.35, 0.1, 0.08], [0.06, 0.3, 0.02]]]),
                                    shape=torch.tensor([[[0.2, 0.2], [0.1, 0.1]]]))
    rotation = torch.eye(3)[None]
    translation = torch.tensor([[0.05, 0.02, 1.6]])
    with torch.no_grad():
        coverage = render_assembly(assembly, rotation, translation,
                                   SilhouetteRenderer(Camera.default(96), spp=16))
    return coverage[0].numpy() > 0.5


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_shaded_target_among_stars_is_segmented(silhouette):
    rng = np.random.default_rng(0)
    height, width = silhouette.shape
    # Lit from the left: brightness falls from 0.8 to 0.15 across the target.
    shading = np.linspace(0.8, 0.15, width)[None, :].repeat(height, 0)
    image = silhouette * shading + rng.normal(0, 0.005, silhouette.shape)
    stars = rng.integers(0, [height, width], size=(30, 2))
    image[stars[:, 0], stars[:, 1]] = 0.9
    result = segment_target(np.clip(image, 0, 1))
    assert _iou(result.mask, silhouette) > 0.9
    assert result.warning is None


def test_bright_background_warns(silhouette):
    image = silhouette * 0.7
    image[:, : image.shape[1] // 2] = np.maximum(image[:, : image.shape[1] // 2], 0.4)
    assert segment_target(image).warning is not None


def test_bad_images_are_refused():
    with pytest.raises(ValueError, match="nothing brighter"):
        segment_target(np.zeros((16, 16)))
    with pytest.raises(ValueError, match="2D grayscale"):
        segment_target(np.zeros((16, 16, 3)))
    bad = np.zeros((16, 16))
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        segment_target(bad)


def test_the_rule_by_hand_threshold_gaps_and_holes():
    """The documented rule on drawn images: the threshold 0.12 x the 99.5th percentile (above
    the floor), a one-pixel dark gap between two lit panels closed, a shadowed hole inside
    the outline filled."""
    image = np.zeros((40, 40))
    image[10:30, 8:19] = 0.9  # left panel
    image[10:30, 20:31] = 0.9  # right panel, a one-pixel dark seam at column 19
    image[13:27, 10:18] = 0.02  # a shadowed part inside the left panel (a hole)
    image[10:30, 25] = 0.05  # a dim stripe, below 0.12 x 0.9 but above the floor
    result = segment_target(image)
    assert result.threshold == pytest.approx(0.12 * np.percentile(image, 99.5), rel=1e-12)
    expected = np.zeros((40, 40), dtype=bool)
    expected[10:30, 8:31] = True  # one piece: the seam, the hole and the stripe inside it
    np.testing.assert_array_equal(result.mask, expected)
    # A dim image: the floor (8 / 255) decides.
    assert segment_target(image * 0.05).threshold == pytest.approx(8 / 255)
