"""A rotation head added by name only: one module and one registry entry, then trained,
exported and predicted through the public API (the fast path traced by TorchScript included)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

import sq_mitsuba
from sq_mitsuba.apps.export import export_model
from sq_mitsuba.config import apply_overrides
from sq_mitsuba.geometry.rotation import random_rotations
from sq_mitsuba.model.heads import POSE_HEADS, PoseHeadOutput, pose_mlp, register_pose_head
from sq_mitsuba.model.network_config import NetworkConfig
from sq_mitsuba.training.config import load_train_config
from sq_mitsuba.training.train import train

TINY = Path(__file__).resolve().parents[1] / "train" / "configs" / "tiny.toml"


def _skew(w: Tensor) -> Tensor:
    zero = torch.zeros_like(w[:, 0])
    return torch.stack([zero, -w[:, 2], w[:, 1], w[:, 2], zero, -w[:, 0],
                        -w[:, 1], w[:, 0], zero], dim=-1).view(-1, 3, 3)


class FixedPlusResidualHead(nn.Module):
    """A fixed rotation times a learned small residual exp([w]x); the raw position."""

    def __init__(self, config: NetworkConfig) -> None:
        super().__init__()
        self.mlp = pose_mlp(config.latent_dim, config.hidden_dim, 6)
        fixed = random_rotations(1, generator=torch.Generator().manual_seed(7))[0]
        self.register_buffer("fixed", fixed)

    def forward(self, z_pose: Tensor) -> PoseHeadOutput:
        out = self.mlp(z_pose)
        residual = torch.linalg.matrix_exp(_skew(0.1 * torch.tanh(out[:, :3])))
        return PoseHeadOutput(rotation=self.fixed @ residual, position=out[:, 3:])


@pytest.fixture
def toy_head() -> Iterator[str]:
    register_pose_head("fixed_plus_residual", FixedPlusResidualHead)
    yield "fixed_plus_residual"
    POSE_HEADS.pop("fixed_plus_residual")


def test_a_rotation_head_added_by_name_trains_exports_and_predicts(toy_head, train_dataset,
                                                                   tmp_path):
    config = apply_overrides(load_train_config(TINY), [
        f"network.pose_head={toy_head}", "loss.weights.rotation=1.0", "validation.every=0"])
    result = train(config, train_dataset, tmp_path / "run", progress=False, max_steps=2)
    assert result.steps == 2
    exported = export_model(tmp_path / "run" / "last.pt", train_dataset, tmp_path / "model.pt")
    eager = sq_mitsuba.load_model(exported)
    fast = sq_mitsuba.load_model(exported, fast=True, traced=True)  # the stricter path
    assert fast._traced is not None
    assert isinstance(eager.model.pose_head, FixedPlusResidualHead)
    images = torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(8))
    slow_prediction, fast_prediction = eager.predict(images), fast.predict(images)
    for name in ("rotation", "translation", "pixel", "depth"):
        torch.testing.assert_close(getattr(fast_prediction, name),
                                   getattr(slow_prediction, name), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(fast_prediction.assembly.params, slow_prediction.assembly.params,
                               rtol=1e-4, atol=1e-4)
    # The rotation stays within the residual's reach (0.1 rad per axis) of the fixed one.
    fixed = eager.model.pose_head.fixed
    cosine = ((fixed.T @ slow_prediction.rotation).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    assert bool((cosine > torch.cos(torch.tensor(0.2))).all())
    assert fast_prediction.rotation_hypotheses.shape == (3, 1, 3, 3)
