"""Global pose search by render and compare, then the local refinement, from a mask alone.

Refinement (:mod:`sq_mitsuba.inference.refine`) is a local search: from a rotation at chance it
fits the silhouette by deforming the shape. The search here first picks the rotation globally:
every candidate pose of the predicted assembly is rendered by Mitsuba
(:class:`~sq_mitsuba.render.silhouette.batch.PoseSilhouettes`, all candidates of an image in
one launch, forward only) at a low resolution and scored by its soft IoU against the target
mask; the best few are refined a few steps each, the best of those is refined to the end, and
the result with the best IoU is returned, with every candidate's score for inspection.

Candidates (:func:`pose_candidates`): the network's rotation and, when the network has a
rotation-distribution head, its top-K hypotheses, each times the four half turns of the body
frame (``R @ S``: a principal-axes body frame is fixed only up to them); without hypotheses, a
uniform grid of SO(3) (:func:`~sq_mitsuba.geometry.so3_grid.so3_grid`) instead. With
``candidates = "network"`` (the default) a network with hypotheses keeps its own rotation:
the candidates are it and its half turns only, and the silhouette picks the half turn and the
translation; a network without them (a regressed rotation) is searched over the grid either
way. Measured with the shipped model's second stage (before its third; eval/MODEL_CARD.md)
on 64 test images (folded rotation error, median): the network 27 deg; after a search of its
hypotheses too, 35 deg (the best outline of a rough shape is often a wrong rotation); after a
search of its own rotation only, 27 deg; the 2D IoU after refinement 0.557 and 0.551, the
second in half the time. The network's rotation that the search starts from is read from
``turns`` in-plane turns of the image
(:meth:`~sq_mitsuba.inference.predictor.Predictor.read_turns`; the callers in
:mod:`sq_mitsuba.evaluation` pass it), not from one: a distribution multiplied over 8 turns is
23.6 deg median against 26.7 on those 64 images (38.7 against 42.8 on 400). The same copies
give the assembly, the position and the mask the search fits, as means over the copies.
Neither a local search around that rotation nor one with the network's log-probability as a
prior beat it: the outline of a rough shape pulls the rotation away (eval/MODEL_CARD.md).

Each candidate keeps the network's translation, shifted (``recentre``) so that its
silhouette's centroid is the mask's: a wrong rotation also moves the outline's centre, and the
score should judge the rotation, not the translation. The depth stays the network's unless
``fit_depth``: fitting the area also fits the predicted shape's size errors and a partial
mask's missing parts (measured on the shipped model's test images: relative translation error
0.10 -> 0.28).

Limits, plainly: a silhouette cannot tell apart two poses with the same outline (a symmetric
spacecraft, a pose and its mirror through the viewing axis, a face seen from the front or the
back); the search returns one of them, and only shading or a network's scores could choose.

Convention: poses map body to camera, ``x_cam = R x_body + t`` (OpenCV frame); rotations are
(..., 3, 3) matrices. Masks are (B, H, W) at the camera's resolution, bool or float in [0, 1]
(``> 0.5`` is the target), averaged down to the search resolution.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Literal

import torch
from torch import Tensor

from sq_mitsuba.checks import check_rotations, check_tensor
from sq_mitsuba.config import in_range, validate
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.so3_grid import so3_grid, with_half_turns
from sq_mitsuba.inference.refine import RefineOptions, RefineResult, refine_pose_and_shape
from sq_mitsuba.render.silhouette.batch import PoseSilhouettes

__all__ = [
    "SEARCH_REFINEMENT",
    "SearchOptions",
    "SearchRefineResult",
    "SearchRenderers",
    "SearchResult",
    "check_search_inputs",
    "pose_candidates",
    "search_and_refine",
    "search_poses",
]

#: The refinement after a search, by default, each choice measured on 64 test images of the
#: shipped model's second stage from its own mask (eval/MODEL_CARD.md, "Render and compare"):
#: pose only (letting the sizes move too lifts the 2D IoU 0.568 -> 0.62 but worsens Chamfer-L1
#: by 5 %, or by 1 % at 0.59 under a strong prior; every shape parameter, by 40 %); at the network's
#: depth (a free depth raised the 2D IoU by 0.01 and the relative translation error from 0.10
#: to 0.17, turning the shape's size error into a depth error); the rotation held near the
#: search's by a prior of weight 1 (without it the outline of the rough shape pulls the
#: rotation from 24 to 34 deg median, for 0.013 of IoU); 25 steps at most.
SEARCH_REFINEMENT = RefineOptions(steps=25, patience=10, shape="pose", depth="fixed",
                                  rotation_prior=1.0)

# Depth changes of the recentring step are clamped to this factor either way.
_DEPTH_CLAMP = 2.0


@dataclass(frozen=True)
class SearchOptions:
    """Settings of the global pose search and of the refinement that follows it."""

    resolution: int = in_range(8, 512, default=64)
    "Width in pixels of the final scores (the mask is averaged down to it)."
    coarse_resolution: int = in_range(8, 512, default=32)
    "Width in pixels at which every candidate is scored first."
    fine: int = in_range(1, 100_000, default=128)
    "Best candidates of the coarse pass scored again at `resolution`."
    spp: int = in_range(1, 64, default=1)
    "Samples per pixel of the scored silhouettes (1: the pixel centre)."
    grid: int = in_range(0, 100_000, default=1024)
    "Uniform rotations scored when no hypotheses are given (0: the network's rotation only)."
    turns: int = in_range(1, 64, default=8)
    """Read the network's rotation for the candidates from this many in-plane turns of the
    image (Predictor.predict(turns=T); a distribution head and a camera whose roll is an image
    rotation, else 1): the candidates' rotation, not the network row's."""
    candidates: Literal["hypotheses", "network"] = "network"
    "With hypotheses: search them too ('hypotheses') or the network's rotation only ('network')."
    recentre: bool = True
    "Shift each candidate's translation to put its silhouette's centroid on the mask's."
    fit_depth: bool = False
    "When recentring, also scale the depth so the silhouette's area is the mask's."
    level: int = in_range(0, 5, default=2)
    "Icosphere level of the primitives' meshes in the search (2: 162 vertices)."
    keep: int = in_range(1, 64, default=2)
    "Best-scoring candidates refined a few steps each; the best of them is refined to the end."
    screen_steps: int = in_range(0, 1000, default=5)
    "Refinement steps given to each kept candidate (0: refine the best-scoring one only)."
    rounds: int = in_range(1, 10, default=1)
    "Search-and-refine passes; each later one searches again with the refined shape."
    seed: int = in_range(0, 2**31 - 1, default=0)
    "Seed of the renderers' samples."


@dataclass
class SearchResult:
    """What :func:`search_poses` returns; tensors are detached, on the CPU, float64.

    Attributes:
        rotation: (B, 3, 3) the best-scoring candidate; translation: (B, 3) its translation.
        score: (B,) its soft IoU against the mask at the search resolution.
        candidates: (B, N, 3, 3) every candidate rotation; translations: (B, N, 3) the
            translation each was last scored at (recentred); scores: (B, N) their soft IoUs at
            the coarse resolution.
        fine_index: (B, F) the candidates scored again at the search resolution, and
            fine_scores: (B, F) those scores (the ranking that picks the best).
    """

    rotation: Tensor
    translation: Tensor
    score: Tensor
    candidates: Tensor
    translations: Tensor
    scores: Tensor
    fine_index: Tensor
    fine_scores: Tensor

    def best(self, count: int) -> Tensor:
        """Indices (B, count) into ``candidates`` of the ``count`` best, best first (by the
        fine scores)."""
        order = self.fine_scores.topk(min(count, self.fine_scores.shape[1]), dim=1).indices
        return self.fine_index.gather(1, order)


@dataclass
class SearchRefineResult:
    """What :func:`search_and_refine` returns; tensors are detached.

    Attributes:
        assembly: refined assemblies, batch size B; rotation (B, 3, 3); translation (B, 3).
        iou: (B,) IoU of the result against the mask at the refinement resolution.
        search: the first pass's :class:`SearchResult` (every candidate and its score).
        search_rotation, search_translation: (B, 3, 3), (B, 3) the first search's best pose.
        rounds: per pass, the mean IoU after its refinement (to compare passes).
        search_seconds, total_seconds: wall time of the first search, and of everything.
    """

    assembly: Assembly
    rotation: Tensor
    translation: Tensor
    iou: Tensor
    search: SearchResult
    search_rotation: Tensor
    search_translation: Tensor
    rounds: list[float] = field(default_factory=list)
    search_seconds: float = 0.0
    total_seconds: float = 0.0


# ------------------------------------------------------------------------------- checks


def check_search_inputs(assembly: Assembly, candidates: Tensor, translation: Tensor,
                        masks: Tensor, camera: Camera) -> None:
    """One-line ``ValueError`` naming the argument for anything :func:`search_poses` cannot use:
    batch sizes that disagree, no candidates (K = 0), NaN or non-rotation candidates, a
    translation behind the camera, masks of another size than the camera's, an empty mask."""
    if not isinstance(assembly, Assembly):
        raise ValueError(f"assembly: expected an Assembly, got {type(assembly).__name__}")
    if not isinstance(camera, Camera):
        raise ValueError(f"camera: expected a Camera, got {type(camera).__name__}")
    batch = assembly.batch_size
    check_tensor("candidates", candidates, (3, 3), min_dims=4, finite=False)
    if candidates.dim() != 4 or candidates.shape[0] != batch:
        raise ValueError(f"candidates: expected shape ({batch}, K, 3, 3) for an assembly batch "
                         f"of {batch}, got {tuple(candidates.shape)}")
    if candidates.shape[1] == 0:
        raise ValueError("candidates: K = 0 rotations to search; give at least one")
    check_rotations("candidates", candidates)
    check_tensor("translation", translation, (3,))
    if tuple(translation.shape) != (batch, 3):
        raise ValueError(f"translation: expected shape ({batch}, 3), got "
                         f"{tuple(translation.shape)}")
    if bool((translation[:, 2] <= 0).any()):
        raise ValueError("translation: the target must lie in front of the camera (t_z > 0)")
    check_tensor("masks", masks, (None, None), min_dims=3, floating=False)
    if masks.dim() != 3 or masks.shape[0] != batch:
        raise ValueError(f"masks: expected shape ({batch}, H, W), got {tuple(masks.shape)}")
    if tuple(masks.shape[1:]) != (camera.height, camera.width):
        raise ValueError(f"masks: size {tuple(masks.shape[1:])} differs from the camera's "
                         f"{(camera.height, camera.width)} (height, width)")
    empty = [i for i, mask in enumerate(masks) if not bool((mask.double() > 0.5).any())]
    if empty:
        raise ValueError(f"masks: item(s) {empty} are empty (no pixel above 0.5): nothing to "
                         "search against")


