"""The network's exchangeable parts: latent heads, pose heads and the mask head, by name.

:class:`~sq_mitsuba.model.network.SuperquadricNet` is encoder + latent head + shape
generator + pose head (+ mask head). Each exchangeable part is chosen by a name in
:class:`~sq_mitsuba.model.network.NetworkConfig` and looked up in a registry here:

- ``LATENT_HEADS[config.latent](config, pyramid_channels)``: feature maps -> (z_sq, z_pose);
  a latent head whose class says ``uses_head_map = False`` lets the network drop the
  encoder's 1280-channel head.
- ``POSE_HEADS[config.pose_head](config)``: z_pose -> :class:`PoseHeadOutput`.

Adding a head is one module (a class with that constructor and ``forward``) and one
:func:`register_pose_head` / :func:`register_latent_head` call; training, export, the
predictor and its fast paths (folded, traced by TorchScript) take it without edits, since
they only read :class:`PoseHeadOutput`'s fields. Pose heads that predict a distribution over
rotations live in their own modules (:mod:`sq_mitsuba.model.rotation_grid`) and register
themselves.

Convention:
    - Feature maps come from :meth:`~sq_mitsuba.model.encoder.EfficientNet.forward_pyramid`:
      ``[s4, s8, s16, s32, head]`` (strides 4, 8, 16, 32; the head map is 1280 channels).
    - A pose head's ``position`` (B, 3) is raw: ``(a_u, a_v, a_z)``, turned into the image
      position and depth by the network (one convention for every head).
    - ``reset_last_layer(gain)`` makes a head's initial prediction the image centre at the
      typical depth (small last-layer weights, chosen biases), and the 6D head's rotation the
      identity; the grid head starts near uniform over its cells (its first reading is an
      arbitrary cell).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sq_mitsuba.geometry.rotation import IDENTITY_6D, rotation_6d_to_matrix

if TYPE_CHECKING:
    from sq_mitsuba.model.network_config import NetworkConfig

__all__ = [
    "LATENT_HEADS",
    "POSE_HEADS",
    "FineSpatialLatents",
    "MaskHead",
    "PooledLatents",
    "PoseHeadOutput",
    "Rotation6dPoseHead",
    "SpatialLatents",
    "pose_mlp",
    "register_latent_head",
    "register_pose_head",
]

#: Raw position outputs of every pose head: (a_u, a_v) image position, a_z depth.
POSITION_OUTPUTS = 3


@dataclass(frozen=True)
class PoseHeadOutput:
    """What a pose head returns for B items.

    Attributes:
        rotation: (B, 3, 3) body -> camera rotation (orthonormal, det 1).
        position: (B, 3) raw image position and depth ``(a_u, a_v, a_z)``.
        rotation_6d: (B, 6) the raw 6D output of a regressing head, else None.
        rotation_logits: (B, G) scores over a rotation grid of a distribution head, else None.
    """

    rotation: Tensor
    position: Tensor
    rotation_6d: Tensor | None = None
    rotation_logits: Tensor | None = None


LatentHeadFactory = Callable[["NetworkConfig", tuple[int, ...]], nn.Module]
PoseHeadFactory = Callable[["NetworkConfig"], nn.Module]
LATENT_HEADS: dict[str, LatentHeadFactory] = {}
POSE_HEADS: dict[str, PoseHeadFactory] = {}


def register_latent_head(name: str, factory: LatentHeadFactory) -> None:
    """Make ``config.latent = name`` build ``factory(config, pyramid_channels)``."""
    LATENT_HEADS[name] = factory


def register_pose_head(name: str, factory: PoseHeadFactory) -> None:
    """Make ``config.pose_head = name`` build ``factory(config)``."""
    POSE_HEADS[name] = factory


def pose_mlp(latent_dim: int, hidden_dim: int, outputs: int) -> nn.Sequential:
    """The three-layer MLP of the pose heads: Linear, SiLU, Linear, SiLU, Linear."""
    return nn.Sequential(
        nn.Linear(latent_dim, hidden_dim), nn.SiLU(),
        nn.Linear(hidden_dim, hidden_dim), nn.SiLU(),
        nn.Linear(hidden_dim, outputs),
    )


# --- latent heads ---------------------------------------------------------------------------


class PooledLatents(nn.Module):
    """``"pooled"``: the head map averaged over the image, then two linear maps (the paper's
    figure; where each part of the target lies is averaged away).

    maps -> z_sq, z_pose, each (B, latent_dim).
    """

    def __init__(self, config: NetworkConfig, pyramid_channels: tuple[int, ...]) -> None:
        super().__init__()
        width = pyramid_channels[4]
        self.to_z_sq = nn.Linear(width, config.latent_dim)
        self.to_z_pose = nn.Linear(width, config.latent_dim)

    #: Reads the encoder's 1280-channel head map (``maps[4]``).
    uses_head_map = True

    def forward(self, maps: list[Tensor]) -> tuple[Tensor, Tensor]:
        features = maps[4].mean(dim=(2, 3))
        return self.to_z_sq(features), self.to_z_pose(features)


class SpatialLatents(nn.Module):
    """``"spatial"``: the latents read the last stage's map with its layout kept.

    As the authors' network: the stride-32 stage output (320 channels, G x G cells with
    ``G = ceil(image_size / 32)``) goes through one convolution whose kernel covers the whole
    grid (to ``spatial_channels``, SiLU), then two linear maps to z_sq and z_pose. Another
    input size is average-pooled (or repeated) to G x G first, so any size runs.

    maps -> z_sq, z_pose, each (B, latent_dim).
    """

    def __init__(self, config: NetworkConfig, pyramid_channels: tuple[int, ...]) -> None:
        super().__init__()
        self.grid = math.ceil(config.image_size / 32)
        self.reduce = nn.Conv2d(pyramid_channels[3], config.spatial_channels, self.grid)
        self.to_z_sq = nn.Linear(config.spatial_channels, config.latent_dim)
        self.to_z_pose = nn.Linear(config.spatial_channels, config.latent_dim)

    #: Reads the stride-32 stage map (``maps[3]``) only: the encoder's head conv is dropped.
    uses_head_map = False

    def forward(self, maps: list[Tensor]) -> tuple[Tensor, Tensor]:
        features = grid_features(maps[3], self.reduce)
        return self.to_z_sq(features), self.to_z_pose(features)


def grid_features(x: Tensor, reduce: nn.Conv2d) -> Tensor:
    """One map read over its whole grid: (B, C, H, W) average-pooled (or repeated) to the
    convolution's kernel size G x G if it is another size, then ``reduce`` and SiLU ->
    (B, reduce.out_channels)."""
    grid = reduce.kernel_size
    if tuple(x.shape[-2:]) != grid:
        x = F.adaptive_avg_pool2d(x, grid)
    return F.silu(reduce(x)).flatten(1)


class FineSpatialLatents(SpatialLatents):
    """``"spatial_fine"``: ``"spatial"`` with a second reader of the finer stride-16 map for
    the shape latent.

    At 96 px the stride-32 map is a 3 x 3 grid, where a boom or a module a few pixels wide
    is one cell among nine. This head also reads the stride-16 map (112 channels,
    ``2 G x 2 G`` cells, G as ``"spatial"``) through its own grid-wide convolution (to
    ``spatial_channels``, SiLU) and adds a linear map of it to z_sq:
    ``z_sq = to_z_sq(coarse) + to_z_sq_fine(fine)``. z_pose reads the coarse grid only, as
    ``"spatial"``'s does: the rotation term dominates the training loss and would otherwise
    set what the new reader learns.

    Convention: ``to_z_sq_fine`` starts at zero, so the head starts as exactly the
    ``"spatial"`` head it shares its other weights with (a trained ``"spatial"`` network
    loads into it with ``init_from``; the fine weights the file lacks stay as built).

    maps -> z_sq, z_pose, each (B, latent_dim).
    """

    def __init__(self, config: NetworkConfig, pyramid_channels: tuple[int, ...]) -> None:
        super().__init__(config, pyramid_channels)
        self.reduce_fine = nn.Conv2d(pyramid_channels[2], config.spatial_channels,
                                     2 * self.grid)
        self.to_z_sq_fine = nn.Linear(config.spatial_channels, config.latent_dim)
        with torch.no_grad():
            self.to_z_sq_fine.weight.zero_()
            self.to_z_sq_fine.bias.zero_()

    def forward(self, maps: list[Tensor]) -> tuple[Tensor, Tensor]:
        z_sq, z_pose = super().forward(maps)
        fine = grid_features(maps[2], self.reduce_fine)  # (B, spatial_channels)
        return z_sq + self.to_z_sq_fine(fine), z_pose


register_latent_head("pooled", PooledLatents)
register_latent_head("spatial", SpatialLatents)
register_latent_head("spatial_fine", FineSpatialLatents)


# --- pose heads -----------------------------------------------------------------------------


class Rotation6dPoseHead(nn.Module):
    """``"6d"``: one MLP regresses a 6D rotation (Gram-Schmidt of its two rows, Zhou et al.
    2019) and the raw position: z_pose (B, latent_dim) -> :class:`PoseHeadOutput`."""

    def __init__(self, config: NetworkConfig) -> None:
        super().__init__()
        self.mlp = pose_mlp(config.latent_dim, config.hidden_dim, 6 + POSITION_OUTPUTS)

    @torch.no_grad()
    def reset_last_layer(self, gain: float) -> None:
        last = self.mlp[-1]
        last.weight.mul_(gain)
        bias = torch.zeros(6 + POSITION_OUTPUTS)
        bias[:6] = torch.tensor(IDENTITY_6D)
        last.bias.copy_(bias)

    def forward(self, z_pose: Tensor) -> PoseHeadOutput:
        out = self.mlp(z_pose)
        rotation_6d = out[:, :6]
        return PoseHeadOutput(rotation=rotation_6d_to_matrix(rotation_6d),
                              position=out[:, 6:], rotation_6d=rotation_6d)


register_pose_head("6d", Rotation6dPoseHead)


# --- mask head ------------------------------------------------------------------------------


class MaskHead(nn.Module):
    """The target's mask from the encoder's maps: a small top-down pyramid (FPN-style).

    Each of the stride 4, 8, 16 and 32 maps is projected to ``width`` channels (1 x 1 conv);
    from the coarsest, each level is upsampled (bilinear) to the next finer one and added;
    ``layers`` 3 x 3 convs (ReLU; one for the mask) and a 1 x 1 conv give one logit per
    stride-4 cell.

    With ``full_resolution`` the stride-4 logits are upsampled (bilinear) to the input's size
    and a correction is added that is computed from the stride-4 features and the image itself
    (two guided steps: features upsampled x 2, concatenated with a 3 x 3 conv of the image at
    that stride, fused by a 3 x 3 conv). The encoder's finest map is at stride 4, so a thin
    solar panel or boom narrower than 4 pixels can only be drawn from the image's own pixels.
    The correction's last layer starts at zero: a head grown from a quarter-resolution one
    starts as exactly that head's mask, upsampled.

    maps -> logits (B, outputs, ceil(H / 4), ceil(W / 4)) (``outputs`` 1 for a mask; the
    depth and normal heads reuse the pyramid with 1 and 3); with ``full_resolution``,
    (maps, normalised images (B, C, H, W)) -> logits (B, 1, H, W). ``sigmoid`` gives the
    probability that a cell is the target. The bias starts at the logit of 0.25, about the
    share of an image the target covers.
    """

    def __init__(self, pyramid_channels: tuple[int, ...], width: int = 32, *,
                 full_resolution: bool = False, in_channels: int = 1,
                 guide_width: int = 16, outputs: int = 1, layers: int = 1) -> None:
        super().__init__()
        if layers < 1:
            raise ValueError(f"layers: expected at least 1, got {layers}")
        self.full_resolution = full_resolution
        self.lateral = nn.ModuleList(nn.Conv2d(c, width, 1) for c in pyramid_channels[:4])
        self.smooth = nn.Conv2d(width, width, 3, padding=1)
        # Beyond the first (named as before, so that older checkpoints load): more context
        # and nonlinearity per cell, for targets such as a face's normal that one layer of
        # summed pyramid features cannot draw.
        self.deeper = nn.ModuleList(nn.Conv2d(width, width, 3, padding=1)
                                    for _ in range(layers - 1))
        self.to_logit = nn.Conv2d(width, outputs, 1)
        with torch.no_grad():
            self.to_logit.bias.fill_(math.log(0.25 / 0.75))
        if full_resolution:
            # Stride 2, then stride 1: image features beside the upsampled mask features.
            self.image_half = nn.Conv2d(in_channels, guide_width, 3, stride=2, padding=1)
            self.fuse_half = nn.Conv2d(width + guide_width, guide_width, 3, padding=1)
            self.image_full = nn.Conv2d(in_channels, guide_width, 3, padding=1)
            self.fuse_full = nn.Conv2d(2 * guide_width, guide_width, 3, padding=1)
            self.to_correction = nn.Conv2d(guide_width, 1, 1)
            with torch.no_grad():
                self.to_correction.weight.zero_()
                self.to_correction.bias.zero_()

    def forward(self, maps: list[Tensor], images: Tensor | None = None) -> Tensor:
        x = self.lateral[3](maps[3])
        for level in (2, 1, 0):
            finer = maps[level]
            x = F.interpolate(x, size=finer.shape[-2:], mode="bilinear", align_corners=False)
            x = x + self.lateral[level](finer)
        features = F.relu(self.smooth(x))
        for layer in self.deeper:
            features = F.relu(layer(features))
        logits = self.to_logit(features)
        if not self.full_resolution:
            return logits
        if images is None:
            raise ValueError("images: a full-resolution mask head needs the (normalised) images")
        half = F.relu(self.image_half(images))
        x = F.interpolate(features, size=half.shape[-2:], mode="bilinear", align_corners=False)
        x = F.relu(self.fuse_half(torch.cat([x, half], dim=1)))
        full = F.relu(self.image_full(images))
        x = F.interpolate(x, size=full.shape[-2:], mode="bilinear", align_corners=False)
        x = F.relu(self.fuse_full(torch.cat([x, full], dim=1)))
        coarse = F.interpolate(logits, size=images.shape[-2:], mode="bilinear",
                               align_corners=False)
        return coarse + self.to_correction(x)
