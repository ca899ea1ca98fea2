"""Assemblies: fused occupancy against the unfused formula, surface masks, meshes, JSON, files."""

from __future__ import annotations

import json

import pytest
import torch
import trimesh

from sq_mitsuba.geometry.assembly import Assembly, ParameterRanges
from sq_mitsuba.geometry.icosphere import icosphere_angles
from sq_mitsuba.geometry.rotation import random_rotations
from sq_mitsuba.geometry.superquadric import (
    inside_outside_dual,
    surface_points_dual,
    taper,
    untaper,
)
from sq_mitsuba.model.losses import overlap

F64 = torch.float64


def random_assembly(batch: int = 2, count: int = 4, dtype=F64, seed: int = 0) -> Assembly:
    raw = torch.randn(batch, count, 16, generator=torch.Generator().manual_seed(seed),
                      dtype=dtype)
    return Assembly.from_raw(raw)


def two_boxes() -> Assembly:
    """Two overlapping axis-aligned boxes (shape 0): [-0.3, 0.3]x[-0.1, 0.1]^2 and a cube."""
    return Assembly.from_values(
        size=torch.tensor([[[0.3, 0.1, 0.1], [0.15, 0.15, 0.15]]], dtype=F64),
        shape=torch.zeros(1, 2, 2, dtype=F64),
        translation=torch.tensor([[[0.0, 0.0, 0.0], [0.25, 0.0, 0.0]]], dtype=F64),
    )


def test_from_raw_squashes_into_the_published_ranges():
    raw = 50 * torch.randn(3, 5, 16, generator=torch.Generator().manual_seed(1), dtype=F64)
    assembly = Assembly.from_raw(raw)
    assert ((assembly.size >= 0.01) & (assembly.size <= 0.5)).all()
    assert ((assembly.shape >= 0) & (assembly.shape <= 1)).all()
    assert (assembly.translation.abs() <= 0.5).all()
    assert (assembly.taper.abs() <= 0.9).all()
    torch.testing.assert_close(assembly.rotation_6d, raw[..., 8:14])
    half = Assembly.from_raw(raw, ParameterRanges(translation_scale=0.25))
    assert (half.translation.abs() <= 0.25).all()


def test_fused_inside_outside_matches_the_unfused_formula_and_gradients():
    assembly = random_assembly()
    points = 0.5 * torch.randn(2, 300, 3, generator=torch.Generator().manual_seed(2), dtype=F64)
    # Unfused reference: rotate, translate, untaper, then the public dual function.
    local = (points[:, None] - assembly.translation[:, :, None]) @ assembly.rotation
    reference = inside_outside_dual(untaper(local, assembly.taper, assembly.size),
                                    assembly.size, assembly.shape)
    torch.testing.assert_close(assembly.inside_outside(points), reference)


