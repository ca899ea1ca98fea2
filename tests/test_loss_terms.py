"""The loss-term registry: a term added by one function and one entry trains, logs and is
timed with no other edit; unknown or unfeedable terms are one-line errors before any work; the
terms equal the loss functions they wrap; bad inputs to ``train`` leave nothing behind.

The tests that take ``device`` run on ``pytest --device`` (conftest.py)."""

from __future__ import annotations

import csv
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from sq_mitsuba.cli import main
from sq_mitsuba.config import apply_overrides
from sq_mitsuba.model.losses import pose_loss, rotation_6d_loss, taper_loss
from sq_mitsuba.training.batch import TrainingBatch
from sq_mitsuba.training.config import load_train_config
from sq_mitsuba.training.loss_terms import (
    LOSS_TERMS,
    LossConfig,
    LossContext,
    compute_terms,
    register_term,
    total_loss,
)
from sq_mitsuba.training.train import train

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "train" / "configs" / "tiny.toml"


def _mean_depth(output, batch: TrainingBatch, context: LossContext) -> torch.Tensor:
    """A toy term: the mean predicted depth (metres)."""
    return output.depth.mean()


def _needs_a_mask(output, batch: TrainingBatch, context: LossContext) -> torch.Tensor:
    return output.mask_logits.mean()


@pytest.fixture
def toy_terms() -> Iterator[None]:
    register_term("toy_depth", _mean_depth, ("depth",))
    register_term("toy_mask", _needs_a_mask, ("mask_logits",))
    try:
        yield
    finally:
        del LOSS_TERMS["toy_depth"], LOSS_TERMS["toy_mask"]


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def test_a_term_added_through_the_registry_trains_logs_and_is_timed(
        toy_terms, train_dataset, tmp_path):
    config = apply_overrides(load_train_config(TINY), ["loss.weights.toy_depth=0.5",
                                                       "validation.every=0"])
    result = train(config, train_dataset, tmp_path / "run", progress=False, max_steps=2)
    rows = _rows(tmp_path / "run" / "log.csv")
    assert [int(r["step"]) for r in rows] == [1, 2] and result.steps == 2
    for row in rows:
        depth = float(row["toy_depth"])
        assert depth > 0  # a depth in metres, logged under the term's name
        shown = {t: float(row[t]) for t in config.loss.enabled()}
        total = sum(config.loss.weights[t] * v for t, v in shown.items())
        assert float(row["loss"]) == pytest.approx(total, rel=1e-5)  # weighted into the loss
    from sq_mitsuba.bench.train import StepBench
    from sq_mitsuba.training.step import mitsuba_for

    with mitsuba_for(torch.device("cpu"), True):
        bench = StepBench(apply_overrides(config, ["loss.weights.reprojection=0"]))
        try:
            parts = bench.timed_parts(0)
        finally:
            bench.close()
    assert "toy_depth" in parts and parts["toy_depth"] >= 0


def test_an_unknown_term_is_a_one_line_error(tmp_path, train_dataset, capsys):
    out = tmp_path / "run"
    bad = tmp_path / "bad.toml"
    bad.write_text(f'base = "{TINY.as_posix()}"\n[loss.weights]\nchamfr = 1.0\n')
    for extra in (["--config", str(TINY), "--set", "loss.weights.chamfr=1"],
                  ["--config", str(bad)]):
        code = main(["train", *extra, "--data", str(train_dataset), "--out", str(out)])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1, err
        assert "unknown loss term 'chamfr'" in err and "chamfer" in err
    assert not out.exists()


def test_a_term_the_network_cannot_feed_is_refused_before_work(toy_terms, train_dataset,
                                                               tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["train", "--config", str(TINY), "--set", "loss.weights.toy_mask=1", "--data",
                 str(train_dataset), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert "toy_mask" in err and "mask_logits" in err
    assert not out.exists()


def test_terms_equal_the_losses_they_wrap(device):
    from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet

    torch.manual_seed(0)
    network = SuperquadricNet(NetworkConfig(image_size=32, num_primitives=2, latent_dim=16,
                                            hidden_dim=16)).eval().to(device)
    k = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]], device=device)
    with torch.no_grad():
        output = network(torch.rand(3, 1, 32, 32).to(device), k)
    rotation = torch.linalg.qr(torch.randn(3, 3, 3)).Q
    rotation = rotation * torch.linalg.det(rotation)[:, None, None]
    translation = torch.tensor([[0.1, 0.0, 3.0], [0.0, 0.2, 4.0], [-0.1, 0.1, 5.0]])
    flip = torch.diag(torch.tensor([-1.0, -1.0, 1.0]))
    symmetries = torch.stack([torch.eye(3), flip])[None].expand(3, -1, -1, -1)
    batch = TrainingBatch(torch.rand(3, 1, 32, 32), torch.zeros(3, 1, 32, 32), rotation,
                          translation, torch.arange(3), torch.rand(3, 10, 3),
                          torch.rand(3, 12, 3), torch.zeros(3, 12), symmetries).to(device)
    rotation, translation, symmetries = batch.rotation, batch.translation, batch.symmetries
    loss = LossConfig(weights={"rotation": 2.0, "rotation_6d": 0.5, "translation": 3.0,
                               "taper": 1.0})
    terms = compute_terms(output, batch, LossContext(loss))
    assert list(terms) == ["rotation", "rotation_6d", "translation", "taper"]  # registry order
    rot, trans = pose_loss(output.rotation, output.translation, rotation, translation,
                           symmetries)
    assert torch.equal(terms["rotation"], rot.mean())
    assert torch.equal(terms["translation"], trans.mean())
    assert torch.equal(terms["taper"], taper_loss(output.assembly))
    expected_6d = rotation_6d_loss(output.rotation_6d, rotation, symmetries).mean()
    assert torch.equal(terms["rotation_6d"], expected_6d)
    total = total_loss(terms, loss)
    assert float(total) == pytest.approx(2 * float(rot.mean()) + 0.5 * float(expected_6d)
                                         + 3 * float(trans.mean()) + float(terms["taper"]))
    with pytest.raises(ValueError, match="missing"):
        total_loss({"rotation": terms["rotation"]}, loss)


