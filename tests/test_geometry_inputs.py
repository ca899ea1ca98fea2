"""Bad input to the geometry layer (the API sweep's A1, A4-A10, B4, C2): one line naming the
argument, before any work; and valid inputs that came back wrong now give the right value.

References: rotations are compared with matrices written out from Rodrigues' formula with
Python's ``math`` (no code under test); refusals with the one line they must print."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sq_mitsuba.checks import value_checks
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.icosphere import icosphere_faces
from sq_mitsuba.geometry.image_turns import rotate_batch, z_rotation
from sq_mitsuba.geometry.metrics import (
    camera_frame_chamfer,
    mask_iou,
    rotation_error_deg,
    volumetric_iou,
)
from sq_mitsuba.geometry.pose import invert_pose, relative_pose
from sq_mitsuba.geometry.rotation import (
    axis_angle_to_matrix,
    mean_rotation,
    quaternion_to_matrix,
    random_quaternions,
    random_rotations,
)
from sq_mitsuba.geometry.so3_grid import covering_angle_deg, nearest_grid_index, so3_grid

F64 = torch.float64
EYE = torch.eye(3, dtype=F64)[None]
NOT_ROTATION = r"not rotation matrices"


def _x_turn(angle: float) -> torch.Tensor:
    """Rotation by ``angle`` about x, written out (float64)."""
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=F64)


def _assembly(dtype: torch.dtype = torch.float32) -> Assembly:
    return Assembly.from_values(size=torch.tensor([[[0.4, 0.2, 0.1]]], dtype=dtype),
                                shape=torch.tensor([[[0.5, 0.5]]], dtype=dtype))


# ---------------------------------------------------------------- A1: shared cached faces

def test_editing_the_faces_handed_out_leaves_later_meshes_alone():
    assembly = _assembly()
    before = icosphere_faces(2).clone()
    _, faces = assembly.meshes(2)
    faces[:] = faces[:, [0, 2, 1]].clone()  # a caller flips "its" faces in place
    icosphere_faces(2).zero_()
    assert torch.equal(assembly.meshes(2)[1], before)
    assert torch.equal(icosphere_faces(2), before)


# ---------------------------------------------------------------- A4: norms and angles

@pytest.mark.parametrize(("scale", "dtype"), [(1e-30, torch.float32), (1e20, torch.float32),
                                              (1e-200, F64), (1e300, F64)])
def test_quaternions_of_tiny_or_huge_norm_give_the_unit_quaternions_rotation(scale, dtype):
    unit = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.5**0.5, 0.5**0.5, 0.0, 0.0]], dtype=F64)
    expected = torch.stack([EYE[0], _x_turn(math.pi / 2)]).to(dtype)
    torch.testing.assert_close(quaternion_to_matrix((unit * scale).to(dtype)), expected)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("angle", [1e3, 1e5, 1e10, 1e20, 3e38])
def test_large_angles_are_turns_about_the_axis_not_nan(angle, dtype):
    """matrix_exp gave NaN from 1e10 rad (float32) and drifted off SO(3) before: the angle
    is periodic, so the float's exact value wraps into [-pi, pi]."""
    vector = torch.tensor([angle, 0.0, 0.0], dtype=dtype)
    exact = float(vector[0])  # the angle the float holds
    # torch's float32 matrix_exp itself is off by up to 3e-5 (at about 0.5 rad).
    tolerance = 5e-5 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(axis_angle_to_matrix(vector).double(), _x_turn(exact),
                               atol=tolerance, rtol=0)


def test_a_large_angle_off_an_axis_is_a_rotation_about_it():
    # A float32 vector whose squared norm overflows: its axis (1, 1, 0) stays fixed.
    rotation = axis_angle_to_matrix(torch.tensor([1e20, 1e20, 0.0])).double()
    torch.testing.assert_close(rotation.T @ rotation, EYE[0], atol=1e-5, rtol=0)
    axis = torch.tensor([1.0, 1.0, 0.0], dtype=F64) / 2**0.5
    torch.testing.assert_close(rotation @ axis, axis, atol=1e-6, rtol=0)
    assert float(torch.linalg.det(rotation)) == pytest.approx(1.0, abs=1e-5)


