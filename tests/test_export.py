"""`sq-mitsuba export` and the shipped model: small inference checkpoints that predict as the
training checkpoint does, with the trivial baseline stored beside the weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from output_checks import error_line, one_torch_thread  # noqa: F401
from PIL import Image

from sq_mitsuba.cli import main
from sq_mitsuba.evaluation.scoring import baseline_prediction
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.model.checkpoint import SHIPPED_MODEL, read_checkpoint


@pytest.fixture(scope="module")
def exported(eval_checkpoint, train_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "model.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
                 "--out", str(out), "--baseline-images", "8"]) == 0
    return out


def test_export_predicts_as_the_training_checkpoint(exported, eval_checkpoint, train_dataset):
    payload = read_checkpoint(exported)
    floats = [v for v in payload["model"].values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.float16 for v in floats)
    assert exported.stat().st_size < 0.75 * eval_checkpoint.stat().st_size
    assert payload["source"]["checkpoint"] == eval_checkpoint.name
    assert payload["source"]["step"] == 8

    original, shipped = load_model(eval_checkpoint), load_model(exported)
    images = torch.rand(4, 64, 64, generator=torch.Generator().manual_seed(0))
    a, b = original.predict(images), shipped.predict(images)
    # Half-precision weights: outputs agree to a few parts in a thousand, not bit for bit.
    assert torch.allclose(a.assembly.params, b.assembly.params, atol=2e-2)
    assert not torch.equal(a.assembly.params, b.assembly.params)
    assert torch.allclose(a.rotation, b.rotation, atol=2e-2)


def test_export_stores_the_baseline_of_the_exported_weights(exported, train_dataset):
    predictor = load_model(exported)
    assert predictor.baseline is not None
    raw, rotation, translation = predictor.baseline
    assert raw.shape == (1, 2, 16) and rotation.shape == (1, 3, 3) and translation.shape == (1, 3)
    # Independent recomputation with the loaded (rounded) weights.
    expected = baseline_prediction(predictor, train_dataset, 8)
    for got, want in zip((raw, rotation, translation), expected, strict=True):
        assert torch.allclose(got, want, atol=1e-5)
    assert torch.allclose(rotation[0] @ rotation[0].T, torch.eye(3, dtype=torch.float64),
                          atol=1e-5)


def test_export_refuses_bad_input_before_writing(eval_checkpoint, tmp_path, capsys):
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint")
    out = tmp_path / "out" / "model.pt"
    assert main(["export", "--checkpoint", str(corrupt), "--out", str(out)]) == 2
    assert str(corrupt) in error_line(capsys)
    assert not out.parent.exists()
    empty = tmp_path / "no_data"
    empty.mkdir()
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--data", str(empty),
                 "--out", str(out)]) == 2
    assert error_line(capsys)
    assert not out.exists()


@pytest.mark.skipif(not SHIPPED_MODEL.is_file(), reason="no shipped model in this checkout")
def test_shipped_model_is_small_and_predicts_grey_and_rgb_images():
    assert SHIPPED_MODEL.stat().st_size <= 25 * 2**20
    predictor = load_model()
    assert predictor.baseline is not None
    rng = np.random.default_rng(0)
    grey = np.zeros((200, 200), np.uint8)
    grey[70:130, 40:160] = rng.integers(80, 255, (60, 120))  # a bright body on black
    rgb = np.asarray(Image.fromarray(grey).convert("RGB"))
    for image in (grey[None], rgb.mean(-1, keepdims=False)[None].astype(np.uint8)):
        prediction = predictor.predict(image)
        assert torch.isfinite(prediction.assembly.params).all()
        assert prediction.translation[0, 2] > 0  # in front of the camera