def test_fused_inside_outside_gradcheck():
    raw = torch.randn(2, 3, 16, generator=torch.Generator().manual_seed(3), dtype=F64,
                      requires_grad=True)
    points = (0.3 * torch.randn(2, 9, 3, generator=torch.Generator().manual_seed(4),
                                dtype=F64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda r, p: Assembly.from_raw(r).inside_outside(p),
                                    (raw, points))


def test_union_occupancy_inside_and_far_away():
    assembly = random_assembly(seed=5)
    # Points with f = 0.5 in each primitive (homogeneity), mapped into the assembly frame.
    eta, omega = icosphere_angles(2, F64)
    local = 0.5 * surface_points_dual(eta, omega, assembly.size, assembly.shape)
    inside = (taper(local, assembly.taper, assembly.size) @ assembly.rotation.transpose(-1, -2)
              + assembly.translation[:, :, None])
    occupancy = assembly.union_occupancy(inside.reshape(2, -1, 3))
    # sigmoid(10 (1 - 0.5)) = 0.9933: "about 1" at sharpness 10.
    assert occupancy.min().item() >= torch.sigmoid(torch.tensor(5.0, dtype=F64)).item() - 1e-9
    far = 10 + torch.rand(2, 500, 3, dtype=F64)
    assert assembly.union_occupancy(far).max().item() < 1e-6


def test_surface_points_lie_on_their_primitive():
    assembly = random_assembly(seed=6)
    points = assembly.surface_points()  # (2, 4, 642, 3)
    assert points.shape == (2, 4, 642, 3)
    f = assembly.inside_outside(points.reshape(2, -1, 3)).reshape(2, 4, 4, 642)
    own = torch.diagonal(f, dim1=1, dim2=2)  # (2, 642, 4)
    torch.testing.assert_close(own, torch.ones_like(own))


def test_no_retained_surface_point_lies_inside_the_other_box():
    assembly = two_boxes()
    points, inside_other = assembly.surface_points_with_mask()
    retained = points[~inside_other]
    assert 0 < inside_other.sum() < inside_other.numel()
    # Brute-force reference: the boxes' closed forms.
    in_first = ((retained.abs() < torch.tensor([0.3, 0.1, 0.1], dtype=F64)).all(-1))
    in_cube = (((retained - torch.tensor([0.25, 0, 0], dtype=F64)).abs() < 0.15).all(-1))
    owner = torch.arange(2)[None, :, None].expand_as(inside_other)[~inside_other]
    assert not (in_cube & (owner == 0)).any()
    assert not (in_first & (owner == 1)).any()
    # And points dropped do lie inside the other box.
    dropped_owner = torch.arange(2)[None, :, None].expand_as(inside_other)[inside_other]
    dropped = points[inside_other]
    in_other = torch.where(
        dropped_owner == 0,
        ((dropped - torch.tensor([0.25, 0, 0], dtype=F64)).abs() < 0.15).all(-1),
        (dropped.abs() < torch.tensor([0.3, 0.1, 0.1], dtype=F64)).all(-1))
    assert in_other.all()


def test_overlap_term():
    occupancy = torch.tensor([[[1.0, 0.0, 0.9], [1.0, 0.0, 0.2]]], dtype=F64)
    # Sums 2.0, 0.0, 1.1 -> relu(sum - 1.25) = 0.75, 0, 0 -> mean 0.25.
    torch.testing.assert_close(overlap(occupancy), torch.tensor(0.25, dtype=F64))
    assert two_boxes().occupancy(torch.tensor([[[0.2, 0.0, 0.0]]], dtype=F64)).sum() > 1.9


def test_primitive_meshes_are_watertight_with_642_vertices():
    assembly = random_assembly(batch=1, count=3, seed=7)
    vertices, faces = assembly.meshes()
    assert vertices.shape == (1, 3, 642, 3) and faces.shape == (1280, 3)
    for primitive in vertices[0]:
        mesh = trimesh.Trimesh(primitive.numpy(), faces.numpy(), process=False)
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    merged_vertices, merged_faces = assembly.merged_mesh()
    assert merged_vertices.shape == (1, 3 * 642, 3) and merged_faces.shape == (3 * 1280, 3)
    torch.testing.assert_close(merged_vertices[0, 642 + faces], vertices[0, 1, faces])
    torch.testing.assert_close(merged_vertices[0][merged_faces[1280:2560]],
                               vertices[0, 1][faces])


def test_box_mesh_volume_matches_the_box():
    box = Assembly.from_values(size=torch.tensor([[[0.4, 0.2, 0.1]]], dtype=F64),
                               shape=torch.zeros(1, 1, 2, dtype=F64))
    vertices, faces = box.meshes(level=4)
    mesh = trimesh.Trimesh(vertices[0, 0].numpy(), faces.numpy(), process=False)
    assert mesh.volume == pytest.approx(0.8 * 0.4 * 0.2, rel=0.02)


def test_rotation_and_translation_move_the_primitive():
    rotation = random_rotations(1, torch.Generator().manual_seed(8), dtype=F64)[None]
    size = torch.tensor([[[0.3, 0.2, 0.1]]], dtype=F64)
    shape = torch.tensor([[[0.4, 0.7]]], dtype=F64)
    translation = torch.tensor([[[0.1, -0.2, 0.05]]], dtype=F64)
    moved = Assembly.from_values(size, shape, translation, rotation)
    local = surface_points_dual(*[torch.linspace(-1.5, 1.5, 20, dtype=F64)] * 2,
                                size[0], shape[0])
    world = local @ rotation[0, 0].T + translation[0]
    torch.testing.assert_close(moved.inside_outside(world), torch.ones(1, 1, 20, dtype=F64))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_json_round_trip_is_exact(tmp_path, dtype):
    assembly = random_assembly(batch=2, count=5, dtype=dtype, seed=9)
    path = assembly.save(tmp_path / "assembly.json", item=1)
    loaded = Assembly.load(path)
    assert loaded.params.dtype == dtype
    assert torch.equal(loaded.params[0], assembly.params[1])
    data = json.loads(path.read_text())
    assert set(data["primitives"][0]) == {"size", "shape", "translation", "rotation_6d",
                                          "taper"}


def test_json_errors_name_the_problem(tmp_path):
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(ValueError, match=r"broken\.json"):
        Assembly.load(broken)
    data = random_assembly(batch=1, count=1).to_dict()
    data["primitives"][0]["shape"] = [0.5]
    with pytest.raises(ValueError, match=r"primitives\[0\]\.shape"):
        Assembly.from_dict(data)
    data["primitives"][0]["shape"] = [0.5, float("nan")]
    with pytest.raises(ValueError, match="shape"):
        Assembly.from_dict(data)
    data["primitives"][0]["shape"] = [True, False]  # JSON's true is no number
    with pytest.raises(ValueError, match=r"primitives\[0\]\.shape"):
        Assembly.from_dict(data)
    with pytest.raises(FileNotFoundError):
        Assembly.load(tmp_path / "missing.json")


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".glb", ".stl"])
def test_export_writes_loadable_meshes(tmp_path, suffix):
    assembly = random_assembly(batch=1, count=2, seed=10)
    path = assembly.export(tmp_path / f"assembly{suffix}")
    loaded = trimesh.load(path, force="mesh", process=False)
    assert len(loaded.faces) == 2 * 1280
    # Only the final file is left: no temporary files.
    assert [p.name for p in tmp_path.iterdir()] == [path.name]
    assert loaded.bounds[1].max() < 1.0


