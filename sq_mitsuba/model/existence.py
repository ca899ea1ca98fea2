"""Existence of primitives: a network with ``network.existence`` predicts, besides each of its
M superquadrics, the probability p_m that the primitive is part of the assembly at all (as in
Paschalidou et al. 2019, *Superquadrics Revisited*), so a network with a large M can use fewer.

- :func:`probabilistic_chamfer_loss`: the Chamfer loss of :func:`~sq_mitsuba.model.losses.
  chamfer_loss` as an expectation over which primitives exist (each independently, with its
  p_m); equal to it when every p_m = 1;
- :func:`parsimony_loss`: the expected number of primitives, which a small weight turns into a
  price per primitive;
- :func:`kept_primitives` and :func:`gathered_primitives`: the primitives a prediction keeps
  (p_m at least a threshold; an item keeps at least its most probable one), as one batch.

Convention: the primitives of a batch of assemblies share one M (``Assembly`` holds (B, M, 16)
tensors), but each item keeps its own number of primitives. A pruned batch is therefore
(B, W, 16) with W the most any item keeps: item b's kept primitives first, in the network's
order, then W - n_b *stand-ins*: copies of the item's first kept primitive shrunk by
:data:`STAND_IN_SCALE` about their own centre. A stand-in lies strictly inside the primitive
it copies (a primitive is symmetric and star-shaped about its centre, and a taper is relative
to the size, so the copy is the primitive scaled about its centre; the tests check it on random
primitives), so it adds nothing to a silhouette, to the union's inside, or to the surface
samples a Chamfer distance counts (those inside another primitive do not count). ``rows``
(B, W) says which network primitive each row is, -1 for a stand-in. Scaled below the smallest
size the network can output (0.01), a stand-in's raw parameters round to that size (it stays
inside but for such a sliver).
"""

from __future__ import annotations

import torch
from torch import Tensor

from sq_mitsuba.checks import check_tensor, value_checks_enabled
from sq_mitsuba.geometry.assembly import FIELDS, NUM_PARAMS, Assembly
from sq_mitsuba.geometry.nearest import (
    euclidean,
    matched_indices,
    nearest_method,
    nearest_neighbours,
)

__all__ = [
    "EXISTENCE_THRESHOLD",
    "STAND_IN_SCALE",
    "existence_surface_samples",
    "expected_nearest",
    "gathered_primitives",
    "kept_primitives",
    "parsimony_loss",
    "primitive_nearest",
    "probabilistic_chamfer_loss",
]

#: The existence probability from which a primitive counts as present: the predictor's
#: default ``min_existence``, and where the Chamfer loss lets a primitive hide the samples of
#: others inside it in the target -> prediction direction.
EXISTENCE_THRESHOLD = 0.5
#: Size of a stand-in relative to the primitive it copies (module docstring).
STAND_IN_SCALE = 0.5
#: Most pairwise distances :func:`primitive_nearest` holds at once: on the CPU 256 Ki (1 MiB in
#: float32, within a core's cache), elsewhere 16 Mi (64 MiB, few launches).
_CACHE_CHUNK = 1 << 18
_DENSE_CHUNK = 1 << 24


# ------------------------------------------------------------------------------ losses


def existence_surface_samples(assembly: Assembly, level: int = 3) -> tuple[Tensor, Tensor]:
    """Each primitive's dual surface samples and which other primitive each lies inside.

    Returns:
        points (B, M, V, 3) (V = 642 at level 3), with gradient; inside (B, M, M, V) bool,
        without: ``inside[b, j, m, v]`` says that sample v of primitive m lies strictly
        inside primitive j (j != m), as :func:`probabilistic_chamfer_loss` takes them.
    """
    points = assembly.surface_points(level)
    return points, assembly.inside_others(points)


