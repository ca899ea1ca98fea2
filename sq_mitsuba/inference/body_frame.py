"""One body frame for the readings of N frames of one spacecraft (step 2 of
:mod:`sq_mitsuba.inference.sequence`), and an oriented-box body frame for an assembly (step 4).

Each frame's reading lies in a body frame fixed only up to the four half turns (the principal
axes' signs cannot be seen): :func:`align_half_turns` chooses them by shape,
:func:`align_half_turns_by_views` by shape and by the frames whose views lie near each other
(frames in no known order), :func:`align_half_turns_in_order` by shape and smooth motion for
frames in order, :func:`align_half_turns_by_relative` by given rotations between the frames, and
:func:`along_motion` puts frames in order on the one constant-rate turn most of them agree
with. :func:`canonical_frame` and :func:`reframed` express an assembly in the convention of
models processed with ``--align obb``.

Convention: poses map body to camera, ``x_cam = R x_body``; a half turn ``S`` acts on the body
side (``R S``); tensors are float64 on the CPU.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.checks import check_rotations
from sq_mitsuba.geometry.assembly import FIELDS, Assembly
from sq_mitsuba.geometry.pass_motion import constant_rate_motion
from sq_mitsuba.geometry.rotation import rotation_angle
from sq_mitsuba.geometry.so3_grid import half_turns, with_half_turns

__all__ = ["align_half_turns", "align_half_turns_by_relative", "align_half_turns_by_views",
           "align_half_turns_in_order", "along_motion", "canonical_frame", "reframed"]


def _surface(assembly: Assembly, level: int) -> tuple[Tensor, Tensor]:
    """Surface samples (B, P, 3), float64, that count (not inside another primitive; all of an
    item when none does), padded to one length by repeating an item's first point, and which
    of them are its own (B, P) bool: the copies must not count in a mean (where frames keep
    other numbers of primitives one point would weigh as a whole primitive's samples)."""
    from sq_mitsuba.model.losses import counted_surface_samples

    points, keep = counted_surface_samples(Assembly(assembly.params.detach().double()), level)
    kept = [p[k] if bool(k.any()) else p for p, k in zip(points, keep, strict=True)]
    length = max(len(p) for p in kept)
    padded = torch.stack([torch.cat([p, p[:1].expand(length - len(p), 3)]) for p in kept])
    valid = torch.arange(length)[None] < torch.tensor([len(p) for p in kept])[:, None]
    return padded, valid


def _chamfer(a: Tensor, b: Tensor, valid_a: Tensor, valid_b: Tensor) -> Tensor:
    """Symmetric mean nearest-neighbour distance between clouds a (..., P, 3), b (..., Q, 3),
    over their valid points (masks (..., P), (..., Q))."""
    distances = torch.cdist(a, b)
    to_b = distances.masked_fill(~valid_b[..., None, :], torch.inf).amin(dim=-1)  # (..., P)
    to_a = distances.masked_fill(~valid_a[..., :, None], torch.inf).amin(dim=-2)  # (..., Q)
    return 0.5 * ((to_b * valid_a).sum(-1) / valid_a.sum(-1)
                  + (to_a * valid_b).sum(-1) / valid_b.sum(-1))


def _shape_costs(clouds: Tensor, valid: Tensor, reference: int) -> Tensor:
    """(N, 4): the Chamfer distance of each reading's surface samples ``clouds`` (N, P, 3)
    (``valid`` (N, P): its own, not padding) turned by each half turn (the order of
    :func:`~sq_mitsuba.geometry.so3_grid.half_turns`) to the reading ``reference``'s."""
    # (N, 4, P, 3): every reading turned by every half turn (a diagonal matrix: x -> S x).
    signs = torch.diagonal(half_turns(), dim1=-2, dim2=-1)
    turned = (clouds[:, None] * signs[None, :, None, :]).flatten(0, 1)
    count = turned.shape[0]
    costs = _chamfer(turned, clouds[reference][None].expand(count, -1, -1),
                     valid.repeat_interleave(4, dim=0), valid[reference][None].expand(count, -1))
    return costs.reshape(len(clouds), 4)


def align_half_turns(assembly: Assembly, reference: int, level: int = 2) -> Tensor:
    """The half turn S_j (N, 3, 3) that carries each of N readings of one body into the body
    frame of reading ``reference``: ``S_j = argmin_S chamfer(A_ref, S A_j)`` over the four half
    turns (S_ref = I).

    Args:
        assembly: N assemblies (batch size N), each in its own reading of the body frame.
        reference: index of the reading whose body frame is kept.
        level: icosphere level of the surface samples.
    """
    best = _shape_costs(*_surface(assembly, level), reference).argmin(dim=1)
    best[reference] = 0  # the identity comes first in half_turns()
    return half_turns()[best]


def align_half_turns_by_views(assembly: Assembly, rotation: Tensor, reference: int,
                              level: int = 2, near_deg: float = 45.0) -> Tensor:
    """:func:`align_half_turns` for frames in no known order, some of which may show the
    target from nearby views (a pass given unordered): two frames whose readings lie within
    ``near_deg`` of each other under one half turn between them (``R_i S_i`` against ``R_j
    S_j``; every other half turn then puts them at least ``180 - near_deg`` apart) are linked
    by it, nearest pairs first (a spanning forest: a link that would close a loop is left).
    Frames so linked share one half turn into the reference's frame, chosen by the sum of
    their shapes' Chamfer distances to the reference's reading; a frame linked to none takes
    its shape's alone, as in :func:`align_half_turns` (which ``near_deg = 0`` reproduces).

    Why: a reading's shape is often nearly symmetric under one half turn (a relay's twin
    arrays), so its shape alone cannot tell the frames' half turns apart, where a neighbouring
    view's reading, a few degrees away, can. Views of unrelated poses come that near too: two
    uniform rotations lie within ``near_deg`` under one of the half turns with probability
    ``4 (a - sin a) / pi`` (``a`` in radians: 10 % at 45 deg, 0.9 % at 20), and such a link
    is the right half turn only a quarter of the time.

    Args:
        assembly: N readings (batch size N), each in its own reading of the body frame.
        rotation: (N, 3, 3) the frames' body -> camera rotations of those readings.
        reference: index of the reading whose body frame is kept (S_ref = I).
        level: icosphere level of the surface samples.
        near_deg: the largest angle between two frames' readings that links them.

    Returns:
        (N, 3, 3) float64 half turns S_j, ``x_ref = S_j x_j``.
    """
    costs = _shape_costs(*_surface(assembly, level), reference)  # (N, 4)
    count = len(costs)
    rotation = rotation.double()
    # (N, N, 4): the angle between R_i and R_j T_d, radians.
    angles = rotation_angle(rotation[:, None, None], with_half_turns(rotation)[None])
    nearest, turn = angles.min(dim=-1)
    # Half turns as indices into half_turns(): their products are the indices' XOR.
    parent, offset = list(range(count)), [0] * count  # offset: turn into the parent's frame

    def root(k: int) -> tuple[int, int]:
        turned = 0
        while parent[k] != k:
            turned ^= offset[k]
            k = parent[k]
        return k, turned

    pairs = [(float(nearest[i, j]), i, j) for i in range(count) for j in range(i + 1, count)
             if float(nearest[i, j]) <= np.radians(near_deg)]
    for _, i, j in sorted(pairs):
        (root_i, w_i), (root_j, w_j) = root(i), root(j)
        if root_i != root_j:  # S_j S_i = T_d: w_j ^ w_i = d once both share root_i
            parent[root_j], offset[root_j] = root_i, int(turn[i, j]) ^ w_i ^ w_j
    found = torch.zeros(count, dtype=torch.long)
    members: dict[int, list[tuple[int, int]]] = {}
    for k in range(count):
        top, turned = root(k)
        members.setdefault(top, []).append((k, turned))
    for group in members.values():
        held = [turned for k, turned in group if k == reference]
        if held:
            shared = held[0]  # S_ref = I
        else:
            shared = min(range(4), key=lambda g: sum(float(costs[k, g ^ turned])
                                                    for k, turned in group))
        for k, turned in group:
            found[k] = shared ^ turned
    return half_turns()[found]


def align_half_turns_by_relative(rotation: Tensor, relative: Tensor, reference: int) -> Tensor:
    """The half turns S_j (N, 3, 3) that make N readings agree on one ``R_0`` under given
    relative rotations ``Q_j = R_j R_0^T`` (e.g. a servicer's navigation): each reading carried
    back, ``Q_j^T R_j S_j``, is an estimate of ``R_0``, and the frames' half turns are the
    ones that bring those estimates together, whatever the shapes (a near-symmetric shape
    cannot choose them, and frames split between two half turns have no mean rotation).

    Every frame in turn is the anchor: each other frame takes the half turn whose estimate lies
    nearest the anchor's, and the anchor whose choices lie nearest in all (sum of angles) wins,
    so one misread frame cannot decide for the others. ``S_ref = I``: the result is in the
    reference reading's body frame.

    Args:
        rotation: (N, 3, 3) the frames' body -> camera rotation readings, each in its own
            reading of the body frame.
        relative: (N, 3, 3) the given ``Q_j``.
        reference: index of the reading whose body frame is kept.

    Raises:
        ValueError: naming ``rotation``, ``relative`` or ``reference``.
    """
    check_rotations("rotation", rotation)
    check_rotations("relative", relative)
    if rotation.dim() != 3 or relative.shape != rotation.shape:
        raise ValueError(f"relative: expected {tuple(rotation.shape)} (one per reading, "
                         f"(N, 3, 3)), got {tuple(relative.shape)}")
    if not 0 <= reference < len(rotation):
        raise ValueError(f"reference: expected an index below {len(rotation)}, got {reference}")
    carried = relative.double().transpose(-1, -2)[:, None] @ with_half_turns(rotation.double())
    # (anchor, frame, half turn): the angle of each frame's turned estimate from the anchor's.
    angles = rotation_angle(carried[:, None, :], carried[None, :, 0:1])
    nearest, choice = angles.min(dim=2)
    best = choice[int(nearest.sum(dim=1).argmin())]
    # The half turns are diagonal and their own inverses: S_j S_ref gives S_ref = I.
    return half_turns()[best] @ half_turns()[best[reference]]


def align_half_turns_in_order(assembly: Assembly, rotation: Tensor, reference: int,
                              level: int = 2, shape_weight: float = 1.0) -> Tensor:
    """:func:`align_half_turns` for frames in the order they were taken: the half turns
    ``S_j`` minimise, over the whole pass, the rotation angles between consecutive frames
    (``R_j S_j`` against ``R_{j-1} S_{j-1}``: a tumbling target turns little between two
    frames) plus ``shape_weight`` times each reading's Chamfer distance to the reference's
    (relative to the reference's extent), by dynamic programming over the 4^N choices with
    ``S_ref = I``.

    Args:
        assembly: N readings (batch size N), in the frames' order.
        rotation: (N, 3, 3) the frames' body -> camera rotations of those readings.
        reference: index of the reading whose body frame is kept.
    """
    turns = half_turns()
    count = len(rotation)
    clouds, valid = _surface(assembly, level)
    target = clouds[reference]  # its padding repeats a point of its own: the extent holds
    extent = float((target.amax(0) - target.amin(0)).norm()) or 1.0
    unary = shape_weight * _shape_costs(clouds, valid, reference) / extent  # (N, 4)
    # The reference keeps its frame (S_ref = I): the readings' shapes are compared with its
    # own. Left free, a reference turned by G would have every other reading compared with
    # G x_ref, and its one shape cost could outweigh the other frames' together.
    unary[reference, 1:] = torch.inf
    poses = rotation.double()[:, None] @ turns  # (N, 4, 3, 3)

    # (N - 1, 4, 4): the angle between frame k - 1 under each half turn (rows) and frame k
    # under each (columns).
    steps = rotation_angle(poses[:-1, :, None], poses[1:, None])
    cost, back = unary[0].clone(), []
    for k in range(1, count):
        total = cost[:, None] + steps[k - 1]  # previous x current
        best, arg = total.min(dim=0)
        cost = best + unary[k]
        back.append(arg)
    choice = [int(cost.argmin())]
    for arg in reversed(back):
        choice.append(int(arg[choice[-1]]))
    choice.reverse()
    return turns[torch.tensor(choice)]


def canonical_frame(assembly: Assembly, level: int = 3) -> tuple[Tensor, Tensor]:
    """The body frame of models processed with ``--align obb`` for an assembly (batch size 1):
    its minimum-volume oriented box's axes ordered by extent (largest on x, then y, then z; a
    proper rotation), centred on its centre of mass. Not the default ``--align axes`` models'
    frame (the axes they were built along), from which a spacecraft's box is often turned
    tens of degrees by its appendages.

    Returns:
        ``P`` (3, 3) and ``c`` (3,) float64 such that ``x_canonical = P (x - c)``.
    """
    from sq_mitsuba.data.mesh_processing import alignment_rotation

    # The processed models' own rule (their "obb" alignment), on the primitives' meshes: the
    # convex hull of the union is that of all its primitives, so parts inside others do not
    # change the box.
    vertices, faces = assembly.merged_mesh(level)
    points = vertices[0].detach().double().cpu().numpy()
    rotation = alignment_rotation(points, faces.cpu().numpy(), "obb")
    # The centre of mass of the union: uniform points in the bounding box that it holds.
    low, high = points.min(0), points.max(0)
    grid = torch.from_numpy(np.random.default_rng(0).uniform(low, high, (20_000, 3)))
    with torch.no_grad():
        inside = Assembly(assembly.params.detach().double()).union_occupancy(grid[None])[0]
    held = grid[inside > 0.5]
    centre = held.mean(0) if len(held) else torch.from_numpy(points.mean(0))
    return torch.from_numpy(rotation), centre.double()


def reframed(assembly: Assembly, rotation: Tensor, centre: Tensor) -> Assembly:
    """The assembly in the body frame ``x' = rotation (x - centre)``, detached, float64: each
    primitive's translation and rotation carried along (:meth:`Assembly.rotated`)."""
    params = assembly.params.detach().double().clone()
    params[..., FIELDS["translation"]] -= centre.double()
    shifted = Assembly(params)
    return shifted.rotated(rotation.double().expand(shifted.batch_size, 3, 3))


def along_motion(reading: Tensor, shape_turns: Tensor, iou: Tensor, threshold_deg: float,
                 held: bool = False, max_rate_deg: float = 45.0, min_share: float = 0.25
                 ) -> tuple[Tensor, Tensor, int, Tensor] | None:
    """The frames' rotations from the pass's constant-rate motion (``SequenceOptions.motion``),
    or None where too few frames agree on one (for N >= 3: fewer than 3, or than ``min_share``
    of them): the frames then keep their own readings.

    Args:
        reading: (N, 3, 3) each frame's own rotation reading (body frame: its reading's),
            frames in order, one unit of time apart.
        shape_turns: (N, 3, 3) the half turns S_j that carry each reading into one body frame
            by shape (:func:`align_half_turns`, :func:`align_half_turns_in_order`): they give
            the half turns of the frames that disagree with the motion.
        iou: (N,) how well each frame's own fit matches its mask (chooses the reference).
        threshold_deg: see :func:`~sq_mitsuba.geometry.pass_motion.constant_rate_motion`.
        held: every frame's rotation the motion's; else a frame that agrees keeps its reading
            (turned) and only the others take the motion's.
        max_rate_deg: the fastest turn considered, degrees per frame.

    Returns:
        The rotations (N, 3, 3) in the reference's reading frame (at the reference its own
        reading, or with ``held`` the motion's there, within ``threshold_deg`` of it); the half
        turns H_j (N, 3, 3) that carry reading j into that frame (``x = H_j x_j``: the one
        nearest its rotation for a frame that agrees, its shape's for the others); the
        reference (the best-fitting frame that agrees) and the relative rotations
        ``Q_j = R_j R_0^T`` (N, 3, 3) of the result.
    """
    count = len(reading)
    reading = reading.double()
    motion = constant_rate_motion(reading, threshold_deg, max_rate_deg=max_rate_deg)
    agree = motion.inliers
    if count >= 3 and int(agree.sum()) < max(3, math.ceil(min_share * count - 1e-9)):
        return None
    turns = half_turns()
    keep = torch.zeros_like(agree) if held else agree
    chain = torch.where(keep[:, None, None], reading @ turns[motion.turn], motion.predicted)
    reference = int(torch.where(agree, iou.double(), torch.full_like(iou.double(), -1.0))
                    .argmax())
    # Into the reference's reading frame: the chain is the reference's reading turned by its
    # half turn T (or the motion nearest that), so chain @ T (T diagonal, its own inverse) is
    # its reading there; an agreeing frame's reading then needs its own turn times T.
    to_reference = turns[motion.turn[reference]]
    rotation = chain @ to_reference
    by_motion = turns[motion.turn] @ to_reference
    by_shape = shape_turns.double()[reference] @ shape_turns.double()
    found = torch.where(agree[:, None, None], by_motion, by_shape)
    return rotation, found, reference, rotation @ rotation[0].T
