"""The batched silhouette path (issue 34): every item of a batch in one Mitsuba launch each way,
each in its own tile of one film (``render/silhouette/tiled.py``), against the per-item path.

The two paths run the same estimator with other random numbers, so they agree in distribution,
not bit for bit. The equality tests therefore render at high sample counts and compare the
difference between the paths with the difference between two per-item renders of other seeds
(the Monte Carlo noise itself), with a fixed allowance on top; geometry (where a tile's
silhouette lands, its area) is checked against the analytic projection of a sphere, and one
item's gradient against finite differences and the analytic derivative.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import random_rotations
from sq_mitsuba.model.losses import mask_mse, reprojection_loss
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, sensor_dict
from sq_mitsuba.render.silhouette.tiled import TiledSilhouettes, TileLayout, fits, shears

# Off-centre principal point, fx != fy, non-square: every term of the shear is exercised.
CAMERA = Camera(80.0, 70.0, 30.0, 27.0, 64, 56)


def sphere_area(centre: torch.Tensor, radius: float, fx: float, fy: float) -> float:
    """Analytic area in px^2 of a sphere's perspective image (see test_silhouette.py), for
    focal lengths fx, fy (the image is stretched by fy / fx along y)."""
    distance2 = float((centre ** 2).sum())
    cz = float(centre[2])
    return (math.pi * fx * fy * radius ** 2 * math.sqrt(distance2 - radius ** 2)
            / (cz ** 2 - radius ** 2) ** 1.5)


@pytest.fixture(scope="module")
def sphere():
    from sq_mitsuba.geometry.icosphere import icosphere

    vertices, faces = icosphere(4)
    return torch.tensor(vertices, dtype=torch.float32), torch.tensor(faces)


@pytest.fixture(scope="module")
def batch():
    """Four assemblies of 3 primitives (level 2) at random poses, 2.6 m away, and masks."""
    generator = torch.Generator().manual_seed(4)
    raw = torch.randn(4, 3, 16, generator=generator) * 0.7
    vertices, faces = Assembly.from_raw(raw).merged_mesh(2)
    rotation = random_rotations(4, generator=generator)
    translation = torch.tensor([[0.1, -0.1, 2.6]]).expand(4, 3)
    camera_vertices = torch.einsum("bij,bnj->bni", rotation, vertices) + translation[:, None]
    with torch.no_grad():
        masks = (SilhouetteRenderer(CAMERA, spp=4).render(camera_vertices.flip(0), faces)
                 > 0.5).float()
    return camera_vertices.detach().float(), faces, masks


def _loss_and_grad(renderer, vertices, faces, masks):
    leaf = vertices.clone().requires_grad_(True)
    loss, coverage = renderer.render_target_loss(leaf, faces, masks, mask_mse)
    loss.backward()
    return float(loss.detach()), coverage, leaf.grad


def _relative(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-item relative L2 difference of (B, ...) tensors."""
    return (a - b).flatten(1).norm(dim=1) / b.flatten(1).norm(dim=1).clamp_min(1e-12)


# ------------------------------------------------------------------------------ layout


def test_tiles_and_film_round_trip():
    layout = TileLayout(5, 7, 4, 2)
    assert (layout.columns, layout.rows, layout.cell, layout.film) == (3, 2, (8, 11), (16, 33))
    tiles = torch.arange(5 * 4 * 7, dtype=torch.float32).reshape(5, 4, 7)
    film = layout.film_from_tiles(tiles)
    assert torch.equal(layout.tiles(film), tiles)
    assert float(film.sum()) == float(tiles.sum())  # zero outside the images
    origin = layout.origins()[4]  # item 4: row 1, column 1
    assert origin.tolist() == [11 + 2, 8 + 2]
    assert torch.equal(film[int(origin[1]):int(origin[1]) + 4, int(origin[0]):int(origin[0]) + 7],
                       tiles[4])


