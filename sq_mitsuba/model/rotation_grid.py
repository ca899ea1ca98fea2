"""A rotation distribution head: scores over a grid of SO(3), hypotheses, training targets.

One regressed rotation averages the modes of a multi-modal target: the body frame of an
unknown spacecraft is fixed by its extents only up to the four half turns about its axes,
and many spacecraft are symmetric. This head scores every cell of a near-uniform grid of
rotations instead (classification over SO(3), as Implicit-PDF and Image2Sphere), so several
modes can stay side by side; the render-and-compare search then scores the best few
(:func:`rotation_hypotheses`) through the renderer.

Convention:
    - The grid is :func:`~sq_mitsuba.geometry.so3_grid.so3_grid` of ``config.rotation_cells``
      cells (4,608 by default: a cell's radius is about 9 deg); cell ``i`` is the same
      rotation in every run, so the logits of a checkpoint keep their meaning.
    - The head's rotation is the argmax cell refined locally: the quaternions of that cell
      and its ``NEIGHBOURS`` nearest cells, averaged with their probabilities (signs aligned
      to the argmax cell). Accuracy below the grid's spacing comes from that average.
    - Training targets (:func:`soft_rotation_targets`) put mass on every rotation that shows
      the same object: the true rotation times each of the model's symmetries, each spread
      over nearby cells by a Gaussian in angle (``sigma_deg``), normalised to sum to 1; the
      loss is the cross-entropy to that distribution.
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sq_mitsuba.geometry.rotation import matrix_to_quaternion, quaternion_to_matrix
from sq_mitsuba.geometry.so3_grid import (
    covering_angle_deg,
    super_fibonacci_quaternions,
)
from sq_mitsuba.model.heads import POSITION_OUTPUTS, PoseHeadOutput, register_pose_head

if TYPE_CHECKING:
    from sq_mitsuba.model.network_config import NetworkConfig

__all__ = [
    "NEIGHBOURS",
    "RotationGridPoseHead",
    "grid_quaternions",
    "rotation_hypotheses",
    "soft_rotation_targets",
    "turned_cells",
    "turned_log_probabilities",
]

#: Cells besides the argmax averaged by the local refinement.
NEIGHBOURS = 8


@functools.lru_cache(maxsize=4)
def grid_quaternions(cells: int) -> Tensor:
    """The (cells, 4) float32 quaternions of the grid a head of ``cells`` cells scores (cached;
    do not modify the returned tensor)."""
    return super_fibonacci_quaternions(cells).float()


@functools.lru_cache(maxsize=4)
def grid_neighbours(cells: int) -> Tensor:
    """(cells, NEIGHBOURS + 1) indices of each grid cell and its nearest cells, the cell
    itself first (cached: every network of one grid size shares it; do not modify it)."""
    return _nearest_cells(super_fibonacci_quaternions(cells), NEIGHBOURS)


def _nearest_cells(quaternions: Tensor, count: int, chunk: int = 1024) -> Tensor:
    """(G, 4) unit quaternions -> (G, count + 1) indices of each cell and its nearest cells."""
    rows = []
    for start in range(0, quaternions.shape[0], chunk):
        similarity = (quaternions[start:start + chunk] @ quaternions.T).abs()
        rows.append(similarity.topk(count + 1, dim=1).indices)
    return torch.cat(rows)


class RotationGridPoseHead(nn.Module):
    """``"grid"``: an MLP trunk, then logits over ``config.rotation_cells`` grid rotations and
    the raw position. z_pose (B, latent_dim) -> :class:`PoseHeadOutput` with
    ``rotation_logits`` (B, G) and the locally refined argmax rotation.

    Buffers (not saved: the grid is a function of its size): ``quaternions`` (G, 4),
    ``neighbours`` (G, NEIGHBOURS + 1), the cell itself first.
    """

    def __init__(self, config: NetworkConfig) -> None:
        super().__init__()
        cells = config.rotation_cells
        hidden = config.hidden_dim
        self.trunk = nn.Sequential(nn.Linear(config.latent_dim, hidden), nn.SiLU(),
                                   nn.Linear(hidden, hidden), nn.SiLU())
        self.to_logits = nn.Linear(hidden, cells)
        self.to_position = nn.Linear(hidden, POSITION_OUTPUTS)
        self.register_buffer("quaternions", grid_quaternions(cells).clone(), persistent=False)
        self.register_buffer("neighbours", grid_neighbours(cells).clone(), persistent=False)

    @torch.no_grad()
    def reset_last_layer(self, gain: float) -> None:
        for layer in (self.to_logits, self.to_position):
            layer.weight.mul_(gain)
            layer.bias.zero_()

    def grid_rotations(self) -> Tensor:
        """The grid as (G, 3, 3) matrices, in the head's dtype and device."""
        return quaternion_to_matrix(self.quaternions)

    def forward(self, z_pose: Tensor) -> PoseHeadOutput:
        h = self.trunk(z_pose)
        logits = self.to_logits(h)
        return PoseHeadOutput(rotation=self.rotation_from_logits(logits),
                              position=self.to_position(h), rotation_logits=logits)

    def rotation_from_logits(self, logits: Tensor) -> Tensor:
        """(B, G) scores over the grid -> (B, 3, 3): the argmax cell refined by its
        neighbours (the module's convention)."""
        probabilities = logits.softmax(dim=-1)
        best = logits.argmax(dim=-1)  # (B,)
        cells = self.neighbours[best]  # (B, n + 1)
        q = self.quaternions[cells].to(logits)  # (B, n + 1, 4)
        q = q * torch.sign((q * q[:, :1]).sum(-1, keepdim=True) + 1e-12)  # align to argmax
        weights = probabilities.gather(1, cells)[..., None]
        mean = (weights * q).sum(dim=1)
        return quaternion_to_matrix(mean / mean.norm(dim=-1, keepdim=True))