def test_export_rejects_unknown_format(tmp_path):
    with pytest.raises(ValueError, match="format"):
        random_assembly(batch=1).export(tmp_path / "assembly.xyz")


@pytest.mark.parametrize(("build", "name"), [
    (lambda: Assembly(torch.zeros(2, 16)), "params"),
    (lambda: Assembly(torch.zeros(1, 2, 15)), "params"),
    (lambda: Assembly(torch.zeros(1, 2, 16, dtype=torch.int64)), "params"),
    (lambda: Assembly(torch.full((1, 2, 16), float("nan"))), "params"),
    (lambda: Assembly.from_raw(torch.zeros(2, 16)), "raw"),
    (lambda: Assembly.from_values(torch.ones(1, 2, 3), torch.ones(1, 3, 2)), "shape"),
    (lambda: Assembly.from_values(-torch.ones(1, 2, 3), torch.ones(1, 2, 2)), "size"),
    (lambda: Assembly.from_values(torch.ones(1, 2, 3), torch.ones(1, 2, 2),
                                  rotation=torch.zeros(1, 2, 6)), "rotation"),
    (lambda: random_assembly().inside_outside(torch.zeros(3, 5, 3, dtype=F64)), "points"),
    (lambda: random_assembly().inside_outside(torch.zeros(2, 5, 3)), "points"),
    (lambda: random_assembly().union_occupancy(torch.zeros(2, 5, 2, dtype=F64)), "points"),
])
def test_bad_input_names_the_argument(build, name):
    with pytest.raises(ValueError, match=name):
        build()


@pytest.mark.parametrize(("column", "value", "problem"), [
    (0, 0.0, "size must be positive"), (3, 1.5, "shape must lie in"),
    (14, -1.0, "taper"), (8, 0.0, "degenerate 6D"),
])
def test_out_of_range_values_are_refused_unless_value_checks_are_off(column, value, problem):
    """The constructor's range checks read the values (on a GPU, a wait each), so they follow
    the value-check switch, as the NaN scan does."""
    from sq_mitsuba.checks import value_checks

    params = random_assembly(batch=1, count=2).params.clone()
    params[0, 1, column] = value
    if column == 8:  # both 6D rows zero
        params[0, 1, 8:14] = 0.0
    with pytest.raises(ValueError, match=problem):
        Assembly(params)
    with value_checks(False):
        assert Assembly(params).params is params