def pose_candidates(rotation: Tensor, hypotheses: Tensor | None = None,
                    grid: int = 0) -> Tensor:
    """Candidate rotations (B, N, 3, 3) for each image.

    Args:
        rotation: (B, 3, 3) the network's rotation; it and its half turns come first.
        hypotheses: (B, K, 3, 3) the network's top-K rotations (K >= 1), or None.
        grid: without hypotheses, also this many uniform rotations (the same for every image;
            a uniform grid needs no half turns: they map it to another uniform grid).

    Returns:
        ``[rotation x 4 half turns, hypotheses x 4 half turns | grid]`` along dim 1, float64:
        N = 4 + 4 K with hypotheses, 4 + grid without.

    Raises:
        ValueError: naming ``rotation`` or ``hypotheses`` (NaN, K = 0, wrong shape, not a
            rotation).
    """
    check_rotations("rotation", rotation)
    if rotation.dim() != 3:
        raise ValueError(f"rotation: expected shape (B, 3, 3), got {tuple(rotation.shape)}")
    rotation = rotation.detach().double().cpu()
    parts = [with_half_turns(rotation)]
    if hypotheses is not None:
        check_tensor("hypotheses", hypotheses, (3, 3), min_dims=4, finite=False)
        if hypotheses.dim() != 4 or hypotheses.shape[0] != rotation.shape[0]:
            raise ValueError(f"hypotheses: expected shape ({rotation.shape[0]}, K, 3, 3), got "
                             f"{tuple(hypotheses.shape)}")
        if hypotheses.shape[1] == 0:
            raise ValueError("hypotheses: K = 0 rotations; give at least one, or None")
        check_rotations("hypotheses", hypotheses)
        parts.append(with_half_turns(hypotheses.detach().double().cpu()).flatten(1, 2))
    elif grid > 0:
        parts.append(so3_grid(grid).expand(rotation.shape[0], -1, -1, -1))
    return torch.cat(parts, dim=1)


