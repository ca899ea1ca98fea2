"""``sq-mitsuba bench geometry``: the superquadric hot paths of a training step.

1. Union occupancy plus the overlap term, forward + backward, B = 32 assemblies of M = 5
   primitives, 10,000 query points each, float32 (target <= 100 ms on 2 CPU cores); compared
   on the same inputs with the unfused path (``to_primitive_frames`` then the public
   ``inside_outside_dual``) and with the primal function through the same frames.
2. Dual surface sampling of 32 x 5 x 642 points, forward + backward (target <= 10 ms),
   compared with primal sampling on the same angles.
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
from sq_mitsuba.model.losses import overlap

BATCH, PRIMITIVES, QUERY_POINTS = 32, 5, 10_000
SHARPNESS, BETA = 10.0, 1.25


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

    fused = occupancy["dual (fused)"].median
    report.notes += [
        f"occupancy: fused dual / primal = {fused / occupancy['primal'].median:.2f}, "
        f"fused dual / unfused dual = {fused / occupancy['dual (unfused)'].median:.2f} "
        "(same inputs, same run; < 1 means the fused dual is faster)",
        f"sampling: dual / primal = {sampling['dual'].median / sampling['primal'].median:.2f}",
    ]
    return report
