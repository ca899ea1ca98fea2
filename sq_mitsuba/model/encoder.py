"""EfficientNet-B0 and EfficientNet-Lite0 image encoders in plain torch, with BN folding.

Two variants of one architecture (:data:`VARIANTS`):

- ``b0``: the B0 of Tan & Le (2019) layer for layer, with the same parameter shapes as
  torchvision's and timm's ``efficientnet_b0`` (5,288,548 parameters with an RGB stem and a
  1000-class classifier): squeeze-excite in every block, SiLU, BatchNorm eps 1e-5,
  symmetric "same" padding.
- ``lite0``: EfficientNet-Lite0, B0's stage table made for mobile inference: no
  squeeze-excite, ReLU6, BatchNorm eps 1e-3, and TensorFlow's "SAME" padding (asymmetric for
  stride 2: the extra row and column go at the bottom and right), because its ImageNet
  weights were trained in TensorFlow (4,652,008 parameters with an RGB stem and classifier).

Module names are this file's own (``stem``, ``stages``, ``head``, ``classifier``);
:mod:`sq_mitsuba.model.pretrained` maps the published namings (torchvision, timm, and the
lukemelas naming of the Lite0 ImageNet file) onto them.

Convention:
    - Input: ``images`` (B, C, H, W), floating point, C = ``in_channels`` (1 for the grayscale
      renders of this project). Pixel values are expected in [0, 1]. The network does not
      normalise its input: subtracting a mean / dividing by a std (for example ImageNet's when
      starting from ImageNet weights) is the caller's choice, and must be the same in training
      and at inference.
    - Any H, W works; the output stride is 32 (a 128 x 128 image ends as a 4 x 4 map before the
      global average pooling). In training mode BatchNorm needs more than one value per channel,
      i.e. B * ceil(H / 32) * ceil(W / 32) > 1.
    - Output: ``features`` (B, 1280) after global average pooling when ``num_classes`` is None,
      else ``logits`` (B, num_classes) from dropout(0.2) + a linear layer;
      :meth:`EfficientNet.forward_pyramid` gives the feature maps at strides 4, 8, 16 and 32
      instead (spatial latents and the mask head read them).
    - BatchNorm: momentum 0.1 (torch's default) in both variants; eps 1e-5 for B0 (as
      torchvision's and timm's B0) and 1e-3 for Lite0 (as its TensorFlow original).
    - Stochastic depth ("row" mode): block k of the 16 MBConv blocks (k = 0..15) drops its
      residual branch per sample with probability ``drop_connect_rate * k / 16`` (0 for the first
      block, 0.1875 for the last at the default 0.2, as torchvision), only in training mode and
      only in blocks with a residual connection; kept samples are scaled by 1 / (1 - p).
    - Squeeze-excite (B0 only): reduced width max(1, block_input_channels // 4), SiLU then
      sigmoid gate.
"""

from __future__ import annotations

import copy
import math
from collections import OrderedDict
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

# (expand ratio, kernel, stride of the first block, output channels, repeats) per stage.
STAGES: tuple[tuple[int, int, int, int, int], ...] = (
    (1, 3, 1, 16, 1),
    (6, 3, 2, 24, 2),
    (6, 5, 2, 40, 2),
    (6, 3, 2, 80, 3),
    (6, 5, 1, 112, 3),
    (6, 5, 2, 192, 4),
    (6, 3, 1, 320, 1),
)
STEM_CHANNELS = 32
NUM_FEATURES = 1280
CLASSIFIER_DROPOUT = 0.2
#: Stages whose outputs :meth:`EfficientNet.forward_pyramid` returns (strides 4, 8, 16, 32).
PYRAMID_STAGES = (1, 2, 4, 6)


@dataclass(frozen=True)
class Variant:
    """What tells B0 and Lite0 apart (module docstring)."""

    squeeze_excite: bool
    activation: str  # "silu" or "relu6"
    bn_eps: float
    tf_same_padding: bool


VARIANTS: dict[str, Variant] = {
    "b0": Variant(squeeze_excite=True, activation="silu", bn_eps=1e-5, tf_same_padding=False),
    "lite0": Variant(squeeze_excite=False, activation="relu6", bn_eps=1e-3,
                     tf_same_padding=True),
}
_ACTIVATIONS = {"silu": nn.SiLU, "relu6": nn.ReLU6}


