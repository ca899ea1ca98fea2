"""Differentiable silhouettes: pixels against Camera.project and the analytic projected area
of a sphere, gradients against finite differences and the analytic derivative, degenerate
and bad input, kernel re-use."""

from __future__ import annotations

import math

import pytest
import torch

from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import random_rotations
from sq_mitsuba.render.backend import count_kernels
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly


def sphere_area(centre: torch.Tensor, radius: torch.Tensor, focal: float) -> torch.Tensor:
    """Analytic area in px^2 of a sphere's perspective image (an ellipse): the cone of half
    angle a (sin a = R / L) cut by the image plane at angle t to its axis (cos t = c_z / L)
    has area pi f^2 sin^2 a cos a / (cos^2 t - sin^2 a)^(3/2)."""
    distance2 = (centre ** 2).sum(-1)
    return (math.pi * focal ** 2 * radius ** 2 * torch.sqrt(distance2 - radius ** 2)
            / (centre[..., 2] ** 2 - radius ** 2) ** 1.5)


def sphere_vertices(unit_sphere, centre, radius) -> torch.Tensor:
    vertices, _ = unit_sphere
    return (vertices * radius + torch.as_tensor(centre, dtype=torch.float64))[None]


def centroid(image: torch.Tensor) -> torch.Tensor:
    """Coverage-weighted centroid (u, v) of an (H, W) image, continuous pixel coordinates."""
    height, width = image.shape
    v, u = torch.meshgrid(torch.arange(height, dtype=image.dtype) + 0.5,
                          torch.arange(width, dtype=image.dtype) + 0.5, indexing="ij")
    mass = image.sum()
    return torch.stack(((image * u).sum() / mass, (image * v).sum() / mass))


# ---------------------------------------------------------------------------- pixels


@pytest.mark.parametrize("pixel", [(64.0, 64.0), (14.0, 14.0), (114.0, 14.0), (14.0, 114.0),
                                   (114.0, 114.0), (70.0, 57.0)])
def test_centroid_where_camera_projects_centre(precise_renderer, off_centre_camera,
                                               unit_sphere, pixel):
    centre = off_centre_camera.unproject(torch.tensor(pixel, dtype=torch.float64), 3.0)
    image = precise_renderer.render(sphere_vertices(unit_sphere, centre, 0.08),
                                    unit_sphere[1])[0]
    expected = off_centre_camera.project(centre)
    assert image.sum() > 10
    assert torch.allclose(centroid(image), expected, atol=0.5), (centroid(image), expected)


def test_non_square_focal_lengths(unit_sphere):
    from sq_mitsuba.geometry.camera import Camera

    camera = Camera(60.0, 90.0, 30.0, 36.0, 64, 64)
    renderer = SilhouetteRenderer(camera, spp=64)
    centre = camera.unproject(torch.tensor([44.0, 20.0], dtype=torch.float64), 3.0)
    image = renderer.render(sphere_vertices(unit_sphere, centre, 0.25), unit_sphere[1])[0]
    assert torch.allclose(centroid(image), camera.project(centre), atol=0.5)
    # The ellipse is stretched by fy / fx along v: second moments ratio (fy / fx)^2.
    v, u = torch.meshgrid(torch.arange(64.0) + 0.5, torch.arange(64.0) + 0.5, indexing="ij")
    c = centroid(image.float())
    var_u = (image * (u - c[0]) ** 2).sum() / image.sum()
    var_v = (image * (v - c[1]) ** 2).sum() / image.sum()
    assert float(var_v / var_u) == pytest.approx(1.5 ** 2, rel=0.1)


@pytest.mark.parametrize("centre", [(0.0, 0.0, 3.0), (0.5, -0.4, 3.0), (-0.6, 0.3, 2.5)])
def test_area_matches_analytic_projection(precise_renderer, off_centre_camera, unit_sphere,
                                          centre):
    centre = torch.tensor(centre, dtype=torch.float64)
    image = precise_renderer.render(sphere_vertices(unit_sphere, centre, 0.3), unit_sphere[1])
    expected = sphere_area(centre, torch.tensor(0.3, dtype=torch.float64),
                           off_centre_camera.fx)
    assert float(image.sum()) == pytest.approx(float(expected), rel=0.02)
    assert image.shape == (1, 128, 128) and image.dtype == torch.float64
    assert float(image.min()) >= 0 and float(image.max()) <= 1


