"""Superquadric math: dual forms against closed forms, primal forms and finite differences.

The tests that take ``device`` run on ``pytest --device`` (conftest.py): inputs are drawn on
the CPU from the same seeds, then moved."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial import cKDTree

from sq_mitsuba.geometry.icosphere import icosphere_angles
from sq_mitsuba.geometry.superquadric import (
    fexp,
    inside_outside,
    inside_outside_dual,
    surface_points,
    surface_points_dual,
    taper,
    untaper,
)

F64 = torch.float64


def random_parameters(count: int, dtype: torch.dtype, seed: int = 0,
                      device: torch.device | str = "cpu"):
    """Sizes in [0.05, 0.5], shapes in [0, 1]^2 with exact 0 and 1 on either axis, tapers
    (drawn on the CPU, then moved to ``device``)."""
    gen = torch.Generator().manual_seed(seed)
    size = 0.05 + 0.45 * torch.rand(count, 3, generator=gen, dtype=F64)
    shape = torch.rand(count, 2, generator=gen, dtype=F64)
    # Every combination of an exact end value on either axis appears.
    ends = torch.tensor([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0]], dtype=F64)
    shape[: len(ends)] = ends
    shape[4:54, 0] = 0.0
    shape[54:104, 1] = 0.0
    shape[104:154, 0] = 1.0
    shape[154:204, 1] = 1.0
    taper_ = 0.9 * (2 * torch.rand(count, 2, generator=gen, dtype=F64) - 1)
    return tuple(t.to(dtype=dtype, device=device) for t in (size, shape, taper_))


@pytest.mark.parametrize(("dtype", "tolerance"), [(torch.float64, 1e-6), (torch.float32, 1e-4)])
def test_dual_samples_satisfy_dual_function(dtype, tolerance, device):
    size, shape, taper_ = random_parameters(1000, dtype, device=device)
    eta, omega = icosphere_angles(3, dtype, device)
    points = surface_points_dual(eta, omega, size, shape)  # (1000, 642, 3)
    tapered = taper(points, taper_, size)
    f = inside_outside_dual(untaper(tapered, taper_, size), size, shape)
    assert f.shape == (1000, 642)
    assert (f - 1).abs().max().item() < tolerance


def test_dual_samples_cover_all_octants():
    size, shape, _ = random_parameters(200, F64, seed=1)
    eta, omega = icosphere_angles(3, F64)
    points = surface_points_dual(eta, omega, size, shape)
    octant = (points > 1e-9).long() @ torch.tensor([1, 2, 4]) + 8 * torch.arange(200)[:, None]
    # Points exactly on a coordinate plane count for neither side; all 8 must still appear.
    off_plane = (points.abs() > 1e-9).all(-1)
    counts = torch.bincount(octant[off_plane], minlength=8 * 200).view(200, 8)
    assert (counts > 0).all()


def distance_to_primal_surface(points, size, shape, iterations: int = 30):
    """Distance from ``points`` to the primal surface by Newton projection onto h = 0.

    h = F^(e1/2) - 1 is homogeneous of degree 1 (F the primal function), so Newton steps along
    its gradient converge to a nearby surface point; the distance to it bounds the true
    distance from above and matches it where the step follows the normal.
    """
    x = points.detach().clone()
    for _ in range(iterations):
        x.requires_grad_()
        h = inside_outside(x, size, shape) ** (shape[..., None, 0] / 2) - 1
        (grad,) = torch.autograd.grad(h.sum(), x)
        x = (x - (h / (grad * grad).sum(-1))[..., None] * grad).detach()
    assert (inside_outside(x, size, shape) - 1).abs().max() < 1e-9
    return (x - points).norm(dim=-1)


def test_dual_and_primal_surfaces_are_close():
    """The dual family approximates the primal one: identical at e in {0, 1}, close between.

    Measured worst case over shapes in [0.3, 1]^2: 6.9 % of the largest semi-axis, for a cube
    at e = (0.3, 0.3) (3.4 % of its side); mean about 1 %.
    """
    gen = torch.Generator().manual_seed(2)
    grid = torch.linspace(0.3, 1.0, 8, dtype=F64)
    grid_shapes = torch.cartesian_prod(grid, grid)
    random_shapes = 0.3 + 0.7 * torch.rand(36, 2, generator=gen, dtype=F64)
    shape = torch.cat([grid_shapes, random_shapes])
    size = torch.cat([torch.full((64, 3), 0.3, dtype=F64),
                      0.05 + 0.45 * torch.rand(36, 3, generator=gen, dtype=F64)])
    eta, omega = icosphere_angles(3, F64)
    dual = surface_points_dual(eta, omega, size, shape)
    largest = size.amax(-1, keepdim=True)
    gap = distance_to_primal_surface(dual, size, shape) / largest
    assert gap.mean().item() < 0.03
    assert gap.max().item() < 0.07
    assert gap[63].max().item() < 1e-9  # shape (1, 1): the same ellipsoid
    # Every point of a dense primal sampling has a dual sample within 0.2 x the largest size.
    grid_eta = torch.linspace(-math.pi / 2, math.pi / 2, 200, dtype=F64)
    grid_omega = torch.linspace(-math.pi, math.pi, 250, dtype=F64)
    mesh_eta, mesh_omega = torch.meshgrid(grid_eta, grid_omega, indexing="ij")
    primal = surface_points(mesh_eta.reshape(-1), mesh_omega.reshape(-1), size, shape)
    for dense, samples, scale in zip(primal.numpy(), dual.numpy(), largest.numpy(), strict=True):
        nearest, _ = cKDTree(samples).query(dense)
        assert nearest.max() / scale[0] < 0.2


def test_unit_shape_is_the_ellipsoid_for_both_functions(device):
    gen = torch.Generator().manual_seed(3)
    size = (0.1 + torch.rand(5, 3, generator=gen, dtype=F64)).to(device)
    shape = torch.ones(5, 2, dtype=F64, device=device)
    points = torch.randn(5, 1000, 3, generator=gen, dtype=F64).to(device)
    ellipsoid = ((points / size[:, None]) ** 2).sum(-1)  # Eq. 10
    torch.testing.assert_close(inside_outside(points, size, shape), ellipsoid)
    # The dual function is homogeneous of degree 1: its square is the ellipsoid's form.
    torch.testing.assert_close(inside_outside_dual(points, size, shape) ** 2, ellipsoid)


def test_zero_shape_dual_is_the_box(device):
    gen = torch.Generator().manual_seed(4)
    size = torch.tensor([[0.5, 0.3, 0.2]], dtype=F64, device=device)
    points = ((2 * torch.rand(1, 100_000, 3, generator=gen, dtype=F64) - 1) * 0.8).to(device)
    f = inside_outside_dual(points, size, torch.zeros(1, 2, dtype=F64, device=device))
    box = (points.abs() / size[:, None]).amax(-1)
    outside_shell = ((points.abs() - size[:, None]).abs() > 1e-3).all(-1)
    assert outside_shell.sum() > 90_000
    assert torch.equal((f < 1)[outside_shell], (box < 1)[outside_shell])
    torch.testing.assert_close(f, box)


def test_primal_and_dual_classify_alike(device):
    gen = torch.Generator().manual_seed(5)
    size = 0.1 + 0.4 * torch.rand(50, 3, generator=gen, dtype=F64)
    shape = 0.2 + 0.8 * torch.rand(50, 2, generator=gen, dtype=F64)
    points = (2 * torch.rand(50, 4000, 3, generator=gen, dtype=F64) - 1) * size[:, None] * 1.3
    size, shape, points = size.to(device), shape.to(device), points.to(device)
    agree = (inside_outside(points, size, shape) < 1) == (inside_outside_dual(points, size, shape)
                                                          < 1)
    assert agree.double().mean().item() >= 0.97


def test_dual_function_is_positively_homogeneous(device):
    gen = torch.Generator().manual_seed(6)
    size, shape, _ = random_parameters(300, F64, seed=6, device=device)
    points = torch.randn(300, 50, 3, generator=gen, dtype=F64).to(device)
    torch.testing.assert_close(inside_outside_dual(2.5 * points, size, shape),
                               2.5 * inside_outside_dual(points, size, shape))


def test_fexp_is_signed_power():
    x = torch.tensor([-8.0, -1.0, 0.0, 1.0, 8.0], dtype=F64)
    torch.testing.assert_close(fexp(x, 1 / 3), torch.tensor([-2.0, -1.0, 0.0, 1.0, 2.0],
                                                             dtype=F64))


# ------------------------------------------------------------------------------ gradients


def generic_inputs(seed: int = 7, device: torch.device | str = "cpu"):
    gen = torch.Generator().manual_seed(seed)
    points = 0.3 * torch.randn(2, 6, 3, generator=gen, dtype=F64)
    size = 0.1 + 0.4 * torch.rand(2, 3, generator=gen, dtype=F64)
    shape = 0.1 + 0.8 * torch.rand(2, 2, generator=gen, dtype=F64)
    taper_ = 0.8 * (2 * torch.rand(2, 2, generator=gen, dtype=F64) - 1)
    return [t.to(device).requires_grad_() for t in (points, size, shape, taper_)]


def test_gradcheck_inside_outside_dual(device):
    points, size, shape, _ = generic_inputs(device=device)
    assert torch.autograd.gradcheck(inside_outside_dual, (points, size, shape))


def test_gradcheck_inside_outside_dual_with_taper(device):
    points, size, shape, taper_ = generic_inputs(8, device)

    def tapered_field(p, a, e, k):
        return inside_outside_dual(untaper(p, k, a), a, e)

    assert torch.autograd.gradcheck(tapered_field, (points, size, shape, taper_))


def test_gradcheck_surface_points_dual_and_taper(device):
    _, size, shape, taper_ = generic_inputs(9, device)
    gen = torch.Generator().manual_seed(9)
    eta = ((torch.rand(2, 8, generator=gen, dtype=F64) - 0.5) * math.pi).to(device)
    omega = ((torch.rand(2, 8, generator=gen, dtype=F64) - 0.5) * 2 * math.pi).to(device)
    eta.requires_grad_()
    omega.requires_grad_()

    def sampled(eta_, omega_, a, e, k):
        return taper(surface_points_dual(eta_, omega_, a, e), k, a)

    assert torch.autograd.gradcheck(sampled, (eta, omega, size, shape, taper_))


def test_hand_derived_backward_matches_autograd_of_the_formula(device):
    """The fused backward against autograd of the plain formula (float64, generic points)."""
    points, size, shape, _ = generic_inputs(10, device)

    def formula(p, a, e):
        e_dual = (2 - e)[..., None, :]
        g = 2 ** (e_dual / 2 - 1)
        a = a[..., None, :]

        def phi(u, v, ed):
            return (((u + v) / 2).abs() ** (2 / ed) + ((u - v) / 2).abs() ** (2 / ed)) ** (ed / 2)

        xb = p[..., 0] / (a[..., 0] * g[..., 0] * g[..., 1])
        yb = p[..., 1] / (a[..., 1] * g[..., 0] * g[..., 1])
        zb = p[..., 2] / (a[..., 2] * g[..., 0])
        return phi(phi(xb, yb, e_dual[..., 1]), zb, e_dual[..., 0])

    weights = torch.randn(2, 6, dtype=F64).to(device)
    ours = torch.autograd.grad((inside_outside_dual(points, size, shape) * weights).sum(),
                               (points, size, shape))
    reference = torch.autograd.grad((formula(points, size, shape) * weights).sum(),
                                    (points, size, shape))
    for mine, theirs in zip(ours, reference, strict=True):
        torch.testing.assert_close(mine, theirs)


def special_points() -> torch.Tensor:
    """The origin, points on the axes and on the coordinate planes, and a generic point."""
    values = [(0.0, 0.0, 0.0), (0.3, 0.0, 0.0), (0.0, -0.2, 0.0), (0.0, 0.0, 0.1),
              (0.2, 0.2, 0.0), (0.0, 0.1, -0.1), (0.1, 0.0, 0.3), (0.1, 0.2, 0.3),
              (0.25, 0.25, 0.0), (1e-30, 0.0, 0.0)]
    return torch.tensor([values], dtype=F64)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape_value", [(0.0, 0.0), (0.0, 1.0), (1.0, 0.0), (0.5, 0.0)])
def test_dual_function_finite_at_zero_shape_and_special_points(dtype, shape_value, device):
    points = special_points().to(dtype=dtype, device=device).requires_grad_()
    size = torch.tensor([[0.3, 0.2, 0.1]], dtype=dtype, device=device, requires_grad=True)
    shape = torch.tensor([shape_value], dtype=dtype, device=device, requires_grad=True)
    f = inside_outside_dual(points, size, shape)
    grads = torch.autograd.grad(f.sum(), (points, size, shape))
    assert torch.isfinite(f).all()
    assert all(torch.isfinite(g).all() for g in grads)


@pytest.mark.parametrize("shape_value", [(0.0, 0.0), (0.0, 1.0), (1.0, 0.0)])
def test_dual_samples_finite_at_zero_shape(shape_value, device):
    eta, omega = icosphere_angles(3, F64, device)
    # Add the poles, the equator and the quarter angles where cos or sin vanish.
    specials = torch.tensor([-math.pi / 2, -math.pi / 4, 0.0, math.pi / 4, math.pi / 2],
                            dtype=F64, device=device)
    eta = torch.cat([eta, specials]).requires_grad_()
    omega = torch.cat([omega, 2 * specials]).requires_grad_()
    size = torch.tensor([[0.3, 0.2, 0.1]], dtype=F64, device=device, requires_grad=True)
    shape = torch.tensor([shape_value], dtype=F64, device=device, requires_grad=True)
    points = surface_points_dual(eta, omega, size, shape)
    grads = torch.autograd.grad(points.sum(), (eta, omega, size, shape))
    assert torch.isfinite(points).all()
    assert all(torch.isfinite(g).all() for g in grads)


def test_primal_function_breaks_down_at_zero_shape():
    """Why the dual form exists: the classic function is not finite at e = 0 (computed with
    the value checks off: on, e = 0 is refused)."""
    from sq_mitsuba.checks import value_checks

    points = special_points().requires_grad_()
    size = torch.tensor([[0.3, 0.2, 0.1]], dtype=F64)
    shape = torch.tensor([[0.0, 0.0]], dtype=F64, requires_grad=True)
    with pytest.raises(ValueError, match="the primal form needs e > 0"):
        inside_outside(points, size, shape)
    with value_checks(False):
        f = inside_outside(points, size, shape)
    assert not torch.isfinite(f).all()
    # Small but non-zero shapes: values overflow or gradients do.
    shape_small = torch.tensor([[0.01, 0.01]], dtype=torch.float32, requires_grad=True)
    points32 = special_points().float().requires_grad_()
    f_small = inside_outside(points32, size.float(), shape_small)
    grads = torch.autograd.grad(f_small.sum(), (points32, shape_small))
    assert not (torch.isfinite(f_small).all() and all(torch.isfinite(g).all() for g in grads))


# ------------------------------------------------------------------------------ taper


def test_untaper_inverts_taper_inside_the_slab(device):
    gen = torch.Generator().manual_seed(11)
    size, _, taper_ = random_parameters(100, F64, seed=11)
    points = (2 * torch.rand(100, 500, 3, generator=gen, dtype=F64) - 1) * size[:, None]
    size, taper_, points = size.to(device), taper_.to(device), points.to(device)
    torch.testing.assert_close(untaper(taper(points, taper_, size), taper_, size), points)
    torch.testing.assert_close(taper(untaper(points, taper_, size), taper_, size), points)


def test_untaper_stays_finite_far_away():
    size = torch.tensor([[0.2, 0.2, 0.1]], dtype=F64)
    taper_ = torch.tensor([[0.99, -0.99]], dtype=F64)
    far = torch.tensor([[[0.1, 0.1, 5.0], [0.1, -0.1, -5.0], [0.0, 0.0, 0.1]]], dtype=F64)
    untapered = untaper(far, taper_, size)
    assert torch.isfinite(untapered).all()
    # The points beyond the slab stay outside, as f >= |z| / a3 there.
    f = inside_outside_dual(untapered, size, torch.full((1, 2), 0.5, dtype=F64))
    assert (f[0, :2] > 1).all()


# ------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"points": torch.zeros(4, 2)}, "points"),
    ({"points": torch.zeros(1, 4, 3, dtype=torch.int64)}, "points"),
    ({"size": torch.zeros(1, 3)}, "size"),
    ({"size": torch.full((1, 2), 0.2)}, "size"),
    ({"shape": torch.tensor([[float("nan"), 0.5]])}, "shape"),
    ({"shape": torch.tensor([[1.5, 0.5]])}, "shape"),
])
def test_inside_outside_dual_rejects_bad_input(kwargs, name):
    args = {"points": torch.zeros(1, 4, 3), "size": torch.full((1, 3), 0.2),
            "shape": torch.full((1, 2), 0.5), **kwargs}
    with pytest.raises(ValueError, match=name):
        inside_outside_dual(**args)


def test_surface_and_taper_functions_reject_bad_input():
    eta, omega = icosphere_angles(1, torch.float32)
    size, shape = torch.full((1, 3), 0.2), torch.full((1, 2), 0.5)
    with pytest.raises(ValueError, match="eta"):
        surface_points_dual(torch.tensor(1.0), omega, size, shape)
    with pytest.raises(ValueError, match="size"):
        surface_points(eta, omega, torch.full((1, 3), float("nan")), shape)
    with pytest.raises(ValueError, match="taper"):
        taper(torch.zeros(1, 4, 3), torch.zeros(1, 3), size)
    with pytest.raises(ValueError, match="taper"):
        untaper(torch.zeros(1, 4, 3), torch.ones(1, 2), size)


def test_the_taper_narrows_towards_plus_z_as_the_paper_writes():
    """Paper Eq. 3 by hand: x' = (1 - k1 z / a3) x, y' = (1 - k2 z / a3) y, so a positive k
    narrows the primitive towards +z. The round trips above hold for either sign; these pin it,
    for the functions and for the assembly's fused inside-outside."""
    from sq_mitsuba.geometry.assembly import Assembly

    points = torch.tensor([[0.5, 0.2, 1.0], [0.5, 0.2, -1.0]], dtype=F64)
    tapered = taper(points, torch.tensor([0.5, 0.25], dtype=F64), torch.tensor([1.0, 1.0, 2.0],
                                                                                dtype=F64))
    # z / a3 = +-0.5: factors 0.75 and 0.875 at +z, 1.25 and 1.125 at -z.
    expected = torch.tensor([[0.375, 0.175, 1.0], [0.625, 0.225, -1.0]], dtype=F64)
    torch.testing.assert_close(tapered, expected, rtol=0, atol=1e-12)

    k, a3, z = 0.5, 2.0, 1.0
    assembly = Assembly.from_values(torch.tensor([[[1.0, 1.0, a3]]], dtype=F64),
                                    torch.tensor([[[0.4, 0.6]]], dtype=F64),
                                    taper=torch.tensor([[[k, 0.0]]], dtype=F64))

    def crossing(height: float, axis: int) -> float:
        """Where the surface crosses the line through (0, 0, height) along ``axis``."""
        low, high = 0.0, 3.0
        for _ in range(60):
            middle = 0.5 * (low + high)
            point = torch.zeros(1, 1, 3, dtype=F64)
            point[0, 0, axis], point[0, 0, 2] = middle, height
            inside = float(assembly.inside_outside(point)[0, 0, 0]) < 1.0
            low, high = (middle, high) if inside else (low, middle)
        return low

    # The untapered section is the same at +-z, so the width ratio is the factors' ratio.
    ratio = crossing(z, 0) / crossing(-z, 0)
    assert ratio == pytest.approx((1 - k * z / a3) / (1 + k * z / a3), rel=1e-6)
    assert crossing(z, 1) == pytest.approx(crossing(-z, 1), rel=1e-6)  # k2 = 0: y untouched


