"""EfficientNet-B0 image encoder in plain torch, with ImageNet weight loading and BN folding.

The network is the B0 of Tan & Le (2019) layer for layer, with the same parameter shapes as
torchvision's ``efficientnet_b0`` and timm's ``efficientnet_b0`` (5,288,548 parameters with an
RGB stem and a 1000-class classifier), so that their ImageNet state dicts load through
:func:`load_imagenet_weights`. Module names are this file's own (``stem``, ``stages``, ``head``,
``classifier``); the loader maps the two published namings onto them.

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
      else ``logits`` (B, num_classes) from dropout(0.2) + a linear layer.
    - BatchNorm: ``nn.BatchNorm2d`` defaults (eps 1e-5, momentum 0.1), as torchvision's B0
      (torchvision uses eps 1e-3 / momentum 0.01 only for B5-B7) and timm's B0.
    - Stochastic depth ("row" mode): block k of the 16 MBConv blocks (k = 0..15) drops its
      residual branch per sample with probability ``drop_connect_rate * k / 16`` (0 for the first
      block, 0.1875 for the last at the default 0.2, as torchvision), only in training mode and
      only in blocks with a residual connection; kept samples are scaled by 1 / (1 - p).
    - Squeeze-excite: reduced width max(1, block_input_channels // 4), SiLU then sigmoid gate.
"""

from __future__ import annotations

import copy
import math
import os
from collections import OrderedDict
from collections.abc import Callable, Mapping
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sq_mitsuba.inputs import load_torch_file

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


