"""Global pose search by render and compare: batched silhouettes, candidates, search, refinement."""

from __future__ import annotations

import pytest
import torch

from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.metrics import mask_iou
from sq_mitsuba.geometry.rotation import random_rotations
from sq_mitsuba.geometry.so3_grid import covering_angle_deg, so3_grid, with_half_turns
from sq_mitsuba.inference.refine import RefineOptions
from sq_mitsuba.inference.search import (
    SearchOptions,
    pose_candidates,
    search_and_refine,
    search_poses,
)
from sq_mitsuba.render.silhouette.batch import PoseSilhouettes
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

RESOLUTION = 64
GRID = 2048


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    cos = ((a.transpose(-1, -2) @ b).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return torch.rad2deg(torch.arccos(cos.clamp(-1, 1)))


@pytest.fixture(scope="module")
def scene():
    """An assembly without symmetries (three unequal primitives off the axes), three true
    poses, and the masks an independent renderer (the differentiable one) draws of them."""
    batch = 3
    truth = Assembly.from_values(
        size=torch.tensor([[[0.32, 0.14, 0.10], [0.06, 0.28, 0.05], [0.09, 0.09, 0.20]]] * batch,
                          dtype=torch.float64),
        shape=torch.tensor([[[0.3, 0.5], [0.2, 0.2], [0.8, 0.6]]] * batch, dtype=torch.float64),
        translation=torch.tensor([[[0.0, 0.0, 0.0], [0.20, 0.10, 0.0], [-0.15, 0.05, 0.15]]]
                                 * batch, dtype=torch.float64))
    rotation = random_rotations(batch, torch.Generator().manual_seed(3), torch.float64)
    translation = torch.tensor([[0.05, -0.03, 1.8], [0.0, 0.02, 1.6], [-0.06, 0.04, 2.0]],
                               dtype=torch.float64)
    camera = Camera.default(RESOLUTION)
    with torch.no_grad():
        masks = render_assembly(truth, rotation, translation,
                                SilhouetteRenderer(camera, spp=16), level=2) > 0.5
    return truth, rotation, translation, masks, camera


def test_batched_silhouettes_match_the_differentiable_renderer(scene):
    truth, rotation, translation, _, camera = scene
    vertices, faces = truth.merged_mesh(2)
    poses = torch.cat([rotation, so3_grid(5)])
    places = torch.cat([translation, translation[:1].expand(5, 3)])
    reference = render_assembly(Assembly(truth.params[:1]), poses, places,
                                SilhouetteRenderer(camera, spp=64), level=2)
    for spp in (1, 16):
        coverage = PoseSilhouettes(camera, spp=spp, max_rays=3 * 64 * 64 * spp).render(
            vertices[0], faces, poses, places)  # several launches
        assert coverage.shape == (8, RESOLUTION, RESOLUTION)
        assert float(mask_iou(coverage, reference.float()).min()) > 0.97
    behind = PoseSilhouettes(camera).render(vertices[0], faces, rotation[:1],
                                            torch.tensor([0.0, 0.0, -2.0]))
    assert float(behind.sum()) == 0.0


def test_batched_views_share_their_sub_pixel_samples(scene):
    """With several samples a pixel, every view of one call samples the same sub-pixel
    positions (the module's convention): the same pose three times gives three identical
    images, so two candidates' scores never differ by sampling noise; another call draws
    other positions."""
    truth, rotation, translation, _, camera = scene
    vertices, faces = truth.merged_mesh(2)
    renderer = PoseSilhouettes(camera, spp=4)
    same = renderer.render(vertices[0], faces, rotation[:1].expand(3, 3, 3),
                           translation[:1].expand(3, 3))
    assert torch.equal(same[0], same[1]) and torch.equal(same[0], same[2])
    assert ((same[0] > 0) & (same[0] < 1)).any()  # edge pixels are sampled, not all-or-none
    again = renderer.render(vertices[0], faces, rotation[:1], translation[:1])
    assert not torch.equal(again[0], same[0])


def test_search_finds_the_pose_from_a_grid_within_its_spacing(scene):
    """Acceptance: the true pose, found again from the silhouette alone, from a uniform grid
    (the 'network' rotation is a half turn away from the truth), to within the grid's spacing;
    the assembly has no symmetry, so no rotation shows the same outline."""
    truth, rotation, translation, masks, camera = scene
    network = rotation @ torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    off = translation + torch.tensor([0.04, -0.03, 0.0], dtype=torch.float64)
    candidates = pose_candidates(network, grid=GRID)
    assert candidates.shape == (3, 4 + GRID, 3, 3)
    result = search_poses(truth, candidates, off, masks, camera, SearchOptions())
    nearest = _angle_deg(so3_grid(GRID)[None], rotation[:, None]).amin(dim=1)
    error = _angle_deg(result.rotation, rotation)
    spacing = 1.5 * covering_angle_deg(GRID)  # the largest nearest-cell angle measured
    assert bool((error <= spacing).all()), (error, nearest, spacing)
    assert bool((error <= nearest + 8.0).all()), (error, nearest)
    # Recentring found the translation again (the search fits it to the mask), the depth
    # too when asked to.
    distance = translation.norm(dim=-1)
    assert bool(((result.translation - translation).norm(dim=-1) < 0.03 * distance).all())
    deeper = off + torch.tensor([0.0, 0.0, 0.15], dtype=torch.float64)
    fitted = search_poses(truth, result.rotation[:, None], deeper, masks, camera,
                          SearchOptions(fit_depth=True))
    assert bool(((fitted.translation - translation).norm(dim=-1) < 0.04 * distance).all())
    # Every candidate has a score; the winner's is the best of the fine pass.
    assert result.scores.shape == (3, 4 + GRID)
    assert torch.equal(result.score, result.fine_scores.amax(dim=1))
    assert torch.equal(result.best(1)[:, 0], result.fine_index.gather(
        1, result.fine_scores.argmax(1, keepdim=True))[:, 0])


def test_search_and_refine_from_hypotheses(scene):
    """With hypotheses (a near-true one among random ones), the search picks it and the
    refinement ends at a high IoU; the pose-only refinement leaves the shape as it was."""
    truth, rotation, translation, masks, camera = scene
    generator = torch.Generator().manual_seed(5)
    hypotheses = random_rotations(3 * 6, generator, torch.float64).reshape(3, 6, 3, 3)
    axis = torch.tensor([[0.0, -0.6, 0.8], [0.6, 0.0, 0.0], [-0.8, 0.0, 0.0]],
                        dtype=torch.float64)  # the skew matrix of a unit axis
    tilt = torch.linalg.matrix_exp(0.14 * axis)  # 8 degrees
    hypotheses[:, 2] = tilt @ rotation
    network = random_rotations(3, generator, torch.float64)
    result = search_and_refine(
        truth, network, translation, masks, camera, hypotheses,
        SearchOptions(candidates="hypotheses", keep=2, screen_steps=2),
        RefineOptions(steps=4, patience=4, shape="pose"))
    assert result.search.candidates.shape == (3, 4 + 4 * 6, 3, 3)
    assert bool((_angle_deg(result.search_rotation, rotation) < 10.0).all())
    assert bool((result.iou > 0.85).all()), result.iou
    assert torch.allclose(result.assembly.params, truth.params.double(), atol=1e-3)


def test_network_candidates_keep_the_networks_rotation_up_to_a_half_turn(scene):
    """candidates = "network": the hypotheses (one near the truth) are not searched, so the
    result is one of the network's rotation's four half turns, refined a few steps."""
    truth, rotation, translation, masks, camera = scene
    generator = torch.Generator().manual_seed(6)
    network = random_rotations(3, generator, torch.float64)
    result = search_and_refine(
        truth, network, translation, masks, camera, rotation[:, None],
        SearchOptions(candidates="network", keep=1), RefineOptions(steps=1, patience=1))
    assert result.search.candidates.shape == (3, 4, 3, 3)
    turned = with_half_turns(network)  # (3, 4, 3, 3)
    closest = _angle_deg(result.search_rotation[:, None].expand_as(turned), turned).amin(dim=1)
    assert bool((closest < 1e-3).all())


def test_alternating_rounds_never_lower_the_iou(scene):
    truth, rotation, translation, masks, camera = scene
    start = with_half_turns(rotation)[:, 1]  # the true rotation is among its half turns
    result = search_and_refine(truth, start, translation, masks, camera, None,
                               SearchOptions(grid=0, keep=1, rounds=2),
                               RefineOptions(steps=2, patience=2))
    assert len(result.rounds) == 2 and result.rounds[1] >= result.rounds[0]
    # The pose returned is the one its IoU was measured at: rendered again independently.
    resolution = RefineOptions().resolution
    small = camera.rescaled(resolution)
    targets = torch.nn.functional.interpolate(masks[:, None].double(), size=(small.height,
                                              small.width), mode="area")[:, 0]
    with torch.no_grad():
        drawn = render_assembly(result.assembly, result.rotation, result.translation,
                                SilhouetteRenderer(small, spp=64), level=2)
    torch.testing.assert_close(mask_iou(drawn, targets).double(), result.iou.double(),
                               atol=0.03, rtol=0)


def test_a_later_round_replaces_only_the_images_it_betters(scene):
    """Per image, the better of two rounds keeps its assembly, pose and IoU together."""
    from sq_mitsuba.inference.refine import RefineResult
    from sq_mitsuba.inference.search import better_of

    truth, rotation, translation, _, _ = scene
    other = Assembly(truth.params * 1.1)
    first = RefineResult(truth, rotation, translation, torch.tensor([0.1, 0.2, 0.3]),
                         torch.tensor([0.5, 0.9, 0.7]), 4)
    later = RefineResult(other, rotation.transpose(-1, -2), translation + 1,
                         torch.tensor([0.0, 0.0, 0.0]), torch.tensor([0.6, 0.8, 0.7]), 3)
    kept = better_of(first, later)
    assert kept.steps == 7 and torch.equal(kept.iou_before, first.iou_before)
    assert torch.equal(kept.iou_after, torch.tensor([0.6, 0.9, 0.7]))  # a tie keeps the first
    for k, source in enumerate((later, first, first)):
        assert torch.equal(kept.assembly.params[k], source.assembly.params[k].double())
        assert torch.equal(kept.rotation[k], source.rotation[k])
        assert torch.equal(kept.translation[k], source.translation[k])


def test_an_image_is_refined_as_it_would_be_alone(scene):
    """An image's search and refinement do not depend on its batch: its place (which once
    seeded its silhouette samples), its batch-mates' stopping and the stand-ins their counts
    pad it with. Image 1 alone (its two own primitives) and in a batch of three, second,
    padded with one stand-in, its neighbours of other shapes, give the same pose and shape."""
    from sq_mitsuba.model.existence import gathered_primitives

    truth, rotation, translation, masks, camera = scene
    start = with_half_turns(rotation)[:, 2] @ torch.linalg.matrix_exp(
        0.1 * torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
                           dtype=torch.float64))
    own = torch.tensor([[True, True, True], [True, True, False], [True, True, True]])
    padded = gathered_primitives(truth.params * torch.tensor([1.0, 1.2, 0.9],
                                 dtype=torch.float64)[:, None, None],
                                 torch.where(own, torch.arange(3), -1))
    search = SearchOptions(grid=0, keep=2, screen_steps=3, rounds=2)
    refine = RefineOptions(steps=12, patience=2, shape="extent")
    together = search_and_refine(Assembly(padded), start, translation, masks, camera, None,
                                 search, refine, own)
    alone = search_and_refine(Assembly(padded[1:2, :2]), start[1:2], translation[1:2],
                              masks[1:2], camera, None, search, refine)
    torch.testing.assert_close(together.rotation[1:2], alone.rotation, rtol=0, atol=1e-9)
    torch.testing.assert_close(together.translation[1:2], alone.translation, rtol=0, atol=1e-9)
    torch.testing.assert_close(together.iou[1:2], alone.iou, rtol=0, atol=1e-9)
    torch.testing.assert_close(together.assembly.params[1:2, :2], alone.assembly.params,
                               rtol=0, atol=1e-9)
    # The stand-in is rebuilt from the refined first row, shrunk, as the batch made it.
    torch.testing.assert_close(
        together.assembly.params[1:2], gathered_primitives(
            together.assembly.params[1:2], torch.tensor([[0, 1, -1]])), rtol=0, atol=0)