# ---------------------------------------------------------------------------- gradients


def _area(renderer, unit_sphere, radius, shift_x, centre):
    vertices, faces = unit_sphere
    offset = torch.stack([centre[0] + shift_x, centre[1] + 0 * shift_x, centre[2] + 0 * shift_x])
    return renderer.render((vertices * radius + offset)[None], faces).sum()


@pytest.mark.parametrize("which", ["radius", "shift_x"])
def test_gradient_matches_finite_differences(precise_renderer, off_centre_camera, unit_sphere,
                                             which):
    centre = torch.tensor([0.6, -0.3, 2.6], dtype=torch.float64)
    radius = torch.tensor(0.25, dtype=torch.float64, requires_grad=True)
    shift = torch.tensor(0.0, dtype=torch.float64, requires_grad=True)
    grads = []
    for _ in range(2):  # average two independent backward passes (sppp 16 each)
        radius.grad = shift.grad = None
        _area(precise_renderer, unit_sphere, radius, shift, centre).backward()
        grads.append(float((radius if which == "radius" else shift).grad))
    gradient = sum(grads) / len(grads)
    step = 0.02
    with torch.no_grad():
        if which == "radius":
            plus = _area(precise_renderer, unit_sphere, radius + step, shift, centre)
            minus = _area(precise_renderer, unit_sphere, radius - step, shift, centre)
        else:
            plus = _area(precise_renderer, unit_sphere, radius, shift + step, centre)
            minus = _area(precise_renderer, unit_sphere, radius, shift - step, centre)
    finite_difference = float(plus - minus) / (2 * step)
    assert gradient == pytest.approx(finite_difference, rel=0.10)
    # And the analytic derivative of the projected area.
    r0 = radius.detach().clone().requires_grad_(True)
    s0 = torch.zeros((), dtype=torch.float64, requires_grad=True)
    sphere_area(centre + torch.stack([s0, 0 * s0, 0 * s0]), r0, off_centre_camera.fx).backward()
    analytic = float(r0.grad if which == "radius" else s0.grad)
    assert gradient == pytest.approx(analytic, rel=0.10)


def test_gradient_zero_away_from_silhouette(precise_renderer, unit_sphere):
    vertices, faces = unit_sphere
    centre = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    points = (vertices * 0.4 + centre)[None].requires_grad_(True)
    precise_renderer.render(points, faces).sum().backward()
    grad = points.grad[0].norm(dim=-1)
    # Cosine between the outward normal and the line of sight: +-1 faces the camera or away.
    view = torch.nn.functional.normalize(points.detach()[0], dim=-1)
    facing = (vertices * view).sum(-1).abs()
    assert float(grad[facing > 0.5].abs().max()) == 0.0
    assert float(grad[facing < 0.05].sum()) > 0


def test_batch_items_are_independent(renderer64, unit_sphere):
    vertices, faces = unit_sphere
    small = vertices * 0.2 + torch.tensor([0.2, 0.0, 2.0], dtype=torch.float64)
    large = vertices * 0.4 + torch.tensor([-0.1, 0.1, 2.0], dtype=torch.float64)
    points = torch.stack([small, large]).requires_grad_(True)
    images = renderer64.render(points, faces)
    single = renderer64.render(large[None], faces)
    areas = images.detach().sum((1, 2))
    assert float(areas[1]) == pytest.approx(float(single.sum()), rel=0.02)
    assert float(areas[0]) < float(areas[1])
    images[1].sum().backward()
    assert float(points.grad[0].abs().max()) == 0.0
    assert float(points.grad[1].abs().sum()) > 0


def test_no_kernel_compilation_once_warm(renderer64, unit_sphere):
    vertices, faces = unit_sphere
    generator = torch.Generator().manual_seed(0)

    def step() -> None:
        scale = 0.3 * (1 + 0.1 * torch.rand(1, generator=generator, dtype=torch.float64))
        points = vertices * scale + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
        points = points.expand(3, -1, -1).clone().requires_grad_(True)
        renderer64.render(points, faces).square().sum().backward()

    step()
    with count_kernels() as counter:
        step()
        step()
    assert counter.launched > 0
    assert counter.compiled == 0


# ---------------------------------------------------------------------------- assemblies


