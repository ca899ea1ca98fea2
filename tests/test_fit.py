"""Test-time fitting through the silhouette renderer."""

from __future__ import annotations

import pytest
import torch

from sq_mitsuba.evaluation.figures import plot_fit
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.metrics import mask_iou
from sq_mitsuba.geometry.rotation import random_rotations
from sq_mitsuba.inference.fit import default_raw, fit_assembly, resize_masks
from sq_mitsuba.model.losses import silhouette_loss
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly


def _target_views(views: int = 3, resolution: int = 64, seed: int = 3):
    """Masks of a tapered, rotated, off-centre superquadric from ``views`` random poses."""
    generator = torch.Generator().manual_seed(seed)
    target = Assembly.from_values(
        torch.tensor([[[0.38, 0.22, 0.14]]], dtype=torch.float64),
        torch.tensor([[[0.15, 0.8]]], dtype=torch.float64),
        translation=torch.tensor([[[0.04, -0.03, 0.02]]], dtype=torch.float64),
        rotation=random_rotations(1, generator=generator, dtype=torch.float64)[None],
        taper=torch.tensor([[[0.35, -0.25]]], dtype=torch.float64))
    rotations = random_rotations(views, generator=generator, dtype=torch.float64)
    translations = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64).repeat(views, 1)
    camera = Camera.default(resolution)
    with torch.no_grad():
        masks = render_assembly(target, rotations, translations,
                                SilhouetteRenderer(camera, spp=64, seed=5)) > 0.5
    return masks, camera, rotations, translations


@pytest.mark.slow
def test_fit_one_superquadric_reaches_acceptance_iou():
    masks, camera, rotations, translations = _target_views()
    result = fit_assembly(masks, camera, rotations, translations, num_primitives=1, steps=150)
    assert result.mean_iou >= 0.95, result.final_iou
    assert float(result.final_iou.min()) >= 0.9, result.final_iou
    assert result.ious[0][0] < 0.8  # the default start is far from the target
    assert len(result.losses) == 150 and result.losses[-1] < result.losses[0]
    assert [step for step, _ in result.snapshots] == [0, 75, 150]
    assert result.assembly.params.shape == (1, 1, 16)