def test_shear_moves_each_item_by_whole_pixels():
    # The film camera sees a sheared vertex exactly where the item's camera sees the vertex,
    # plus its tile's origin.
    layout = TileLayout(6, CAMERA.width, CAMERA.height, 8)
    film = layout.camera(CAMERA)
    points = torch.rand(6, 10, 3, dtype=torch.float64) + torch.tensor([-0.5, -0.5, 1.5])
    shear = shears(CAMERA, layout)
    stretched = points * torch.tensor([1.0, CAMERA.fy / CAMERA.fx, 1.0], dtype=torch.float64)
    sheared = stretched.clone()
    sheared[..., :2] += stretched[..., 2:3] * shear[:, None]
    u = film.fx * sheared[..., 0] / sheared[..., 2] + film.cx
    v = film.fy * sheared[..., 1] / sheared[..., 2] + film.cy
    u0 = CAMERA.fx * points[..., 0] / points[..., 2] + CAMERA.cx
    v0 = CAMERA.fy * points[..., 1] / points[..., 2] + CAMERA.cy
    origins = layout.origins()
    torch.testing.assert_close(u - u0, origins[:, None, 0].expand_as(u))
    torch.testing.assert_close(v - v0, origins[:, None, 1].expand_as(v))


def test_items_reaching_out_of_their_cells_are_not_tiled():
    vertices = torch.tensor([[[0.0, 0.0, 2.0], [0.1, 0.1, 2.0], [0.0, 0.1, 2.1]]]).repeat(4, 1, 1)
    vertices[1, 0, 0] = 3.0  # far to the right of the image
    vertices[2, 0, 2] = 0.0  # on the camera plane
    vertices[3, 0, 2] = -1.0  # behind the camera
    assert fits(vertices, CAMERA, 8).tolist() == [True, False, False, False]


# ---------------------------------------------------------------------------- geometry


def test_tiled_spheres_land_where_the_camera_projects_them(sphere):
    # Five spheres, one per tile: each tile's area and centroid match the analytic projection
    # of its own sphere (the shear, the tile origins and fy != fx all enter).
    unit, faces = sphere
    centres = torch.tensor([[0.0, 0.0, 3.0], [0.4, -0.3, 3.0], [-0.5, 0.2, 2.5],
                            [0.2, 0.4, 3.5], [-0.3, -0.3, 2.8]])
    radius = 0.35
    vertices = unit[None] * radius + centres[:, None]
    renderer = SilhouetteRenderer(CAMERA, spp=64, batched=True)
    with torch.no_grad():
        _, coverage = renderer.render_target_loss(vertices, faces, torch.zeros(5, 56, 64),
                                                  mask_mse)
    rows, columns = torch.meshgrid(torch.arange(56.0) + 0.5, torch.arange(64.0) + 0.5,
                                   indexing="ij")
    for item in range(5):
        area = float(coverage[item].sum())
        assert area == pytest.approx(sphere_area(centres[item], radius, CAMERA.fx, CAMERA.fy),
                                     rel=0.02)
        mass = coverage[item].sum()
        u = float((coverage[item] * columns).sum() / mass)
        v = float((coverage[item] * rows).sum() / mass)
        x, y, z = centres[item].tolist()
        # A sphere's image centroid lies a little off the projected centre; 0.5 px covers it.
        assert u == pytest.approx(CAMERA.fx * x / z + CAMERA.cx, abs=0.5)
        assert v == pytest.approx(CAMERA.fy * y / z + CAMERA.cy, abs=0.5)


# ---------------------------------------------------------------------------- equality


