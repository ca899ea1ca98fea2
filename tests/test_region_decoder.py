"""The region decoder (``network.shape_decoder = "regions"``): one primitive per stride-32
cell, centred where the cell is seen, checked by projecting the primitives through the camera;
its configuration errors; a slots network's weights growing a regions network."""

from __future__ import annotations

import pytest
import torch

import sq_mitsuba
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.model.checkpoint import checkpoint_payload, load_weights, write_checkpoint
from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet
from sq_mitsuba.model.region_decoder import ANCHOR_LIMIT, RegionDecoder

SMALL = dict(encoder="efficientnet_lite0", latent="spatial", image_size=64, latent_dim=16,
             hidden_dim=16, spatial_channels=8)
REGIONS = dict(shape_decoder="regions", shape_frame="view", existence=True, num_primitives=4)


def _images(count: int, seed: int) -> torch.Tensor:
    return torch.rand(count, 1, 64, 64, generator=torch.Generator().manual_seed(seed))


def test_each_primitive_starts_where_its_cell_is_seen() -> None:
    """With the last layer's weights at zero, primitive c's centre, placed at the predicted
    pose, projects through K onto the centre of cell c (row-major), for a camera whose
    principal point is off the image centre too; anchors beyond the range are clipped."""
    torch.manual_seed(0)
    net = SuperquadricNet(NetworkConfig(**SMALL, **REGIONS)).eval()
    assert isinstance(net.sq_generator, RegionDecoder) and net.sq_generator.grid == 2
    with torch.no_grad():
        net.sq_generator.out.weight.zero_()
    k = torch.tensor([[60.0, 0.0, 30.0], [0.0, 64.0, 35.0], [0.0, 0.0, 1.0]])
    with torch.no_grad():
        out = net(_images(3, 1), k)
    view = Assembly.from_raw(out.raw.double())  # the view frame: camera axes about the origin
    camera_points = view.translation + out.translation.double()[:, None]  # (B, 4, 3)
    projected = camera_points @ k.double().T
    pixels = projected[..., :2] / projected[..., 2:]
    cells = torch.tensor([[16.0, 16.0], [48.0, 16.0], [16.0, 48.0], [48.0, 48.0]]).double()
    limit = ANCHOR_LIMIT * 0.5  # ParameterRanges().translation_scale
    offset = (cells - out.pixel.double()[:, None]) * out.depth.double()[:, None, None]
    inside = (offset / torch.tensor([60.0, 64.0]).double()).abs() < limit - 1e-6
    assert bool(inside.all(-1).any())
    torch.testing.assert_close(pixels[inside.all(-1)],
                               cells.expand_as(pixels)[inside.all(-1)], rtol=0, atol=1e-4)
    # Every centre lies in the plane of the origin at first (the anchors move x and y only).
    torch.testing.assert_close(view.translation[..., 2],
                               torch.zeros_like(view.translation[..., 2]), rtol=0, atol=1e-12)
    # A cell far off the origin is clipped to the range, not beyond it.
    far = net.sq_generator.anchors(torch.tensor([[0.0, 0.0]]), torch.tensor([50.0]),
                                   k[None], 64, 64)
    assert torch.tanh(far[..., :2]).abs().max().item() == pytest.approx(ANCHOR_LIMIT)


@pytest.mark.parametrize(("change", "field"), [
    (dict(shape_frame="body"), "shape_decoder"),
    (dict(existence=False), "shape_decoder"),
    (dict(num_primitives=5), "num_primitives"),
])
def test_a_regions_network_names_what_it_needs(change: dict, field: str) -> None:
    config = NetworkConfig(**SMALL, **{**REGIONS, **change})
    with pytest.raises(ValueError, match=rf"^network\.{field}: "):
        SuperquadricNet(config)


def test_a_slots_network_grows_a_regions_decoder_and_it_predicts(tmp_path) -> None:
    """A trained slots network's weights load (partially) into a regions network: every part
    but the decoder is the file's, every parameter then gets a gradient, and the predictor
    (eager, folded and traced, through a checkpoint) gives the same assembly."""
    torch.manual_seed(2)
    slots = SuperquadricNet(NetworkConfig(**SMALL, num_primitives=5)).eval()
    regions = SuperquadricNet(NetworkConfig(**SMALL, **REGIONS))
    load_weights(regions, slots.state_dict(), "test", partial=True)
    for name, value in slots.state_dict().items():
        if not name.startswith("sq_generator."):
            torch.testing.assert_close(regions.state_dict()[name], value, rtol=0, atol=0)
    with pytest.raises(ValueError, match="weights do not fit"):
        load_weights(regions, slots.state_dict(), "test")  # a full load still refuses
    k = Camera.default(64).matrix(torch.float32)
    out = regions.train()(_images(2, 3), k)
    loss = (out.assembly.params.square().mean() + out.existence_logits.square().mean()
            + out.translation.square().mean() + out.rotation_6d.square().mean())
    loss.backward()
    silent = [n for n, p in regions.named_parameters() if p.grad is None]
    assert silent == []
    path = write_checkpoint(tmp_path / "regions.pt",
                            checkpoint_payload(regions.eval(), Camera.default(64)))
    eager = sq_mitsuba.load_model(path, fast=False).predict(_images(2, 4)[:, 0])
    for traced in (False, True):
        fast = sq_mitsuba.load_model(path, fast=True, traced=traced).predict(_images(2, 4)[:, 0])
        torch.testing.assert_close(fast.assembly.params, eager.assembly.params, rtol=1e-3,
                                   atol=1e-3)
    assert eager.assembly.params.shape[-1] == 16