register_pose_head("grid", RotationGridPoseHead)


def soft_rotation_targets(rotation: Tensor, symmetries: Tensor, grid_quaternions: Tensor,
                          sigma_deg: float | None = None) -> Tensor:
    """Training distribution over the grid for true rotations and the models' symmetries.

    Args:
        rotation: (B, 3, 3) true body -> camera rotations.
        symmetries: (B, S, 3, 3) rotations of the body frame that leave each model unchanged
            (identity included; padded rows repeat the identity: a repeated rotation counts
            once, so padding a model's set to a batch's S leaves its targets as they are).
        grid_quaternions: (G, 4) the head's cells.
        sigma_deg: spread of each mode (default: the grid's covering angle).

    Returns:
        (B, G) probabilities, each row summing to 1: a Gaussian in the angle to each
        equivalent rotation ``R @ S``, the equivalents weighted equally.
    """
    if rotation.shape[-2:] != (3, 3) or symmetries.shape[:1] != rotation.shape[:1]:
        raise ValueError(f"expected rotation (B, 3, 3) and symmetries (B, S, 3, 3), got "
                         f"{tuple(rotation.shape)} and {tuple(symmetries.shape)}")
    sigma = math.radians(sigma_deg if sigma_deg is not None
                         else covering_angle_deg(grid_quaternions.shape[0]))
    equivalents = rotation[:, None] @ symmetries.to(rotation)  # (B, S, 3, 3)
    q = matrix_to_quaternion(equivalents).to(grid_quaternions)  # (B, S, 4)
    cosine = (q @ grid_quaternions.T).abs().clamp(max=1.0)  # (B, S, G): cos(angle / 2)
    angle = 2.0 * torch.acos(cosine)
    log_density = -0.5 * (angle / sigma) ** 2
    per_mode = F.softmax(log_density, dim=-1)  # each equivalent normalised on its own
    # An equivalent equal to an earlier one (the padding's identities) gets no weight of its
    # own: otherwise the identity's mode would outweigh the others by the padding's count.
    same = (q @ q.transpose(-1, -2)).abs() > 1.0 - 1e-6  # (B, S, S), q and -q alike
    repeated = torch.tril(same, diagonal=-1).any(dim=-1)  # equals an earlier row
    weight = (~repeated).to(per_mode)[..., None]
    return (per_mode * weight).sum(dim=1) / weight.sum(dim=1)