def test_render_assembly_sphere_area(renderer64):
    # Shape 1 is an ellipsoid; equal sizes make a sphere of radius 0.3.
    assembly = Assembly.from_values(torch.full((1, 1, 3), 0.3, dtype=torch.float64),
                                    torch.ones(1, 1, 2, dtype=torch.float64))
    rotation = random_rotations(2, generator=torch.Generator().manual_seed(1)).double()
    translation = torch.tensor([[0.1, -0.2, 2.0], [-0.3, 0.1, 2.4]], dtype=torch.float64)
    images = render_assembly(assembly, rotation, translation, renderer64)
    expected = sphere_area(translation, torch.tensor(0.3, dtype=torch.float64),
                           renderer64.camera.fx)
    # Level-3 icosphere: the inscribed polyhedron covers about 1 % less than the sphere.
    assert torch.allclose(images.sum((1, 2)), expected, rtol=0.03)


def test_render_assembly_gradients_reach_parameters(renderer64):
    raw = torch.zeros(1, 2, 16, dtype=torch.float64)
    raw[..., 8:14] = torch.tensor([1.0, 0, 0, 0, 1, 0], dtype=torch.float64)
    raw[0, 1, 5] = 0.6
    raw.requires_grad_(True)
    rotation = torch.eye(3, dtype=torch.float64)[None]
    translation = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
    images = render_assembly(Assembly.from_raw(raw), rotation, translation, renderer64)
    images.sum().backward()
    assert torch.isfinite(raw.grad).all()
    assert float(raw.grad[..., 0:3].sum()) > 0  # bigger primitives cover more pixels


# ---------------------------------------------------------------------------- degenerate


def _finite_render(renderer, assembly_params, rotation, translation):
    params = assembly_params.clone().requires_grad_(True)
    images = render_assembly(Assembly(params), rotation, translation, renderer)
    images.square().sum().backward()
    assert torch.isfinite(images).all() and torch.isfinite(params.grad).all()
    return images.detach(), params.grad


def test_degenerate_inputs_stay_finite(renderer64):
    identity = torch.eye(3, dtype=torch.float64)[None]
    boxes = Assembly.from_values(torch.tensor([[[0.3, 0.2, 0.1], [0.01, 0.01, 0.01]]],
                                              dtype=torch.float64),
                                 torch.zeros(1, 2, 2, dtype=torch.float64),
                                 translation=torch.tensor([[[0.0, 0, 0], [0.3, 0, 0]]],
                                                          dtype=torch.float64)).params
    # Shape exactly 0 (boxes) and a primitive of size 0.01.
    images, _ = _finite_render(renderer64, boxes, identity,
                               torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64))
    assert float(images.sum()) > 10
    # Partly outside the frame.
    images, grad = _finite_render(renderer64, boxes, identity,
                                  torch.tensor([[0.55, 0.0, 2.0]], dtype=torch.float64))
    assert 0 < float(images.sum())
    # All vertices behind the camera: nothing visible, zero gradient.
    images, grad = _finite_render(renderer64, boxes, identity,
                                  torch.tensor([[0.0, 0.0, -2.0]], dtype=torch.float64))
    assert float(images.sum()) == 0.0 and float(grad.abs().sum()) == 0.0
    # Straddling the camera plane, and the camera inside the object.
    _finite_render(renderer64, boxes, identity, torch.tensor([[0.0, 0.0, 0.05]],
                                                             dtype=torch.float64))
    images, _ = _finite_render(renderer64, boxes, identity,
                               torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64))
    assert float(images.mean()) > 0.99  # inside a box, every pixel is covered


# ---------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(("vertices", "faces", "message"), [
    (torch.zeros(4, 3), torch.tensor([[0, 1, 2]]), "vertices"),
    (torch.zeros(1, 4, 2), torch.tensor([[0, 1, 2]]), "vertices"),
    (torch.zeros(1, 4, 3, dtype=torch.int64), torch.tensor([[0, 1, 2]]), "vertices"),
    (torch.full((1, 4, 3), float("nan")), torch.tensor([[0, 1, 2]]), "vertices"),
    (torch.zeros(1, 4, 3), torch.tensor([[0, 1, 4]]), "faces"),
    (torch.zeros(1, 4, 3), torch.tensor([[0, 1, -1]]), "faces"),
    (torch.zeros(1, 4, 3), torch.tensor([[0.0, 1.0, 2.0]]), "faces"),
    (torch.zeros(1, 4, 3), torch.tensor([0, 1, 2]), "faces"),
    (torch.zeros(1, 4, 3), [[0, 1, 2]], "faces"),
])
def test_bad_input_raises_value_error(renderer64, vertices, faces, message):
    with pytest.raises(ValueError, match=message):
        renderer64.render(vertices, faces)


