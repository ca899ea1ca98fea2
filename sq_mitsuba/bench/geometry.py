"""``sq-mitsuba bench geometry``: the superquadric hot paths of a training step.

1. Union occupancy plus the overlap term, forward + backward, B = 32 assemblies of M = 5
   primitives, 10,000 query points each, float32 (target <= 100 ms on 2 CPU cores); compared
   on the same inputs with the unfused path (``to_primitive_frames`` then the public
   ``inside_outside_dual``) and with the primal function through the same frames.
2. Dual surface sampling of 32 x 5 x 642 points, forward + backward (target <= 10 ms),
   compared with primal sampling on the same angles.
3. The Chamfer term of a training step (level-2 samples, 2,500 target points, batch 32),
   forward + backward: today's ``chamfer_loss`` against the expectation over which primitives
   exist (``probabilistic_chamfer_loss``, ``network.existence``), at M = 5 and M = 8.
"""

from __future__ import annotations

import torch

from sq_mitsuba.bench import BenchOptions, Report, Timing, time_callable
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.icosphere import icosphere_angles
from sq_mitsuba.geometry.superquadric import (
    inside_outside,
    inside_outside_dual,
    surface_points,
    surface_points_dual,
)
from sq_mitsuba.model.existence import existence_surface_samples, probabilistic_chamfer_loss
from sq_mitsuba.model.losses import chamfer_loss, counted_surface_samples, overlap

BATCH, PRIMITIVES, QUERY_POINTS = 32, 5, 10_000
SHARPNESS, BETA = 10.0, 1.25
TARGET_POINTS, CHAMFER_LEVEL = 2_500, 2


def _occupancy_step(raw: torch.Tensor, points: torch.Tensor, field: str) -> None:
    assembly = Assembly.from_raw(raw)
    if field == "dual (fused)":
        values = assembly.inside_outside(points)
    else:
        local = assembly.to_primitive_frames(points)
        function = inside_outside if field == "primal" else inside_outside_dual
        values = function(local, assembly.size, assembly.shape)
    occupancy = torch.sigmoid(SHARPNESS * (1.0 - values))
    loss = occupancy.amax(dim=1).mean() + overlap(occupancy, BETA)
    loss.backward()
    raw.grad = None


def _sampling_step(raw: torch.Tensor, dual: bool) -> None:
    assembly = Assembly.from_raw(raw)
    eta, omega = icosphere_angles(3, raw.dtype, raw.device)
    function = surface_points_dual if dual else surface_points
    points = function(eta, omega, assembly.size, assembly.shape)
    points.square().mean().backward()
    raw.grad = None


def _chamfer_step(raw: torch.Tensor, logits: torch.Tensor | None, target: torch.Tensor
                  ) -> None:
    """The Chamfer term as the training step computes it (loss_terms.chamfer_term)."""
    assembly = Assembly.from_raw(raw)
    if logits is None:
        points, keep = counted_surface_samples(assembly, CHAMFER_LEVEL)
        loss = chamfer_loss(points, keep, target)
    else:
        points, inside = existence_surface_samples(assembly, CHAMFER_LEVEL)
        loss = probabilistic_chamfer_loss(points, inside, torch.sigmoid(logits), target)
    loss.backward()
    raw.grad = None


def run(options: BenchOptions) -> Report:
    device = torch.device(options.device)
    gen = torch.Generator(device=device).manual_seed(0)
    raw = torch.randn(BATCH, PRIMITIVES, 16, generator=gen, device=device).requires_grad_()
    points = torch.rand(BATCH, QUERY_POINTS, 3, generator=gen, device=device) - 0.5
    sync = torch.cuda.synchronize if device.type == "cuda" else None
    report = Report("geometry", options=options)

    occupancy = {}
    for field in ("dual (fused)", "dual (unfused)", "primal"):
        samples = time_callable(lambda f=field: _occupancy_step(raw, points, f),
                                options.repeats, options.warmup, sync)
        occupancy[field] = Timing(
            f"occupancy + overlap fwd+bwd, {field}", samples,
            target_s=0.100 if field == "dual (fused)" else None,
            note=f"B={BATCH}, M={PRIMITIVES}, N={QUERY_POINTS}, float32")
    report.timings += occupancy.values()

    sampling = {}
    for dual in (True, False):
        name = "dual" if dual else "primal"
        samples = time_callable(lambda d=dual: _sampling_step(raw, d), options.repeats,
                                options.warmup, sync)
        sampling[name] = Timing(f"surface sampling fwd+bwd, {name}", samples,
                                target_s=0.010 if dual else None,
                                note=f"{BATCH} x {PRIMITIVES} x 642 points")
    report.timings += sampling.values()

    chamfer = {}
    for count in (PRIMITIVES, 8):
        shapes = torch.randn(BATCH, count, 16, generator=gen, device=device).requires_grad_()
        logits = torch.randn(BATCH, count, generator=gen, device=device).requires_grad_()
        target = torch.rand(BATCH, TARGET_POINTS, 3, generator=gen, device=device) - 0.5
        for kind, existence in (("plain", None), ("with existence", logits)):
            samples = time_callable(lambda r=shapes, e=existence, t=target: _chamfer_step(r, e, t),
                                    options.repeats, options.warmup, sync)
            chamfer[count, kind] = Timing(
                f"Chamfer term fwd+bwd, M={count}, {kind}", samples,
                note=f"B={BATCH}, level {CHAMFER_LEVEL} samples, {TARGET_POINTS} target points")
    report.timings += chamfer.values()

    fused = occupancy["dual (fused)"].median
    report.notes += [
        f"occupancy: fused dual / primal = {fused / occupancy['primal'].median:.2f}, "
        f"fused dual / unfused dual = {fused / occupancy['dual (unfused)'].median:.2f} "
        "(same inputs, same run; < 1 means the fused dual is faster)",
        f"sampling: dual / primal = {sampling['dual'].median / sampling['primal'].median:.2f}",
        *(f"Chamfer term, M={m}: with existence / plain = "
          f"{chamfer[m, 'with existence'].median / chamfer[m, 'plain'].median:.2f}"
          for m in (PRIMITIVES, 8)),
    ]
    return report