def test_angles_up_to_pi_are_unchanged_and_differentiable_at_zero():
    vectors = torch.tensor([[0.0, 0.0, 0.0], [0.3, -1.2, 2.0], [math.pi, 0.0, 0.0]], dtype=F64)
    skew = torch.zeros(3, 3, 3, dtype=F64)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -vectors[:, 2], vectors[:, 1], -vectors[:, 0]
    assert torch.equal(axis_angle_to_matrix(vectors),
                       torch.linalg.matrix_exp(skew - skew.transpose(-1, -2)))
    zero = torch.zeros(3, dtype=F64, requires_grad=True)
    axis_angle_to_matrix(zero)[1, 2].backward()
    assert zero.grad.tolist() == [-1.0, 0.0, 0.0]  # d R[1, 2] / d w_x = -1 at 0


# ---------------------------------------------------------------- A5: not rotations

@pytest.mark.parametrize("matrix", [-EYE, 2 * EYE, torch.zeros(1, 3, 3, dtype=F64),
                                    torch.full((1, 3, 3), math.nan, dtype=F64)])
def test_rotation_metrics_and_helpers_refuse_matrices_that_are_not_rotations(matrix):
    t = torch.tensor([[0.0, 0.0, 2.0]], dtype=F64)
    points = torch.rand(1, 10, 3, dtype=F64)
    bad = r"(not rotation matrices|contains NaN)"
    with pytest.raises(ValueError, match=rf"^pred_rotation: {bad}"):
        rotation_error_deg(matrix, EYE)
    with pytest.raises(ValueError, match=rf"^gt_rotation: {bad}"):
        rotation_error_deg(EYE, matrix)
    with pytest.raises(ValueError, match=rf"^symmetries: {bad}"):
        rotation_error_deg(EYE, EYE, symmetries=matrix)
    with pytest.raises(ValueError, match=rf"^rotations: {bad}"):
        nearest_grid_index(matrix.expand(2, 3, 3), so3_grid(64))
    with pytest.raises(ValueError, match=rf"^grid: {bad}"):
        nearest_grid_index(EYE, torch.cat([so3_grid(8), matrix]))
    with pytest.raises(ValueError, match=rf"^rotation: {bad}"):
        invert_pose(matrix[0], t[0])
    with pytest.raises(ValueError, match=rf"^a: rotation: {bad}"):
        relative_pose(matrix, t, EYE, t)
    with pytest.raises(ValueError, match=rf"^b: rotation: {bad}"):
        relative_pose(EYE, t, matrix, t)
    with pytest.raises(ValueError, match=rf"^rotations: {bad}"):
        mean_rotation(matrix.expand(2, 3, 3))
    with pytest.raises(ValueError, match=rf"^pred_rotation: {bad}"):
        camera_frame_chamfer(points, matrix, t, points, EYE, t)


def test_rotation_checks_are_value_checks_and_genuine_rotations_pass():
    with value_checks(False):  # a hot loop's choice: the arithmetic's own answer
        assert float(rotation_error_deg(-EYE, EYE)[0]) == pytest.approx(180.0)
        assert torch.equal(invert_pose(2 * EYE[0], torch.ones(3, dtype=F64))[0], 2 * EYE[0])
    rotations = random_rotations(6, torch.Generator().manual_seed(5))  # float32 readings
    truth = rotations.double()
    assert float(rotation_error_deg(rotations, truth).max()) < 1e-3
    assert float(rotation_error_deg(rotations, truth, EYE.float()).max()) < 1e-3
    grid = so3_grid(64)
    assert torch.equal(nearest_grid_index(grid[5:7].float(), grid), torch.tensor([5, 6]))


def test_symmetries_of_another_batch_or_none_are_refused():
    rotations = random_rotations(4, torch.Generator().manual_seed(6), F64)
    for symmetries in (EYE.expand(3, 2, 3, 3), EYE[:0], EYE.expand(4, 1, 1, 3, 3)):
        with pytest.raises(ValueError, match=r"^symmetries: expected \(S, 3, 3\) or \(4, S, 3, "
                                             r"3\) with S >= 1, got "):
            rotation_error_deg(rotations, rotations, symmetries)


def test_grid_lookup_refuses_numpy_and_an_empty_grid():
    with pytest.raises(ValueError, match=r"^rotations: expected a torch.Tensor, got ndarray$"):
        nearest_grid_index(np.eye(3)[None], so3_grid(8))
    with pytest.raises(ValueError, match=r"^grid: expected \(N, 3, 3\) with N >= 1, got "
                                         r"\(0, 3, 3\)$"):
        nearest_grid_index(EYE, so3_grid(8)[:0])


# ---------------------------------------------------------------- A6: IoU of NaN