def test_bad_renderer_arguments(off_centre_camera):
    with pytest.raises(ValueError, match="camera"):
        SilhouetteRenderer("camera.json")
    with pytest.raises(ValueError, match="sppp"):
        SilhouetteRenderer(off_centre_camera, sppp=0)
    with pytest.raises(ValueError, match="workers: 2 with batched=True"):
        SilhouetteRenderer(off_centre_camera, workers=2, batched=True)
    with pytest.raises(ValueError, match="rotation"):
        render_assembly(Assembly.from_values(torch.ones(1, 1, 3) * 0.2, torch.ones(1, 1, 2)),
                        torch.eye(3), torch.zeros(1, 3), None)


def test_render_loss_matches_render_then_backward():
    """The fused loss (one vertex load per item) gives the loss, images and gradient of the
    two-pass path: same values, gradients equal up to their Monte Carlo noise."""
    generator = torch.Generator().manual_seed(3)
    assembly = Assembly.from_raw(0.5 * torch.randn(3, 2, 16, generator=generator))
    vertices, faces = assembly.merged_mesh(level=2)
    vertices = (vertices + torch.tensor([0.0, 0.0, 2.0])).detach()
    renderer = SilhouetteRenderer(Camera.default(48), spp=64, sppp=32)
    target = (renderer.render(vertices.flip(0), faces) > 0.5).float()

    def per_item(coverage, item):
        return ((coverage - target[item]) ** 2).sum()

    two_pass, fused = [], []
    for _ in range(4):
        leaf = vertices.clone().requires_grad_()
        coverage = renderer.render(leaf, faces)
        loss_two = sum(per_item(c, i) for i, c in enumerate(coverage))
        loss_two.backward()
        two_pass.append(leaf.grad)
        leaf = vertices.clone().requires_grad_()
        loss, images = renderer.render_loss(leaf, faces, per_item)
        (2.0 * loss).backward()  # the incoming gradient scales the result
        fused.append(leaf.grad / 2.0)
        assert not images.requires_grad and images.shape == coverage.shape
        assert abs(loss.item() - loss_two.item()) < 0.05 * loss_two.item() + 1.0
    mean_two, mean_fused = torch.stack(two_pass).mean(0), torch.stack(fused).mean(0)
    cosine = torch.nn.functional.cosine_similarity(mean_two.flatten(), mean_fused.flatten(), 0)
    assert cosine > 0.98
    with pytest.raises(ValueError, match="loss_fn"):
        renderer.render_loss(vertices, faces, "not callable")
    # Without a gradient to compute (no_grad, or vertices that need none) no backward pass
    # is rendered: the same loss and images as the forward pass of the gradient path.
    calls = []
    backward = renderer._vertex_gradient
    renderer._vertex_gradient = lambda *args: calls.append(1) or backward(*args)
    renderer.reseed(5)
    with_grad = renderer.render_loss(vertices.clone().requires_grad_(), faces, per_item)
    assert calls
    calls.clear()
    renderer.reseed(5)
    with torch.no_grad():
        without = renderer.render_loss(vertices.clone().requires_grad_(), faces, per_item)
    assert not calls and without[0].item() == with_grad[0].item()
    assert torch.equal(without[1], with_grad[1])


# ---------------------------------------------------------------------------- topology cache


def _two_spheres(unit_sphere):
    """One vertex buffer holding a sphere left and one right of the optical axis; faces of
    the left one and of the right one (same shape, different content)."""
    vertices, faces = unit_sphere
    left = vertices * 0.2 + torch.tensor([-0.35, 0.0, 2.0], dtype=torch.float64)
    right = vertices * 0.2 + torch.tensor([0.35, 0.0, 2.0], dtype=torch.float64)
    return torch.cat([left, right])[None], faces.clone(), faces + vertices.shape[0]