# ------------------------------------------------------------------------------- search


def soft_iou(coverage: Tensor, target: Tensor) -> Tensor:
    """Soft IoU (...,) of coverage images (..., H, W) and a target (H, W), both in [0, 1]:
    sum(c m) / sum(c + m - c m)."""
    inter = (coverage * target).flatten(-2).sum(-1)
    union = (coverage + target - coverage * target).flatten(-2).sum(-1)
    return inter / union.clamp_min(1e-12)


def _moments(images: Tensor, camera: Camera) -> tuple[Tensor, Tensor]:
    """Area (...,) in pixels and centroid (..., 2) as (u, v) of images (..., H, W)."""
    centres = camera.pixel_centers(images.dtype)  # (H, W, 2)
    area = images.flatten(-2).sum(-1)
    moment = (images[..., None] * centres).flatten(-3, -2).sum(-2)
    return area, moment / area.clamp_min(1e-12)[..., None]


def _recentred(translation: Tensor, coverage: Tensor, target: Tensor, camera: Camera,
               fit_depth: bool) -> Tensor:
    """Translations (N, 3) moved so that each silhouette's centroid (and, with ``fit_depth``,
    its area) match the target's: the depth scales by sqrt(area ratio) (clamped), then the
    silhouette shifts in the image plane; a candidate that covers nothing keeps its
    translation."""
    area, centroid = _moments(coverage, camera)
    target_area, target_centroid = _moments(target, camera)
    visible = area > 0.5
    ratio = (area / target_area).clamp(1 / _DEPTH_CLAMP**2, _DEPTH_CLAMP**2).sqrt()
    ratio = torch.where(visible & fit_depth, ratio, torch.ones_like(ratio))
    # Scaling t moves the body origin along its ray: its image stays, the outline scales
    # about it by 1 / ratio.
    origin = camera.project(translation)
    centroid = origin + (centroid - origin) / ratio[:, None]
    scaled = translation * ratio[:, None]
    shift = (target_centroid - centroid) * scaled[:, 2:] / scaled.new_tensor(
        [camera.fx, camera.fy])
    shift = torch.where(visible[:, None], shift, torch.zeros_like(shift))
    return scaled + torch.cat([shift, torch.zeros_like(shift[:, :1])], dim=1)