def test_a_rotated_assembly_is_the_assembly_at_turned_points():
    """Turning an assembly by Q moves its occupancy field and its surface with it: occupancy
    of the turned one at Q x equals the original's at x, and its surface samples are Q times
    the original's (the same icosphere parameters)."""
    assembly = random_assembly(batch=3, count=4, seed=11)
    turn = random_rotations(3, torch.Generator().manual_seed(12), dtype=F64)
    turned = assembly.rotated(turn)
    points = 0.4 * torch.randn(3, 200, 3, generator=torch.Generator().manual_seed(13),
                               dtype=F64)
    torch.testing.assert_close(turned.union_occupancy(points @ turn.transpose(1, 2)),
                               assembly.union_occupancy(points))
    torch.testing.assert_close(turned.surface_points(2),
                               assembly.surface_points(2) @ turn[:, None].transpose(-1, -2))
    torch.testing.assert_close(turned.size, assembly.size)
    back = turned.rotated(turn.transpose(1, 2))
    torch.testing.assert_close(back.rotation, assembly.rotation)  # 6D comes back normalised
    torch.testing.assert_close(back.translation, assembly.translation)
    with pytest.raises(ValueError, match="rotation"):
        assembly.rotated(turn[:2])
    with pytest.raises(ValueError, match="rotation"):
        assembly.rotated(turn.float())
    # A reflection or a scaled matrix is no turn: the frames would be rebuilt as rotations
    # while the centres moved by the matrix as given.
    for matrix in (turn @ torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=F64)), 2 * turn):
        with pytest.raises(ValueError, match=r"^rotation: not rotation matrices"):
            assembly.rotated(matrix)
        with pytest.raises(ValueError, match=r"^rotation: not rotation matrices"):
            Assembly.from_values(size=assembly.size[:1], shape=assembly.shape[:1],
                                 rotation=matrix[:1, None].expand(1, 4, 3, 3))


def test_a_scaled_assembly_is_the_assembly_at_scaled_points():
    """Scaling an assembly by s about its origin scales its inside-outside field with it (the
    scaled one at s x equals the original at x: tapers and exponents are relative) and its
    surface samples; a factor per item; bad factors are named."""
    assembly = random_assembly(batch=3, count=4, seed=21)
    points = 0.4 * torch.randn(3, 200, 3, generator=torch.Generator().manual_seed(22),
                               dtype=F64)
    factor = torch.tensor([0.5, 2.0, 7.3], dtype=F64)
    scaled = assembly.scaled(factor)
    torch.testing.assert_close(scaled.inside_outside(points * factor[:, None, None]),
                               assembly.inside_outside(points))
    torch.testing.assert_close(scaled.surface_points(2),
                               assembly.surface_points(2) * factor[:, None, None, None])
    torch.testing.assert_close(assembly.scaled(3.0).size, 3.0 * assembly.size)
    for name in ("shape", "rotation_6d", "taper"):  # relative: the same numbers
        assert torch.equal(getattr(scaled, name), getattr(assembly, name)), name
    torch.testing.assert_close(scaled.scaled(1.0 / factor).params, assembly.params)
    # Differentiable in the factor: d(sum of sizes)/d(factor_b) = item b's sum of sizes.
    free = factor.clone().requires_grad_()
    assembly.scaled(free).size.sum().backward()
    torch.testing.assert_close(free.grad, assembly.size.sum((1, 2)))
    for bad in (0.0, -1.0, float("nan"), float("inf"), True, "2"):
        with pytest.raises(ValueError, match=r"^factor: "):
            assembly.scaled(bad)
    single = Assembly(assembly.params.float())
    for bad in (1e39, 1e-320):  # past float32's range: an infinite or a zero size
        with pytest.raises(ValueError, match=r"^factor: .* past torch.float32's range"):
            single.scaled(bad)
    for bad in (factor[:2], factor.float(), torch.tensor([1.0, 0.0, 1.0], dtype=F64),
                torch.tensor(2.0, dtype=F64)):
        with pytest.raises(ValueError, match=r"^factor: "):
            assembly.scaled(bad)
