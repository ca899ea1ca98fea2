"""The network's configuration: which encoder and heads, their sizes, initialisation.

:class:`NetworkConfig` names the exchangeable parts of
:class:`~sq_mitsuba.model.network.SuperquadricNet` (encoder, latent head, pose head, mask
head), looked up in :data:`ENCODERS` and the registries of :mod:`sq_mitsuba.model.heads`
when the network is built.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from sq_mitsuba.config import in_range, positive

__all__ = ["DEFAULT_FOCAL_RATIO", "ENCODERS", "NetworkConfig"]

#: Focal length over image width of the project's default camera (SPEED's field of view):
#: 0.0176 m / 5.86 um / 1920 px.
DEFAULT_FOCAL_RATIO = 0.0176 / 5.86e-6 / 1920

#: Encoder name -> (EfficientNet variant, default input mean, default input std).
ENCODERS: dict[str, tuple[str, float, float]] = {
    "efficientnet_b0": ("b0", 0.449, 0.226),
    "efficientnet_lite0": ("lite0", 0.498, 0.502),
}


@dataclass(frozen=True)
class NetworkConfig:
    """Shape and initialisation of :class:`SuperquadricNet`."""

    in_channels: int = in_range(1, 4, default=1)
    "Channels of the input images (1: the grey renders of this project)."
    num_primitives: int = in_range(1, 64, default=5)
    "Superquadrics per assembly (M)."
    existence: bool = False
    """Also predict each primitive's probability of existing (NetworkOutput.existence_logits,
    (B, M)); the predictor drops the primitives below its min_existence, so a network with a
    large M can use fewer."""
    encoder: str = "efficientnet_b0"
    "Encoder by name (ENCODERS): efficientnet_b0 (the paper's) or efficientnet_lite0."
    latent: str = "pooled"
    """Latent head by name (heads.LATENT_HEADS): pooled (global average), spatial (the
    stride-32 grid) or spatial_fine (spatial, and the stride-16 grid for the shape latent)."""
    shape_frame: Literal["body", "view"] = "body"
    """Frame the generators' assembly is read in. 'body': the spacecraft's body frame (the
    paper's). 'view': the camera's axes about the body origin, what the image shows; the
    assembly is turned into the body frame by the predicted rotation (NetworkOutput.assembly)
    and, in training, by the true one, so the shape terms do not ask which way the body's
    axes point. Viewer-centred shapes generalise better to unseen classes (Shin et al. 2018,
    Tatarchenko et al. 2019)."""
    shape_decoder: Literal["slots", "regions"] = "slots"
    """How the primitives are read. 'slots': M generator MLPs, each reading the global z_sq into
    its own output slot (the paper's G_sq). 'regions': one primitive per cell of the G x G
    stride-32 grid (G = ceil(image_size / 32), so num_primitives = G^2), from that cell's
    features and z_sq through one shared MLP, its centre starting at the cell
    (region_decoder.RegionDecoder); needs shape_frame = 'view' and existence."""
    pose_head: str = "6d"
    "Pose head by name (heads.POSE_HEADS): 6d (regression) or grid (a distribution over SO(3))."
    mask_head: bool = False
    "Also predict the target's mask (NetworkOutput.mask_logits, see mask_resolution)."
    depth_head: bool = False
    """Also predict the depth of the surface the camera sees, relative to the body origin's,
    per stride-4 cell (NetworkOutput.surface_depth; the surface_depth loss term,
    model.surface_depth): a dense target alike for every family of spacecraft."""
    normal_head: bool = False
    """Also predict the camera-frame normal of the surface the camera sees, per stride-4 cell
    (NetworkOutput.surface_normals; the surface_normal loss term, model.surface_normals): the
    body axes as the camera sees them cluster the normals of every family alike."""
    normal_head_width: int = in_range(1, 1024, default=32)
    "Channels of the normal head's pyramid and convolutions (heads.MaskHead's width)."
    normal_head_layers: int = in_range(1, 8, default=1)
    "3 x 3 convolutions of the normal head at stride 4 (heads.MaskHead's layers)."
    mask_resolution: Literal["quarter", "full"] = "quarter"
    """The mask head's output: 'quarter' (a logit per stride-4 cell) or 'full' (the input's
    size, the stride-4 mask corrected from the image's own pixels; heads.MaskHead)."""
    latent_dim: int = in_range(1, 4096, default=256)
    "Width of each of the two latents z_sq and z_pose."
    hidden_dim: int = in_range(1, 4096, default=256)
    "Width of the two hidden layers of every generator MLP."
    spatial_channels: int = in_range(1, 4096, default=128)
    "Channels of the spatial latent head's grid-wide convolution (the authors' 128)."
    rotation_cells: int = in_range(9, 100_000, default=4608)
    """Cells of the grid pose head's SO(3) grid (4,608: about 9 deg apart; each cell's 8
    nearest refine its reading, so at least 9)."""
    image_size: int = in_range(32, 1024, default=128)
    "Side S in pixels of the square images the network is trained on (the predictor resizes to it)."
    drop_connect_rate: float = in_range(0.0, 1.0, high_inclusive=False, default=0.2)
    "Stochastic-depth rate of the encoder (block k of 16 drops with rate * k / 16)."
    pretrained: Path | None = None
    "ImageNet weights for the encoder: 'imagenet' (the installed Lite0 file) or a path."
    input_mean: float | None = None
    "Subtracted from the [0, 1] input (None: the encoder's, see ENCODERS)."
    input_std: float | None = None
    "Divides the centred input (None: the encoder's, see ENCODERS)."
    depth_prior: float = positive(1.8)
    "Depth in metres predicted at a_z = 0 for a camera of focal ratio prior_focal_ratio."
    prior_focal_ratio: float = positive(DEFAULT_FOCAL_RATIO)
    "Focal length over image width at which depth_prior holds (the default camera's, 1.564)."
    pixel_extent: float = in_range(0.1, 2.0, default=1.0)
    "Largest distance of the predicted image position from the centre, in half image sides."
    init_spread: float = in_range(0.0, 0.45, default=0.25)
    "Distance from the origin of the initial primitive centres (models are unit size)."
    init_gain: float = in_range(0.0, 1.0, default=0.01)
    "Scale of the last layers' initial weights (small: the initial prediction is the biases')."

    def __post_init__(self) -> None:
        # The encoders are this file's table, so a config file naming another one is refused
        # as it loads, naming the file; heads are checked when the network is built, since a
        # user's own heads may be registered after the config is read.
        if self.encoder not in ENCODERS:
            raise ValueError(f"unknown encoder {self.encoder!r}; expected one of "
                             f"{', '.join(sorted(ENCODERS))}")

    def normalisation(self) -> tuple[float, float]:
        """(mean, std) subtracted from and dividing the [0, 1] input."""
        _, mean, std = ENCODERS[self.encoder]
        return (mean if self.input_mean is None else self.input_mean,
                std if self.input_std is None else self.input_std)