def test_no_points_give_no_values_and_a_second_derivative_is_refused():
    """N = 0 points: (0,) values, as Assembly.inside_outside gives (an IndexError before).
    The dual function's backward is hand-written, first order: asked for a graph of its
    gradient (a gradient penalty) it raises, where it had handed back a gradient whose own
    derivative came out zero."""
    from sq_mitsuba.geometry.superquadric import inside_outside

    size, shape = torch.ones(3, dtype=torch.float64), torch.tensor([0.5, 0.5], dtype=torch.float64)
    assert inside_outside(torch.zeros(0, 3, dtype=torch.float64), size, shape).shape == (0,)
    assert inside_outside_dual(torch.zeros(0, 3, dtype=torch.float64), size, shape).shape == (0,)
    points = torch.rand(5, 3, dtype=torch.float64, requires_grad=True)
    first, = torch.autograd.grad(inside_outside_dual(points, size, shape).sum(), points)
    assert torch.isfinite(first).all()
    with pytest.raises(RuntimeError, match="first derivatives only"):
        torch.autograd.grad(inside_outside_dual(points, size, shape).sum(), points,
                            create_graph=True)


def test_the_icosphere_angles_are_copies():
    eta, _ = icosphere_angles(2, torch.float64)
    eta[0] = 5.0
    assert float(icosphere_angles(2, torch.float64)[0][0]) != 5.0