def test_iou_of_nan_is_an_error_not_a_perfect_score():
    half = torch.zeros(1, 8, 8)
    half[:, :4] = 1.0
    with pytest.raises(ValueError, match=r"^prediction: contains NaN or infinite values$"):
        mask_iou(torch.full((1, 8, 8), math.nan), torch.zeros(1, 8, 8))
    with pytest.raises(ValueError, match=r"^target: contains NaN or infinite values$"):
        mask_iou(half, torch.full((1, 8, 8), math.nan))
    for threshold in (math.nan, math.inf, "0.5", None, True):
        with pytest.raises(ValueError, match=r"^threshold: expected a finite number, got "):
            mask_iou(half, torch.zeros(1, 8, 8), threshold=threshold)
    with pytest.raises(ValueError, match=r"^prediction: expected a torch.Tensor, got ndarray$"):
        mask_iou(np.zeros((1, 8, 8)), torch.zeros(1, 8, 8))
    with pytest.raises(ValueError, match=r"^prediction: expected shape \(\.\.\., N, M\), got "
                                         r"\(8,\)$"):
        mask_iou(torch.zeros(8), torch.zeros(8))
    with pytest.raises(ValueError, match=r"^pred_inside: contains NaN or infinite values$"):
        volumetric_iou(torch.full((1, 10), math.nan), torch.zeros(1, 10))
    with pytest.raises(ValueError, match=r"^pred_inside: expected a torch.Tensor, got ndarray$"):
        volumetric_iou(np.zeros((1, 10)), torch.zeros(1, 10))
    # Bool masks and a numpy threshold still score as before.
    assert float(mask_iou(half > 0, half > 0, threshold=np.float32(0.5))[0]) == 1.0
    assert float(mask_iou(half, torch.ones(1, 8, 8))[0]) == 0.5


# ---------------------------------------------------------------- A7: image turns

def test_turning_refuses_images_that_are_not_square_and_angles_of_another_shape():
    with pytest.raises(ValueError, match=r"^images: expected square images \(B, C, S, S\), got "
                                         r"\(1, 1, 32, 64\)$"):
        rotate_batch(torch.zeros(1, 1, 32, 64), torch.tensor([math.pi / 2]))
    with pytest.raises(ValueError, match=r"^images: expected shape \(\.\.\., N, M, K, L\), got "
                                         r"\(1, 32, 32\)$"):
        rotate_batch(torch.zeros(1, 32, 32), torch.tensor([0.0]))
    with pytest.raises(ValueError, match=r"^images: expected a floating-point dtype, got "
                                         r"torch.uint8$"):
        rotate_batch(torch.zeros(1, 1, 8, 8, dtype=torch.uint8), torch.tensor([0.0]))
    with pytest.raises(ValueError, match=r"^angles: expected shape \(2,\), got \(1,\)$"):
        rotate_batch(torch.zeros(2, 1, 8, 8), torch.tensor([0.0]))
    with pytest.raises(ValueError, match=r"^angles: expected a torch.Tensor, got float$"):
        rotate_batch(torch.zeros(1, 1, 8, 8), 0.5)
    with pytest.raises(ValueError, match=r"^angles: expected shape \(B,\), got \(2, 2\)$"):
        z_rotation(torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"^angles: expected a floating-point dtype, got "
                                         r"torch.int64$"):
        z_rotation(torch.zeros(3, dtype=torch.int64))
    torch.testing.assert_close(z_rotation(torch.tensor([0.5], dtype=F64))[0],
                               torch.tensor([[math.cos(0.5), -math.sin(0.5), 0.0],
                                             [math.sin(0.5), math.cos(0.5), 0.0],
                                             [0.0, 0.0, 1.0]], dtype=F64))


# ---------------------------------------------------------------- A8: save what load reads

def test_save_refuses_what_load_would_refuse_and_writes_nothing(tmp_path):
    with value_checks(False):
        nan = Assembly(torch.full((1, 1, 16), math.nan))
        small = Assembly(_assembly().params * torch.tensor([-1.0] + [1.0] * 15))
    with pytest.raises(ValueError, match=r"^params: item 0 contains NaN or infinite values$"):
        nan.save(tmp_path / "nan.json")
    with value_checks(False), pytest.raises(ValueError, match=r"^params: size must be "
                                                              r"positive$"):
        small.save(tmp_path / "negative.json")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_assemblies_load_back_as_saved(tmp_path, dtype):
    assembly = Assembly(_assembly().params.to(dtype))
    loaded = Assembly.load(assembly.save(tmp_path / "half.json"))
    assert loaded.params.dtype == dtype and torch.equal(loaded.params, assembly.params)