def _score_views(renderer: PoseSilhouettes, mesh: tuple[Tensor, Tensor], rotations: Tensor,
                 translations: Tensor, target: Tensor, options: SearchOptions
                 ) -> tuple[Tensor, Tensor]:
    """Soft IoUs (n,) of one mesh (vertices (V, 3), faces (F, 3)) at n poses against a target
    (H, W), and the translations (n, 3) scored (recentred as ``options`` say)."""
    coverage = renderer.render(*mesh, rotations, translations).double()
    if options.recentre:
        translations = _recentred(translations, coverage, target, renderer.camera,
                                  options.fit_depth)
        coverage = renderer.render(*mesh, rotations, translations).double()
    return soft_iou(coverage, target), translations


def search_poses(assembly: Assembly, candidates: Tensor, translation: Tensor, masks: Tensor,
                 camera: Camera, options: SearchOptions | None = None,
                 renderers: SearchRenderers | None = None) -> SearchResult:
    """Score every candidate rotation of each image by its silhouette's soft IoU with the mask.

    Args:
        assembly: predicted assemblies (body frame), batch size B.
        candidates: (B, N, 3, 3) rotations to score (:func:`pose_candidates`), N >= 1.
        translation: (B, 3) the translation every candidate starts from.
        masks: (B, H, W) target masks at ``camera``'s resolution (bool, or float in [0, 1]).
        camera: intrinsics of the masks.
        options: :class:`SearchOptions` (resolutions, fine, spp, recentre, level, seed).
        renderers: :class:`SearchRenderers` to reuse (made when None).

    Every candidate is rendered at ``coarse_resolution`` (and, with ``recentre``, rendered
    again at its fitted translation) and scored; the ``fine`` best are rendered and scored
    again at ``resolution``, and the best of those wins.

    Returns:
        :class:`SearchResult`: the best candidate per image and every candidate's score.

    Raises:
        ValueError: naming the argument (see :func:`check_search_inputs`).
    """
    options = options if options is not None else SearchOptions()
    validate(options)
    check_search_inputs(assembly, candidates, translation, masks, camera)
    renderers = renderers or SearchRenderers(camera, options)
    candidates = candidates.detach().double().cpu()
    batch, count = candidates.shape[:2]
    vertices, faces = Assembly(assembly.params.detach().double().cpu()).merged_mesh(
        options.level)
    coarse_targets = renderers.targets(masks, coarse=True)
    fine_targets = renderers.targets(masks, coarse=False)
    fine = min(options.fine, count)
    scores = torch.empty(batch, count, dtype=torch.float64)
    fine_index = torch.empty(batch, fine, dtype=torch.int64)
    fine_scores = torch.empty(batch, fine, dtype=torch.float64)
    translations = translation.detach().double().cpu()[:, None].repeat(1, count, 1)
    for item in range(batch):
        mesh = (vertices[item], faces)
        scores[item], translations[item] = _score_views(
            renderers.coarse, mesh, candidates[item], translations[item], coarse_targets[item],
            options)
        fine_index[item] = scores[item].topk(fine).indices
        chosen = fine_index[item]
        fine_scores[item], translations[item, chosen] = _score_views(
            renderers.fine, mesh, candidates[item, chosen], translations[item, chosen],
            fine_targets[item], options)
    best = fine_index.gather(1, fine_scores.argmax(dim=1, keepdim=True))[:, 0]
    rows = torch.arange(batch)
    return SearchResult(candidates[rows, best], translations[rows, best],
                        fine_scores.amax(dim=1), candidates, translations, scores, fine_index,
                        fine_scores)


