"""The three orthogonal directions most surface normals lie along (a Manhattan frame).

Spacecraft are built along their body axes, so the normals of the surface a camera sees
cluster along those axes as the camera sees them; their Manhattan frame is the body frame up
to which axis is which and its ends. :func:`manhattan_frame` finds it by sampling (two
normals make a candidate frame, the one most normals agree with wins) and refines it by
alternating assignment and orthogonal Procrustes; :func:`frame_by_extent` orders its axes by
a cloud's extent along them, as the processed models' convention orders the body axes.

Convention: a frame is a proper rotation F (3, 3) whose columns are the axes in the frame the
normals are given in (F maps frame coordinates to those), so ``x = F x_frame``; tensors are
float64.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from sq_mitsuba.checks import check_tensor
from sq_mitsuba.geometry.rotation import best_rotation

__all__ = ["frame_by_extent", "manhattan_frame"]


def _proper(frame: Tensor) -> Tensor:
    """The frame with its last axis flipped where it is a reflection."""
    sign = torch.where(torch.linalg.det(frame) < 0, -1.0, 1.0).to(frame)
    return torch.cat([frame[:, :2], frame[:, 2:] * sign], dim=1)


def manhattan_frame(normals: Tensor, weights: Tensor | None = None, *, tries: int = 300,
                    inlier_deg: float = 12.0, refine_deg: float = 25.0, refine_steps: int = 10,
                    generator: torch.Generator | None = None) -> tuple[Tensor, float]:
    """The proper frame whose axes (either end) the most normals lie along.

    Args:
        normals: (N, 3) normals, N >= 2, normalised here (zero rows are ignored).
        weights: (N,) non-negative weights (default all 1): a normal map's lengths, say,
            where a cell's length says how alike its normals were.
        tries: candidate frames, each from two normals at least 30 deg apart.
        inlier_deg: a normal within this angle of an axis counts for a candidate.
        refine_deg, refine_steps: the winner is refined by assigning each normal within
            ``refine_deg`` to its nearest axis end and solving orthogonal Procrustes.
        generator: the candidates' random draws (default: seeded 0, so the result is
            reproducible).

    Returns:
        frame F (3, 3) float64 and the weighted share of normals within ``inlier_deg`` of an
        axis (how Manhattan the surface is: 1 for a box's faces).
    """
    check_tensor("normals", normals, (None, 3))
    n = normals.detach().double()
    w = torch.ones(len(n), dtype=torch.float64) if weights is None else \
        weights.detach().double().clamp_min(0)
    usable = (n.norm(dim=1) > 1e-9) & (w > 0)
    n, w = torch.nn.functional.normalize(n[usable], dim=1), w[usable]
    if len(n) < 2 or float(w.sum()) <= 0:
        raise ValueError(f"normals: need at least 2 non-zero normals with weight, got {len(n)}")
    generator = generator or torch.Generator().manual_seed(0)
    cos_in = math.cos(math.radians(inlier_deg))
    pairs = torch.randint(len(n), (tries, 2), generator=generator)
    first, second = n[pairs[:, 0]], n[pairs[:, 1]]
    second = second - (second * first).sum(1, keepdim=True) * first
    apart = second.norm(dim=1) > 0.5  # at least 30 deg apart
    if not bool(apart.any()):
        raise ValueError("normals: all lie within 30 deg of one direction; no frame is defined")
    first, second = first[apart], torch.nn.functional.normalize(second[apart], dim=1)
    candidates = torch.stack([first, second, torch.linalg.cross(first, second)], dim=2)
    agree = (n @ candidates).abs().amax(dim=2) > cos_in  # (C, N)
    frame = candidates[int((agree.double() * w).sum(1).argmax())]
    cos_refine = math.cos(math.radians(refine_deg))
    for _ in range(refine_steps):
        projection = n @ frame  # (N, 3)
        axis = projection.abs().argmax(1)
        near = projection.abs().amax(1) > cos_refine
        target = torch.zeros_like(n)
        target[torch.arange(len(n)), axis] = torch.sign(projection[torch.arange(len(n)), axis])
        # Procrustes: the rotation F maximising sum w_i n_i . F e_i.
        frame = best_rotation((n * (w * near)[:, None]).T @ target)
    share = float((w * ((n @ frame).abs().amax(1) > cos_in)).sum() / w.sum())
    return frame, share


def frame_by_extent(frame: Tensor, cloud: Tensor) -> Tensor:
    """The frame's axes reordered by the cloud's extent along them, longest first (the body
    axes' convention), the last flipped where needed to keep a proper rotation.

    Args:
        frame: (3, 3) a frame (columns the axes); cloud: (P, 3) points, P >= 1, in the same
            coordinates as the frame's axes.
    """
    check_tensor("cloud", cloud, (None, 3))
    along = cloud.double() @ frame.double()
    extent = along.amax(0) - along.amin(0)
    order = torch.argsort(-extent, stable=True)
    return _proper(frame.double()[:, order])