class ConvBNAct(nn.Module):
    """Conv2d (no bias, "same" padding) + BatchNorm2d + optional SiLU.

    (B, in_channels, H, W) -> (B, out_channels, ceil(H / stride), ceil(W / stride)).
    :func:`fold_batchnorm` turns ``bn`` into ``nn.Identity`` and gives ``conv`` a bias.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int,
        stride: int = 1,
        groups: int = 1,
        activation: bool = True,
    ) -> None:
        super().__init__()
        self.conv = nn.Conv2d(
            in_channels,
            out_channels,
            kernel_size,
            stride=stride,
            padding=(kernel_size - 1) // 2,
            groups=groups,
            bias=False,
        )
        self.bn: nn.Module = nn.BatchNorm2d(out_channels)
        self.act: nn.Module = nn.SiLU() if activation else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        """(B, C_in, H, W) -> (B, C_out, H', W')."""
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
    """Inverted residual block: [1x1 expand] -> depthwise kxk -> squeeze-excite -> 1x1 project.

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
    ) -> None:
        super().__init__()
        hidden = in_channels * expand_ratio
        self.expand: ConvBNAct | None = (
            ConvBNAct(in_channels, hidden, 1) if expand_ratio != 1 else None
        )
        self.depthwise = ConvBNAct(hidden, hidden, kernel_size, stride=stride, groups=hidden)
        self.se = SqueezeExcite(hidden, max(1, in_channels // 4))
        self.project = ConvBNAct(hidden, out_channels, 1, activation=False)
        self.use_residual = stride == 1 and in_channels == out_channels
        self.drop_path = StochasticDepth(drop_rate)

    def forward(self, x: Tensor) -> Tensor:
        """(B, C_in, H, W) -> (B, C_out, H', W')."""
        y = x if self.expand is None else self.expand(x)
        y = self.project(self.se(self.depthwise(y)))
        if self.use_residual:
            y = self.drop_path(y) + x
        return y


class EfficientNetB0(nn.Module):
    """EfficientNet-B0 encoder: images (B, in_channels, H, W) -> features (B, 1280).

    Args:
        in_channels: channels of the input images (1 for grayscale, 3 for RGB).
        num_classes: None for the feature encoder; an int adds dropout(0.2) + Linear(1280,
            num_classes) and ``forward`` returns logits (B, num_classes).
        drop_connect_rate: stochastic-depth rate; block k of 16 drops with rate * k / 16.

    Attributes:
        stem: 3x3 stride-2 conv to 32 channels (+ BN + SiLU).
        stages: 7 ``nn.Sequential`` stages of :class:`MBConv` blocks (``STAGES``).
        head: 1x1 conv 320 -> 1280 (+ BN + SiLU).
        classifier: ``Sequential(dropout, fc)`` or None.
        num_features: 1280, the width of ``features``.
    """

    def __init__(
        self,
        in_channels: int = 1,
        num_classes: int | None = None,
        drop_connect_rate: float = 0.2,
    ) -> None:
        super().__init__()
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

        self.stem = ConvBNAct(in_channels, STEM_CHANNELS, 3, stride=2)
        total_blocks = sum(stage[4] for stage in STAGES)
        stages: list[nn.Module] = []
        channels, block_index = STEM_CHANNELS, 0
        for expand_ratio, kernel, stride, out_channels, repeats in STAGES:
            blocks = []
            for j in range(repeats):
                rate = drop_connect_rate * block_index / total_blocks
                block_stride = stride if j == 0 else 1
                blocks.append(
                    MBConv(channels, out_channels, expand_ratio, kernel, block_stride, rate)
                )
                channels, block_index = out_channels, block_index + 1
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.Sequential(*stages)
        self.head = ConvBNAct(channels, NUM_FEATURES, 1)
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

    def forward_features(self, images: Tensor) -> Tensor:
        """Pooled features (B, 1280) of images (B, in_channels, H, W), ignoring the classifier."""
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
        x = self.head(self.stages(self.stem(images)))  # (B, 1280, H/32, W/32)
        return x.mean(dim=(2, 3))

    def forward(self, images: Tensor) -> Tensor:
        """images (B, in_channels, H, W) -> features (B, 1280), or logits (B, num_classes)."""
        features = self.forward_features(images)
        return features if self.classifier is None else self.classifier(features)


# --- ImageNet weights -----------------------------------------------------------------------


def _split_block_key(key: str) -> tuple[int, str, str, list[str]]:
    """``stages.s.j.part.sub.rest`` -> (s, "s.j", part, [sub, *rest])."""
    parts = key.split(".")
    return int(parts[1]), f"{parts[1]}.{parts[2]}", parts[3], parts[4:]


def _torchvision_key(key: str) -> str:
    """This module's state-dict key -> torchvision ``efficientnet_b0`` key."""
    parts = key.split(".")
    conv_bn = {"conv": "0", "bn": "1"}
    if parts[0] in ("stem", "head"):
        index = 0 if parts[0] == "stem" else len(STAGES) + 1
        return ".".join(["features", str(index), conv_bn[parts[1]], *parts[2:]])
    if parts[0] == "stages":
        stage, block, part, rest = _split_block_key(key)
        offset = 0 if STAGES[stage][0] == 1 else 1  # position of the depthwise conv
        prefix = f"features.{stage + 1}.{block.split('.')[1]}.block"
        if part == "se":
            fc = {"reduce": "fc1", "expand": "fc2"}[rest[0]]
            return ".".join([prefix, str(offset + 1), fc, *rest[1:]])
        position = {"expand": 0, "depthwise": offset, "project": offset + 2}[part]
        return ".".join([prefix, str(position), conv_bn[rest[0]], *rest[1:]])
    if parts[0] == "classifier" and parts[1] == "fc":
        return ".".join(["classifier", "1", *parts[2:]])
    raise KeyError(key)


def _timm_key(key: str) -> str:
    """This module's state-dict key -> timm ``efficientnet_b0`` key."""
    parts = key.split(".")
    if parts[0] == "stem":
        return ".".join([{"conv": "conv_stem", "bn": "bn1"}[parts[1]], *parts[2:]])
    if parts[0] == "head":
        return ".".join([{"conv": "conv_head", "bn": "bn2"}[parts[1]], *parts[2:]])
    if parts[0] == "stages":
        stage, block, part, rest = _split_block_key(key)
        prefix = f"blocks.{block}"
        if part == "se":
            conv = {"reduce": "conv_reduce", "expand": "conv_expand"}[rest[0]]
            return ".".join([prefix, "se", conv, *rest[1:]])
        if STAGES[stage][0] == 1:  # timm DepthwiseSeparableConv
            names = {
                ("depthwise", "conv"): "conv_dw",
                ("depthwise", "bn"): "bn1",
                ("project", "conv"): "conv_pw",
                ("project", "bn"): "bn2",
            }
        else:  # timm InvertedResidual
            names = {
                ("expand", "conv"): "conv_pw",
                ("expand", "bn"): "bn1",
                ("depthwise", "conv"): "conv_dw",
                ("depthwise", "bn"): "bn2",
                ("project", "conv"): "conv_pwl",
                ("project", "bn"): "bn3",
            }
        return ".".join([prefix, names[(part, rest[0])], *rest[1:]])
    if parts[0] == "classifier" and parts[1] == "fc":
        return ".".join(["classifier", *parts[2:]])
    raise KeyError(key)


_NAMINGS: dict[str, tuple[str, Callable[[str], str]]] = {
    "torchvision": ("features.0.0.weight", _torchvision_key),
    "timm": ("conv_stem.weight", _timm_key),
}


def _listing(keys: set[str], limit: int = 5) -> str:
    ordered = sorted(keys)
    more = f" (+{len(ordered) - limit} more)" if len(ordered) > limit else ""
    return ", ".join(ordered[:limit]) + more


def load_imagenet_weights(model: EfficientNetB0, path: str | os.PathLike[str]) -> EfficientNetB0:
    """Load a local ImageNet state dict (torchvision or timm naming) into ``model`` in place.

    The naming is detected from the stem key (``features.0.0.weight`` or ``conv_stem.weight``).
    For a 1-channel model the RGB stem weight (32, 3, 3, 3) is summed over its input channels,
    so that a gray image x gives what the RGB network gives for (x, x, x). The file's classifier
    is skipped when ``model`` has none. A missing ``num_batches_tracked`` buffer keeps the
    model's value. Values are copied into the model's dtype and device.

    Args:
        model: an unfolded :class:`EfficientNetB0`.
        path: file written by ``torch.save(state_dict)``; read with ``weights_only=True``.

    Returns:
        ``model``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: a file that is no torch file of tensors (random, damaged or hostile),
            unrecognised naming, unknown or missing keys, or a shape mismatch (naming the key).
    """
    path = Path(path)
    # The one safe reader of torch files: a random or hostile file is one line naming it.
    state = load_torch_file(path, "ImageNet weights")
    if not isinstance(state, Mapping) or not all(isinstance(v, Tensor) for v in state.values()):
        raise ValueError(f"{path}: expected a state dict of tensors, got {type(state).__name__}")
    naming = next((name for name, (probe, _) in _NAMINGS.items() if probe in state), None)
    if naming is None:
        first = next(iter(state), None)
        raise ValueError(
            f"{path}: unrecognised key naming (first key {first!r}); expected torchvision "
            "('features.0.0.weight') or timm ('conv_stem.weight')"
        )
    rename = _NAMINGS[naming][1]
    if any(isinstance(m, ConvBNAct) and isinstance(m.bn, nn.Identity) for m in model.modules()):
        raise ValueError("model: is BN-folded; load weights before fold_batchnorm")

    own = model.state_dict()
    source_of = {key: rename(key) for key in own}
    expected = set(source_of.values())
    skipped = (
        {k for k in state if k.startswith("classifier.")} if model.classifier is None else set()
    )
    unknown = set(state) - expected - skipped
    if unknown:
        raise ValueError(f"{path}: {len(unknown)} unknown {naming} key(s): {_listing(unknown)}")
    missing = {k for k in expected - set(state) if not k.endswith("num_batches_tracked")}
    if missing:
        raise ValueError(f"{path}: {len(missing)} missing {naming} key(s): {_listing(missing)}")

    loaded: dict[str, Tensor] = {}
    for key, current in own.items():
        source = source_of[key]
        if source not in state:  # num_batches_tracked only
            loaded[key] = current
            continue
        value = state[source]
        if key == "stem.conv.weight" and model.in_channels == 1 and value.shape[1:2] == (3,):
            value = value.sum(dim=1, keepdim=True)  # gray x acts as RGB (x, x, x)
        if value.shape != current.shape:
            raise ValueError(
                f"{path}: shape mismatch for {source} (model {key}): file {tuple(value.shape)},"
                f" model {tuple(current.shape)}"
            )
        loaded[key] = value
    model.load_state_dict(loaded, strict=True)
    return model


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


def fold_batchnorm(model: EfficientNetB0, channels_last: bool = False) -> EfficientNetB0:
    """Inference copy of ``model`` with every conv + BatchNorm pair fused into one conv.

    The copy is in eval mode, has no BatchNorm layers (each ``ConvBNAct.bn`` becomes
    ``nn.Identity`` and its conv gains a bias) and no gradients (``requires_grad`` False). Its
    output equals ``model.eval()``'s up to rounding: ~1e-14 in float64, ~1e-5 relative in float32.
    ``model`` itself is left untouched. Do not train the copy or load weights into it.

    Args:
        model: an :class:`EfficientNetB0` (any dtype, any device).
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
