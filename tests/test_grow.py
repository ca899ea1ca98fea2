"""A primitive grown where the silhouettes miss the masks.

References: a known assembly rendered by Mitsuba from known poses (the masks), started without
one of its parts, whose true place and direction the grown primitive must find; a residual
image of known pieces; points placed on known rays."""

from __future__ import annotations

import math

import torch
from output_checks import one_torch_thread  # noqa: F401 (autouse fixture)

from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.metrics import mask_iou
from sq_mitsuba.geometry.rotation import random_rotations
from sq_mitsuba.inference.grow import box_primitive, grow_primitive, missed_pieces, piece_points
from sq_mitsuba.inference.sequence import SequenceOptions, fit_sequence
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

CAMERA = Camera.default(64)


def _spacecraft() -> Assembly:
    """A bus and a long thin boom off one side (the part to grow back)."""
    def tensor(rows: list) -> torch.Tensor:
        return torch.tensor([rows], dtype=torch.float64)

    return Assembly.from_values(
        size=tensor([[0.16, 0.14, 0.12], [0.30, 0.03, 0.03]]),
        shape=tensor([[0.2, 0.2], [0.1, 0.1]]),
        translation=tensor([[0.0, 0.0, 0.0], [0.34, 0.05, 0.0]]))


def _pass(count: int = 6) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    body = _spacecraft()
    rotations = random_rotations(count, torch.Generator().manual_seed(5), torch.float64)
    translations = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64).expand(count, 3).clone()
    renderer = SilhouetteRenderer(CAMERA, spp=16)
    with torch.no_grad():
        masks = render_assembly(Assembly(body.params.expand(count, -1, -1)), rotations,
                                translations, renderer, 3)
    return rotations, translations, (masks > 0.5).double()


def test_the_largest_missed_pieces_come_first():
    targets = torch.zeros(2, 16, 16, dtype=torch.float64)
    targets[0, 2:4, 2:6] = 1  # 8 pixels
    targets[1, 8:14, 8:12] = 1  # 24 pixels, half of them covered
    targets[1, 0:2, 0:2] = 1  # 4 pixels, below min_pixels=5
    coverage = torch.zeros_like(targets)
    coverage[1, 8:11, 8:12] = 1
    pieces = missed_pieces(coverage, targets, min_pixels=5, count=3)
    assert [(frame, len(pixels)) for frame, pixels in pieces] == [(1, 12), (0, 8)]
    assert set(map(tuple, pieces[0][1].tolist())) == {(r, c) for r in range(11, 14)
                                                       for c in range(8, 12)}


def test_a_piece_is_placed_at_the_depth_the_other_frames_see():
    """Pixels of frame 0 whose true points lie 0.3 nearer than the target's centre: the
    frames turned about the vertical see those points, and only them, in their masks."""
    rotations = torch.stack([torch.linalg.matrix_exp(torch.tensor(
        [[0.0, 0.0, a], [0.0, 0.0, 0.0], [-a, 0.0, 0.0]], dtype=torch.float64))
        for a in (0.0, 0.5, -0.5, 1.0)])
    translations = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64).expand(4, 3).clone()
    truth = torch.tensor([[0.1, 0.05, -0.3], [0.15, 0.05, -0.3]], dtype=torch.float64)
    camera_points = truth @ rotations.transpose(1, 2) + translations[:, None]
    u = camera_points[..., 0] / camera_points[..., 2] * CAMERA.fx + CAMERA.cx
    v = camera_points[..., 1] / camera_points[..., 2] * CAMERA.fy + CAMERA.cy
    targets = torch.zeros(4, CAMERA.height, CAMERA.width, dtype=torch.float64)
    for frame in range(4):
        targets[frame, v[frame].floor().long(), u[frame].floor().long()] = 1
    pixels = torch.stack([v[0].floor().long(), u[0].floor().long()], 1)
    points = piece_points(pixels, 0, targets, CAMERA, rotations, translations,
                          depth_span=0.6, depths=49, grow_pixels=0)
    # Along frame 0's line of sight the points are found to within a depth step (0.025);
    # across it to within the pixel they were seen in.
    assert torch.allclose(points[:, 2], truth[:, 2], atol=0.03)
    assert torch.allclose(points[:, :2], truth[:, :2], atol=2.0 * 2.0 / CAMERA.fx)