class SearchRenderers:
    """The two :class:`~sq_mitsuba.render.silhouette.batch.PoseSilhouettes` of a search (coarse
    and fine resolution), kept between calls so their scenes and kernels are reused."""

    def __init__(self, camera: Camera, options: SearchOptions) -> None:
        self.coarse = PoseSilhouettes(camera.rescaled(options.coarse_resolution),
                                      spp=options.spp, seed=options.seed)
        self.fine = PoseSilhouettes(camera.rescaled(options.resolution), spp=options.spp,
                                    seed=options.seed)

    def targets(self, masks: Tensor, coarse: bool) -> Tensor:
        """Masks (B, H, W) thresholded at 0.5 and averaged down to a renderer's size."""
        from sq_mitsuba.inference.fit import resize_masks

        camera = (self.coarse if coarse else self.fine).camera
        return resize_masks((masks.double() > 0.5).double(), camera.height, camera.width)


# ------------------------------------------------------------------------------- with refinement


def _refine_each(assembly: Assembly, rotations: Tensor, translations: Tensor, masks: Tensor,
                 camera: Camera, search: SearchOptions, refine: RefineOptions,
                 own: Tensor | None = None) -> RefineResult:
    """Refine ``keep`` starts per image ((B, k, 3, 3) rotations, (B, k, 3) translations):
    ``screen_steps`` each, then the best (by IoU) to ``refine.steps``. Image by image, on its
    own rows (``own``): its fit is what it would be alone (in a batch its samples were drawn
    by its place, it stopped with the batch, its mesh held its batch-mates' stand-ins, which
    come back rebuilt from the refined first row: :func:`gathered_primitives`)."""
    from sq_mitsuba.model.existence import gathered_primitives
    params = assembly.params.detach().double()
    rows, kept = torch.arange(params.shape[1]), rotations.shape[1]
    results: list[tuple[Tensor, RefineResult]] = []
    for i in range(rotations.shape[0]):
        mine = torch.ones_like(rows, dtype=torch.bool) if own is None else own[i].cpu()
        start, rotation, translation = params[i:i + 1, mine], rotations[i], translations[i]
        if kept > 1 and search.screen_steps > 0:
            screened = refine_pose_and_shape(
                Assembly(start.repeat(kept, 1, 1)), rotation, translation,
                masks[i:i + 1].repeat(kept, 1, 1), camera,
                replace(refine, steps=search.screen_steps, patience=search.screen_steps))
            best = int(screened.iou_after.argmax())  # the first of equals, as argmax was
            start = screened.assembly.params.detach().double()[best:best + 1]
            rotation, translation = screened.rotation[best:], screened.translation[best:]
        result = refine_pose_and_shape(Assembly(start), rotation[:1], translation[:1],
                                       masks[i:i + 1], camera, refine)
        padded = params[i:i + 1].clone()
        padded[:, mine] = result.assembly.params.detach().double()
        results.append((gathered_primitives(padded, torch.where(mine, rows, -1)[None]), result))
    cat = {name: torch.cat([getattr(r, name) for _, r in results]) for name in
           ("rotation", "translation", "iou_before", "iou_after")}
    return RefineResult(Assembly(torch.cat([p for p, _ in results])), **cat,
                        steps=max(r.steps for _, r in results))