# ---------------------------------------------------------------- A9: integer dtypes

def test_random_quaternions_refuse_integer_dtypes_and_non_counts():
    with pytest.raises(ValueError, match=r"^dtype: expected a floating-point dtype, got "
                                         r"torch.int64$"):
        random_quaternions(3, dtype=torch.int64)
    for n in (2.5, True, "3", -1):
        with pytest.raises(ValueError, match=r"^n: expected an integer >= 0, got "):
            random_rotations(n)
    assert random_quaternions(np.int64(2)).shape == (2, 4)


# ---------------------------------------------------------------- A10: sharpness

@pytest.mark.parametrize("sharpness", [math.nan, -10.0, 0.0, math.inf, "10", True, None,
                                       torch.tensor([10.0, 10.0]), torch.tensor(10),
                                       torch.tensor(math.nan)])
def test_occupancy_refuses_a_sharpness_that_is_not_a_positive_number(sharpness):
    assembly = _assembly()
    with pytest.raises(ValueError, match=r"^sharpness: expected a finite number > 0, got "):
        assembly.occupancy(torch.zeros(1, 4, 3), sharpness)
    with pytest.raises(ValueError, match=r"^sharpness: expected a finite number > 0, got "):
        assembly.union_occupancy(torch.zeros(1, 4, 3), sharpness)


def test_occupancy_takes_numbers_and_a_zero_d_tensor_alike():
    assembly, points = _assembly(), torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    expected = assembly.union_occupancy(points, 10.0)
    assert expected[0, 0] > 0.99 and expected[0, 1] < 0.01  # inside, then outside
    for sharpness in (10, np.float32(10.0), torch.tensor(10.0)):
        torch.testing.assert_close(assembly.union_occupancy(points, sharpness), expected)


# ---------------------------------------------------------------- B4: no primitives

def test_an_assembly_of_no_primitives_is_refused():
    with pytest.raises(ValueError, match=r"^params: expected shape \(B, M, 16\) with M >= 1 "
                                         r"primitives, got \(1, 0, 16\)$"):
        Assembly.from_values(size=torch.zeros(1, 0, 3), shape=torch.zeros(1, 0, 2))
    assert Assembly(torch.zeros(0, 2, 16)).batch_size == 0  # an empty batch stays allowed


# ---------------------------------------------------------------- C2: bools as counts

def test_bools_are_not_counts_or_levels_and_numpy_integers_are():
    assembly = _assembly()
    for call in (lambda: so3_grid(True), lambda: so3_grid(np.bool_(True)),
                 lambda: covering_angle_deg(math.nan)):
        with pytest.raises(ValueError, match=r"^count: expected a positive integer, got "):
            call()
    for call in (lambda: assembly.surface_points(level=True), lambda: assembly.meshes(True),
                 lambda: icosphere_faces(False)):
        with pytest.raises(ValueError, match=r"^level: expected an integer in \[0, 7\], got "):
            call()
    assert torch.equal(so3_grid(np.int64(8)), so3_grid(8))
    assert torch.equal(assembly.surface_points(np.int64(1)), assembly.surface_points(1))


@pytest.mark.parametrize(("low", "high", "expected"), [
    (1, None, "a positive integer"), (0, None, "an integer >= 0"),
    (1, 360, r"an integer in \[1, 360\]"), (None, 5, "an integer <= 5"),
])
def test_one_integer_check_for_every_count(low, high, expected):
    """check_int (every count, size and level of the API): numpy's integers as Python's, a
    bool, a float, a string or a value out of range refused in one line naming the argument."""
    from sq_mitsuba.checks import check_int

    assert check_int("k", np.int64(3), low, high) == 3
    assert type(check_int("k", np.int32(3), low, high)) is int
    out_of_range = ([low - 1] if low is not None else []) + ([high + 1] if high is not None
                                                            else [])
    for bad in (True, 3.0, "3", None, *out_of_range):
        with pytest.raises(ValueError, match=rf"^k: expected {expected}, got "):
            check_int("k", bad, low, high)


def test_a_camera_built_from_numpy_integers_holds_python_integers():
    """``Camera(..., width=np.int64(64))`` was refused ("expected a positive integer, got 64")
    where a dataset or a predictor took numpy's integers: taken, and stored as Python's."""
    from sq_mitsuba.geometry.camera import Camera

    camera = Camera(80.0, 80.0, 32.0, 32.0, np.int64(64), np.int64(64))
    assert camera == Camera(80.0, 80.0, 32.0, 32.0, 64, 64) and type(camera.width) is int
    assert Camera.default(np.int64(64)) == Camera.default(64)
    assert camera.rescaled(np.int64(32), np.int32(32)) == camera.rescaled(32, 32)


