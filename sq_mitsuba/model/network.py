"""The superquadric network: encoder, latents, M superquadric generators, pose and mask heads.

``images (B, C, S, S) in [0, 1]`` and the intrinsics ``K`` of those S x S pixels go in; the
raw parameters of an assembly of M superquadrics, its pose in the camera frame and (with a
mask head) the target's mask come out, as one :class:`NetworkOutput`.

Architecture (each exchangeable part chosen by name in :class:`NetworkConfig`):
    - Encoder (``encoder``): EfficientNet-B0 (the paper's) or EfficientNet-Lite0
      (:mod:`~sq_mitsuba.model.encoder`), optionally from ImageNet weights
      (``pretrained``); it gives feature maps at strides 4, 8, 16 and 32.
    - Latent head (``latent``, :data:`~sq_mitsuba.model.heads.LATENT_HEADS`): the maps ->
      two latents z_sq and z_pose, pooled (the paper's figure) or spatial (the authors' code).
    - G_sq (``shape_decoder``): M three-layer MLPs (latent -> hidden -> hidden -> 16, SiLU
      between layers), run as ONE batched operation over a (M, in, out) weight tensor
      (:class:`GroupedLinear`), giving ``raw`` (B, M, 16), squashed into valid parameters by
      :meth:`~sq_mitsuba.geometry.assembly.Assembly.from_raw`; with ``existence`` each MLP has
      a 17th output, the primitive's existence logit (``existence_logits`` (B, M)); or
      (``"regions"``) one primitive per cell of the stride-32 grid through one shared MLP
      (:class:`~sq_mitsuba.model.region_decoder.RegionDecoder`).
    - Pose head (``pose_head``, :data:`~sq_mitsuba.model.heads.POSE_HEADS`): z_pose -> a
      rotation (regressed 6D, or a distribution over a grid of SO(3)) and the raw image
      position (u, v) of the body origin and its depth z, back-projected through K to the
      full translation ``t = z K^-1 [u, v, 1]``.
    - Mask head (``mask_head``): the target's mask at a quarter of the input size, or at its
      full size (``mask_resolution = "full"``: corrected from the image's own pixels).
    - Depth head (``depth_head``): the depth of the surface seen in each stride-4 cell, an
      auxiliary output trained by the ``surface_depth`` term
      (:mod:`~sq_mitsuba.model.surface_depth`).
    - Normal head (``normal_head``): the camera-frame normal of the surface seen in each
      stride-4 cell, trained by the ``surface_normal`` term
      (:mod:`~sq_mitsuba.model.surface_normals`); the body axes can be read from it.

Convention:
    - Input normalisation happens inside the network: ``(x - input_mean) / input_std`` with
      the encoder's statistics by default (B0: ImageNet's channel statistics averaged over
      RGB; Lite0: 0.498 / 0.502, TensorFlow's 127 / 128), so callers pass [0, 1] images and
      ImageNet weights (whose grey stem sums the RGB filters) see what they were trained on.
    - Pose: body to camera, OpenCV camera frame, ``x_cam = R x_body + t``.
    - Image position: ``u = W / 2 (1 + pixel_extent tanh(a_u))``, ``v`` likewise with H; it is
      measured from the image centre, not the principal point, because the encoder sees where
      the target lies in the image; the principal point enters only through K^-1.
    - Depth: ``z = depth_prior * (f / S) / prior_focal_ratio * softplus(a_z) / ln 2`` with
      ``f / S = sqrt(fx fy / (W H))``, the focal length in image widths. A target of a given
      size in pixels lies proportionally farther from a longer lens, so scaling the depth with
      the focal length keeps one set of weights right for any camera, and ``a_z = 0`` gives the
      typical depth ``depth_prior`` at the dataset camera.
    - Initial prediction (last layers: small weights, chosen biases): M primitives of semi-axes
      0.255 (raw size 0), shape 0.5, identity rotation, no taper, centres spread on a sphere of
      radius ``init_spread`` around the origin; pose rotation near identity (the 6D head; the
      grid head's scores near uniform), origin near the image centre at the typical depth.
      Existence logits start at ln 9 (p = 0.9: one grown from a network without them starts as it).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sq_mitsuba.checks import value_checks_enabled
from sq_mitsuba.config import validate
from sq_mitsuba.geometry.assembly import NUM_PARAMS, Assembly, ParameterRanges
from sq_mitsuba.geometry.rotation import IDENTITY_6D
from sq_mitsuba.model import rotation_grid  # noqa: F401  (registers the "grid" pose head)
from sq_mitsuba.model.encoder import EfficientNet, fold_batchnorm
from sq_mitsuba.model.heads import LATENT_HEADS, POSE_HEADS, MaskHead
from sq_mitsuba.model.network_config import ENCODERS, NetworkConfig
from sq_mitsuba.model.pretrained import load_imagenet_weights, resolve_pretrained
from sq_mitsuba.model.region_decoder import RegionDecoder, region_grid

__all__ = [
    "ENCODERS",
    "INITIAL_EXISTENCE",
    "GroupedLinear",
    "NetworkConfig",
    "NetworkOutput",
    "SuperquadricGenerators",
    "SuperquadricNet",
    "check_camera_matrix",
    "initial_raw",
    "sphere_directions",
    "upgrade_state_dict",
]

_LN2 = math.log(2.0)
#: Initial existence probability of every primitive (its logit is the last layer's bias).
INITIAL_EXISTENCE = 0.9

# --- the batched generators ---------------------------------------------------------------


class GroupedLinear(nn.Module):
    """M independent linear layers applied as one batched matrix product.

    (M, B, in_features) -> (M, B, out_features), ``y[m] = x[m] @ weight[m] + bias[m]``. A
    (B, in_features) input is shared by all M layers. Initialised as ``nn.Linear``:
    U(-1/sqrt(in), 1/sqrt(in)) for weights and biases.

    Attributes:
        weight: (M, in_features, out_features), so ``weight[m]`` is ``nn.Linear.weight.T``.
        bias: (M, out_features).
    """

    def __init__(self, groups: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(groups, in_features, out_features))
        self.bias = nn.Parameter(torch.empty(groups, out_features))
        bound = 1.0 / math.sqrt(in_features)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: Tensor) -> Tensor:
        """(M, B, in) or shared (B, in) -> (M, B, out)."""
        if x.dim() == 2:
            groups, out = self.weight.shape[0], self.weight.shape[2]
            # A shared input is one matmul against all M weight matrices side by side.
            flat = self.weight.permute(1, 0, 2).reshape(x.shape[1], groups * out)
            y = (x @ flat).view(x.shape[0], groups, out).transpose(0, 1)
            return y + self.bias[:, None, :]
        return torch.baddbmm(self.bias[:, None, :], x, self.weight)

    def extra_repr(self) -> str:
        groups, fan_in, fan_out = self.weight.shape
        return f"groups={groups}, in_features={fan_in}, out_features={fan_out}"


class SuperquadricGenerators(nn.Module):
    """G_sq: M three-layer MLPs evaluated together: z_sq (B, latent) -> (B, M, 16), or
    (B, M, 17) with ``existence`` (the 16 raw parameters, then the existence logit).

    Layer k of primitive m is ``layers[k].weight[m]`` / ``.bias[m]``; SiLU follows the first
    two layers.
    """

    def __init__(self, num_primitives: int, latent_dim: int, hidden_dim: int,
                 existence: bool = False) -> None:
        super().__init__()
        self.layers = nn.ModuleList([
            GroupedLinear(num_primitives, latent_dim, hidden_dim),
            GroupedLinear(num_primitives, hidden_dim, hidden_dim),
            GroupedLinear(num_primitives, hidden_dim, NUM_PARAMS + int(existence)),
        ])

    def forward(self, z_sq: Tensor) -> Tensor:
        """(B, latent_dim) -> (B, M, 16), or (B, M, 17) with existence."""
        h = F.silu(self.layers[0](z_sq))
        h = F.silu(self.layers[1](h))
        return self.layers[2](h).transpose(0, 1)



# --- the network ----------------------------------------------------------------------------


@dataclass(frozen=True)
class NetworkOutput:
    """What :meth:`SuperquadricNet.forward` returns (B items, M primitives).

    Attributes:
        raw: (B, M, 16) unconstrained assembly parameters (see :attr:`assembly`).
        rotation: (B, 3, 3) body -> camera rotation (orthonormal, det 1).
        pixel: (B, 2) image position (u, v) of the body origin, in pixels of the input.
        depth: (B,) camera-frame z of the body origin, metres, > 0.
        translation: (B, 3) body origin in the camera frame, ``depth K^-1 [u, v, 1]``.
        rotation_6d: (B, 6) raw 6D rotation of a regressing pose head, else None.
        rotation_logits: (B, G) scores over the SO(3) grid of a distribution head, else None.
        mask_logits: (B, 1, ceil(H / 4), ceil(W / 4)) the mask head's logits (B, 1, H, W with
            ``mask_resolution = "full"``), else None.
        existence_logits: (B, M) each primitive's existence logit (``network.existence``),
            else None; the probability is its sigmoid (:attr:`existence`).
        view_to_body: (B, 3, 3) the rotation that turns ``raw``'s assembly into the body
            frame (``shape_frame = "view"``: the predicted rotation's transpose), else None
            (``raw`` is already in the body frame).
        surface_depth: (B, 1, ceil(H / 4), ceil(W / 4)) the depth of the surface seen in each
            stride-4 cell relative to the body origin's, metres (``depth_head``), else None.
        surface_normals: (B, 3, ceil(H / 4), ceil(W / 4)) the normal of the surface seen in
            each stride-4 cell, camera frame, not normalised (``normal_head``), else None.
    """

    raw: Tensor
    rotation: Tensor
    pixel: Tensor
    depth: Tensor
    translation: Tensor
    rotation_6d: Tensor | None = None
    rotation_logits: Tensor | None = None
    mask_logits: Tensor | None = None
    existence_logits: Tensor | None = None
    view_to_body: Tensor | None = None
    surface_depth: Tensor | None = None
    surface_normals: Tensor | None = None

    @property
    def assembly(self) -> Assembly:
        """The assembly in the body frame: ``Assembly.from_raw(raw)`` with the default
        :class:`ParameterRanges`, turned by ``view_to_body`` where the network reads shapes in
        the view frame. Built anew on each access: each loss term backpropagates through its
        own (one shared assembly sums the terms' gradients in another order, and training
        would no longer repeat the shipped model's runs bit for bit)."""
        assembly = Assembly.from_raw(self.raw, ParameterRanges())
        if self.view_to_body is None:
            return assembly
        return assembly.rotated(self.view_to_body.to(assembly.params))

    def with_true_rotation(self, rotation: Tensor) -> NetworkOutput:
        """This output with a view-frame assembly turned into the body frame by the true
        rotation (B, 3, 3) instead of the predicted one (what the training losses score: the
        shape then owes nothing to the rotation's error); unchanged for a body-frame network."""
        if self.view_to_body is None:
            return self
        return dataclasses.replace(self, view_to_body=rotation.transpose(-1, -2))

    @property
    def existence(self) -> Tensor | None:
        """(B, M) each primitive's existence probability (None without an existence head)."""
        return None if self.existence_logits is None else torch.sigmoid(self.existence_logits)


def sphere_directions(count: int) -> Tensor:
    """``count`` unit vectors spread evenly on the sphere (Fibonacci lattice), (count, 3)."""
    k = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * k / count
    radius = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    return torch.stack([radius * torch.cos(phi), radius * torch.sin(phi), z], dim=-1)


def initial_raw(num_primitives: int, spread: float = 0.25) -> Tensor:
    """The network's initial assembly as raw parameters, (1, M, 16) float64: every primitive
    at mid size and mid exponent, unrotated, untapered, its centre ``spread`` from the body
    origin along :func:`sphere_directions` (one primitive: at the origin). The last layer's
    biases start here, and part targets are fitted from here (``model.part_targets``)."""
    raw = torch.zeros(1, num_primitives, NUM_PARAMS, dtype=torch.float64)
    raw[..., 8:14] = torch.tensor(IDENTITY_6D, dtype=torch.float64)
    if num_primitives > 1:
        # Raw translation r gives translation_scale tanh(r): invert for the wanted centres.
        centres = spread * sphere_directions(num_primitives)
        raw[0, :, 5:8] = torch.atanh(centres / ParameterRanges().translation_scale)
    return raw


def check_camera_matrix(camera_matrix: Tensor, batch: int) -> Tensor:
    """Validate intrinsics (3, 3) or (batch, 3, 3) and return them as (batch, 3, 3).

    K must be finite, upper triangular with positive focal lengths and last row (0, 0, 1).
    """
    if not isinstance(camera_matrix, Tensor) or not camera_matrix.is_floating_point():
        got = camera_matrix.dtype if isinstance(camera_matrix, Tensor) else type(camera_matrix)
        raise ValueError(f"camera_matrix: expected a floating-point tensor, got {got}")
    if camera_matrix.shape not in ((3, 3), (batch, 3, 3)):
        raise ValueError(f"camera_matrix: expected shape (3, 3) or ({batch}, 3, 3), "
                         f"got {tuple(camera_matrix.shape)}")
    k = camera_matrix.expand(batch, 3, 3)
    if not value_checks_enabled():  # each check reads the device: a training step skips them
        return k
    with torch.no_grad():
        if not bool(torch.isfinite(k).all()):
            raise ValueError("camera_matrix: contains NaN or infinite values")
        last = k[:, 2] - k.new_tensor([0.0, 0.0, 1.0])
        if bool(last.abs().amax() > 0) or bool(k[:, 1, 0].abs().amax() > 0):
            raise ValueError("camera_matrix: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
        if bool((k[:, 0, 0] <= 0).any()) or bool((k[:, 1, 1] <= 0).any()):
            raise ValueError("camera_matrix: focal lengths must be > 0")
    return k



def _check_names(config: NetworkConfig) -> None:
    """One-line ValueError for an unknown head or normalisation (the config checks encoders)."""
    for field, registry in (("latent", LATENT_HEADS), ("pose_head", POSE_HEADS)):
        value = getattr(config, field)
        if value not in registry:
            raise ValueError(f"network.{field}: unknown {value!r}; "
                             f"expected one of {', '.join(sorted(registry))}")
    if config.input_std is not None and not config.input_std > 0:
        raise ValueError(f"network.input_std: expected > 0, got {config.input_std}")
    if config.shape_decoder == "regions":
        cells = region_grid(config.image_size) ** 2
        if config.shape_frame != "view":
            raise ValueError("network.shape_decoder: 'regions' reads shapes in the view frame; "
                             "set network.shape_frame = \"view\"")
        if not config.existence:
            raise ValueError("network.shape_decoder: 'regions' switches off the cells that show "
                             "empty space; set network.existence = true")
        if config.num_primitives != cells:
            raise ValueError(f"network.num_primitives: the 'regions' decoder reads one primitive "
                             f"per cell of the stride-32 grid, {cells} at image_size "
                             f"{config.image_size}; got {config.num_primitives}")


class SuperquadricNet(nn.Module):
    """Images and intrinsics -> assembly, pose and mask (:class:`NetworkOutput`).

    Args:
        config: a :class:`NetworkConfig`; ``config.pretrained`` (if set) is loaded into the
            encoder here.

    Attributes:
        config: the config.
        encoder: :class:`~sq_mitsuba.model.encoder.EfficientNet` of ``config.encoder``.
        latent_head: ``LATENT_HEADS[config.latent]``: feature maps -> z_sq, z_pose.
        sq_generator: G_sq, :class:`SuperquadricGenerators` (``shape_decoder = "slots"``) or
            :class:`~sq_mitsuba.model.region_decoder.RegionDecoder` (``"regions"``).
        pose_head: ``POSE_HEADS[config.pose_head]``: z_pose -> rotation and raw position.
        mask_head: :class:`~sq_mitsuba.model.heads.MaskHead` or None.
        depth_head: a quarter-resolution :class:`~sq_mitsuba.model.heads.MaskHead` whose one
            output is the visible surface's depth instead of a logit, or None.
    """

    def __init__(self, config: NetworkConfig | None = None) -> None:
        super().__init__()
        config = NetworkConfig() if config is None else config
        validate(config)
        _check_names(config)
        self.config = config
        variant = ENCODERS[config.encoder][0]
        self.encoder = EfficientNet(config.in_channels, None, config.drop_connect_rate, variant)
        if config.pretrained is not None:
            load_imagenet_weights(self.encoder, resolve_pretrained(config.pretrained, variant))
        channels = (*self.encoder.pyramid_channels, self.encoder.num_features)
        self.latent_head = LATENT_HEADS[config.latent](config, channels)
        if not getattr(self.latent_head, "uses_head_map", True):
            self.encoder.head = None  # unused: no parameter without a gradient (DDP)
        self.sq_generator: SuperquadricGenerators | RegionDecoder = (
            RegionDecoder(config, channels) if config.shape_decoder == "regions"
            else SuperquadricGenerators(config.num_primitives, config.latent_dim,
                                        config.hidden_dim, config.existence))
        self.pose_head = POSE_HEADS[config.pose_head](config)
        self.mask_head = (MaskHead(self.encoder.pyramid_channels,
                                   full_resolution=config.mask_resolution == "full",
                                   in_channels=config.in_channels)
                          if config.mask_head else None)
        self.depth_head = MaskHead(self.encoder.pyramid_channels) if config.depth_head else None
        if self.depth_head is not None:
            with torch.no_grad():  # depth 0 (the origin's) at first, not a mask's prior logit
                self.depth_head.to_logit.bias.zero_()
        self.normal_head = (MaskHead(self.encoder.pyramid_channels,
                                     width=config.normal_head_width, outputs=3,
                                     layers=config.normal_head_layers)
                            if config.normal_head else None)
        if self.normal_head is not None:
            with torch.no_grad():  # facing the camera at first (z < 0), not a mask's prior
                self.normal_head.to_logit.bias.copy_(torch.tensor([0.0, 0.0, -1.0]))
        mean, std = config.normalisation()
        self.register_buffer("input_mean", torch.tensor(mean), persistent=False)
        self.register_buffer("input_std", torch.tensor(std), persistent=False)
        # Set by folded(): the encoder stores its weights channels-last, so feed it that way.
        self.channels_last = False
        self._init_last_layers()

    def freeze_except(self, prefixes: Sequence[str]) -> None:
        """Train only the parameters whose names start with one of ``prefixes`` (e.g.
        ``("mask_head.",)``); every other parameter gets no gradient, and every module holding
        only frozen parameters stays in eval mode through :meth:`train` (no batch-norm
        statistics, no stochastic depth), so the frozen part computes exactly what it did.
        An empty ``prefixes`` trains everything.

        Raises:
            ValueError: a prefix that names no parameter.
        """
        names = [name for name, _ in self.named_parameters()]
        for prefix in prefixes:
            if not any(name.startswith(prefix) for name in names):
                parts = sorted({name.split(".")[0] for name in names})
                raise ValueError(f"trainable: {prefix!r} names no parameter of the network "
                                 f"(its parts: {', '.join(parts)})")
        for name, parameter in self.named_parameters():
            parameter.requires_grad_(not prefixes or name.startswith(tuple(prefixes)))
        self.train(self.training)

    def train(self, mode: bool = True) -> SuperquadricNet:
        """``nn.Module.train``; modules of frozen parameters alone stay in eval mode."""
        super().train(mode)
        if mode:
            for module in self.modules():
                parameters = list(module.parameters())
                if parameters and not any(p.requires_grad for p in parameters):
                    module.eval()
        return self

    @torch.no_grad()
    def _init_last_layers(self) -> None:
        """Small last-layer weights, biases that give a sane initial prediction (module doc)."""
        gain = self.config.init_gain
        regions = isinstance(self.sq_generator, RegionDecoder)
        last_sq = self.sq_generator.last_layer if regions else self.sq_generator.layers[2]
        last_sq.weight.mul_(gain)
        # Regions: one bias shared by every cell, one primitive at the origin (the cell's
        # anchor moves it); slots: a bias per primitive, the centres spread about the origin.
        rows = 1 if regions else self.config.num_primitives
        bias = torch.zeros(rows, last_sq.bias.shape[-1], dtype=torch.float64)
        bias[:, :NUM_PARAMS] = initial_raw(rows, self.config.init_spread)[0]
        if self.config.existence:  # every primitive present at first (module doc)
            bias[:, NUM_PARAMS] = math.log(INITIAL_EXISTENCE / (1.0 - INITIAL_EXISTENCE))
        last_sq.bias.copy_(bias.view_as(last_sq.bias))
        reset = getattr(self.pose_head, "reset_last_layer", None)
        if reset is not None:  # a_u = a_v = 0: image centre; a_z = 0: depth prior
            reset(gain)

    def normalise(self, images: Tensor) -> Tensor:
        """Images (B, C, H, W) in [0, 1] -> the encoder's input (centred, scaled)."""
        x = (images - self.input_mean) / self.input_std
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        return x

    def forward(self, images: Tensor, camera_matrix: Tensor) -> NetworkOutput:
        """Predict the assembly, its pose and (with a mask head) the mask.

        Args:
            images: (B, in_channels, H, W) floating point in [0, 1] (normalised inside); H = W =
                ``config.image_size`` in training and in :class:`~sq_mitsuba.inference.predictor.
                Predictor`, though any size runs.
            camera_matrix: intrinsics K (3, 3) or (B, 3, 3) in pixels of these H x W images.

        Returns:
            :class:`NetworkOutput`.

        Raises:
            ValueError: wrong shape or dtype of ``images``; bad ``camera_matrix``.
        """
        channels = self.config.in_channels
        if (not isinstance(images, Tensor) or images.dim() != 4 or images.shape[1] != channels
                or not images.is_floating_point()):
            got = (f"{tuple(images.shape)} {images.dtype}" if isinstance(images, Tensor)
                   else type(images).__name__)
            raise ValueError(f"images: expected a floating-point tensor (B, {channels}, H, W), "
                             f"got {got}")
        batch, _, height, width = images.shape
        k = check_camera_matrix(camera_matrix, batch).to(images)
        normalised = self.normalise(images)
        maps = self.encoder.forward_pyramid(normalised)
        z_sq, z_pose = self.latent_head(maps)
        pose = self.pose_head(z_pose)
        spread = 1.0 + self.config.pixel_extent * torch.tanh(pose.position[:, :2])  # no copy
        pixel = torch.stack([0.5 * width * spread[:, 0], 0.5 * height * spread[:, 1]], dim=-1)
        focal_ratio = torch.sqrt(k[:, 0, 0] * k[:, 1, 1] / (width * height))  # (B,)
        depth_scale = self.config.depth_prior / self.config.prior_focal_ratio / _LN2
        depth = depth_scale * focal_ratio * F.softplus(pose.position[:, 2])
        homogeneous = torch.cat([pixel, pixel.new_ones(batch, 1)], dim=-1)[..., None]
        ray = torch.linalg.solve_triangular(k, homogeneous, upper=True)[..., 0]  # K^-1 [u,v,1]
        translation = depth[:, None] * ray
        if isinstance(self.sq_generator, RegionDecoder):
            generated = self.sq_generator(maps[3], z_sq, pixel, depth, k, width, height)
        else:
            generated = self.sq_generator(z_sq)  # (B, M, 16), or (B, M, 17) with existence
        raw, existence_logits = generated, None
        if self.config.existence:
            raw, existence_logits = generated[..., :NUM_PARAMS], generated[..., NUM_PARAMS]
        mask_logits = None if self.mask_head is None else self.mask_head(maps, normalised)
        surface_depth = None if self.depth_head is None else self.depth_head(maps)
        surface_normals = None if self.normal_head is None else self.normal_head(maps)
        return NetworkOutput(raw, pose.rotation, pixel, depth, translation,
                             rotation_6d=pose.rotation_6d,
                             rotation_logits=pose.rotation_logits, mask_logits=mask_logits,
                             existence_logits=existence_logits,
                             view_to_body=(pose.rotation.transpose(-1, -2)
                                           if self.config.shape_frame == "view" else None),
                             surface_depth=surface_depth, surface_normals=surface_normals)

    def folded(self, channels_last: bool = True) -> SuperquadricNet:
        """Inference copy: eval mode, no gradients, encoder BatchNorm folded into its convs.

        Equal to ``self.eval()``'s output up to float rounding (~1e-5 relative in float32).
        The copy is a snapshot: later training of ``self`` does not reach it.
        """
        # The encoder is copied once, by the folding: the memo keeps deepcopy from copying it
        # first with the rest (half the time of a copy of the whole network).
        fast = copy.deepcopy(self, memo={id(self.encoder): self.encoder})
        fast.encoder = fold_batchnorm(self.encoder, channels_last=channels_last)
        fast.channels_last = channels_last
        return fast.eval().requires_grad_(False)


#: Module paths before the heads were exchangeable -> today's (checkpoints of that layout,
#: the shipped model's included, load through :func:`upgrade_state_dict`).
_LEGACY_PREFIXES = (
    ("to_z_sq.", "latent_head.to_z_sq."),
    ("to_z_pose.", "latent_head.to_z_pose."),
    ("pose_generator.", "pose_head.mlp."),
)


def upgrade_state_dict(state: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """A state dict of the fixed-head layout (one pooled latent pair, one 6D pose MLP) in
    today's module names; a state dict already in today's names is returned unchanged."""
    upgraded = {}
    for key, value in state.items():
        for old, new in _LEGACY_PREFIXES:
            if key.startswith(old):
                key = new + key[len(old):]
                break
        upgraded[key] = value
    return upgraded
