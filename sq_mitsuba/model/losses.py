"""Training and fitting losses, each a documented function on batched tensors.

The training terms (:mod:`sq_mitsuba.training.loss_terms` names them, weighs them and feeds them
from the network output and the batch) are computed by

- :func:`chamfer_loss`, :func:`surface_chamfer_loss`: squared-L2 Chamfer distance between the
  assembly's surface samples and points on the ground-truth mesh (paper Eq. 12);
  :func:`probabilistic_chamfer_loss` its expectation over which primitives exist, and
  :func:`parsimony_loss` the expected number of primitives, for a network with existence
  probabilities (both in :mod:`sq_mitsuba.model.existence`);
- :func:`occupancy_loss`: binary cross-entropy of the union occupancy at labelled points
  (Eq. 14);
- :func:`reprojection_loss`: pixel MSE (:func:`mask_mse`) between the Mitsuba silhouette at the
  true pose and the mask;
- :func:`pose_loss` (:func:`rotation_loss`, :func:`translation_loss`): the SPEED pose errors,
  the rotation one minimised over the model's symmetries; :func:`rotation_6d_loss`: the
  regression of a 6D rotation output onto the true matrix's rows;
  :func:`rotation_distribution_loss`: cross-entropy of a distribution head's scores over the
  SO(3) grid against every rotation that shows the same object;
- :func:`mask_loss`: binary cross-entropy of the mask head's logits against the mask;
- :func:`overlap`: summed occupancy above a tolerance (Eq. 18);
- :func:`taper_loss`: mean squared taper.

The per-view silhouette losses (:func:`mask_mse`, :func:`soft_iou_loss`, and
:func:`silhouette_loss` naming one of them) are what the renderer is handed: it renders the
coverage and back-propagates the gradient they return (see
:meth:`~sq_mitsuba.render.silhouette.renderer.SilhouetteRenderer.render_target_loss`).

Convention: shapes are given per argument; every loss returns a scalar tensor (the mean over
the batch) unless its docstring says otherwise.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor
from torch.nn import functional as F

from sq_mitsuba.checks import check_tensor, value_checks_enabled
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.nearest import euclidean, gathered_differences, matched_indices
from sq_mitsuba.geometry.rotation import rotation_angle
from sq_mitsuba.model.existence import parsimony_loss, probabilistic_chamfer_loss
from sq_mitsuba.model.rotation_grid import grid_quaternions, soft_rotation_targets
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, assembly_camera_vertices

__all__ = [
    "SILHOUETTE_LOSSES",
    "chamfer_loss",
    "counted_surface_samples",
    "mask_loss",
    "mask_mse",
    "occupancy_loss",
    "overlap",
    "parsimony_loss",
    "pose_loss",
    "probabilistic_chamfer_loss",
    "reprojection_loss",
    "rotation_6d_loss",
    "rotation_distribution_loss",
    "rotation_loss",
    "silhouette_loss",
    "soft_iou_loss",
    "surface_chamfer_loss",
    "taper_loss",
    "translation_loss",
]

#: Per-view silhouette losses of :func:`silhouette_loss`.
SILHOUETTE_LOSSES = ("mse", "iou")


# ------------------------------------------------------------------------------- Chamfer


def chamfer_loss(pred_points: Tensor, pred_mask: Tensor | None, target: Tensor,
                 method: str | None = None, *, squared: bool = True) -> Tensor:
    """Squared-L2 Chamfer distance (paper Eq. 12), mean over the batch; with ``squared=False``
    the distances themselves (Euclidean, as the evaluation's Chamfer-L1 "occnet" convention
    times 2).

    Per item: mean over predicted points of the squared distance to the nearest target point,
    plus mean over target points of the squared distance to the nearest predicted point.
    Equal in value and gradient to the dense form (all pairwise distances, min per row and
    column): nearest-neighbour indices come from
    :func:`~sq_mitsuba.geometry.nearest.matched_indices` (no gradient; a KD-tree per item on
    the CPU, O((N + K) log(N + K)), all pairs in batched chunks on a GPU), and the gradient
    flows through the differences of the matched pairs, which is exactly where the dense
    form's min sends it.

    Args:
        pred_points: (B, N, 3), e.g. an assembly's surface samples.
        pred_mask: (B, N) bool, True for the points that count (e.g. not inside another
            primitive), or None for all. Points that do not count are left out of both
            directions. Convention: an item where no point counts uses all its points.
        target: (B, K, 3) ground-truth surface points, same dtype.
        method: the nearest-neighbour search, ``"kdtree"``, ``"dense"`` or None (by the
            device: :func:`~sq_mitsuba.geometry.nearest.nearest_method`); equal results.
        squared: squared distances (the paper's loss: pulls hardest on the farthest points,
            so an uncertain reading is drawn to the mean of what it might be) or Euclidean
            ones (each point pulled alike: the median of what it might be).

    Returns:
        Scalar tensor.
    """
    check_tensor("pred_points", pred_points, (None, 3), min_dims=3)
    check_tensor("target", target, (None, 3), min_dims=3)
    if pred_points.dim() != 3 or target.dim() != 3 or pred_points.shape[0] != target.shape[0]:
        raise ValueError(f"pred_points, target: expected (B, N, 3) and (B, K, 3), got "
                         f"{tuple(pred_points.shape)} and {tuple(target.shape)}")
    if pred_points.shape[1] < 1 or target.shape[1] < 1:
        raise ValueError("pred_points, target: need at least one point per item")
    if target.dtype != pred_points.dtype:
        raise ValueError(f"target: dtype {target.dtype} differs from pred_points' "
                         f"{pred_points.dtype}")
    batch, count = pred_points.shape[:2]
    if pred_mask is None:
        keep = torch.ones(batch, count, dtype=torch.bool, device=pred_points.device)
    else:
        if not isinstance(pred_mask, Tensor) or pred_mask.dtype != torch.bool or \
                pred_mask.shape != (batch, count):
            shape = tuple(pred_mask.shape) if isinstance(pred_mask, Tensor) else pred_mask
            raise ValueError(f"pred_mask: expected a bool tensor of shape {(batch, count)}, "
                             f"got {shape}")
        keep = pred_mask.to(pred_points.device)
        keep = keep | ~keep.any(dim=1, keepdim=True)  # an empty item keeps all its points
    to_target, to_pred = matched_indices(pred_points, keep, target, method=method)
    forward = gathered_differences(pred_points, target, to_target).square().sum(-1)  # (B, N)
    backward = gathered_differences(target, pred_points, to_pred).square().sum(-1)  # (B, K)
    if not squared:
        forward, backward = euclidean(forward), euclidean(backward)
    weight = keep.to(pred_points.dtype)
    forward_mean = (forward * weight).sum(1) / weight.sum(1)
    return (forward_mean + backward.mean(1)).mean()


def counted_surface_samples(assembly: Assembly, level: int = 3) -> tuple[Tensor, Tensor]:
    """An assembly's dual surface samples (642 per primitive at level 3) as one cloud, with
    the mask of those that count in a Chamfer loss or metric (not strictly inside another
    primitive).

    Convention: an item none of whose samples count keeps them all (as :func:`chamfer_loss`
    does with any mask), so training, validation and evaluation compare the same cloud.

    Returns:
        points (B, M * V, 3) and keep (B, M * V) bool, as :func:`chamfer_loss` takes them.
    """
    points, inside_other = assembly.surface_points_with_mask(level)
    keep = ~inside_other.flatten(1, 2)
    return points.flatten(1, 2), keep | ~keep.any(dim=1, keepdim=True)


def surface_chamfer_loss(assembly: Assembly, target: Tensor, level: int = 3) -> Tensor:
    """:func:`chamfer_loss` of :func:`counted_surface_samples` against ``target`` (B, K, 3)."""
    points, keep = counted_surface_samples(assembly, level)
    return chamfer_loss(points, keep, target.to(points.dtype))


# ------------------------------------------------------------------------------ occupancy


def occupancy_loss(assembly: Assembly, points: Tensor, labels: Tensor,
                   sharpness: float = 10.0, balance: bool = True) -> Tensor:
    """Binary cross-entropy of the union occupancy at labelled points (paper Eq. 14).

    The union occupancy is ``max_m sigmoid(s (1 - f_m))`` with f_m the dual inside-outside
    function of primitive m; since the sigmoid is increasing this equals
    ``sigmoid(s (1 - min_m f_m))``, and the loss is evaluated from that logit (stable where
    the occupancy saturates at 0 or 1; same value and gradient as the BCE of the max
    otherwise).

    Args:
        assembly: batch size B.
        points: (B, N, 3) query points in the assembly frame, the assembly's dtype.
        labels: (B, N) bool or float in [0, 1], 1 = inside the ground-truth solid.
        sharpness: s (10 in the published configuration).
        balance: weight inside and outside points equally per item (mean over inside points
            and mean over outside points, averaged). Equal to the plain mean over points when
            half the labels are inside, as the dataset samples them; an item with one class
            only uses that class's mean. False: plain mean over points.

    Returns:
        Scalar tensor, the mean over the batch.
    """
    if not isinstance(labels, Tensor) or labels.shape != points.shape[:-1] or \
            labels.dim() != 2:
        shape = tuple(labels.shape) if isinstance(labels, Tensor) else type(labels).__name__
        raise ValueError(f"labels: expected shape {tuple(points.shape[:-1])} (B, N), got "
                         f"{shape}")
    target = labels.to(points.dtype)
    # A value check (off inside a training step): a scan of the labels is a host sync on a GPU.
    if value_checks_enabled() and bool(((target < 0) | (target > 1)).any()):
        raise ValueError("labels: expected values in [0, 1]")
    if not sharpness > 0:
        raise ValueError(f"sharpness: expected a positive number, got {sharpness}")
    logits = sharpness * (1.0 - assembly.inside_outside(points).amin(dim=1))  # (B, N)
    per_point = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
    if not balance:
        return per_point.mean()
    inside_count, outside_count = target.sum(1), (1.0 - target).sum(1)
    inside_mean = (per_point * target).sum(1) / inside_count.clamp_min(1e-12)
    outside_mean = (per_point * (1.0 - target)).sum(1) / outside_count.clamp_min(1e-12)
    per_item = torch.where(inside_count == 0, outside_mean,
                           torch.where(outside_count == 0, inside_mean,
                                       0.5 * (inside_mean + outside_mean)))
    return per_item.mean()


# --------------------------------------------------------------------------- reprojection


def reprojection_loss(assembly: Assembly, rotations: Tensor, translations: Tensor,
                      masks: Tensor, renderer: SilhouetteRenderer, level: int = 3,
                      items: int | None = None, generator: torch.Generator | None = None) -> Tensor:
    """Pixel MSE between the Mitsuba silhouette at the true pose and the mask, batch mean.

    Per item: :func:`mask_mse` ``= mean over pixels (coverage - mask)^2``, with coverage the
    silhouette of the merged primitive meshes rendered by the renderer's fused
    :meth:`~sq_mitsuba.render.silhouette.renderer.SilhouetteRenderer.render_target_loss` (one BVH
    rebuild per item, items shared among the renderer's worker processes if it has any; or,
    with a ``batched`` renderer, the default on CUDA, every item in one launch each way, each in
    its own tile of one film; gradients from Mitsuba's projective integrator, w.r.t. the
    assembly parameters and the pose). Without a gradient to compute (``torch.no_grad()`` or
    constant inputs) only the forward images are rendered.

    Args:
        assembly: batch size B (or 1, shared by every pose).
        rotations: (B, 3, 3) body-to-camera rotations (the ground-truth pose in training).
        translations: (B, 3) body-to-camera translations.
        masks: (B, H, W) target masks in [0, 1], (H, W) = ``renderer.resolution``.
        renderer: draws the silhouettes at the masks' resolution.
        level: icosphere level of each primitive's mesh (3: 642 vertices).
        items: render only this many batch items, drawn without replacement; the mean over
            them is an unbiased estimate of the batch mean (rendering dominates the cost of a
            training step). None (or B): every item.
        generator: torch.Generator (CPU) drawing the subset, for reproducibility.

    Returns:
        Scalar tensor, the dtype of ``rotations``.
    """
    check_tensor("rotations", rotations, (3, 3), min_dims=3)
    check_tensor("translations", translations, (3,), min_dims=2)
    check_tensor("masks", masks, (None, None), min_dims=3)
    batch = rotations.shape[0]
    if rotations.dim() != 3 or translations.shape != (batch, 3) or masks.dim() != 3 or \
            masks.shape[0] != batch:
        raise ValueError(f"rotations, translations, masks: expected (B, 3, 3), (B, 3) and "
                         f"(B, H, W), got {tuple(rotations.shape)}, "
                         f"{tuple(translations.shape)} and {tuple(masks.shape)}")
    if tuple(masks.shape[1:]) != tuple(renderer.resolution):
        raise ValueError(f"masks: image size {tuple(masks.shape[1:])} differs from the "
                         f"renderer's {tuple(renderer.resolution)}")
    if assembly.batch_size not in (1, batch):
        raise ValueError(f"assembly: batch size {assembly.batch_size} does not match the "
                         f"{batch} poses")
    if items is not None:
        if isinstance(items, bool) or not isinstance(items, int) or not 1 <= items <= batch:
            raise ValueError(f"items: expected an integer in [1, {batch}] or None, got "
                             f"{items!r}")
        if items < batch:
            chosen = torch.randperm(batch, generator=generator)[:items].sort().values
            if rotations.device.type != "cpu":
                # From pinned memory the copy does not make the host wait for the device.
                chosen = chosen.pin_memory().to(rotations.device, non_blocking=True)
            if assembly.batch_size == batch:
                assembly = Assembly(assembly.params[chosen.to(assembly.params.device)])
            rotations = rotations[chosen.to(rotations.device)]
            translations = translations[chosen.to(translations.device)]
            masks = masks[chosen.to(masks.device)]
    vertices, faces = assembly_camera_vertices(assembly, rotations, translations, level)
    loss, _ = renderer.render_target_loss(vertices, faces, masks, mask_mse)
    return loss / rotations.shape[0]


# ------------------------------------------------------------------------------------ pose

def translation_loss(pred_translation: Tensor, gt_translation: Tensor) -> Tensor:
    """Relative translation error per item, ``|t_true - t_pred| / |t_true|``, shape (B,).

    Args:
        pred_translation, gt_translation: (B, 3); ``gt_translation`` non-zero.
    """
    check_tensor("pred_translation", pred_translation, (3,))
    check_tensor("gt_translation", gt_translation, (3,))
    if pred_translation.dim() != 2 or pred_translation.shape != gt_translation.shape:
        raise ValueError(f"pred_translation, gt_translation: expected (B, 3) each, got "
                         f"{tuple(pred_translation.shape)} and {tuple(gt_translation.shape)}")
    distance = torch.linalg.vector_norm(gt_translation, dim=-1)
    # Read back only with value checks on: inside a training step (checks off) it would make
    # the host wait for the device every step.
    if value_checks_enabled() and bool((distance == 0).any()):
        raise ValueError("gt_translation: must be non-zero (the error is relative to it)")
    return torch.linalg.vector_norm(gt_translation - pred_translation, dim=-1) / distance


@functools.cache
def _grid_on(cells: int, device: torch.device) -> Tensor:
    """:func:`~sq_mitsuba.model.rotation_grid.grid_quaternions` on ``device``, copied once
    (a copy per step from pageable memory would make the host wait for a GPU)."""
    return grid_quaternions(cells).to(device=device)


def _symmetric_targets(gt_rotation: Tensor, symmetries: Tensor | None) -> Tensor:
    """The rotations that show the same image as ``gt_rotation`` (B, 3, 3): (B, S, 3, 3),
    ``R_true S`` for each symmetry S (S = 1, the identity, when ``symmetries`` is None)."""
    batch = gt_rotation.shape[0]
    if symmetries is None:
        return gt_rotation[:, None]
    check_tensor("symmetries", symmetries, (3, 3), min_dims=3)
    if symmetries.dim() == 3:
        symmetries = symmetries[None].expand(batch, -1, -1, -1)
    if symmetries.dim() != 4 or symmetries.shape[0] != batch or symmetries.shape[1] < 1:
        raise ValueError(f"symmetries: expected (B, S, 3, 3) or (S, 3, 3) with B = {batch}, "
                         f"got {tuple(symmetries.shape)}")
    return gt_rotation[:, None] @ symmetries.to(gt_rotation.dtype)


def rotation_loss(pred_rotation: Tensor, gt_rotation: Tensor,
                  symmetries: Tensor | None = None) -> Tensor:
    """The paper's rotation error per item (radians, shape (B,)), minimised over symmetries.

    rotation = min over the model's symmetries S of angle(R_pred, R_true S): R_true S shows
    the same image as R_true when S maps the model onto itself, so no symmetric pose is
    penalised. With ``symmetries`` None (or the identity alone) this is the angle of
    R_true^T R_pred (= 2 arccos |<q, q_hat>|), from
    :func:`sq_mitsuba.geometry.rotation.rotation_angle` (atan2 form: its gradient is finite
    everywhere, zero error included).

    Args:
        pred_rotation, gt_rotation: (B, 3, 3).
        symmetries: (B, S, 3, 3) or (S, 3, 3) body-frame symmetries of each model, the
            identity among them (pad a shorter set with identities), or None.
    """
    check_tensor("pred_rotation", pred_rotation, (3, 3))
    check_tensor("gt_rotation", gt_rotation, (3, 3))
    if pred_rotation.dim() != 3 or pred_rotation.shape != gt_rotation.shape:
        raise ValueError(f"pred_rotation, gt_rotation: expected (B, 3, 3) each, got "
                         f"{tuple(pred_rotation.shape)} and {tuple(gt_rotation.shape)}")
    candidates = _symmetric_targets(gt_rotation, symmetries)  # (B, S, 3, 3)
    return rotation_angle(pred_rotation[:, None], candidates).amin(dim=1)


def rotation_6d_loss(pred_rotation_6d: Tensor, gt_rotation: Tensor,
                     symmetries: Tensor | None = None) -> Tensor:
    """Regression of a raw 6D rotation onto the true rotation, per item (B,).

    The squared distance between the network's 6D output (before Gram-Schmidt) and the first
    two rows of ``R_true S`` (what :func:`~sq_mitsuba.geometry.rotation.rotation_6d_to_matrix`
    maps to ``R_true S``), minimised over the symmetries S: 0 at the target, about 8 at most
    for unit rows (the raw output is not normalised). Why: the angle's gradient has the same
    size at every error, so over images whose poses the network cannot yet tell apart the
    gradients cancel and a constant prediction is a stable point; this regression's gradient
    is linear in the target, so the network first learns its expectation given the image (see
    the model card for what it measured).

    Args:
        pred_rotation_6d: (B, 6) raw 6D output, the two rows concatenated.
        gt_rotation: (B, 3, 3).
        symmetries: as :func:`rotation_loss`.
    """
    check_tensor("pred_rotation_6d", pred_rotation_6d, (6,))
    check_tensor("gt_rotation", gt_rotation, (3, 3))
    batch = gt_rotation.shape[0]
    if gt_rotation.dim() != 3 or pred_rotation_6d.shape != (batch, 6):
        raise ValueError(f"pred_rotation_6d: expected shape ({batch}, 6) for {batch} rotations, "
                         f"got {tuple(pred_rotation_6d.shape)}")
    rows = pred_rotation_6d.reshape(batch, 1, 2, 3)
    candidates = _symmetric_targets(gt_rotation, symmetries)  # (B, S, 3, 3)
    return (rows - candidates[..., :2, :]).square().sum((-1, -2)).amin(dim=1)


def pose_loss(pred_rotation: Tensor, pred_translation: Tensor, gt_rotation: Tensor,
              gt_translation: Tensor, symmetries: Tensor | None = None
              ) -> tuple[Tensor, Tensor]:
    """SPEED pose errors per item: (:func:`rotation_loss` (B,) in radians,
    :func:`translation_loss` (B,)).

    Args:
        pred_rotation: (B, 3, 3); pred_translation: (B, 3).
        gt_rotation: (B, 3, 3); gt_translation: (B, 3), non-zero.
        symmetries: (B, S, 3, 3), (S, 3, 3) or None, as :func:`rotation_loss`.
    """
    for name, value, trailing in (("pred_rotation", pred_rotation, (3, 3)),
                                  ("gt_rotation", gt_rotation, (3, 3)),
                                  ("pred_translation", pred_translation, (3,)),
                                  ("gt_translation", gt_translation, (3,))):
        check_tensor(name, value, trailing)
    batch = pred_rotation.shape[0]
    if pred_rotation.shape != (batch, 3, 3) or gt_rotation.shape != (batch, 3, 3) or \
            pred_translation.shape != (batch, 3) or gt_translation.shape != (batch, 3):
        raise ValueError(f"pose: expected rotations (B, 3, 3) and translations (B, 3), got "
                         f"{tuple(pred_rotation.shape)}, {tuple(pred_translation.shape)}, "
                         f"{tuple(gt_rotation.shape)}, {tuple(gt_translation.shape)}")
    return (rotation_loss(pred_rotation, gt_rotation, symmetries),
            translation_loss(pred_translation, gt_translation))


# ------------------------------------------------------------------------ regularisers


def rotation_distribution_loss(logits: Tensor, gt_rotation: Tensor,
                               symmetries: Tensor | None = None) -> Tensor:
    """Cross-entropy of scores over the SO(3) grid against the true rotations' distribution.

    Args:
        logits: (B, G) scores over the super-Fibonacci grid of G cells (a distribution head's
            ``rotation_logits``).
        gt_rotation: (B, 3, 3) true body -> camera rotations.
        symmetries: (B, S, 3, 3) each model's body-frame symmetries (identity included), or
            (S, 3, 3) shared by the batch (as :func:`rotation_loss`); None: the identity.

    Returns:
        (B,) ``-sum_g target_g log softmax(logits)_g`` with the targets of
        :func:`~sq_mitsuba.model.rotation_grid.soft_rotation_targets`: every symmetric
        equivalent of the true rotation counts as right, each spread over nearby cells.
    """
    check_tensor("logits", logits, min_dims=2)
    check_tensor("gt_rotation", gt_rotation, (3, 3), min_dims=3)
    if logits.dim() != 2 or gt_rotation.dim() != 3 or len(logits) != len(gt_rotation):
        raise ValueError(f"logits, gt_rotation: expected (B, G) and (B, 3, 3), got "
                         f"{tuple(logits.shape)} and {tuple(gt_rotation.shape)}")
    equivalents = _symmetric_targets(gt_rotation.float(), symmetries)  # (B, S, 3, 3): R S
    identity = torch.eye(3, device=equivalents.device).expand(len(equivalents), 3, 3)
    cells = _grid_on(logits.shape[-1], logits.device)
    targets = soft_rotation_targets(identity, equivalents, cells)
    return -(targets.to(logits) * logits.log_softmax(dim=-1)).sum(dim=-1)


def mask_loss(logits: Tensor, mask: Tensor) -> Tensor:
    """Binary cross-entropy of the mask head's logits against the target's mask.

    Args:
        logits: (B, 1, h, w) the mask head's logits (a quarter of the image's size, or all of it).
        mask: (B, 1, H, W) in [0, 1], area-averaged to h x w (a soft target at the outline).

    Returns:
        Scalar: the mean over cells and images.
    """
    check_tensor("logits", logits, (1, None, None), min_dims=4)
    target = F.interpolate(mask.to(logits), size=logits.shape[-2:], mode="area")
    return F.binary_cross_entropy_with_logits(logits, target)


def taper_loss(assembly: Assembly) -> Tensor:
    """Taper regulariser: mean over primitives and both factors of k^2, a scalar.

    Convention: k^2 rather than |k|: smooth at k = 0 (no gradient kink that would pin tapers
    to exactly zero) and growing fastest for the large tapers that turn a primitive into a
    wedge; at the weight 0.01, one factor k of one primitive costs 0.01 k^2 / (2 M) against
    one item's shape terms (the mean runs over the M primitives' two factors).
    """
    if not isinstance(assembly, Assembly):
        raise ValueError(f"assembly: expected an Assembly, got {type(assembly).__name__}")
    return assembly.taper.square().mean()


def mask_mse(coverage: Tensor, target: Tensor) -> Tensor:
    """Pixel-mean squared error of one view: ``mean (coverage - target)^2`` (the paper's
    reprojection loss per image). coverage, target: (H, W) (or any equal shapes); a scalar.

    A module-level function, so the renderer's worker processes can run it (see
    :meth:`~sq_mitsuba.render.silhouette.renderer.SilhouetteRenderer.render_target_loss`)."""
    return (coverage - target).square().mean()


def soft_iou_loss(coverage: Tensor, target: Tensor) -> Tensor:
    """``1 - soft IoU`` of one view: ``1 - sum(c t) / sum(c + t - c t)`` (the union clamped
    at 1e-6). coverage, target: (H, W) in [0, 1]; a scalar."""
    inter = (coverage * target).sum()
    union = (coverage + target - coverage * target).sum().clamp_min(1e-6)
    return 1 - inter / union


#: Per-view silhouette losses by name (:func:`silhouette_loss`).
_SILHOUETTE_LOSS_FUNCTIONS = {"mse": mask_mse, "iou": soft_iou_loss}


def silhouette_loss(coverage: Tensor, target: Tensor, kind: str = "mse") -> Tensor:
    """A per-view loss summed over views: ``mse`` (:func:`mask_mse`) or ``iou``
    (:func:`soft_iou_loss`). coverage, target: (V, H, W)."""
    if kind not in _SILHOUETTE_LOSS_FUNCTIONS:
        raise ValueError(f"loss: expected one of {SILHOUETTE_LOSSES}, got {kind!r}")
    view_loss = _SILHOUETTE_LOSS_FUNCTIONS[kind]
    return torch.stack([view_loss(c, t) for c, t in zip(coverage, target, strict=True)]).sum()


def overlap(occupancy: Tensor, beta: float = 1.25) -> Tensor:
    """Overlap penalty (paper Eq. 18): mean over points of relu(sum_m g_m - beta).

    Args:
        occupancy: per-primitive occupancy (B, M, N).
        beta: how much summed occupancy is tolerated (1.25 in the published configuration).

    Returns:
        Scalar tensor.
    """
    check_tensor("occupancy", occupancy, (None, None), min_dims=3)
    return torch.relu(occupancy.sum(dim=1) - beta).mean()