def test_short_fit_and_figure(tmp_path):
    masks, camera, rotations, translations = _target_views(views=2, resolution=128)
    seen = []
    result = fit_assembly(masks, camera, rotations, translations, num_primitives=2, steps=3,
                          resolution=32, loss="iou",
                          callback=lambda step, loss, coverage: seen.append(coverage.shape))
    assert seen == [(2, 32, 32)] * 3
    assert result.targets.shape == (2, 32, 32)
    assert result.final_iou.shape == (2,) and torch.isfinite(result.final_iou).all()
    path = plot_fit(result, tmp_path / "figures" / "fit.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_mask_iou_and_losses():
    a = torch.zeros(2, 4, 4)
    b = torch.zeros(2, 4, 4)
    a[0, :2] = 1
    b[0, :1] = 1
    assert torch.allclose(mask_iou(a, b), torch.tensor([0.5, 1.0], dtype=torch.float64))
    assert float(silhouette_loss(a, a)) == 0.0
    assert float(silhouette_loss(a, b)) == pytest.approx(4 / 16)
    assert float(silhouette_loss(a, b, "iou")) == pytest.approx(0.5 + 1.0, abs=1e-5)
    with pytest.raises(ValueError, match="loss"):
        silhouette_loss(a, b, "l1")


def test_default_raw_and_resize():
    raw = default_raw(3, torch.Generator().manual_seed(0))
    assembly = Assembly.from_raw(raw)
    assert torch.allclose(assembly.size, torch.full((1, 3, 3), 0.255, dtype=torch.float64))
    assert torch.allclose(assembly.rotation, torch.eye(3, dtype=torch.float64).expand(1, 3, 3, 3))
    assert not torch.allclose(assembly.translation[0, 0], assembly.translation[0, 1])
    masks = torch.zeros(1, 8, 8, dtype=torch.bool)
    masks[0, :4, :4] = True
    assert torch.allclose(resize_masks(masks, 2, 2)[0],
                          torch.tensor([[1.0, 0.0], [0.0, 0.0]], dtype=torch.float64))
    # Shrunk in height, grown in width: nearest, values 0 or 1 (area, chosen by the height
    # alone before, averaged 3 set rows of 4 to 0.75).
    masks[0, 3] = False
    mixed = resize_masks(masks, 2, 16)[0]
    assert mixed.shape == (2, 16) and set(mixed.unique().tolist()) == {0.0, 1.0}


def test_fit_bad_input():
    camera = Camera.default(16)
    masks = torch.ones(2, 16, 16, dtype=torch.bool)
    rotations = torch.eye(3).expand(2, 3, 3)
    translations = torch.tensor([[0.0, 0.0, 2.0]]).repeat(2, 1)
    with pytest.raises(ValueError, match="masks"):
        fit_assembly(torch.ones(2, 8, 8), camera, rotations, translations)
    with pytest.raises(ValueError, match="rotations, translations"):
        fit_assembly(masks, camera, rotations[:1], translations)
    with pytest.raises(ValueError, match="translations"):
        fit_assembly(masks, camera, rotations, -translations)
    with pytest.raises(ValueError, match="steps"):
        fit_assembly(masks, camera, rotations, translations, steps=0)
    with pytest.raises(ValueError, match="loss"):
        fit_assembly(masks, camera, rotations, translations, loss="l2")
    # One assembly for every view: a start per view would fit each view its own.
    with pytest.raises(ValueError, match=r"^init_raw: expected \(1, 1, 16\), got \(2, 1, 16\)"):
        fit_assembly(masks, camera, rotations, translations, init_raw=torch.zeros(2, 1, 16))


def test_fit_options_defaults_bounds_and_keyword_overrides():
    from sq_mitsuba.config import ConfigError, field_docs, from_dict
    from sq_mitsuba.inference.fit import FitOptions

    options = FitOptions()
    assert (options.num_primitives, options.steps, options.resolution, options.lr,
            options.loss, options.seed) == (1, 150, 64, 0.05, "mse", 0)
    assert set(field_docs(FitOptions)) == {f for f in FitOptions.__dataclass_fields__}
    for field, value in (("steps", 0), ("seed", -1), ("seed", 2**31), ("resolution", 4),
                         ("lr", 0.0), ("loss", "l1"), ("num_primitives", 0), ("sppp", 0)):
        with pytest.raises(ConfigError, match=f"^{field}: "):
            from_dict(FitOptions, {field: value})
    masks = torch.ones(1, 16, 16, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"^seed: "):
        fit_assembly(masks, Camera.default(16), torch.eye(3)[None],
                     torch.tensor([[0.0, 0.0, 2.0]]), FitOptions(), seed=-5)
    with pytest.raises(TypeError, match="stpes"):
        fit_assembly(masks, Camera.default(16), torch.eye(3)[None],
                     torch.tensor([[0.0, 0.0, 2.0]]), stpes=3)


def test_options_object_and_keywords_fit_identically():
    from sq_mitsuba.inference.fit import FitOptions

    masks, camera, rotations, translations = _target_views(views=1, resolution=32)
    by_keywords = fit_assembly(masks, camera, rotations, translations, num_primitives=1,
                               steps=2, resolution=16, seed=4)
    options = FitOptions(steps=2, resolution=16, seed=4)
    by_options = fit_assembly(masks, camera, rotations, translations, options)
    assert by_options.options == options == by_keywords.options
    assert by_keywords.losses[0] == by_options.losses[0]  # same start, same samples
    # On one Dr.Jit thread (the default) the same seed is the same fit to the last bit.
    assert torch.equal(by_keywords.raw, by_options.raw)
    assert by_keywords.losses == by_options.losses


def test_a_deterministic_fit_is_bit_identical_and_leaves_the_threads_as_they_were():
    """Several Dr.Jit threads sum gradients in the order of their timing; the default fit
    runs on one, so that twenty steps of two runs agree to the last bit."""
    import drjit as dr

    masks, camera, rotations, translations = _target_views(views=2, resolution=32)
    before = dr.thread_count()
    runs = [fit_assembly(masks, camera, rotations, translations, num_primitives=2, steps=20,
                         resolution=24, seed=1) for _ in range(2)]
    assert torch.equal(runs[0].raw, runs[1].raw) and runs[0].losses == runs[1].losses
    assert dr.thread_count() == before


def test_resolution_beyond_the_machine_memory_is_refused_with_the_estimate():
    from sq_mitsuba.inference.fit import (
        RENDER_BYTES_PER_PIXEL,
        VIEW_BYTES_PER_PIXEL,
        check_fit_memory,
        fit_memory_bytes,
    )
    from sq_mitsuba.machine import available_memory

    assert fit_memory_bytes(2, 100, 50) == 100 * 50 * (RENDER_BYTES_PER_PIXEL
                                                       + 2 * VIEW_BYTES_PER_PIXEL)
    camera = Camera.default(48).rescaled(48, 24)  # 2:1: the fit keeps the aspect
    check_fit_memory(3, camera, 512)  # about 50 MB
    if available_memory() is None:
        pytest.skip("the OS does not report its memory")
    need = 100_000 * 50_000 * (80 + 3 * 48)  # bytes, written out independently
    with pytest.raises(ValueError, match=r"^resolution: 100000 \(100000 x 50000 px, 3 view"
                                         r"\(s\)\) needs about (\d+(\.\d+)?) TiB") as error:
        check_fit_memory(3, camera, 100_000)
    shown = float(str(error.value).split("about ")[1].split(" TiB")[0])
    assert shown == pytest.approx(need / 2**40, rel=0.01)
    # fit_assembly refuses before rendering anything.
    masks = torch.ones(3, 24, 48, dtype=torch.bool)
    with pytest.raises(ValueError, match="needs about"):
        fit_assembly(masks, camera, torch.eye(3).expand(3, 3, 3),
                     torch.tensor([[0.0, 0.0, 2.0]]).repeat(3, 1), resolution=100_000)