@torch.no_grad()
def primitive_nearest(target: Tensor, points: Tensor, excluded: Tensor) -> Tensor:
    """For each target point, the index of the nearest sample of each primitive.

    All pairwise distances in chunks, by matrix products as
    :func:`~sq_mitsuba.geometry.nearest.matched_indices`' dense search (two samples whose
    distances differ by less than the dtype's rounding may be swapped). On the CPU a chunk
    fits a core's cache (256 Ki distances), which makes this about a fifth faster than a
    KD-tree per item and primitive at 2,500 targets and 5 to 8 x 162 samples (1 thread).

    Args:
        target: (B, K, 3).
        points: (B, M, V, 3) the primitives' samples, target's dtype and device.
        excluded: (B, M, V) bool, samples that are nobody's nearest.

    Returns:
        (B, K, M) int64 index into V (0 for a primitive all of whose samples are excluded).
    """
    batch, count, per, _ = points.shape
    targets = target.shape[1]
    flat = points.detach().reshape(batch, count * per, 3)
    target = target.detach()
    # argmin_x |t - x|^2 = argmin_x (|x|^2 - 2 t.x): one product per chunk, with an infinite
    # |x|^2 for the excluded samples.
    norms = flat.square().sum(-1).masked_fill(excluded.reshape(batch, -1), float("inf"))
    index = torch.zeros(batch, targets, count, dtype=torch.int64, device=points.device)
    budget = _CACHE_CHUNK if points.device.type == "cpu" else _DENSE_CHUNK
    rows = max(1, min(targets, budget // max(1, count * per)))
    items = max(1, budget // max(1, rows * count * per))
    for first in range(0, batch, items):
        part = slice(first, first + items)
        for start in range(0, targets, rows):
            span = slice(start, start + rows)
            scores = torch.baddbmm(norms[part, None, :], target[part, span],
                                   flat[part].transpose(1, 2), alpha=-2.0)
            index[part, span] = scores.view(*scores.shape[:2], count, per).argmin(-1)
    return index


def expected_nearest(distances: Tensor, probabilities: Tensor,
                     found: Tensor | None = None) -> Tensor:
    """The expected distance to the nearest existing primitive, primitives existing
    independently: ``sum_k d_(k) p_(k) prod_{j<k} (1 - p_(j))`` over the distances sorted
    ascending, plus ``d_max prod_j (1 - p_j)``.

    Convention: when no primitive exists (probability ``prod_j (1 - p_j)``), the farthest one
    stands in for the empty assembly: the expectation stays finite and smooth in p, that case
    costs the most any pattern costs, and every p = 1 gives the plain minimum.

    Args:
        distances: (..., M) >= 0.
        probabilities: (..., M) in [0, 1], broadcastable to ``distances``.
        found: (..., M) bool broadcastable to ``distances``, False for a primitive with no
            distance (no sample that counts): it never exists. None: all found. Every row
            needs one found.

    Returns:
        (...).
    """
    chance = probabilities.expand_as(distances)
    if found is not None:
        chance = chance * found
        # Distances are >= 0, so a primitive not found (0 here) is never the farthest.
        distances = distances * found
    ordered, order = distances.sort(dim=-1)
    chance = chance.gather(-1, order)
    absent = torch.cumprod(1.0 - chance, dim=-1)  # prod_{j <= k} (1 - p_(j))
    before = torch.cat([torch.ones_like(absent[..., :1]), absent[..., :-1]], dim=-1)
    return (chance * before * ordered).sum(-1) + absent[..., -1] * ordered[..., -1]


def _nearest_target(points: Tensor, target: Tensor, method: str | None) -> Tensor:
    """(B, N) int64 index into target (B, K, 3) of each point's (B, N, 3) nearest, no grad."""
    if nearest_method(points.device, method) == "dense":
        keep = torch.ones(points.shape[:2], dtype=torch.bool, device=points.device)
        return matched_indices(points, keep, target, method="dense")[0]
    source = points.detach().to("cpu", torch.float64).numpy()
    cloud = target.detach().to("cpu", torch.float64).numpy()
    found = [torch.from_numpy(nearest_neighbours(a, b)[1]) for a, b in zip(source, cloud,
                                                                           strict=True)]
    return torch.stack(found).to(points.device)


def probabilistic_chamfer_loss(points: Tensor, inside: Tensor | None, probabilities: Tensor,
                               target: Tensor, threshold: float = EXISTENCE_THRESHOLD,
                               method: str | None = None, *, squared: bool = True) -> Tensor:
    """Squared-L2 Chamfer distance of an assembly whose primitives exist with probabilities
    p_m, each independently; mean over the batch. With every p_m = 1 it equals
    :func:`~sq_mitsuba.model.losses.chamfer_loss` of the samples that count (not strictly
    inside another primitive), in value.

    Per item, with f_mv the squared distance of sample v of primitive m to its nearest target
    point and d_km that of target point k to the nearest counted sample of primitive m:

    - prediction -> target: ``sum w_mv f_mv / sum w_mv`` with ``w_mv = p_m prod_{j: v inside
      j} (1 - p_j)``, the probability that the sample is on the union's surface (its primitive
      exists, none that holds it does). So it is the ratio of the expected sum of the counted
      samples' distances to their expected number: per primitive, the mean of its counted
      samples' distances weighted by p_m and by its expected share of the counted samples. It
      moves a p_m by how that primitive's distances compare with the others', not by the
      number of primitives (the parsimony term prices that). An item none of whose samples
      is free of the others weighs them all by p_m alone (``chamfer_loss`` then keeps all).
    - target -> prediction: the mean over k of :func:`expected_nearest` of d_k (M,): the
      expected squared distance to the nearest sample of an existing primitive, the farthest
      primitive standing in when none exists.

    Convention (the union filter, target -> prediction): a sample inside another primitive j
    is not a nearest candidate when ``p_j >= threshold``, the primitives the predictor keeps;
    so a primitive being switched off (p_j falling under the threshold) gives back the
    surface of the others it covered, and with every p_m = 1 the filter is chamfer_loss's.
    The exact expectation would need each existence pattern's own filter, which does not
    factor over primitives. The filter carries no gradient (as in chamfer_loss); a primitive
    with no sample left never exists in this direction; an item with no sample left keeps
    them all.

    Args:
        points: (B, M, V, 3) each primitive's surface samples
            (:func:`existence_surface_samples`).
        inside: (B, M, M, V) bool, ``inside[b, j, m, v]``: sample v of primitive m lies
            strictly inside primitive j (the diagonal is ignored); None: none is.
        probabilities: (B, M) in [0, 1], the points' dtype.
        target: (B, K, 3) ground-truth surface points, the points' dtype.
        threshold: the existence probability from which a primitive hides samples (above).
        method: the prediction -> target nearest-neighbour search, ``"kdtree"``, ``"dense"``
            or None (by the device, as chamfer_loss's); equal results. The other direction
            needs each primitive's nearest sample: :func:`primitive_nearest`.
        squared: squared distances, or Euclidean ones (``chamfer_loss``'s ``squared``).

    Returns:
        Scalar tensor.

    Raises:
        ValueError: one line naming the argument of a wrong shape, dtype or value.
    """
    check_tensor("points", points, (None, None, 3), min_dims=4)
    check_tensor("target", target, (None, 3), min_dims=3)
    check_tensor("probabilities", probabilities, (None,), min_dims=2)
    if points.dim() != 4 or target.dim() != 3 or target.shape[0] != points.shape[0]:
        raise ValueError(f"points, target: expected (B, M, V, 3) and (B, K, 3), got "
                         f"{tuple(points.shape)} and {tuple(target.shape)}")
    batch, count, per, _ = points.shape
    if per < 1 or target.shape[1] < 1:
        raise ValueError("points, target: need at least one point per primitive and item")
    if probabilities.shape != (batch, count):
        raise ValueError(f"probabilities: expected shape {(batch, count)}, got "
                         f"{tuple(probabilities.shape)}")
    for name, value in (("target", target), ("probabilities", probabilities)):
        if value.dtype != points.dtype:
            raise ValueError(f"{name}: dtype {value.dtype} differs from points' {points.dtype}")
    if value_checks_enabled() and bool(((probabilities < 0) | (probabilities > 1)).any()):
        raise ValueError("probabilities: expected values in [0, 1]")
    if not 0.0 <= threshold <= 1.0:
        raise ValueError(f"threshold: expected a number in [0, 1], got {threshold!r}")
    if inside is None:
        inside = torch.zeros(batch, count, count, per, dtype=torch.bool, device=points.device)
    if not isinstance(inside, Tensor) or inside.dtype != torch.bool or \
            inside.shape != (batch, count, count, per):
        shape = tuple(inside.shape) if isinstance(inside, Tensor) else type(inside).__name__
        raise ValueError(f"inside: expected a bool tensor of shape {(batch, count, count, per)},"
                         f" got {shape}")
    own = torch.eye(count, dtype=torch.bool, device=points.device)[None, :, :, None]
    covered = inside.to(points.device) & ~own  # (B, holder j, owner m, V)

    # Prediction -> target: samples weighed by their chance of being on the union's surface.
    flat = points.reshape(batch, count * per, 3)
    to_target = _nearest_target(flat, target, method)
    nearest = target.gather(1, to_target[..., None].expand(-1, -1, 3))
    forward = (flat - nearest).square().sum(-1).view(batch, count, per)
    if not squared:
        forward = euclidean(forward)
    survives = torch.where(covered, 1.0 - probabilities[:, :, None, None],
                           torch.ones_like(probabilities)[:, :, None, None]).prod(1)
    all_covered = covered.any(1).flatten(1).all(1)  # chamfer_loss: such an item keeps all
    survives = torch.where(all_covered[:, None, None], torch.ones_like(survives), survives)
    weight = probabilities[:, :, None] * survives  # (B, M, V)
    forward_mean = (weight * forward).sum((1, 2)) / weight.sum((1, 2)).clamp_min(1e-30)

    # Target -> prediction: the expected nearest over existence patterns.
    present = probabilities.detach() >= threshold
    excluded = (covered & present[:, :, None, None]).any(1)  # (B, M, V)
    excluded = excluded & ~excluded.flatten(1).all(1)[:, None, None]
    index = primitive_nearest(target, points, excluded)  # (B, K, M)
    flat_index = index + per * torch.arange(count, device=points.device)
    chosen = flat.gather(1, flat_index.flatten(1)[..., None].expand(-1, -1, 3))
    distances = (target[:, :, None, :] - chosen.view(*index.shape, 3)).square().sum(-1)
    if not squared:
        distances = euclidean(distances)
    found = (~excluded).any(-1)[:, None, :]  # (B, 1, M): a primitive with a sample left
    backward = expected_nearest(distances, probabilities[:, None, :], found).mean(1)
    return (forward_mean + backward).mean()


def parsimony_loss(probabilities: Tensor) -> Tensor:
    """The expected number of primitives, ``sum_m p_m``, mean over the batch (a scalar).

    Convention: linear in p, so a weight w is a fixed price per primitive: one stays when it
    lowers the rest of the loss by more than w (a concave form such as sqrt(sum p) would make
    the last primitives the dearest). probabilities: (B, M) in [0, 1].
    """
    check_tensor("probabilities", probabilities, (None,), min_dims=2)
    if probabilities.dim() != 2:
        raise ValueError(f"probabilities: expected shape (B, M), got "
                         f"{tuple(probabilities.shape)}")
    return probabilities.sum(1).mean()


# ------------------------------------------------------------------------------ pruning


def kept_primitives(probabilities: Tensor, threshold: float = EXISTENCE_THRESHOLD,
                    width: int | None = None) -> Tensor:
    """Which primitives each item keeps: those with ``p >= threshold``, and always its most
    probable one (threshold 0 keeps every primitive, in order).

    Args:
        probabilities: (B, M) existence probabilities.
        threshold: in [0, 1].
        width: W, the rows per item (None: the most any item keeps).

    Returns:
        rows (B, W) int64: item b's kept primitives (indices into M) in increasing order, then
        -1 (a stand-in, see the module docstring).
    """
    check_tensor("probabilities", probabilities, (None,), min_dims=2)
    if probabilities.dim() != 2 or probabilities.shape[1] < 1:
        raise ValueError(f"probabilities: expected shape (B, M), got "
                         f"{tuple(probabilities.shape)}")
    if isinstance(threshold, bool) or not isinstance(threshold, int | float) \
            or not 0.0 <= threshold <= 1.0:
        raise ValueError(f"threshold: expected a number in [0, 1], got {threshold!r}")
    keep = probabilities >= threshold
    keep.scatter_(1, probabilities.argmax(1, keepdim=True), True)
    count = keep.sum(1)
    most = int(count.max()) if len(count) else 1
    width = most if width is None else width
    if not most <= width <= probabilities.shape[1]:
        raise ValueError(f"width: expected {most} to {probabilities.shape[1]} rows, got {width}")
    order = torch.sort((~keep).to(torch.uint8), dim=1, stable=True).indices[:, :width]
    position = torch.arange(width, device=keep.device)
    return torch.where(position[None] < count[:, None], order, -1)


def gathered_primitives(params: Tensor, rows: Tensor) -> Tensor:
    """The rows of :func:`kept_primitives` taken from an assembly's params: (B, M, 16) and
    (B, W) -> (B, W, 16), a stand-in (row -1) being the item's first row shrunk by
    :data:`STAND_IN_SCALE` (module docstring). Differentiable w.r.t. ``params``."""
    check_tensor("params", params, (None, NUM_PARAMS), min_dims=3)
    if not isinstance(rows, Tensor) or rows.dtype != torch.int64 or rows.dim() != 2 or \
            rows.shape[0] != params.shape[0] or rows.shape[1] < 1 or bool((rows[:, 0] < 0).any()):
        shape = tuple(rows.shape) if isinstance(rows, Tensor) else type(rows).__name__
        raise ValueError(f"rows: expected int64 (B, W) indices from kept_primitives for "
                         f"{params.shape[0]} items, got {shape}")
    real = rows >= 0
    index = torch.where(real, rows, rows[:, :1]).to(params.device)
    gathered = params.gather(1, index[..., None].expand(-1, -1, params.shape[-1]))
    scale = torch.where(real.to(params.device), 1.0, STAND_IN_SCALE).to(params.dtype)
    size = gathered[..., FIELDS["size"]] * scale[..., None]
    return torch.cat([size, gathered[..., FIELDS["size"].stop:]], dim=-1)
