"""The fast paths of the reprojection renderer, each against its reference: the lean
``silhouette_projective`` integrator against Mitsuba's ``prb_projective``, the per-target loss
(the renderer renders, the loss from ``learning.losses`` is handed in) against the general
fused loss, worker processes against one process, bit for bit. All on the per-item path
(``batched=False``, also on CUDA; the batched path has tests/test_silhouette_batched.py)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import pytest
import torch

from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.model.losses import mask_mse, soft_iou_loss
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer
from sq_mitsuba.render.silhouette.workers import WorkerError


@contextlib.contextmanager
def one_drjit_thread() -> Iterator[None]:
    """One Dr.Jit thread: gradient sums in a fixed order, so repeated renders agree exactly."""
    import drjit as dr

    previous = dr.thread_count()
    dr.set_thread_count(1)
    try:
        yield
    finally:
        dr.set_thread_count(previous)


@pytest.fixture(scope="module")
def batch() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Camera-frame vertices (5, V, 3) of 3-primitive assemblies (overlapping parts, so some
    silhouette edges are hidden), faces, and target masks (5, 40, 40) of other poses."""
    generator = torch.Generator().manual_seed(7)
    assembly = Assembly.from_raw(0.6 * torch.randn(5, 3, 16, generator=generator))
    vertices, faces = assembly.merged_mesh(level=2)
    vertices = (vertices + torch.tensor([0.05, -0.03, 2.2])).detach()
    with one_drjit_thread():
        masks = (SilhouetteRenderer(Camera.default(40), spp=16).render(
            vertices.roll(1, 0) * torch.tensor([1.1, 0.9, 1.0]), faces) > 0.5).float()
    return vertices, faces, masks


def _mask_mse(renderer: SilhouetteRenderer, vertices, faces, masks, seed: int = 5,
              loss_fn=mask_mse):
    renderer.reseed(seed)
    leaf = vertices.clone().requires_grad_()
    loss, coverage = renderer.render_target_loss(leaf, faces, masks, loss_fn)
    (3.0 * loss).backward()  # the incoming gradient scales the vertex gradients
    return loss.detach(), coverage, leaf.grad / 3.0


def test_lean_integrator_renders_what_prb_projective_renders(batch):
    """Same samples, the same images and gradients bit for bit: the lean integrator only
    skips work that cannot change a mask's radiance."""
    vertices, faces, masks = batch
    camera = Camera.default(40)
    with one_drjit_thread():
        lean = _mask_mse(SilhouetteRenderer(camera, spp=8, sppp=4, batched=False), vertices,
                         faces, masks)
        reference = _mask_mse(SilhouetteRenderer(camera, spp=8, sppp=4,
                                                 integrator="prb_projective"),
                              vertices, faces, masks)
    for ours, theirs in zip(lean, reference, strict=True):
        assert torch.equal(ours, theirs)
    assert lean[2].abs().sum() > 0  # the gradients are not trivially equal
    with pytest.raises(ValueError, match="integrator"):
        SilhouetteRenderer(camera, integrator="path")


def test_mask_loss_matches_the_general_fused_loss(batch):
    """``render_target_loss`` with ``mask_mse`` against ``render_loss`` with the same MSE
    written as a per-index callback."""
    vertices, faces, masks = batch
    renderer = SilhouetteRenderer(Camera.default(40), spp=8, sppp=4, batched=False)
    with one_drjit_thread():
        loss, coverage, grad = _mask_mse(renderer, vertices, faces, masks)
        renderer.reseed(5)
        leaf = vertices.clone().requires_grad_()
        general, general_coverage = renderer.render_loss(
            leaf, faces, lambda c, i: (c - masks[i]).square().mean())
        general.backward()
    torch.testing.assert_close(coverage, general_coverage, rtol=0, atol=0)
    torch.testing.assert_close(loss, general.detach(), rtol=1e-12, atol=0)
    torch.testing.assert_close(grad, leaf.grad, rtol=1e-5, atol=1e-7)
    with torch.no_grad():  # no gradient wanted: forward images only, the same loss
        renderer.reseed(5)
        value, images = renderer.render_target_loss(vertices, faces, masks, mask_mse)
    torch.testing.assert_close(images, coverage, rtol=0, atol=0)
    torch.testing.assert_close(value, loss, rtol=0, atol=0)


def test_mask_loss_rejects_bad_masks(batch):
    vertices, faces, masks = batch
    renderer = SilhouetteRenderer(Camera.default(40), spp=4)
    with pytest.raises(ValueError, match="targets: expected shape"):
        renderer.render_target_loss(vertices, faces, masks[:, :20], mask_mse)
    with pytest.raises(ValueError, match="targets"):
        renderer.render_target_loss(vertices, faces, masks.clone().fill_(float("nan")),
                                    mask_mse)
    with pytest.raises(ValueError, match="loss"):
        renderer.render_target_loss(vertices, faces, masks, "mse")
    with pytest.raises(ValueError, match="workers"):
        SilhouetteRenderer(Camera.default(40), workers=-1)


def test_workers_match_one_process_bit_for_bit(batch):
    """Five items over two workers (an uneven split) give exactly the one-process,
    one-thread result; a dead worker is reported and replaced on the next call."""
    vertices, faces, masks = batch
    camera = Camera.default(40)
    pooled = SilhouetteRenderer(camera, spp=8, sppp=4, workers=2, batched=False)
    try:
        with one_drjit_thread():
            expected = _mask_mse(SilhouetteRenderer(camera, spp=8, sppp=4, batched=False),
                                 vertices, faces, masks)
        for _ in range(2):  # the second call reuses the running workers
            for ours, theirs in zip(_mask_mse(pooled, vertices, faces, masks), expected,
                                    strict=True):
                assert torch.equal(ours, theirs)
        pooled._pool._processes[0].kill()
        pooled._pool._processes[0].wait()
        with pytest.raises(WorkerError, match=r"worker 0 .* exited"):
            _mask_mse(pooled, vertices, faces, masks)
        assert pooled._pool is None
        for ours, theirs in zip(_mask_mse(pooled, vertices, faces, masks), expected,
                                strict=True):
            assert torch.equal(ours, theirs)
        # Another loss of learning.losses runs in the workers as it runs here.
        with one_drjit_thread():
            expected = _mask_mse(SilhouetteRenderer(camera, spp=8, sppp=4, batched=False),
                                 vertices, faces, masks, loss_fn=soft_iou_loss)
        for ours, theirs in zip(_mask_mse(pooled, vertices, faces, masks,
                                          loss_fn=soft_iou_loss), expected, strict=True):
            assert torch.equal(ours, theirs)
        with pytest.raises(ValueError, match="module-level function"):
            _mask_mse(pooled, vertices, faces, masks, loss_fn=lambda c, t: c.mean())
    finally:
        pooled.close()