def test_topology_cache_picks_up_new_and_modified_faces(unit_sphere):
    points, faces_left, faces_right = _two_spheres(unit_sphere)
    renderer = SilhouetteRenderer(Camera.default(48), spp=16, seed=1)
    half = 24.0

    def side(image: torch.Tensor) -> float:
        return float(centroid(image[0])[0]) - half

    faces = faces_left.clone()
    assert side(renderer.render(points, faces)) < -5
    assert renderer.scenes_built == 1
    assert side(renderer.render(points, faces)) < -5  # same tensor, unchanged: no rebuild
    assert renderer.scenes_built == 1
    faces += unit_sphere[0].shape[0]  # in place: same tensor object, new topology
    modified = renderer.render(points, faces)
    assert side(modified) > 5 and renderer.scenes_built == 2
    assert side(renderer.render(points, faces_right.clone())) > 5  # equal copy: no rebuild
    assert renderer.scenes_built == 2
    assert side(renderer.render(points, faces_left.to(torch.int32))) < -5  # other content
    assert renderer.scenes_built == 3
    # Same faces, fewer vertices: another topology too.
    count = unit_sphere[0].shape[0]
    renderer.render(points[:, :count].contiguous(), faces_left)
    assert renderer.scenes_built == 4
    with torch.inference_mode():  # tensors without a version counter are compared instead
        inferred = faces_right.clone()
        assert side(renderer.render(points, inferred)) > 5
        assert side(renderer.render(points, inferred)) > 5
    assert renderer.scenes_built == 5

    # Results are those of a renderer that saw only fresh tensors (same seed, same calls).
    reference = SilhouetteRenderer(Camera.default(48), spp=16, seed=1)
    reference.render(points, faces_left.clone())
    reference.render(points, faces_left.clone())
    assert torch.equal(reference.render(points, faces_right.clone()), modified)


def test_backward_restores_the_topology_of_its_forward_pass(unit_sphere):
    points, faces_left, faces_right = _two_spheres(unit_sphere)
    gradients = []
    for interleave in (faces_right, faces_left):
        renderer = SilhouetteRenderer(Camera.default(48), spp=16, sppp=4, seed=2)
        leaf = points.clone().requires_grad_(True)
        image = renderer.render(leaf, faces_left)
        with torch.no_grad():
            renderer.render(points, interleave)  # the other topology (or the same) meanwhile
        image.sum().backward()
        gradients.append(leaf.grad)
    assert float(gradients[0].abs().sum()) > 0
    count = unit_sphere[0].shape[0]
    assert float(gradients[0][:, count:].abs().max()) == 0.0  # right sphere: not rendered
    # Equal up to the order of Dr.Jit's float32 atomic additions (not bit-reproducible).
    scale = float(gradients[1].abs().max())
    assert torch.allclose(gradients[0], gradients[1], rtol=0, atol=1e-5 * scale)


def test_reseed_restarts_the_sample_sequence(unit_sphere):
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    vertices, faces = unit_sphere
    posed = (0.3 * vertices + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64))[None].float()
    used = SilhouetteRenderer(Camera.default(32), spp=1, seed=5)
    used.render(posed, faces)
    used.render(posed, faces)
    used.reseed(9)
    fresh = SilhouetteRenderer(Camera.default(32), spp=1, seed=9)
    assert torch.equal(used.render(posed, faces), fresh.render(posed, faces))


def test_a_backward_pass_after_a_reseed_differentiates_its_own_mesh(unit_sphere):
    """Render A, reseed, render B (A moved 0.35 m), then back-propagate A: A's gradient is the
    one it has with nothing in between (the loaded vertices are recognised by a render count
    that reseed() does not restart, the samples by the forward pass's seed); it used to be
    B's, 134 % off."""
    vertices, faces = unit_sphere
    weights = torch.linspace(0.0, 1.0, 32)
    start = (0.3 * vertices + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)).float()

    def gradient(between: bool) -> torch.Tensor:
        renderer = SilhouetteRenderer(Camera.default(32), spp=4, seed=3)
        leaf = start[None].clone().requires_grad_()
        image = renderer.render(leaf, faces)
        if between:
            renderer.reseed(0)
            moved = (start + torch.tensor([0.35, 0.0, 0.0]))[None].requires_grad_()
            renderer.render(moved, faces)
        (image * weights).sum().backward()
        return leaf.grad

    alone, after = gradient(False), gradient(True)
    assert float(alone.abs().sum()) > 0
    # Equal up to the order of Dr.Jit's float32 atomic additions.
    assert torch.allclose(after, alone, rtol=0, atol=1e-4 * float(alone.abs().max()))