# ------------------------------------------------------------------------ bad inputs


def test_an_unloadable_pretrained_file_leaves_nothing(train_dataset, tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x80\x04not a checkpoint at all" * 10)
    out = tmp_path / "run"
    for path in (junk, tmp_path / "missing.pt"):
        code = main(["train", "--config", str(TINY), "--set", f"network.pretrained={path}",
                     "--data", str(train_dataset), "--out", str(out), "--quiet"])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1, err
        assert "network.pretrained" in err or str(path) in err, err
        assert "Traceback" not in err and "weights_only=False" not in err
        assert not out.exists()


def test_a_truncated_image_leaves_no_run_folder_or_cache(train_dataset, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(train_dataset, data)
    victim = sorted(data.glob("*/images/*.png"))[0]
    victim.write_bytes(victim.read_bytes()[:200])
    out = tmp_path / "run"
    code = main(["train", "--config", str(TINY), "--data", str(data), "--out", str(out),
                 "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and str(victim) in err and err.count("\n") == 1, err
    assert not out.exists()
    # A run folder that existed before keeps what it held, and gets no cache.
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    code = main(["train", "--config", str(TINY), "--data", str(data), "--out", str(out),
                 "--quiet"])
    assert code == 2 and [p.name for p in out.iterdir()] == ["notes.txt"]


def test_a_stale_temporary_checkpoint_is_removed_by_the_next_run(train_dataset, tmp_path):
    config = apply_overrides(load_train_config(TINY), ["validation.every=0"])
    out = tmp_path / "run"
    train(config, train_dataset, out, progress=False, max_steps=1)
    stale = out / ".last.abc123de.tmp.pt"  # what a kill during a checkpoint write leaves
    stale.write_bytes(b"")
    train(config, train_dataset, out, resume=True, progress=False, max_steps=2)
    assert not stale.exists() and (out / "last.pt").is_file()


def test_a_view_frame_shape_is_scored_through_the_true_rotation():
    """``network.shape_frame = "view"``: the network's assembly is turned into the body frame
    by the predicted rotation, but the shape terms score it through the true one: its Chamfer
    term equals the Chamfer of the unturned (view-frame) assembly against the true surface
    turned into the camera's axes, whatever rotation the network predicts."""
    from sq_mitsuba.geometry.assembly import Assembly
    from sq_mitsuba.geometry.rotation import random_rotations
    from sq_mitsuba.model.losses import chamfer_loss, counted_surface_samples
    from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet

    torch.manual_seed(1)
    network = SuperquadricNet(NetworkConfig(image_size=32, num_primitives=2, latent_dim=16,
                                            hidden_dim=16, shape_frame="view")).eval()
    k = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    with torch.no_grad():
        output = network(torch.rand(3, 1, 32, 32), k)
    view = Assembly.from_raw(output.raw)
    predicted = output.rotation
    torch.testing.assert_close(output.assembly.params,
                               view.rotated(predicted.transpose(1, 2)).params)
    rotation = random_rotations(3, torch.Generator().manual_seed(2))
    surface = torch.rand(3, 10, 3) - 0.5
    batch = TrainingBatch(torch.rand(3, 1, 32, 32), torch.zeros(3, 1, 32, 32), rotation,
                          torch.tensor([[0.0, 0.0, 3.0]] * 3), torch.arange(3), surface,
                          torch.rand(3, 12, 3), torch.zeros(3, 12),
                          torch.eye(3)[None, None].expand(3, 1, 3, 3))
    context = LossContext(LossConfig(weights={"chamfer": 1.0}))
    points, keep = counted_surface_samples(view, context.loss.level)
    expected = chamfer_loss(points, keep, surface @ rotation.transpose(1, 2))
    got = compute_terms(output, batch, context)["chamfer"]
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    # Scored through the predicted rotation instead, the term would differ.
    body_points, body_keep = counted_surface_samples(output.assembly, context.loss.level)
    assert abs(float(chamfer_loss(body_points, body_keep, surface)) - float(expected)) > 1e-4


def test_every_registered_term_has_its_own_name_on_the_progress_bar() -> None:
    """The progress bar shortens the terms' names; two terms sharing a first word
    (surface_depth, surface_normal) must not show as one."""
    from sq_mitsuba.training.loss_terms import LOSS_TERMS, short_term_name

    shown = [short_term_name(name) for name in LOSS_TERMS]
    assert len(set(shown)) == len(shown)
    assert short_term_name("surface_depth") != short_term_name("surface_normal")
    assert short_term_name("chamfer") == "chamf"


def test_every_registered_term_is_named_where_users_look(capsys):
    """The term names are written by hand in `train --help` (LossConfig.weights' docstring)
    and in docs/training.md: a term registered in the package must appear in both."""
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    guide = (ROOT / "docs" / "training.md").read_text()
    for name in LOSS_TERMS:
        assert name in help_text, f"{name}: not in train --help"
        assert name in guide, f"{name}: not in docs/training.md"