@torch.no_grad()
def rotation_hypotheses(logits: Tensor, grid: Tensor, count: int,
                        separation_deg: float = 20.0) -> tuple[Tensor, Tensor]:
    """The ``count`` best distinct rotations of a distribution head, best first.

    Greedy non-maximum suppression: cells in order of probability, each kept unless it lies
    within ``separation_deg`` of one already kept, so the hypotheses are separate modes rather
    than one peak's neighbours.

    Args:
        logits: (B, G) scores over the grid.
        grid: (G, 3, 3) the grid's rotations.
        count: K >= 1 hypotheses per image.
        separation_deg: the smallest angle between two kept hypotheses.

    Returns:
        rotations (B, K, 3, 3) and their probabilities (B, K) (softmax of the logits; where
        fewer than K separate modes exist, the last ones repeat the best with score 0).
    """
    if count < 1:
        raise ValueError(f"count: expected K >= 1 hypotheses, got {count}")
    if logits.dim() != 2 or grid.shape != (logits.shape[1], 3, 3):
        raise ValueError(f"expected logits (B, G) and grid (G, 3, 3), got "
                         f"{tuple(logits.shape)} and {tuple(grid.shape)}")
    # The greedy loop runs on the host, whatever the device: on a GPU each of its small
    # steps would wait for the device (about a hundred an image); one copy each way instead.
    probabilities = logits.detach().float().softmax(dim=-1).cpu()
    order = probabilities.argsort(dim=-1, descending=True)[:, : max(8 * count, 64)]
    limit = math.cos(math.radians(separation_deg))
    flat = grid.detach().reshape(-1, 9).cpu().to(probabilities)
    chosen = torch.zeros(logits.shape[0], count, dtype=torch.long)
    scores = probabilities.new_zeros(logits.shape[0], count)
    for item in range(logits.shape[0]):
        kept: list[int] = []
        for cell in order[item].tolist():
            if kept:
                # cos(angle) = (trace(A^T B) - 1) / 2
                cosine = (flat[kept] @ flat[cell] - 1.0) / 2.0
                if bool((cosine > limit).any()):
                    continue
            kept.append(cell)
            if len(kept) == count:
                break
        chosen[item] = torch.tensor(kept + [kept[0]] * (count - len(kept)))
        scores[item, : len(kept)] = probabilities[item, kept]
    return grid[chosen.to(grid.device)], scores.to(logits.device)


@torch.no_grad()
def turned_cells(grid: Tensor, turns: Tensor) -> Tensor:
    """Where each cell goes when the camera rolls: (G, 3, 3) grid, (T, 3, 3) rotations about
    the optical axis -> (T, G) long, the cell nearest ``turns[k] @ grid[g]``.

    An image turned in its plane about the principal point shows the pose ``Rz R`` when the
    original shows ``R`` (:func:`~sq_mitsuba.geometry.image_turns.z_rotation`), so the score of
    cell g for the original image is the turned image's score of cell ``[k, g]``.

    The nearest cell by a k-d tree over the grid's quaternions and their negatives: for unit
    quaternions ``|p - q|^2 = 2 - 2 p.q`` and the angle between two rotations falls as ``|p.q|``
    grows, so the nearest point is the cell at the smallest angle (what
    :func:`~sq_mitsuba.geometry.so3_grid.nearest_grid_index` finds by brute force, T G x G
    traces: 1.3 s at 8 turns of 4,608 cells on one core, against a few tens of ms).
    """
    if turns.dim() != 3 or turns.shape[1:] != (3, 3) or grid.dim() != 3 or \
            grid.shape[1:] != (3, 3):
        raise ValueError(f"expected rotations grid (G, 3, 3) and turns (T, 3, 3), got "
                         f"{tuple(grid.shape)} and {tuple(turns.shape)}")
    from scipy.spatial import cKDTree

    cells = grid.shape[0]
    grid64 = grid.detach().double().cpu()
    moved = turns.detach().double().cpu()[:, None] @ grid64[None]  # (T, G, 3, 3)
    points = matrix_to_quaternion(grid64)
    tree = cKDTree(torch.cat([points, -points]).numpy())
    _, index = tree.query(matrix_to_quaternion(moved.reshape(-1, 3, 3)).numpy())
    nearest = torch.from_numpy(index).long() % cells
    return nearest.reshape(turns.shape[0], cells).to(grid.device)


def turned_log_probabilities(logits: Tensor, cells: Tensor) -> Tensor:
    """One distribution from the scores of T turned copies of each image.

    Args:
        logits: (T, B, G) a distribution head's scores for each copy, copy k turned as row k of
            ``cells`` says (:func:`turned_cells`; the unturned copy's row is the identity).
        cells: (T, G) long.

    Returns:
        (B, G) the sum over copies of their log-probabilities, mapped back to the unturned
        image's cells, normalised (a product of experts: a cell scores high only where every
        turned copy agrees).
    """
    if logits.dim() != 3 or cells.shape != (logits.shape[0], logits.shape[2]):
        raise ValueError(f"expected logits (T, B, G) and cells (T, G), got "
                         f"{tuple(logits.shape)} and {tuple(cells.shape)}")
    log_p = logits.float().log_softmax(dim=-1)
    index = cells[:, None, :].expand(-1, logits.shape[1], -1)
    total = log_p.gather(2, index).sum(dim=0)
    return total - total.logsumexp(dim=-1, keepdim=True)