def test_the_primal_form_and_the_taper_refuse_what_makes_them_infinite():
    """Shape 0 gave exponents 2 / 0 (f not finite); a taper |k| >= 1 or a3 = 0 was taken by
    taper (untaper and the assembly refuse it)."""
    from sq_mitsuba.geometry.superquadric import inside_outside, taper

    points = torch.rand(1, 5, 3, dtype=torch.float64)
    size = torch.tensor([[0.3, 0.2, 0.1]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^shape: the primal form needs e > 0"):
        inside_outside(points, size, torch.tensor([[0.0, 0.5]], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"^taper: \|k\| must be < 1"):
        taper(points, torch.tensor([[1.0, 0.0]], dtype=torch.float64), size)
    with pytest.raises(ValueError, match=r"^size: a3 must be positive"):
        taper(points, torch.tensor([[0.5, 0.0]], dtype=torch.float64),
              torch.tensor([[0.3, 0.2, 0.0]], dtype=torch.float64))
    assert torch.isfinite(inside_outside(points, size, torch.tensor([[0.1, 0.5]],
                                                                    dtype=torch.float64))).all()


def test_small_helpers_name_their_bad_inputs():
    """Each failed inside torch, numpy or pathlib, or named the wrong thing."""
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.geometry.metrics import chamfer_l1
    from sq_mitsuba.geometry.so3_grid import with_half_turns
    from sq_mitsuba.geometry.superquadric import surface_points_dual

    with pytest.raises(ValueError, match=r"^rotations: expected a torch.Tensor, got ndarray$"):
        with_half_turns(np.eye(3)[None])
    with pytest.raises(ValueError, match=r"^rotations: expected shape \(\.\.\., 3, 3\)"):
        with_half_turns(torch.zeros(3))
    points = torch.rand(1, 5, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^pred_mask: expected a torch.Tensor, got ndarray$"):
        chamfer_l1(points, points, pred_mask=np.ones((1, 5), bool))
    with pytest.raises(ValueError, match=r"^pred: expected shape \(\.\.\., N, 3\), got "
                                         r"\(100, 3\)$"):
        chamfer_l1(torch.rand(100, 3), torch.rand(120, 3))
    with pytest.raises(ValueError, match=r"^eta, omega: one of each per point, got 10 and 5$"):
        surface_points_dual(torch.zeros(10), torch.zeros(5), torch.ones(3), torch.ones(2) / 2)
    with pytest.raises(ValueError, match=r"^fov_x_deg: expected a value in \(0, 180\), "
                                         r"got '30'$"):
        Camera.from_fov("30", 64, 64)
    assembly = Assembly.from_values(torch.tensor([[[0.3, 0.2, 0.1], [0.1, 0.1, 0.1]]]),
                                    torch.tensor([[[0.5, 0.5], [0.5, 0.5]]]))
    with pytest.raises(ValueError, match=r"^points: expected shape \(\.\.\., N, M, 3\), got "):
        assembly.inside_others(torch.zeros(1, 7, 3))
    surface = assembly.surface_points(1)
    assert assembly.inside_others(surface).shape == (1, 2, 2, surface.shape[2])


def test_a_prediction_scales_by_any_real_number(tmp_path):
    """A Fraction passed the number check, scaled the assembly, then failed on a tensor."""
    from fractions import Fraction

    import sq_mitsuba

    image = np.zeros((1, 64, 64), np.uint8)
    image[0, 20:40, 16:48] = 200
    prediction = sq_mitsuba.load_model().predict(image, turns=1)
    by_fraction, by_float = prediction.scaled(Fraction(2)), prediction.scaled(2.0)
    torch.testing.assert_close(by_fraction.translation, by_float.translation, rtol=0, atol=0)
    assert by_fraction.scale == 2.0


def test_inside_others_wants_each_primitives_own_points():
    assembly = Assembly.from_values(torch.tensor([[[0.3, 0.2, 0.1], [0.1, 0.1, 0.1]]]),
                                    torch.tensor([[[0.5, 0.5], [0.5, 0.5]]]))
    with pytest.raises(ValueError, match=r"^points: expected \(B, M, V, 3\) = \(1, 2, V, 3\), "
                                         r"got \(1, 3, 5, 3\)$"):
        assembly.inside_others(torch.zeros(1, 3, 5, 3))
