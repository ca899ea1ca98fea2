"""EfficientNet-B0 encoder: architecture size, shapes, gradients, stochastic depth, ImageNet
weight loading (torchvision and timm namings), BatchNorm folding, input checks.

The tests that take ``device`` run on ``pytest --device`` (conftest.py): the model is built
and its inputs drawn on the CPU from the same seeds, then moved."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor, nn

from sq_mitsuba.model.encoder import EfficientNetB0, StochasticDepth, fold_batchnorm
from sq_mitsuba.model.pretrained import load_imagenet_weights

# (expand ratio, repeats) of the 7 B0 stages, from the published stage table.
B0_STAGES = ((1, 1), (6, 2), (6, 2), (6, 3), (6, 3), (6, 4), (6, 1))


def _module_renames() -> dict[str, tuple[str, str]]:
    """Our module path -> (torchvision path, timm path), written from the published namings.

    torchvision: ``features.0`` stem, ``features.1..7`` stages of MBConv whose ``block`` is a
    Sequential of [expand], depthwise, SE (fc1, fc2), project, each conv/BN pair as ``.0``/``.1``;
    ``features.8`` head; ``classifier.1`` linear. timm: ``conv_stem``/``bn1``, ``blocks.s.j``
    (DepthwiseSeparableConv: conv_dw, bn1, se, conv_pw, bn2; InvertedResidual: conv_pw, bn1,
    conv_dw, bn2, se, conv_pwl, bn3; SE convs conv_reduce/conv_expand), ``conv_head``/``bn2``,
    ``classifier``.
    """
    table = {
        "stem.conv": ("features.0.0", "conv_stem"),
        "stem.bn": ("features.0.1", "bn1"),
        "head.conv": ("features.8.0", "conv_head"),
        "head.bn": ("features.8.1", "bn2"),
        "classifier.fc": ("classifier.1", "classifier"),
    }
    for s, (expand, repeats) in enumerate(B0_STAGES):
        for j in range(repeats):
            ours, tv, tm = f"stages.{s}.{j}", f"features.{s + 1}.{j}.block", f"blocks.{s}.{j}"
            if expand == 1:
                rows = {
                    "depthwise.conv": ("0.0", "conv_dw"),
                    "depthwise.bn": ("0.1", "bn1"),
                    "se.reduce": ("1.fc1", "se.conv_reduce"),
                    "se.expand": ("1.fc2", "se.conv_expand"),
                    "project.conv": ("2.0", "conv_pw"),
                    "project.bn": ("2.1", "bn2"),
                }
            else:
                rows = {
                    "expand.conv": ("0.0", "conv_pw"),
                    "expand.bn": ("0.1", "bn1"),
                    "depthwise.conv": ("1.0", "conv_dw"),
                    "depthwise.bn": ("1.1", "bn2"),
                    "se.reduce": ("2.fc1", "se.conv_reduce"),
                    "se.expand": ("2.fc2", "se.conv_expand"),
                    "project.conv": ("3.0", "conv_pwl"),
                    "project.bn": ("3.1", "bn3"),
                }
            for ours_part, (tv_part, tm_part) in rows.items():
                table[f"{ours}.{ours_part}"] = (f"{tv}.{tv_part}", f"{tm}.{tm_part}")
    return table


def _published_state_dict(model: nn.Module, naming: str) -> dict[str, Tensor]:
    """``model``'s state dict renamed to ``naming`` ("torchvision" or "timm")."""
    renames = _module_renames()
    column = {"torchvision": 0, "timm": 1}[naming]
    out = {}
    for key, value in model.state_dict().items():
        module, leaf = key.rsplit(".", 1)
        out[f"{renames[module][column]}.{leaf}"] = value.clone()
    return out