def better_of(best: RefineResult, result: RefineResult) -> RefineResult:
    """Per image, the one of two refinements of B images with the higher ``iou_after``
    (``best``'s on a tie): its assembly, pose and IoU together; ``iou_before`` stays
    ``best``'s, the steps add up."""
    better = result.iou_after > best.iou_after
    params = torch.where(better[:, None, None], result.assembly.params.double(),
                         best.assembly.params.double())
    return RefineResult(Assembly(params),
                        torch.where(better[:, None, None], result.rotation, best.rotation),
                        torch.where(better[:, None], result.translation, best.translation),
                        best.iou_before, torch.maximum(result.iou_after, best.iou_after),
                        best.steps + result.steps)


def search_and_refine(assembly: Assembly, rotation: Tensor, translation: Tensor,
                      masks: Tensor, camera: Camera, hypotheses: Tensor | None = None,
                      search: SearchOptions | None = None,
                      refine: RefineOptions | None = None,
                      own: Tensor | None = None) -> SearchRefineResult:
    """The global search, then the local refinement of its best few, for B images.

    Args:
        assembly: the network's assemblies, batch size B.
        rotation: (B, 3, 3) the network's rotations; translation: (B, 3).
        masks: (B, H, W) target masks at ``camera``'s resolution (bool or float in [0, 1]).
        camera: intrinsics of the masks.
        hypotheses: (B, K, 3, 3) the network's top-K rotations, or None (a uniform grid of
            ``search.grid`` rotations instead).
        search: :class:`SearchOptions`; refine: :class:`RefineOptions` of the final
            refinement (default :data:`SEARCH_REFINEMENT`; the screening uses its settings
            with ``screen_steps`` steps).
        own: (B, M) bool, each item's own rows (False: a stand-in the batch pads it with);
            see :func:`~sq_mitsuba.inference.refine.refine_pose_and_shape`.

    Returns:
        :class:`SearchRefineResult`. Each pass keeps the best result so far by IoU, so a later
        pass never makes an image worse at the refinement resolution. An image's result is
        what it would be alone, wherever the batch puts it (refined image by image).

    Raises:
        ValueError: naming the argument: see :func:`pose_candidates` and
            :func:`check_search_inputs` (mask size, empty mask, NaN hypotheses, K = 0).
    """
    started = time.perf_counter()
    search = search if search is not None else SearchOptions()  # {} is no default
    refine = refine if refine is not None else SEARCH_REFINEMENT
    validate(search)
    validate(refine)
    candidates = pose_candidates(rotation, hypotheses, search.grid)  # checks the hypotheses
    if search.candidates == "network" and hypotheses is not None:
        candidates = candidates[:, :4]  # the network's rotation and its half turns come first
    check_search_inputs(assembly, candidates, translation, masks, camera)  # before any use
    translation = translation.detach().double().cpu()
    masks = masks.detach().cpu()
    renderers = SearchRenderers(camera, search)
    first = search_poses(assembly, candidates, translation, masks, camera, search, renderers)
    search_seconds = time.perf_counter() - started
    current, rounds = first, []
    best: RefineResult | None = None
    shape = Assembly(assembly.params.detach().double().cpu())
    for round_index in range(search.rounds):
        top = current.best(search.keep)
        rows = torch.arange(shape.batch_size)[:, None]
        result = _refine_each(shape, current.candidates[rows, top],
                              current.translations[rows, top], masks, camera, search, refine,
                              own)
        best = result if best is None else better_of(best, result)
        rounds.append(float(best.iou_after.mean()))
        if round_index + 1 < search.rounds:
            # Search again with the refined shape: its own rotation (and half turns) joins the
            # candidates, every translation starts from the refined one.
            shape = Assembly(best.assembly.params.detach().double())
            again = torch.cat([with_half_turns(best.rotation.double()), candidates], dim=1)
            current = search_poses(shape, again, best.translation.double(), masks, camera,
                                   search, renderers)
    assert best is not None
    return SearchRefineResult(best.assembly, best.rotation, best.translation, best.iou_after,
                              first, first.rotation, first.translation, rounds, search_seconds,
                              time.perf_counter() - started)