def test_batched_equals_per_item_at_high_sample_counts(batch, device):
    vertices, faces, masks = batch
    spp, sppp = 256, 32
    batched = SilhouetteRenderer(CAMERA, spp=spp, sppp=sppp, seed=1, batched=True)
    first = SilhouetteRenderer(CAMERA, spp=spp, sppp=sppp, seed=2, batched=False)
    second = SilhouetteRenderer(CAMERA, spp=spp, sppp=sppp, seed=3, batched=False)
    loss_b, coverage_b, grad_b = _loss_and_grad(batched, vertices.to(device), faces.to(device),
                                                masks.to(device))
    assert coverage_b.device.type == grad_b.device.type == torch.device(device).type
    loss_1, coverage_1, grad_1 = _loss_and_grad(first, vertices, faces, masks)
    loss_2, coverage_2, grad_2 = _loss_and_grad(second, vertices, faces, masks)
    coverage_b, grad_b = coverage_b.cpu(), grad_b.cpu()
    # The noise between two per-item renders measures what "equal" can mean at these counts.
    noise_loss = abs(loss_1 - loss_2)
    noise_pixels = float((coverage_1 - coverage_2).abs().mean())
    noise_grad = _relative(grad_2, grad_1)
    # The allowance: 2.5 x the measured noise (a difference of two independent estimates
    # scatters as much as one pair does; 2.5 x leaves room for one unlucky draw) plus a floor
    # for a draw where the two per-item renders happen to agree closely.
    assert abs(loss_b - loss_1) <= 2.5 * noise_loss + 2e-4 * abs(loss_1)
    assert float((coverage_b - coverage_1).abs().mean()) <= 2.5 * noise_pixels + 1e-4
    assert float((coverage_b - coverage_1).mean().abs()) < 1e-3  # no bias in the coverage
    difference = _relative(grad_b, grad_1)
    assert bool((difference <= 2.5 * noise_grad + 0.02).all()), (difference, noise_grad)
    assert float(difference.mean()) < 0.15  # about sqrt(2) x 5 % at sppp 32


def test_gradient_matches_finite_differences_and_the_analytic_derivative(sphere):
    # One sphere among others: d(area)/d(shift along x) and d(area)/d(radius) of the tiled
    # render against finite differences of its forward images and the analytic projection.
    unit, faces = sphere
    centres = torch.tensor([[0.5, -0.2, 2.6], [0.0, 0.0, 3.0], [-0.4, 0.3, 2.8]])
    radius0 = 0.3
    renderer = SilhouetteRenderer(CAMERA, spp=256, sppp=64, seed=9, batched=True)

    def area(radius, shift):
        offset = torch.stack([shift, 0 * shift, 0 * shift])
        vertices = torch.cat([(unit * radius + centres[0] + offset)[None],
                              unit[None] * 0.25 + centres[1:, None]])
        loss, _ = renderer.render_target_loss(vertices, faces, torch.zeros(3, 56, 64),
                                              _area_loss)
        return loss

    radius = torch.tensor(radius0, requires_grad=True)
    shift = torch.tensor(0.0, requires_grad=True)
    area(radius, shift).backward()
    step = 0.02

    def central(plus_args, minus_args):
        # The same samples for both sides (reseed): the other tiles cancel exactly, and so
        # does most of this tile's noise.
        renderer.reseed(100)
        plus = float(area(*plus_args))
        renderer.reseed(100)
        return (plus - float(area(*minus_args))) / (2 * step)

    with torch.no_grad():
        d_radius = central((radius + step, shift), (radius - step, shift))
        d_shift = central((radius, shift + step), (radius, shift - step))
    assert float(radius.grad) == pytest.approx(d_radius, rel=0.10)
    assert float(shift.grad) == pytest.approx(d_shift, rel=0.15, abs=5.0)
    # The analytic derivative of the projected area with respect to the radius.
    r = torch.tensor(radius0, dtype=torch.float64, requires_grad=True)
    centre = centres[0].double()
    analytic_area = (math.pi * CAMERA.fx * CAMERA.fy * r ** 2
                     * torch.sqrt((centre ** 2).sum() - r ** 2)
                     / (centre[2] ** 2 - r ** 2) ** 1.5)
    analytic_area.backward()
    assert float(radius.grad) == pytest.approx(float(r.grad), rel=0.10)