def _randomise_batchnorm(model: EfficientNetB0, seed: int) -> EfficientNetB0:
    """Random BN affine parameters, then running statistics measured on random images.

    With the fresh statistics (mean 0, var 1) an eval-mode network at initialisation barely
    depends on its input; measured statistics keep the features input-dependent, O(1).
    """
    generator = torch.Generator().manual_seed(seed)
    batchnorms = [m for m in model.modules() if isinstance(m, nn.BatchNorm2d)]
    with torch.no_grad():
        for module in batchnorms:
            c = module.num_features
            module.weight.copy_(0.5 + torch.rand(c, generator=generator))
            module.bias.copy_(0.1 * torch.randn(c, generator=generator))
            module.reset_running_stats()
            module.momentum = None  # cumulative average over the calibration batch
        model.train()
        model.forward_features(_images(8, model.in_channels, 96, seed=seed))
        for module in batchnorms:
            module.momentum = 0.1
            module.num_batches_tracked.fill_(7)
    return model.eval()


def _images(batch: int, channels: int, size: int, seed: int = 0) -> Tensor:
    return torch.rand(batch, channels, size, size, generator=torch.Generator().manual_seed(seed))


def test_parameter_count_matches_torchvision_efficientnet_b0() -> None:
    model = EfficientNetB0(in_channels=3, num_classes=1000)
    assert sum(p.numel() for p in model.parameters()) == 5_288_548


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("size", [128, 96])
def test_output_shapes(channels: int, size: int, device: torch.device) -> None:
    model = EfficientNetB0(in_channels=channels).eval().to(device)
    with torch.no_grad():
        features = model(_images(2, channels, size).to(device))
    assert features.shape == (2, 1280)
    assert torch.isfinite(features).all()


def test_classifier_gives_logits() -> None:
    model = EfficientNetB0(in_channels=1, num_classes=10).eval()
    with torch.no_grad():
        logits = model(_images(2, 1, 96))
        features = model.forward_features(_images(2, 1, 96))
    assert logits.shape == (2, 10)
    assert features.shape == (2, 1280)


def test_gradients_reach_every_parameter_in_train_mode(device: torch.device) -> None:
    torch.manual_seed(0)
    model = EfficientNetB0(in_channels=1, num_classes=4, drop_connect_rate=0.0).train()
    logits = model.to(device)(_images(2, 1, 64).to(device))
    (logits * torch.randn_like(logits)).sum().backward()
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None, name
        assert torch.isfinite(parameter.grad).all(), name
        assert parameter.grad.abs().sum() > 0, name


def test_stochastic_depth_rates_increase_linearly() -> None:
    model = EfficientNetB0(drop_connect_rate=0.2)
    rates = [m.p for m in model.modules() if isinstance(m, StochasticDepth)]
    assert rates == pytest.approx([0.2 * k / 16 for k in range(16)])


def test_stochastic_depth_module_identity_in_eval_random_in_train() -> None:
    drop = StochasticDepth(0.5)
    x = torch.ones(2000, 3, 2, 2)
    drop.eval()
    assert drop(x) is x
    drop.train()
    torch.manual_seed(0)
    first, second = drop(x), drop(x)
    for out in (first, second):
        per_row = out.flatten(1)
        assert ((per_row == 0).all(1) | (per_row == 2).all(1)).all()  # whole rows, 1 / (1 - p)
        assert 0.4 < (per_row[:, 0] == 0).float().mean() < 0.6
    assert not torch.equal(first, second)


def test_stochastic_depth_in_model_only_acts_in_training() -> None:
    torch.manual_seed(0)
    dropping = EfficientNetB0(in_channels=1, drop_connect_rate=0.5)
    plain = EfficientNetB0(in_channels=1, drop_connect_rate=0.0)
    plain.load_state_dict(dropping.state_dict())
    images = _images(4, 1, 64)
    with torch.no_grad():
        dropping.eval()
        plain.eval()
        assert torch.equal(dropping(images), dropping(images))
        assert torch.equal(dropping(images), plain(images))
        dropping.train()
        torch.manual_seed(1)
        a = dropping(images)
        b = dropping(images)
    assert not torch.equal(a, b)


