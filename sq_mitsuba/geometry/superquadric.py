"""Superquadric surface points and inside-outside functions, primal and dual.

Pure torch, batched over leading dims, float32 or float64, any device.

Convention:
    - ``size`` a = (a1, a2, a3) are the semi-axes along x, y, z; shape (..., 3).
    - ``shape`` e = (e1, e2): e1 shapes the (r, z) profile (latitude), e2 the (x, y) cross-section
      (longitude); shape (..., 2), each in [0, 1] for the dual forms (0 = box-like, 1 = ellipsoid).
    - ``taper`` k = (k1, k2) scales x and y linearly along z (paper Eq. 3); |k| < 1.
    - Angles: ``eta`` is the latitude in [-pi/2, pi/2], ``omega`` the longitude in [-pi, pi].
    - ``points`` are (..., N, 3); per-primitive parameters broadcast against the batch dims (...).

The *primal* forms are the classic superquadric (paper Eq. 1, 2). Their exponents 2/e blow up as
e -> 0, so they are kept for comparison and tests only. The *dual* forms (paper Eq. 6-9, with the
paper's slips corrected: the dual superellipse turns by theta + 45 deg, not - 45 deg, and the
last exponent of Eq. 9 is e'/2, not 2/e1) use e' = 2 - e in [1, 2]; every power stays tame, e = 0
included, and dual samples satisfy the dual inside-outside function exactly (f = 1). The dual
family is a close relative of the superquadric: identical at e in {0, 1}, slightly different in
between.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from sq_mitsuba.checks import (
    check_broadcast,
    check_same_dtype,
    check_tensor,
    value_checks_enabled,
)

__all__ = [
    "dual_superellipse",
    "fexp",
    "inside_outside",
    "inside_outside_dual",
    "surface_points",
    "surface_points_dual",
    "taper",
    "untaper",
]

_LN2 = math.log(2.0)


def fexp(x: Tensor, p: Tensor | float) -> Tensor:
    """Signed power ``sign(x) * |x| ** p`` (elementwise, broadcasting)."""
    return torch.sign(x) * torch.abs(x) ** p


def _check_params(size: Tensor, shape: Tensor) -> None:
    check_tensor("size", size, (3,))
    check_tensor("shape", shape, (2,))
    if value_checks_enabled() and bool((size <= 0).any()):  # a value check: a GPU wait
        raise ValueError("size: semi-axes must be positive")


def _check_dual_shape(shape: Tensor) -> None:
    if value_checks_enabled() and bool(((shape < 0) | (shape > 1)).any()):
        raise ValueError("shape: the dual forms need e in [0, 1]")


def _check_angles(eta: Tensor, omega: Tensor) -> None:
    check_tensor("eta", eta, (None,))
    check_tensor("omega", omega, (None,))
    if eta.shape[-1] != omega.shape[-1]:  # one (eta, omega) pair per point
        raise ValueError(f"eta, omega: one of each per point, got {eta.shape[-1]} and "
                         f"{omega.shape[-1]}")


# --------------------------------------------------------------------------------------------
# Surface points
# --------------------------------------------------------------------------------------------


def surface_points(eta: Tensor, omega: Tensor, size: Tensor, shape: Tensor) -> Tensor:
    """Primal superquadric surface points (paper Eq. 1).

    Args:
        eta: latitudes (..., N) in [-pi/2, pi/2].
        omega: longitudes (..., N) in [-pi, pi].
        size: semi-axes (..., 3).
        shape: exponents (e1, e2) (..., 2), > 0 (gradients blow up as e -> 0).

    Returns:
        Points (..., N, 3).
    """
    _check_angles(eta, omega)
    _check_params(size, shape)
    a1, a2, a3 = size[..., None, 0], size[..., None, 1], size[..., None, 2]
    e1, e2 = shape[..., None, 0], shape[..., None, 1]
    cos_eta = fexp(torch.cos(eta), e1)
    x = a1 * cos_eta * fexp(torch.cos(omega), e2)
    y = a2 * cos_eta * fexp(torch.sin(omega), e2)
    z = a3 * fexp(torch.sin(eta), e1)
    return torch.stack(torch.broadcast_tensors(x, y, z), dim=-1)


def dual_superellipse(theta: Tensor, a1: Tensor, a2: Tensor, shape: Tensor) -> Tensor:
    """Points of the dual 2D superellipse (paper Eq. 6, with the +45 degree rotation).

    e' = 2 - e, g = 2 ** (e'/2 - 1), theta' = theta + pi/4,
    c = fexp(cos theta', e'), s = fexp(sin theta', e'), point = g (a1 (c + s), a2 (s - c)).
    For theta in [-pi/2, pi/2] the first coordinate is non-negative, as the spherical product
    needs.

    Args:
        theta: angles (..., N).
        a1, a2: semi-axes, broadcastable to theta.
        shape: e in [0, 1], broadcastable to theta.

    Returns:
        Points (..., N, 2).
    """
    e_dual = 2.0 - shape
    g = torch.exp2(0.5 * e_dual - 1.0)
    rotated = theta + 0.25 * math.pi
    c = fexp(torch.cos(rotated), e_dual)
    s = fexp(torch.sin(rotated), e_dual)
    first, second = g * a1 * (c + s), g * a2 * (s - c)
    return torch.stack(torch.broadcast_tensors(first, second), dim=-1)


def surface_points_dual(eta: Tensor, omega: Tensor, size: Tensor, shape: Tensor) -> Tensor:
    """Dual superquadric surface points (paper Eq. 7).

    r1 = dual2d(eta; 1, a3, e1), r2 = dual2d(omega; a1, a2, e2),
    point = (r1[0] r2[0], r1[0] r2[1], r1[1]).
    Finite with finite gradients for every shape in [0, 1]^2.

    Args:
        eta: latitudes (..., N) in [-pi/2, pi/2].
        omega: longitudes (..., N) in [-pi, pi].
        size: semi-axes (..., 3).
        shape: (e1, e2) (..., 2) in [0, 1].

    Returns:
        Points (..., N, 3), on the surface ``inside_outside_dual == 1``.
    """
    _check_angles(eta, omega)
    _check_params(size, shape)
    _check_dual_shape(shape)
    a1, a2, a3 = size[..., None, 0], size[..., None, 1], size[..., None, 2]
    e1, e2 = shape[..., None, 0], shape[..., None, 1]
    profile = dual_superellipse(eta, torch.ones_like(a3), a3, e1)
    section = dual_superellipse(omega, a1, a2, e2)
    radius = profile[..., 0:1]
    points = torch.cat([radius * section, profile[..., 1:2]], dim=-1)
    return points


# --------------------------------------------------------------------------------------------
# Inside-outside functions
# --------------------------------------------------------------------------------------------


def inside_outside(points: Tensor, size: Tensor, shape: Tensor) -> Tensor:
    """Primal inside-outside function (paper Eq. 2, standard form).

    f = (|x/a1| ** (2/e2) + |y/a2| ** (2/e2)) ** (e2/e1) + |z/a3| ** (2/e1);
    inside where f < 1. Unstable as e -> 0 (exponents 2/e): that is why the dual form exists.

    Args:
        points: (..., N, 3) in the primitive frame.
        size: (..., 3).
        shape: (..., 2), > 0.

    Returns:
        f (..., N).
    """
    check_tensor("points", points, (3,), min_dims=2)
    _check_params(size, shape)
    if value_checks_enabled() and bool((shape <= 0).any()):  # exponents 2 / e: inf at 0
        raise ValueError("shape: the primal form needs e > 0 (the dual forms take e = 0)")
    check_broadcast(points=points[..., :1, :], size=size[..., None, :], shape=shape[..., None, :])
    scaled = torch.abs(points / size[..., None, :])
    e1, e2 = shape[..., None, 0], shape[..., None, 1]
    cross = scaled[..., 0] ** (2.0 / e2) + scaled[..., 1] ** (2.0 / e2)
    return cross ** (e2 / e1) + scaled[..., 2] ** (2.0 / e1)


def _dual_norm(u: Tensor, v: Tensor, alpha: Tensor, with_grad: bool):
    """phi(u, v) = (|(u+v)/2| ** alpha + |(u-v)/2| ** alpha) ** (1/alpha), alpha = 2/e'.

    Returns phi and, with ``with_grad``, (d phi/du, d phi/dv, d phi/d alpha), computed from the
    forward's logs and powers (no further transcendentals, no branches). Magnitudes are clamped
    to the dtype's smallest normal number, so at u = v = 0 phi is ~1e-19 instead of 0 and every
    derivative is finite (0 * log 0 terms vanish, as their limits do).
    """
    tiny = torch.finfo(u.dtype).tiny
    p, q = 0.5 * (u + v), 0.5 * (u - v)
    abs_p, abs_q = p.abs().clamp_min_(tiny), q.abs().clamp_min_(tiny)
    log_p, log_q = abs_p.log(), abs_q.log()
    pow_p, pow_q = (alpha * log_p).exp_(), (alpha * log_q).exp_()
    total = (pow_p + pow_q).clamp_min_(tiny)
    log_total = total.log()
    inv_alpha = 1.0 / alpha
    phi = (log_total * inv_alpha).exp_()
    if not with_grad:
        return phi, None
    # d phi/dp = phi/S * sign(p) |p|^(alpha-1) = phi/S * sign(p) P/|p|.
    scale = phi / total
    d_p = torch.copysign(pow_p.div_(abs_p), p).mul_(scale)
    d_q = torch.copysign(pow_q.div_(abs_q), q).mul_(scale)
    # d phi/d alpha = phi (-log S / alpha^2 + (P log|p| + Q log|q|) / (alpha S)); P log|p| is
    # rebuilt from P/|p| (now in d_p, up to sign and scale) to spare the stored powers.
    weighted_logs = (d_p * p).mul_(log_p).addcmul_(d_q * q, log_q)  # = scale (P lp + Q lq)
    d_alpha = (weighted_logs - phi * log_total * inv_alpha).mul_(inv_alpha)
    return phi, (0.5 * (d_p + d_q), 0.5 * (d_p - d_q), d_alpha)


class DualFieldGrad(NamedTuple):
    """Per-point derivatives of the dual inside-outside value f w.r.t. its scaled inputs."""

    d_x: Tensor
    d_y: Tensor
    d_z: Tensor
    d_alpha1: Tensor
    d_alpha2: Tensor


def dual_field(xb: Tensor, yb: Tensor, zb: Tensor, alpha1: Tensor, alpha2: Tensor,
               with_grad: bool) -> tuple[Tensor, DualFieldGrad | None]:
    """f = phi(phi(xb, yb; alpha2), zb; alpha1) on scaled coordinates, with its derivatives.

    Internal building block of the hand-derived backward passes (no input checks).

    Args:
        xb, yb, zb: scaled coordinates, broadcastable.
        alpha1, alpha2: 2 / (2 - e1), 2 / (2 - e2), broadcastable.
        with_grad: also return the per-point derivatives.
    """
    inner, d_inner = _dual_norm(xb, yb, alpha2, with_grad)
    f, d_outer = _dual_norm(inner, zb, alpha1, with_grad)
    if not with_grad:
        return f, None
    dinner_dx, dinner_dy, dinner_dalpha = d_inner
    df_dinner, df_dz, df_dalpha1 = d_outer
    return f, DualFieldGrad(df_dinner * dinner_dx, df_dinner * dinner_dy, df_dz,
                            df_dalpha1, dinner_dalpha.mul_(df_dinner))


def dual_scales(shape: Tensor) -> tuple[Tensor, Tensor]:
    """g = 2 ** (e'/2 - 1) and alpha = 2 / e' for e' = 2 - e: shape (..., 2) -> 2 x (..., 2)."""
    e_dual = 2.0 - shape
    return torch.exp2(0.5 * e_dual - 1.0), 2.0 / e_dual


def first_derivatives_only(backward):
    """Decorate a hand-written ``backward`` (under ``once_differentiable``) to raise when asked
    for a graph of its gradient (``create_graph=True``: a gradient penalty, a Hessian):
    ``once_differentiable`` alone hands back gradients without one, and a second derivative
    through them came out zero without a word."""

    @functools.wraps(backward)
    def checked(ctx, *grads):
        if torch.is_grad_enabled():  # the engine enables grad mode for create_graph=True
            raise RuntimeError("the dual inside-outside function has first derivatives only (a "
                               "hand-written backward): no second derivative (create_graph=True)")
        return backward(ctx, *grads)

    return checked


class _InsideOutsideDual(torch.autograd.Function):
    """Dual inside-outside function with a hand-derived backward (see ``inside_outside_dual``).

    Inputs are broadcast views: points (..., N, 3), size (..., 1, 3), shape (..., 1, 2).
    """

    @staticmethod
    def forward(ctx, points: Tensor, size: Tensor, shape: Tensor) -> Tensor:
        with_grad = any(ctx.needs_input_grad)
        g, alpha = dual_scales(shape)
        g1, g2 = g[..., 0], g[..., 1]
        # Per-primitive scales: xb = x / (a1 g1 g2), yb = y / (a2 g1 g2), zb = z / (a3 g1).
        g12 = g1 * g2
        inv_scale = torch.stack([g12, g12, g1], dim=-1) * size
        scaled = points / inv_scale
        xb, yb, zb = scaled.unbind(-1)
        f, grads = dual_field(xb, yb, zb, alpha[..., 0], alpha[..., 1], with_grad)
        if with_grad:
            ctx.save_for_backward(scaled, inv_scale, size, alpha, *grads)
            ctx.shapes = (points.shape, size.shape, shape.shape)
        return f

    @staticmethod
    @first_derivatives_only
    @once_differentiable
    def backward(ctx, grad_f: Tensor):
        scaled, inv_scale, size, alpha, d_x, d_y, d_z, d_alpha1, d_alpha2 = ctx.saved_tensors
        points_shape, size_shape, shape_shape = ctx.shapes
        grad_scaled = torch.stack([grad_f * d_x, grad_f * d_y, grad_f * d_z], dim=-1)
        grad_points = grad_size = grad_shape = None
        if ctx.needs_input_grad[0]:
            grad_points = (grad_scaled / inv_scale).sum_to_size(points_shape)
        if ctx.needs_input_grad[1] or ctx.needs_input_grad[2]:
            # d xb/d a1 = -xb/a1 etc.; s_xyz holds sums of grad * scaled coordinate.
            s_xyz = (grad_scaled * scaled).sum_to_size(size_shape)
            if ctx.needs_input_grad[1]:
                grad_size = -s_xyz / size
            if ctx.needs_input_grad[2]:
                sx, sy, sz = s_xyz.unbind(-1)
                grad_alpha1 = (grad_f * d_alpha1).sum_to_size(sx.shape)
                grad_alpha2 = (grad_f * d_alpha2).sum_to_size(sx.shape)
                grad_shape = _shape_grad(sx + sy + sz, sx + sy, grad_alpha1, grad_alpha2,
                                         alpha).sum_to_size(shape_shape)
        return grad_points, grad_size, grad_shape


def _shape_grad(sum_g1: Tensor, sum_g2: Tensor, grad_alpha1: Tensor, grad_alpha2: Tensor,
                alpha: Tensor) -> Tensor:
    """Chain rule from (g, alpha) to e, stacked to (..., 2).

    ``sum_gi`` is the sum over coordinates scaled by g_i of grad * scaled coordinate. With
    g = 2^(e'/2 - 1), e' = 2 - e: dg/de = -g ln2 / 2 and d xb/d g = -xb/g give +ln2/2 * sum;
    alpha = 2/e' gives d alpha/de = alpha^2 / 2.
    """
    grad_e1 = 0.5 * _LN2 * sum_g1 + grad_alpha1 * 0.5 * alpha[..., 0] ** 2
    grad_e2 = 0.5 * _LN2 * sum_g2 + grad_alpha2 * 0.5 * alpha[..., 1] ** 2
    return torch.stack([grad_e1, grad_e2], dim=-1)


def inside_outside_dual(points: Tensor, size: Tensor, shape: Tensor) -> Tensor:
    """Dual inside-outside function (paper Eq. 8-9; the appendix's last exponent 2/e1 is a
    slip for e'/2).

    xb = x / (a1 g1 g2), yb = y / (a2 g1 g2), zb = z / (a3 g1), g_i = 2 ** (e_i'/2 - 1),
    phi(u, v, e') = (|(u+v)/2| ** (2/e') + |(u-v)/2| ** (2/e')) ** (e'/2),
    f = phi(phi(xb, yb, e2'), zb, e1'); inside where f < 1, f = 1 on ``surface_points_dual``.
    f is positively homogeneous of degree 1 in the point (f(s x) = s f(x) for s >= 0).

    Values and gradients are finite for every shape in [0, 1]^2 and every point, including the
    origin, the axes and the coordinate planes. The backward pass is hand-derived and reuses the
    forward's powers (first derivatives only).

    Args:
        points: (..., N, 3) in the (untapered) primitive frame.
        size: semi-axes (..., 3), positive.
        shape: (e1, e2) (..., 2) in [0, 1].

    Returns:
        f (..., N).
    """
    check_tensor("points", points, (3,), min_dims=2)
    _check_params(size, shape)
    _check_dual_shape(shape)
    check_broadcast(points=points[..., :1, :], size=size[..., None, :], shape=shape[..., None, :])
    check_same_dtype(points=points, size=size, shape=shape)
    return _InsideOutsideDual.apply(points, size[..., None, :], shape[..., None, :])


# --------------------------------------------------------------------------------------------
# Tapering
# --------------------------------------------------------------------------------------------


def taper(points: Tensor, taper: Tensor, size: Tensor) -> Tensor:
    """Linear tapering along z (paper Eq. 3): x' = (1 - k1 z/a3) x, y' = (1 - k2 z/a3) y.

    Args:
        points: (..., N, 3) in the primitive frame.
        taper: (k1, k2) (..., 2).
        size: (..., 3); only a3 is used.

    Returns:
        Tapered points (..., N, 3).
    """
    check_tensor("points", points, (3,), min_dims=2)
    check_tensor("taper", taper, (2,))
    check_tensor("size", size, (3,))
    if value_checks_enabled():  # as untaper and the assembly refuse them (a GPU wait)
        if bool((taper.abs() >= 1).any()):
            raise ValueError("taper: |k| must be < 1 (the cross-section collapses at |k| = 1)")
        if bool((size[..., 2] <= 0).any()):
            raise ValueError("size: a3 must be positive (z is measured in it)")
    z_rel = points[..., 2:3] / size[..., None, 2:3]
    factor = 1.0 - taper[..., None, :] * z_rel
    return torch.cat([points[..., :2] * factor, points[..., 2:3]], dim=-1)


def untaper(points: Tensor, taper: Tensor, size: Tensor) -> Tensor:
    """Inverse of :func:`taper` on the slab |z| <= a3 that holds the primitive.

    Outside that slab the factor is frozen at its value at z = +-a3. This keeps the division
    finite for far-away query points, and changes no classification: untapering leaves z as it
    is, and the dual inside-outside function satisfies f >= |z|/a3, so such points are outside
    either way.

    Args:
        points: (..., N, 3) tapered points.
        taper: (k1, k2) (..., 2), |k| < 1.
        size: (..., 3).

    Returns:
        Untapered points (..., N, 3).
    """
    check_tensor("points", points, (3,), min_dims=2)
    check_tensor("taper", taper, (2,))
    check_tensor("size", size, (3,))
    if bool((taper.abs() >= 1).any()):
        raise ValueError("taper: |k| must be < 1 (the cross-section collapses at |k| = 1)")
    z_rel = (points[..., 2:3] / size[..., None, 2:3]).clamp(-1.0, 1.0)
    factor = 1.0 - taper[..., None, :] * z_rel
    return torch.cat([points[..., :2] / factor, points[..., 2:3]], dim=-1)