class ConvBNAct(nn.Module):
    """Conv2d (no bias, "same" padding) + BatchNorm2d + optional activation.

    (B, in_channels, H, W) -> (B, out_channels, ceil(H / stride), ceil(W / stride)).
    :func:`fold_batchnorm` turns ``bn`` into ``nn.Identity`` and gives ``conv`` a bias.
    ``tf_same_padding`` pads a strided conv as TensorFlow's "SAME" does (total padding
    ``max((ceil(n / s) - 1) s + k - n, 0)``, the odd one at the end); for stride 1 and odd
    kernels that equals the symmetric padding.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int,
        stride: int = 1,
        groups: int = 1,
        activation: str | None = "silu",
        bn_eps: float = 1e-5,
        tf_same_padding: bool = False,
    ) -> None:
        super().__init__()
        self.pad_like_tf = tf_same_padding and stride > 1
        self.conv = nn.Conv2d(
            in_channels,
            out_channels,
            kernel_size,
            stride=stride,
            padding=0 if self.pad_like_tf else (kernel_size - 1) // 2,
            groups=groups,
            bias=False,
        )
        self.bn: nn.Module = nn.BatchNorm2d(out_channels, eps=bn_eps)
        self.act: nn.Module = _ACTIVATIONS[activation]() if activation else nn.Identity()

    def _tf_pad(self, x: Tensor) -> Tensor:
        pads = []
        for size, k, s in zip(x.shape[:-3:-1], self.conv.kernel_size[::-1],
                              self.conv.stride[::-1], strict=True):  # width, then height
            total = max((math.ceil(size / s) - 1) * s + k - size, 0)
            pads += [total // 2, total - total // 2]
        return F.pad(x, pads)

    def forward(self, x: Tensor) -> Tensor:
        """(B, C_in, H, W) -> (B, C_out, H', W')."""
        if self.pad_like_tf:
            x = self._tf_pad(x)
        return self.act(self.bn(self.conv(x)))


class SqueezeExcite(nn.Module):
    """Channel gate: global mean -> 1x1 conv -> SiLU -> 1x1 conv -> sigmoid, times the input.

    (B, channels, H, W) -> (B, channels, H, W).
    """

    def __init__(self, channels: int, reduced_channels: int) -> None:
        super().__init__()
        self.reduce = nn.Conv2d(channels, reduced_channels, 1)
        self.expand = nn.Conv2d(reduced_channels, channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        """(B, C, H, W) -> (B, C, H, W)."""
        scale = x.mean(dim=(2, 3), keepdim=True)  # (B, C, 1, 1)
        scale = torch.sigmoid(self.expand(F.silu(self.reduce(scale))))
        return x * scale


class StochasticDepth(nn.Module):
    """Row-mode stochastic depth: zero whole samples with probability ``p`` in training.

    (B, ...) -> (B, ...). Kept samples are divided by 1 - p so the expectation is unchanged;
    in eval mode (or with p = 0) the input is returned as is.
    """

    def __init__(self, p: float) -> None:
        super().__init__()
        if not 0.0 <= p < 1.0:
            raise ValueError(f"p: expected a drop probability in [0, 1), got {p}")
        self.p = float(p)

    def forward(self, x: Tensor) -> Tensor:
        """(B, ...) -> (B, ...)."""
        if not self.training or self.p == 0.0:
            return x
        survival = 1.0 - self.p
        shape = (x.shape[0],) + (1,) * (x.dim() - 1)
        keep = torch.empty(shape, dtype=x.dtype, device=x.device).bernoulli_(survival)
        return x * keep.div_(survival)

    def extra_repr(self) -> str:
        return f"p={self.p}"


class MBConv(nn.Module):
    """Inverted residual block: [1x1 expand] -> depthwise kxk -> [squeeze-excite] -> 1x1 project.

    (B, in_channels, H, W) -> (B, out_channels, ceil(H / stride), ceil(W / stride)). The
    residual connection (with stochastic depth on the branch) exists when stride is 1 and
    in_channels == out_channels; there is no expand conv when the expand ratio is 1.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        expand_ratio: int,
        kernel_size: int,
        stride: int,
        drop_rate: float,
        variant: Variant = VARIANTS["b0"],
    ) -> None:
        super().__init__()
        hidden = in_channels * expand_ratio
        common = {"activation": variant.activation, "bn_eps": variant.bn_eps,
                  "tf_same_padding": variant.tf_same_padding}
        self.expand: ConvBNAct | None = (
            ConvBNAct(in_channels, hidden, 1, **common) if expand_ratio != 1 else None
        )
        self.depthwise = ConvBNAct(hidden, hidden, kernel_size, stride=stride, groups=hidden,
                                   **common)
        self.se: nn.Module = (SqueezeExcite(hidden, max(1, in_channels // 4))
                              if variant.squeeze_excite else nn.Identity())
        self.project = ConvBNAct(hidden, out_channels, 1, **{**common, "activation": None})
        self.use_residual = stride == 1 and in_channels == out_channels
        self.drop_path = StochasticDepth(drop_rate)

    def forward(self, x: Tensor) -> Tensor:
        """(B, C_in, H, W) -> (B, C_out, H', W')."""
        y = x if self.expand is None else self.expand(x)
        y = self.project(self.se(self.depthwise(y)))
        if self.use_residual:
            y = self.drop_path(y) + x
        return y


class EfficientNet(nn.Module):
    """EfficientNet-B0 or -Lite0 encoder: images (B, in_channels, H, W) -> features (B, 1280).

    Args:
        in_channels: channels of the input images (1 for grayscale, 3 for RGB).
        num_classes: None for the feature encoder; an int adds dropout(0.2) + Linear(1280,
            num_classes) and ``forward`` returns logits (B, num_classes).
        drop_connect_rate: stochastic-depth rate; block k of 16 drops with rate * k / 16.
        variant: ``"b0"`` or ``"lite0"`` (:data:`VARIANTS`).

    Attributes:
        stem: 3x3 stride-2 conv to 32 channels (+ BN + SiLU).
        stages: 7 ``nn.Sequential`` stages of :class:`MBConv` blocks (``STAGES``).
        head: 1x1 conv 320 -> 1280 (+ BN + activation).
        classifier: ``Sequential(dropout, fc)`` or None.
        num_features: 1280, the width of ``features``.
        pyramid_channels: channels of the :meth:`forward_pyramid` maps, (24, 40, 112, 320).
    """

    def __init__(
        self,
        in_channels: int = 1,
        num_classes: int | None = None,
        drop_connect_rate: float = 0.2,
        variant: str = "b0",
    ) -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"variant: expected one of {sorted(VARIANTS)}, got {variant!r}")
        if isinstance(in_channels, bool) or not isinstance(in_channels, int) or in_channels < 1:
            raise ValueError(f"in_channels: expected a positive int, got {in_channels!r}")
        if num_classes is not None and (
            isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 1
        ):
            raise ValueError(f"num_classes: expected None or a positive int, got {num_classes!r}")
        if not 0.0 <= drop_connect_rate < 1.0:
            raise ValueError(f"drop_connect_rate: expected [0, 1), got {drop_connect_rate}")
        self.in_channels = in_channels
        self.num_classes = num_classes
        self.num_features = NUM_FEATURES
        self.variant = variant
        self.pyramid_channels = tuple(STAGES[i][3] for i in PYRAMID_STAGES)
        spec = VARIANTS[variant]
        common = {"activation": spec.activation, "bn_eps": spec.bn_eps,
                  "tf_same_padding": spec.tf_same_padding}

        self.stem = ConvBNAct(in_channels, STEM_CHANNELS, 3, stride=2, **common)
        total_blocks = sum(stage[4] for stage in STAGES)
        stages: list[nn.Module] = []
        channels, block_index = STEM_CHANNELS, 0
        for expand_ratio, kernel, stride, out_channels, repeats in STAGES:
            blocks = []
            for j in range(repeats):
                rate = drop_connect_rate * block_index / total_blocks
                block_stride = stride if j == 0 else 1
                blocks.append(MBConv(channels, out_channels, expand_ratio, kernel, block_stride,
                                     rate, spec))
                channels, block_index = out_channels, block_index + 1
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.Sequential(*stages)
        self.head: ConvBNAct | None = ConvBNAct(channels, NUM_FEATURES, 1, **common)
        self.classifier: nn.Sequential | None = None
        if num_classes is not None:
            self.classifier = nn.Sequential(
                OrderedDict(
                    dropout=nn.Dropout(CLASSIFIER_DROPOUT),
                    fc=nn.Linear(NUM_FEATURES, num_classes),
                )
            )
        self._init_weights()

    def _init_weights(self) -> None:
        """Kaiming-normal (fan out) convs, unit/zero BN, uniform(+-1/sqrt(out)) linear."""
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out")
                if module.bias is not None:
                    nn.init.zeros_(module.bias)
            elif isinstance(module, nn.BatchNorm2d):
                nn.init.ones_(module.weight)
                nn.init.zeros_(module.bias)
            elif isinstance(module, nn.Linear):
                bound = 1.0 / math.sqrt(module.out_features)
                nn.init.uniform_(module.weight, -bound, bound)
                nn.init.zeros_(module.bias)

    def _check_images(self, images: Tensor) -> None:
        if (
            not isinstance(images, Tensor)
            or images.dim() != 4
            or images.shape[1] != self.in_channels
            or not images.is_floating_point()
        ):
            got = (
                f"{tuple(images.shape)} {images.dtype}"
                if isinstance(images, Tensor)
                else type(images).__name__
            )
            raise ValueError(
                f"images: expected a floating-point tensor (B, {self.in_channels}, H, W), got {got}"
            )

    def forward_pyramid(self, images: Tensor) -> list[Tensor]:
        """Feature maps of images (B, in_channels, H, W), finest first.

        Returns:
            ``[s4, s8, s16, s32, head]``: the outputs of stages 1, 2, 4 and 6, of
            ``pyramid_channels`` (24, 40, 112, 320) channels at strides 4, 8, 16, 32
            (``ceil(H / stride)`` rows), then the head's (B, 1280, ceil(H / 32), ceil(W / 32)),
            which is left out when ``head`` is None (a network whose heads do not read it
            drops it, so that no parameter goes without a gradient).
        """
        self._check_images(images)
        x = self.stem(images)
        maps = []
        for index, stage in enumerate(self.stages):
            x = stage(x)
            if index in PYRAMID_STAGES:
                maps.append(x)
        if self.head is not None:
            maps.append(self.head(x))
        return maps

    def forward_features(self, images: Tensor) -> Tensor:
        """Pooled features (B, 1280) of images (B, in_channels, H, W), ignoring the classifier;
        an encoder whose 1280-channel head was dropped (a network with spatial latents) has
        none: use :meth:`forward_pyramid`."""
        self._check_images(images)
        if self.head is None:
            raise ValueError("encoder: its 1280-channel head was dropped (spatial latents); "
                             "read its maps with forward_pyramid")
        x = self.head(self.stages(self.stem(images)))  # (B, 1280, H/32, W/32)
        return x.mean(dim=(2, 3))

    def forward(self, images: Tensor) -> Tensor:
        """images (B, in_channels, H, W) -> features (B, 1280), or logits (B, num_classes)."""
        features = self.forward_features(images)
        return features if self.classifier is None else self.classifier(features)


# --- inference ------------------------------------------------------------------------------


@torch.no_grad()
def _fuse_conv_bn(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> None:
    """Fold eval-mode ``bn`` into ``conv`` in place: W' = W * s, b' = beta + (b - mean) * s.

    s = gamma / sqrt(running_var + eps); computed in float64, stored in the conv's dtype.
    """
    dtype = conv.weight.dtype
    scale = bn.weight.double() / torch.sqrt(bn.running_var.double() + bn.eps)  # (C_out,)
    bias = torch.zeros_like(scale) if conv.bias is None else conv.bias.double()
    weight = conv.weight.double() * scale.view(-1, 1, 1, 1)
    bias = bn.bias.double() + (bias - bn.running_mean.double()) * scale
    conv.weight = nn.Parameter(weight.to(dtype))
    conv.bias = nn.Parameter(bias.to(dtype))


def fold_batchnorm(model: EfficientNet, channels_last: bool = False) -> EfficientNet:
    """Inference copy of ``model`` with every conv + BatchNorm pair fused into one conv.

    The copy is in eval mode, has no BatchNorm layers (each ``ConvBNAct.bn`` becomes
    ``nn.Identity`` and its conv gains a bias) and no gradients (``requires_grad`` False). Its
    output equals ``model.eval()``'s up to rounding: ~1e-14 in float64, ~1e-5 relative in float32.
    ``model`` itself is left untouched. Do not train the copy or load weights into it.

    Args:
        model: an :class:`EfficientNet` (any dtype, any device).
        channels_last: store the conv weights in ``torch.channels_last`` memory format; feed it
            ``images.contiguous(memory_format=torch.channels_last)`` for the fast CPU path.

    Returns:
        The folded copy: images (B, in_channels, H, W) -> features (B, 1280) or logits.
    """
    folded = copy.deepcopy(model).eval()
    pairs = [m for m in folded.modules() if isinstance(m, ConvBNAct)]
    for module in pairs:
        if isinstance(module.bn, nn.BatchNorm2d):
            _fuse_conv_bn(module.conv, module.bn)
            module.bn = nn.Identity()
    folded.requires_grad_(False)
    if channels_last:
        folded = folded.to(memory_format=torch.channels_last)
    return folded


#: The paper's encoder under its historical name.
EfficientNetB0 = EfficientNet