def test_a_box_spans_its_points_along_their_principal_axes():
    direction = torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64) / math.sqrt(2)
    points = torch.linspace(-0.2, 0.2, 41, dtype=torch.float64)[:, None] * direction + \
        torch.tensor([0.1, -0.1, 0.05], dtype=torch.float64)
    box = Assembly(box_primitive(points, thickness=0.02)[None, None])
    assert torch.allclose(box.translation[0, 0], torch.tensor([0.1, -0.1, 0.05],
                                                              dtype=torch.float64), atol=1e-9)
    assert torch.allclose(box.size[0, 0], torch.tensor([0.2, 0.02, 0.02],
                                                       dtype=torch.float64), atol=1e-9)
    axis = box.rotation[0, 0][:, 0]
    assert abs(float(axis @ direction)) > 1 - 1e-9


def test_a_missing_boom_is_grown_back_where_it_belongs():
    rotations, translations, masks = _pass()
    truth = _spacecraft()
    bus = Assembly(truth.params[:, :1].clone())
    grown, before, after = grow_primitive(bus, rotations, translations, masks, CAMERA, spp=8)
    assert grown.num_primitives == 2 and after > before + 0.05
    boom = grown.params[0, 1]
    centre = Assembly(boom[None, None]).translation[0, 0]
    assert float((centre - truth.translation[0, 1]).norm()) < 0.06
    direction = Assembly(boom[None, None]).rotation[0, 0][:, 0]
    assert abs(float(direction[0])) > math.cos(math.radians(10))  # along the boom (x)
    # Nothing missed: the assembly comes back as it was.
    same, before, after = grow_primitive(truth, rotations, translations, masks, CAMERA, spp=8)
    assert same is truth and before == after


def test_the_joint_fit_grows_what_the_start_lacks():
    rotations, translations, masks = _pass()
    bus = Assembly(_spacecraft().params[:, :1].clone())
    options = SequenceOptions(steps=10, patience=10, spp=8, shape="free")
    plain = fit_sequence(bus, rotations, translations, masks, CAMERA, options)
    grown = fit_sequence(bus, rotations, translations, masks, CAMERA,
                         SequenceOptions(steps=10, patience=10, spp=8, grow=1, grow_steps=10))
    assert plain[0].num_primitives == 1 and grown[0].num_primitives == 2
    renderer = SilhouetteRenderer(CAMERA, spp=16)

    def iou(result: tuple) -> float:
        assembly, rotation, translation = result[:3]
        with torch.no_grad():
            coverage = render_assembly(Assembly(assembly.params.expand(len(rotation), -1, -1)),
                                       rotation, translation, renderer, 3)
        return float(mask_iou(coverage, masks).mean())

    assert iou(grown) > iou(plain) + 0.05 and iou(grown) > 0.85


def test_bad_input_is_a_one_line_error():
    rotations, translations, masks = _pass(2)
    bus = Assembly(_spacecraft().params[:, :1].clone())
    for args, name in (
            ((Assembly(bus.params.expand(2, -1, -1)), rotations, translations, masks), "assembly"),
            ((bus, rotations, translations[:1], masks), "translation"),
            ((bus, rotations, translations, masks[:, :32]), "targets"),
            ((bus, rotations, translations, masks * float("nan")), "targets")):
        try:
            grow_primitive(*args, CAMERA)
        except ValueError as error:
            assert str(error).startswith(name) and "\n" not in str(error)
        else:
            raise AssertionError(f"no error for a bad {name}")