def test_bad_input_gives_one_line_errors(scene):
    truth, rotation, translation, masks, camera = scene
    candidates = pose_candidates(rotation, grid=8)

    def refused(match: str, **changes) -> None:
        arguments = dict(assembly=truth, candidates=candidates, translation=translation,
                         masks=masks, camera=camera)
        arguments.update(changes)
        with pytest.raises(ValueError, match=match) as error:
            search_poses(**arguments)
        assert "\n" not in str(error.value)

    refused(r"masks: size \(32, 32\) differs", masks=masks[:, ::2, ::2])
    empty = masks.clone()
    empty[1] = False
    refused(r"masks: item\(s\) \[1\] are empty", masks=empty)
    refused("candidates: K = 0", candidates=candidates[:, :0])
    nan = candidates.clone()
    nan[0, 3, 0, 0] = float("nan")
    refused("candidates: contains NaN", candidates=nan)
    refused("candidates: not rotation matrices", candidates=2 * candidates)
    refused(r"translation: the target must lie in front", translation=-translation)
    bad = with_half_turns(rotation)
    bad[1, 2, 1, 1] = float("nan")
    for hypotheses, match in ((bad, "hypotheses: contains NaN"),
                              (bad[:, :0], "hypotheses: K = 0"),
                              (bad[:2], r"hypotheses: expected shape \(3, K, 3, 3\)")):
        with pytest.raises(ValueError, match=match) as error:
            search_and_refine(truth, rotation, translation, masks, camera, hypotheses)
        assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match="spp: expected a positive integer"):
        PoseSilhouettes(camera, spp=0)


