"""Part targets: each training model's own assembly, fitted once to its surface, as a target
for the network's primitives one by one.

Why: the Chamfer term compares the union of the primitives with the model's surface, so a
primitive is pulled towards whatever surface lies nearest it, and one network must move the
same M output slots to every model's parts. Trained that way the shape reader stops far short
of what M superquadrics reach (eval/MODEL_CARD.md, "Fitting, not generalising": 0.08-0.15
Chamfer-L1 on its own training models against 0.04-0.06 fitted directly), and a heavier
Chamfer term no longer helps. A fit to each model's surface from one common start (the
network's initial layout, :func:`~sq_mitsuba.model.network.initial_raw`) reaches the same
Chamfer-L1 as one from the network's reading, so such fits exist for every model; the
``parts`` training term then pulls each predicted primitive towards one fitted part.
Measured on one small library (eval/MODEL_CARD.md, "Part targets, a pilot"): the network
lowered the term but fitted its training shapes no nearer, and read held-out families worse;
the term is off by default.

Convention: predicted and fitted primitives are paired per item by the Hungarian assignment
(scipy's ``linear_sum_assignment``) on their symmetric per-primitive Chamfer distance, so the
network need not put a part in the same output slot as the fit did; the pairing is not
differentiated (it is piecewise constant).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.checks import check_tensor
from sq_mitsuba.geometry.assembly import NUM_PARAMS, Assembly
from sq_mitsuba.model.losses import occupancy_loss, surface_chamfer_loss
from sq_mitsuba.model.network import initial_raw

__all__ = ["fit_to_surface", "matched_part_loss", "part_costs", "part_matching"]


def fit_to_surface(target: Tensor, num_primitives: int, steps: int = 300, lr: float = 0.05,
                   level: int = 2, start: Tensor | None = None,
                   occupancy: tuple[Tensor, Tensor] | None = None,
                   occupancy_weight: float = 0.0) -> tuple[Tensor, Tensor]:
    """M superquadrics fitted to each model's surface points by Adam on the raw parameters,
    on the training's shape term (:func:`~sq_mitsuba.model.losses.surface_chamfer_loss`),
    plus ``occupancy_weight`` times its occupancy term (paper Eq. 14) when ``occupancy``
    (labelled points (B, N, 3), labels (B, N)) is given.

    Args:
        target: (B, K, 3) surface points of B models, body frame; the fit runs in its dtype
            (float32 is 2-3 x faster than float64 on the CPU and ends as near).
        num_primitives: M.
        steps, lr: Adam steps and learning rate (300 and 0.05 reach the fit's plateau).
        level: icosphere level of the primitives' surface samples.
        start: (B or 1, M, 16) raw start; default the network's initial layout.

    Returns:
        raw (B, M, 16), the fitted parameters, and (B,) their squared-L2 Chamfer loss at the
        end (the occupancy term left out), both in ``target``'s dtype.
    """
    check_tensor("target", target, (None, None, 3))
    batch = target.shape[0]
    start = initial_raw(num_primitives) if start is None else start
    start = start.to(target.dtype)
    check_tensor("start", start, (None, num_primitives, NUM_PARAMS))
    raw = start.expand(batch, -1, -1).clone().requires_grad_(True)
    optimizer = torch.optim.Adam([raw], lr=lr)
    for _ in range(steps):
        optimizer.zero_grad(set_to_none=True)
        # The batch mean: Adam scales each parameter's step by its own gradient's size, and
        # each model's parameters see only its own loss, so every model is fitted as alone.
        assembly = Assembly.from_raw(raw)
        loss = surface_chamfer_loss(assembly, target, level)
        if occupancy is not None and occupancy_weight > 0:
            loss = loss + occupancy_weight * occupancy_loss(assembly, *occupancy)
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        final = torch.stack([surface_chamfer_loss(Assembly.from_raw(raw[i:i + 1]),
                                                  target[i:i + 1], level)
                             for i in range(batch)])
    return raw.detach(), final


def part_costs(pred: Assembly, target: Assembly, level: int = 1) -> Tensor:
    """Symmetric squared-L2 Chamfer distance between every predicted and every target
    primitive's surface samples (icosphere ``level``), (B, M, M): ``[b, i, j]`` compares
    predicted primitive i with target primitive j of item b."""
    if pred.params.shape != target.params.shape:
        raise ValueError(f"part targets: predicted assembly {tuple(pred.params.shape)} and "
                         f"targets {tuple(target.params.shape)} differ in shape")
    a = pred.surface_points(level)  # (B, M, V, 3)
    b = target.surface_points(level).to(a)
    batch, count, samples, _ = a.shape
    squared = torch.cdist(a.reshape(batch, count * samples, 3),
                          b.reshape(batch, count * samples, 3)).square()
    squared = squared.view(batch, count, samples, count, samples)
    forward = squared.amin(dim=4).mean(dim=2)  # (B, M_pred, M_target)
    backward = squared.amin(dim=2).mean(dim=3)  # (B, M_pred, M_target)
    return forward + backward


def part_matching(costs: Tensor) -> Tensor:
    """(B, M, M) costs -> (B, M) int64: the target primitive paired with each predicted one
    (minimum total cost per item)."""
    # Imported here: scipy.optimize takes half a second, and every training command (its
    # --help included) imports this module, most without the parts term.
    from scipy.optimize import linear_sum_assignment

    values = costs.detach().cpu().double().numpy()
    pairs = np.empty(values.shape[:2], dtype=np.int64)
    for item, matrix in enumerate(values):
        rows, cols = linear_sum_assignment(matrix)
        pairs[item, rows] = cols
    return torch.from_numpy(pairs).to(costs.device)


def matched_part_loss(pred: Assembly, target: Assembly, level: int = 1) -> Tensor:
    """Mean over items and primitives of the per-primitive Chamfer distance
    (:func:`part_costs`) between each predicted primitive and its paired target primitive
    (:func:`part_matching`). Zero when the prediction is the target, in any order."""
    costs = part_costs(pred, target, level)
    pairs = part_matching(costs)
    return costs.gather(2, pairs[..., None]).mean()
