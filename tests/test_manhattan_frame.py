"""The Manhattan frame of surface normals (``geometry.manhattan_frame``): a turned box's
faces give back its turn up to which axis is which, also among outliers; the axes ordered by
a cloud's extent; bad input refused."""

from __future__ import annotations

import pytest
import torch

from sq_mitsuba.geometry.manhattan_frame import frame_by_extent, manhattan_frame
from sq_mitsuba.geometry.rotation import random_rotations


def _box_normals(rotation: torch.Tensor, count: int, generator: torch.Generator
                 ) -> torch.Tensor:
    """(count, 3) normals of a box's faces turned by ``rotation``, drawn at random."""
    faces = torch.cat([torch.eye(3), -torch.eye(3)]).double() @ rotation.T
    return faces[torch.randint(6, (count,), generator=generator)]


def _angle_up_to_axes_deg(frame: torch.Tensor, rotation: torch.Tensor) -> float:
    """The largest angle between a frame axis and its nearest axis of ``rotation`` (either
    end), degrees: 0 when the frame is the rotation up to a signed permutation."""
    cosine = (frame.T @ rotation).abs().amax(1).clamp(max=1.0)
    return float(torch.rad2deg(torch.arccos(cosine)).max())


def test_a_turned_box_gives_back_its_turn_up_to_the_axes() -> None:
    generator = torch.Generator().manual_seed(0)
    for rotation in random_rotations(5, generator, dtype=torch.float64):
        frame, share = manhattan_frame(_box_normals(rotation, 200, generator))
        assert _angle_up_to_axes_deg(frame, rotation) < 1e-4  # arccos near 1: ~1e-6 deg
        assert share == pytest.approx(1.0)
        assert torch.linalg.det(frame).item() == pytest.approx(1.0)


def test_noise_and_outliers_move_it_little() -> None:
    """Normals jittered by about 3 deg, and a third of them drawn at random: within 2 deg,
    and the share of agreeing normals says how many were the box's."""
    generator = torch.Generator().manual_seed(1)
    rotation = random_rotations(1, generator, dtype=torch.float64)[0]
    box = _box_normals(rotation, 400, generator)
    box = torch.nn.functional.normalize(
        box + 0.05 * torch.randn(box.shape, generator=generator, dtype=torch.float64), dim=1)
    outliers = torch.nn.functional.normalize(
        torch.randn(200, 3, generator=generator, dtype=torch.float64), dim=1)
    frame, share = manhattan_frame(torch.cat([box, outliers]))
    assert _angle_up_to_axes_deg(frame, rotation) < 2.0
    assert 0.6 < share < 0.85


def test_axes_are_ordered_by_extent() -> None:
    generator = torch.Generator().manual_seed(2)
    cloud = (torch.rand(500, 3, generator=generator, dtype=torch.float64) - 0.5) * \
        torch.tensor([0.3, 2.0, 0.8], dtype=torch.float64)  # longest along y, then z
    ordered = frame_by_extent(torch.eye(3, dtype=torch.float64), cloud)
    assert ordered[:, 0].abs().tolist() == [0.0, 1.0, 0.0]
    assert ordered[:, 1].abs().tolist() == [0.0, 0.0, 1.0]
    assert torch.linalg.det(ordered).item() == pytest.approx(1.0)


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="normals"):
        manhattan_frame(torch.zeros(10, 3))
    with pytest.raises(ValueError, match="30 deg"):
        manhattan_frame(torch.tensor([[0.0, 0.0, 1.0]] * 5))
    with pytest.raises(ValueError, match="normals"):
        manhattan_frame(torch.tensor([[0.0, float("nan"), 1.0]] * 5))


def test_weights_decide_which_normals_count() -> None:
    """Half the normals a box's, half another box's turned 30 deg from it: the frame is the
    box whose normals weigh more, exactly."""
    generator = torch.Generator().manual_seed(3)
    first = random_rotations(1, generator, dtype=torch.float64)[0]
    turn = torch.tensor([[1.0, 0, 0], [0, 0.8660254037844387, -0.5], [0, 0.5, 0.8660254037844387]],
                        dtype=torch.float64)
    normals = torch.cat([_box_normals(first, 300, generator),
                         _box_normals(first @ turn, 300, generator)])
    for heavy, rotation in ((0, first), (1, first @ turn)):
        weights = torch.full((600,), 0.1, dtype=torch.float64)
        weights[heavy * 300:(heavy + 1) * 300] = 1.0
        frame, _ = manhattan_frame(normals, weights)
        assert _angle_up_to_axes_deg(frame, rotation) < 1e-4


def test_frame_by_extent_refuses_a_cloud_of_another_shape_or_with_nan() -> None:
    with pytest.raises(ValueError, match="cloud"):
        frame_by_extent(torch.eye(3, dtype=torch.float64), torch.zeros(5, 2))
    with pytest.raises(ValueError, match="cloud"):
        frame_by_extent(torch.eye(3, dtype=torch.float64),
                        torch.tensor([[0.0, float("nan"), 1.0]] * 4))


def test_best_rotation_beats_every_other_rotation_reflections_included() -> None:
    """Orthogonal Procrustes: for matrices whose SVD's U V^T is a reflection as well as for the
    others, no rotation of a dense random sample scores a larger trace(F^T M) (flipping an axis
    of U V^T, the former answer, scored lower on such matrices)."""
    from sq_mitsuba.geometry.rotation import best_rotation

    generator = torch.Generator().manual_seed(5)
    sample = random_rotations(20_000, generator, torch.float64)
    matrices = torch.randn(20, 3, 3, generator=generator, dtype=torch.float64)
    reflected = 0
    for matrix in matrices:
        u, _, vt = torch.linalg.svd(matrix)
        reflected += int(torch.linalg.det(u @ vt) < 0)
        best = best_rotation(matrix)
        torch.testing.assert_close(best.T @ best, torch.eye(3, dtype=torch.float64))
        assert float(torch.linalg.det(best)) > 0
        score = float(torch.trace(best.T @ matrix))
        assert score >= float(torch.einsum("kij,ij->k", sample, matrix).max()) - 1e-9
    assert reflected >= 5  # both kinds of matrix were tried
    # A batch (here (4, 5, 3, 3)) gives each matrix's own answer.
    batched = best_rotation(matrices.reshape(4, 5, 3, 3)).reshape(20, 3, 3)
    torch.testing.assert_close(batched, torch.stack([best_rotation(m) for m in matrices]))


@pytest.mark.parametrize("matrix", [torch.zeros(3, 2), torch.zeros(2, 3, 4),
                                    torch.full((3, 3), float("nan"))])
def test_best_rotation_names_a_bad_matrix(matrix) -> None:
    from sq_mitsuba.geometry.rotation import best_rotation

    with pytest.raises(ValueError, match=r"^matrix"):
        best_rotation(matrix)
