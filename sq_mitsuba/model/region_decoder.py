"""G_sq by image region: one primitive per cell of the encoder's coarsest grid.

The default shape generators (:class:`~sq_mitsuba.model.network.SuperquadricGenerators`) read
every primitive from one global code z_sq into a fixed output slot, so a slot learns where the
parts of the spacecraft it trained on usually are. This decoder ties each primitive to a
region of the image instead: the stride-32 map has G x G cells (G = ceil(S / 32): 3 x 3 at
96 px), and cell c gives primitive c through one MLP shared by every cell, from that cell's
features, the global z_sq and a learned embedding of the cell. Its centre starts at the cell:
the anchor is where a point seen at the cell's centre lies about the body origin, at the
origin's predicted depth. A part in an unusual place then still gets a primitive from the
cell that shows it, and the existence logits switch off the cells that show empty space.

Convention:
    - Cells are numbered row-major (row v, then column u), as ``Tensor.flatten(2)`` of the map.
    - The decoder reads shapes in the view frame (``network.shape_frame = "view"``: the camera's
      axes about the body origin, x right, y down, z away from the camera), the frame in which
      an image position is a position: a point at pixel offset ``(du, dv)`` from the origin's
      pixel, at the origin's depth z, lies at ``(du z / fx, dv z / fy, 0)``.
    - The anchor uses the pose head's pixel and depth without their gradient: the shape terms
      do not move the pose through it.
    - Its raw translation is ``atanh(anchor / translation_scale)`` (clipped to 0.9 of the
      range), added to the MLP's translation output, so the last layer's small initial weights
      put each primitive at its cell.

maps, z_sq, pose -> raw (B, G^2, 17): the 16 raw assembly parameters and the existence logit.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sq_mitsuba.geometry.assembly import FIELDS, NUM_PARAMS, ParameterRanges

if TYPE_CHECKING:
    from sq_mitsuba.model.network_config import NetworkConfig

__all__ = ["ANCHOR_LIMIT", "RegionDecoder", "region_grid"]

#: Anchors are clipped to this fraction of the translation range (tanh saturates at 1).
ANCHOR_LIMIT = 0.9


def region_grid(image_size: int) -> int:
    """G, the side of the stride-32 grid at an input of ``image_size`` pixels (M = G^2)."""
    return math.ceil(image_size / 32)


class RegionDecoder(nn.Module):
    """One primitive per cell of the G x G stride-32 grid (module doc).

    Attributes:
        grid: G.
        cell_in: cell features (C_32) -> hidden.
        latent_in: z_sq -> hidden, added to every cell.
        position: (G^2, hidden) learned embedding of each cell, added likewise.
        hidden: hidden -> hidden.
        out: hidden -> 17 (16 raw parameters, the existence logit).
    """

    def __init__(self, config: NetworkConfig, pyramid_channels: tuple[int, ...]) -> None:
        super().__init__()
        self.grid = region_grid(config.image_size)
        width = config.hidden_dim
        self.cell_in = nn.Linear(pyramid_channels[3], width)
        self.latent_in = nn.Linear(config.latent_dim, width)
        self.position = nn.Parameter(torch.zeros(self.grid * self.grid, width))
        self.hidden = nn.Linear(width, width)
        self.out = nn.Linear(width, NUM_PARAMS + 1)
        self.translation_scale = ParameterRanges().translation_scale

    @property
    def last_layer(self) -> nn.Linear:
        """The layer whose bias sets the initial prediction (the network resets it)."""
        return self.out

    def cell_centres(self, width: int, height: int, like: Tensor) -> Tensor:
        """(G^2, 2) pixel (u, v) of each cell's centre in a ``width`` x ``height`` input."""
        steps = (torch.arange(self.grid, dtype=like.dtype, device=like.device) + 0.5) / self.grid
        v, u = torch.meshgrid(steps * height, steps * width, indexing="ij")
        return torch.stack([u.flatten(), v.flatten()], dim=-1)

    def anchors(self, pixel: Tensor, depth: Tensor, camera_matrix: Tensor, width: int,
                height: int) -> Tensor:
        """(B, G^2, 3) raw translations that put each cell's primitive at its cell.

        Args:
            pixel: (B, 2) predicted image position of the body origin.
            depth: (B,) its predicted depth.
            camera_matrix: (B, 3, 3) intrinsics of the input.
        """
        offset = self.cell_centres(width, height, pixel)[None] - pixel[:, None]  # (B, G^2, 2)
        focal = torch.stack([camera_matrix[:, 0, 0], camera_matrix[:, 1, 1]], dim=-1)
        metres = offset * (depth[:, None] / focal)[:, None]
        limit = ANCHOR_LIMIT
        xy = torch.atanh((metres / self.translation_scale).clamp(-limit, limit))
        return torch.cat([xy, xy.new_zeros(*xy.shape[:-1], 1)], dim=-1)

    def forward(self, stride32: Tensor, z_sq: Tensor, pixel: Tensor, depth: Tensor,
                camera_matrix: Tensor, width: int, height: int) -> Tensor:
        """(B, C_32, h, w) map, z_sq (B, latent), pose -> raw (B, G^2, 17).

        A map of another size than G x G is average-pooled (or repeated) to it first.
        """
        if tuple(stride32.shape[-2:]) != (self.grid, self.grid):
            stride32 = F.adaptive_avg_pool2d(stride32, self.grid)
        cells = stride32.flatten(2).transpose(1, 2)  # (B, G^2, C)
        h = F.silu(self.cell_in(cells) + self.latent_in(z_sq)[:, None] + self.position)
        raw = self.out(F.silu(self.hidden(h)))
        anchor = self.anchors(pixel.detach(), depth.detach(), camera_matrix, width, height)
        translation = FIELDS["translation"]
        shift = torch.zeros_like(raw)
        shift[..., translation] = anchor.to(raw.dtype)
        return raw + shift