def _area_loss(coverage: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Covered area in pixels (the target is unused): its gradient is the silhouette's."""
    return coverage.sum() + 0 * target.sum()


def test_an_item_out_of_its_tile_is_rendered_alone_bit_for_bit(batch):
    # Item 1 comes so close that it reaches far out of its image: it is rendered per item,
    # with the per-item path's samples (seed, call, item), so it equals a per-item render
    # exactly; the others are tiled.
    vertices, faces, masks = batch
    vertices = vertices.clone()
    vertices[1] = (vertices[1] - vertices[1].mean(0)) * 1.0 + torch.tensor([0.0, 0.0, 0.9])
    assert fits(vertices, CAMERA, TiledSilhouettes(CAMERA, 8, 4, sensor_dict).margin).tolist() == [
        True, False, True, True]
    batched = SilhouetteRenderer(CAMERA, spp=8, seed=5, batched=True)
    per_item = SilhouetteRenderer(CAMERA, spp=8, seed=5, batched=False)
    import drjit as dr

    previous = dr.thread_count()
    dr.set_thread_count(1)  # gradient sums in a fixed order, as training renders on the CPU
    try:
        _, coverage_b, grad_b = _loss_and_grad(batched, vertices, faces, masks)
        _, coverage_p, grad_p = _loss_and_grad(per_item, vertices, faces, masks)
    finally:
        dr.set_thread_count(previous)
    assert torch.equal(coverage_b[1], coverage_p[1])
    if batched._mi.variant().startswith("cuda"):  # atomic sums on a GPU: last bits may differ
        torch.testing.assert_close(grad_b[1], grad_p[1], rtol=1e-4, atol=1e-6)
    else:
        assert torch.equal(grad_b[1], grad_p[1])
    assert not torch.equal(coverage_b[0], coverage_p[0])  # tiled: other samples
    assert float(grad_b[0].abs().sum()) > 0


def test_reprojection_loss_through_the_batched_renderer():
    # The training loss: a batched renderer gives the per-item value up to the noise, and
    # gradients reach the assembly's parameters.
    generator = torch.Generator().manual_seed(0)
    raw = 0.6 * torch.randn(3, 2, 16, generator=generator, dtype=torch.float64)
    rotation = random_rotations(3, torch.Generator().manual_seed(7), dtype=torch.float64)
    translation = torch.tensor([[0.0, 0.0, 2.5]], dtype=torch.float64).expand(3, 3)
    masks = (torch.rand(3, 32, 32, generator=generator) < 0.3).double()
    camera = Camera.default(32)
    leaf = raw.clone().requires_grad_()
    batched = reprojection_loss(Assembly.from_raw(leaf), rotation, translation, masks,
                                SilhouetteRenderer(camera, spp=128, batched=True), level=2)
    batched.backward()
    assert batched.dtype == torch.float64 and leaf.grad.abs().sum() > 0
    with torch.no_grad():
        per_item = reprojection_loss(Assembly.from_raw(raw), rotation, translation, masks,
                                     SilhouetteRenderer(camera, spp=128), level=2)
        forward_only = reprojection_loss(Assembly.from_raw(raw), rotation, translation, masks,
                                         SilhouetteRenderer(camera, spp=128, batched=True),
                                         level=2)
    assert float(batched.detach()) == pytest.approx(float(per_item), rel=0.01)
    assert float(forward_only) == pytest.approx(float(per_item), rel=0.01)


def test_a_loss_that_vmap_cannot_map_runs_item_by_item(batch):
    vertices, faces, masks = batch

    def thresholded(coverage: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        if float(target.sum()) < 0:  # data-dependent control flow: vmap refuses it
            return coverage.sum()
        return (coverage - target).square().mean()

    renderer = SilhouetteRenderer(CAMERA, spp=8, seed=1, batched=True)
    loss_vmap, _ = renderer.render_target_loss(vertices, faces, masks, mask_mse)
    renderer.reseed(1)
    loss_loop, _ = renderer.render_target_loss(vertices, faces, masks, thresholded)
    assert float(loss_loop) == pytest.approx(float(loss_vmap), rel=1e-5)
    # A loss of one element, shape (1,), passes as the per-item path takes it.
    renderer.reseed(1)
    loss_one, _ = renderer.render_target_loss(
        vertices, faces, masks, lambda coverage, target: mask_mse(coverage, target).reshape(1))
    assert float(loss_one) == pytest.approx(float(loss_vmap), rel=1e-5)


# ---------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"batched": "yes"}, "batched: expected True, False or None"),
    ({"batched": True, "integrator": "prb_projective"}, "batched: needs the integrator"),
])
def test_bad_batched_option(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SilhouetteRenderer(CAMERA, **kwargs)


def test_batched_defaults_to_the_per_item_path_on_the_cpu():
    renderer = SilhouetteRenderer(CAMERA)
    assert renderer.batched == renderer._mi.variant().startswith("cuda")
    assert "batched=" in repr(renderer)


@pytest.mark.parametrize(("change", "message"), [
    ("targets", r"targets: expected shape \(4, 56, 64\)"),
    ("faces", r"faces: indices must lie in"),
    ("vertices", r"vertices: expected shape"),
    ("loss", "loss: expected a callable"),
])
def test_bad_batched_input_raises_one_line_errors(batch, change, message):
    vertices, faces, masks = batch
    renderer = SilhouetteRenderer(CAMERA, spp=4, batched=True)
    args = {"vertices": vertices, "faces": faces, "targets": masks, "loss": mask_mse}
    args[change] = {"targets": masks[:, :8], "faces": faces + 10_000,
                    "vertices": vertices[0], "loss": "mse"}[change]
    with pytest.raises(ValueError, match=message) as error:
        renderer.render_target_loss(**args)
    assert "\n" not in str(error.value)


def test_bad_tiled_margin():
    with pytest.raises(ValueError, match="margin: expected a positive integer"):
        TiledSilhouettes(CAMERA, 8, 4, sensor_dict, margin=0)


def test_faces_numpy_topology_is_reused(batch):
    vertices, faces, masks = batch
    renderer = SilhouetteRenderer(CAMERA, spp=2, batched=True)
    with torch.no_grad():
        renderer.render_target_loss(vertices, faces, masks, mask_mse)
        renderer.render_target_loss(vertices * 1.01, faces.clone(), masks, mask_mse)
    assert renderer._tiled.scenes_built == 1
    assert isinstance(renderer._tiled_topology.faces, np.ndarray)


def test_chunks_of_a_large_batch_render_like_one_launch(sphere):
    # Five spheres in chunks of two (the last padded with a hidden copy): every tile still
    # shows its own sphere's analytic area, and every item gets a gradient.
    unit, faces = sphere
    centres = torch.tensor([[0.0, 0.0, 3.0], [0.4, -0.3, 3.0], [-0.5, 0.2, 2.5],
                            [0.2, 0.4, 3.5], [-0.3, -0.3, 2.8]])
    vertices = unit[None] * 0.35 + centres[:, None]
    tiled = TiledSilhouettes(CAMERA, 64, 4, sensor_dict, max_items=2)
    faces_np = np.ascontiguousarray(faces.numpy().astype(np.uint32))
    result = tiled.target_loss(vertices, faces_np, torch.zeros(5, 56, 64), _area_loss,
                               (1, 2), True)
    assert tiled.scenes_built == 1 and bool(result.tiled.all())
    for item in range(5):
        assert float(result.coverage[item].sum()) == pytest.approx(
            sphere_area(centres[item], 0.35, CAMERA.fx, CAMERA.fy), rel=0.02)
        assert float(result.losses[item]) == pytest.approx(float(result.coverage[item].sum()))
        assert float(result.grad[item].norm()) > 0
    with pytest.raises(ValueError, match="max_items: expected a positive integer"):
        TiledSilhouettes(CAMERA, 8, 4, sensor_dict, max_items=0)