def test_search_and_refine_checks_its_inputs_before_touching_them(scene):
    """numpy masks, a list translation or no camera: a ValueError naming the argument, not
    an AttributeError from the first use."""
    truth, rotation, translation, masks, camera = scene
    arguments = dict(assembly=truth, rotation=rotation, translation=translation, masks=masks,
                     camera=camera)
    for name, bad, match in (("masks", masks.numpy(), "masks: expected a torch.Tensor"),
                             ("translation", translation.tolist(),
                              "translation: expected a torch.Tensor"),
                             ("camera", None, "camera: expected a Camera, got NoneType"),
                             ("assembly", truth.params, "assembly: expected an Assembly")):
        with pytest.raises(ValueError, match=f"^{match}") as error:
            search_and_refine(**{**arguments, name: bad})
        assert "\n" not in str(error.value)


def test_recentring_moves_the_translation_by_the_pinhole_shift_on_non_square_pixels():
    """A silhouette 6 px right of and 4 px above its target, fx != fy: the translation moves
    by (-6 z / fx, +4 z / fy) (pinhole, by hand); with the depth fitted too, a target of
    1.25 x the silhouette's size brings the target 1.25 x nearer (area ratio 1 / 1.5625)."""
    from sq_mitsuba.inference.search import _recentred

    camera = Camera(120.0, 70.0, 31.0, 25.0, 64, 48)
    centres = camera.pixel_centers(torch.float64)

    def disc(u: float, v: float, radius: float) -> torch.Tensor:
        return (((centres - centres.new_tensor([u, v])) ** 2).sum(-1) <= radius**2).double()

    translation = torch.tensor([[0.1, -0.05, 2.0]], dtype=torch.float64)
    u, v = camera.project(translation)[0].tolist()
    coverage, target = disc(u + 6, v - 4, 6)[None], disc(u, v, 6)[None]
    moved = _recentred(translation, coverage, target, camera, fit_depth=False)
    expected = translation + torch.tensor([[-6 * 2.0 / 120.0, 4 * 2.0 / 70.0, 0.0]],
                                          dtype=torch.float64)
    torch.testing.assert_close(moved, expected, atol=2e-3, rtol=0)  # discs on a pixel grid
    nearer = _recentred(translation, disc(u, v, 8)[None], disc(u, v, 10)[None], camera,
                        fit_depth=True)
    assert float(nearer[0, 2]) == pytest.approx(2.0 / 1.25, rel=0.03)