@pytest.mark.parametrize("naming", ["torchvision", "timm"])
def test_weight_loading_round_trip(naming: str, tmp_path) -> None:
    torch.manual_seed(0)
    source = _randomise_batchnorm(EfficientNetB0(in_channels=3, num_classes=1000), seed=1).eval()
    published = _published_state_dict(source, naming)
    # Spot checks of the published names and shapes.
    if naming == "torchvision":
        assert published["features.1.0.block.1.fc1.weight"].shape == (8, 32, 1, 1)
        assert published["features.2.0.block.3.0.weight"].shape == (24, 96, 1, 1)
        assert published["features.8.0.weight"].shape == (1280, 320, 1, 1)
    else:
        assert published["blocks.0.0.se.conv_reduce.weight"].shape == (8, 32, 1, 1)
        assert published["blocks.1.0.conv_pwl.weight"].shape == (24, 96, 1, 1)
        assert published["conv_head.weight"].shape == (1280, 320, 1, 1)
    path = tmp_path / f"{naming}.pth"
    torch.save(published, path)

    images = _images(2, 3, 64)
    torch.manual_seed(5)
    target = load_imagenet_weights(EfficientNetB0(in_channels=3, num_classes=1000), path).eval()
    encoder = load_imagenet_weights(EfficientNetB0(in_channels=3), path).eval()  # no classifier
    with torch.no_grad():
        features = source.forward_features(images)
        assert not torch.allclose(features[0], features[1], atol=1e-3)  # input-dependent
        assert torch.equal(target(images), source(images))
        assert torch.equal(encoder(images), source.forward_features(images))
    assert int(target.head.bn.num_batches_tracked) == 7


def test_grayscale_stem_equals_rgb_on_replicated_gray(tmp_path) -> None:
    torch.manual_seed(0)
    rgb = _randomise_batchnorm(EfficientNetB0(in_channels=3), seed=2).double().eval()
    path = tmp_path / "rgb.pth"
    torch.save(_published_state_dict(rgb, "torchvision"), path)
    gray = load_imagenet_weights(EfficientNetB0(in_channels=1).double(), path).eval()
    images = _images(2, 1, 32).double()
    with torch.no_grad():
        expected = rgb(images.expand(-1, 3, -1, -1))
        got = gray(images)
        assert not torch.allclose(expected, rgb(_images(2, 3, 32, seed=9).double()), atol=1e-3)
    torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-10)


def test_weight_loading_errors(tmp_path) -> None:
    model = EfficientNetB0(in_channels=3)
    with pytest.raises(FileNotFoundError, match=r"nope\.pth"):
        load_imagenet_weights(model, tmp_path / "nope.pth")

    good = _published_state_dict(EfficientNetB0(in_channels=3, num_classes=1000), "timm")

    def attempt(state: dict[str, Tensor], target: EfficientNetB0 = model) -> None:
        path = tmp_path / "w.pth"
        torch.save(state, path)
        load_imagenet_weights(target, path)

    with pytest.raises(ValueError, match=r"unknown timm key\(s\): blocks\.9\.9\.extra"):
        attempt({**good, "blocks.9.9.extra": torch.zeros(1)})
    without = {k: v for k, v in good.items() if k != "blocks.2.1.conv_dw.weight"}
    with pytest.raises(ValueError, match=r"missing timm key\(s\): blocks\.2\.1\.conv_dw\.weight"):
        attempt(without)
    wrong = {**good, "blocks.3.0.bn2.bias": torch.zeros(5)}
    with pytest.raises(ValueError, match=r"shape mismatch for blocks\.3\.0\.bn2\.bias"):
        attempt(wrong)
    with pytest.raises(ValueError, match="unrecognised key naming"):
        attempt({"model.stem.weight": torch.zeros(32, 3, 3, 3)})
    with pytest.raises(ValueError, match=r"shape mismatch for classifier\.weight"):
        attempt(good, EfficientNetB0(in_channels=3, num_classes=10))
    with pytest.raises(ValueError, match="BN-folded"):
        attempt(good, fold_batchnorm(EfficientNetB0(in_channels=3)))


def test_missing_num_batches_tracked_is_accepted(tmp_path) -> None:
    source = _randomise_batchnorm(EfficientNetB0(in_channels=1), seed=3).eval()
    state = _published_state_dict(source, "torchvision")
    state = {k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}
    torch.save(state, tmp_path / "w.pth")
    loaded = load_imagenet_weights(EfficientNetB0(in_channels=1), tmp_path / "w.pth").eval()
    images = _images(1, 1, 64)
    with torch.no_grad():
        assert torch.equal(loaded(images), source(images))


def test_fold_batchnorm_float64_float32_channels_last() -> None:
    torch.manual_seed(0)
    model = _randomise_batchnorm(EfficientNetB0(in_channels=1, num_classes=5), seed=4).train()

    # float64 at 32 x 32: CPU depthwise convs in float64 take a slow per-group path.
    model64 = model.double()
    folded64 = fold_batchnorm(model64)
    assert model64.training  # the original is untouched
    assert not folded64.training
    assert not any(isinstance(m, nn.BatchNorm2d) for m in folded64.modules())
    assert sum(isinstance(m, nn.BatchNorm2d) for m in model64.modules()) == 49
    assert not any(p.requires_grad for p in folded64.parameters())
    images64 = _images(2, 1, 32).double()
    with torch.no_grad():
        reference = model64.eval()(images64)
        assert not torch.allclose(reference[0], reference[1], atol=1e-3)  # input-dependent
        torch.testing.assert_close(folded64(images64), reference, rtol=1e-10, atol=1e-10)

    model32 = model64.float()
    images = _images(2, 1, 96)
    with torch.no_grad():
        reference = model32(images)
        # float32: rounding differences of ~1e-7 grow through 16 blocks to ~1e-5 relative.
        tolerance = {"rtol": 1e-4, "atol": 1e-4 * float(reference.abs().max())}
        torch.testing.assert_close(fold_batchnorm(model32)(images), reference, **tolerance)
        fast = fold_batchnorm(model32, channels_last=True)
        assert fast.stem.conv.weight.is_contiguous(memory_format=torch.channels_last)
        out = fast(images.contiguous(memory_format=torch.channels_last))
        torch.testing.assert_close(out, reference, **tolerance)


def test_bad_inputs() -> None:
    model = EfficientNetB0(in_channels=1).eval()
    expected = r"images: expected .*\(B, 1, H, W\), got \(2, 3, 32, 32\)"
    with pytest.raises(ValueError, match=expected):
        model(torch.zeros(2, 3, 32, 32))
    with pytest.raises(ValueError, match="images"):
        model(torch.zeros(1, 32, 32))
    with pytest.raises(ValueError, match="images"):
        model(torch.zeros(1, 1, 32, 32, dtype=torch.int64))
    with pytest.raises(ValueError, match="in_channels"):
        EfficientNetB0(in_channels=0)
    with pytest.raises(ValueError, match="num_classes"):
        EfficientNetB0(num_classes=0)
    with pytest.raises(ValueError, match="drop_connect_rate"):
        EfficientNetB0(drop_connect_rate=1.0)


def test_an_encoder_without_its_head_says_to_read_its_maps() -> None:
    """A network with spatial latents drops the encoder's 1280-channel head: pooled features
    are then no more (it failed with "'NoneType' object is not callable")."""
    from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet

    network = SuperquadricNet(NetworkConfig(image_size=64, latent="spatial", latent_dim=8,
                                            hidden_dim=8, num_primitives=2))
    images = torch.rand(1, 1, 64, 64)
    assert network.encoder.head is None
    with pytest.raises(ValueError, match="forward_pyramid"):
        network.encoder(images)
    assert len(network.encoder.forward_pyramid(images)) == 4  # strides 4, 8, 16, 32
