"""Training's limits: the CPU memory estimate checked before the run folder is made, and the
warm-up's bound and warning.

The memory checks run as on a machine of a given size: ``available_memory`` (the machine's
size, not the part under test) is replaced by a small number."""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import pytest
import torch

from sq_mitsuba.cli import main
from sq_mitsuba.config import ConfigError, apply_overrides
from sq_mitsuba.machine import LaunchRanks
from sq_mitsuba.training import step as step_module
from sq_mitsuba.training.config import load_train_config
from sq_mitsuba.training.data_stream import warn_long_warmup
from sq_mitsuba.training.step import (
    RENDER_WORKER_BYTES,
    STEP_BYTES_PER_IMAGE,
    STEP_FIXED_BYTES,
    STEP_MEMORY_IMAGE_SIZE,
    VALIDATION_BYTES_PER_IMAGE,
    check_step_memory,
)
from sq_mitsuba.training.train import TrainError, train

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "train" / "configs" / "tiny.toml"
CPU = torch.device("cpu")
GB = 1_000_000_000


def _machine_of(monkeypatch: pytest.MonkeyPatch, size: int | None) -> None:
    """Run the training checks as on a machine of ``size`` bytes (None: unknown)."""
    monkeypatch.setattr(step_module, "available_memory", lambda *args, **kwargs: size)


def _tiny(*overrides: str):
    return apply_overrides(load_train_config(TINY), list(overrides))


def _image_bytes(size: int, per_image: int = STEP_BYTES_PER_IMAGE) -> float:
    return per_image * (size / STEP_MEMORY_IMAGE_SIZE) ** 2


# ------------------------------------------------------------------------ memory


def test_cli_refuses_a_batch_beyond_memory_before_the_run_folder(train_dataset, tmp_path,
                                                                 monkeypatch, capsys):
    # A machine with room for 10 images of tiny.toml (32 px, no reprojection workers) beside
    # the fixed part; a batch of 64 (cheap here, were it run) is refused.
    memory = int(STEP_FIXED_BYTES + 10.5 * _image_bytes(32))
    _machine_of(monkeypatch, memory)
    out = tmp_path / "run"
    code = main(["train", "--config", str(TINY), "--data", str(train_dataset), "--out",
                 str(out), "--set", "optim.batch_size=64", "--max-steps", "1", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1, err
    assert "optim.batch_size: 64 images of 32 px on the CPU" in err
    assert "lower --set optim.batch_size (at most 10 fits)" in err
    assert not out.exists()  # no config.json, log.csv or cache/


def test_the_largest_batch_said_to_fit_passes_and_one_more_is_refused(monkeypatch):
    _machine_of(monkeypatch, 2 * GB)
    most = int((2 * GB - STEP_FIXED_BYTES) // _image_bytes(32))
    check_step_memory(_tiny(f"optim.batch_size={most}"), CPU)
    with pytest.raises(TrainError, match=rf"at most {most} fits"):
        check_step_memory(_tiny(f"optim.batch_size={most + 1}"), CPU)


def test_the_per_image_cost_follows_the_input_size(monkeypatch):
    # Room for 100 images at 96 px: 100 fit at 96 px, but not at 192 px (4x the pixels).
    _machine_of(monkeypatch, STEP_FIXED_BYTES + 100 * STEP_BYTES_PER_IMAGE)
    check_step_memory(_tiny("optim.batch_size=100", "network.image_size=96"), CPU)
    with pytest.raises(TrainError, match=r"of 192 px .*at most 25 fits"):
        check_step_memory(_tiny("optim.batch_size=100", "network.image_size=192"), CPU)


def test_reprojection_workers_count_and_are_named(monkeypatch):
    memory = STEP_FIXED_BYTES + 10 * RENDER_WORKER_BYTES + 4 * _image_bytes(32)
    _machine_of(monkeypatch, int(memory) + 1)
    check_step_memory(_tiny("reprojection.workers=10"), CPU)
    with pytest.raises(TrainError) as error:
        check_step_memory(_tiny("reprojection.workers=11"), CPU)
    message = str(error.value)
    assert "with 11 reprojection worker(s)" in message
    assert "reprojection.workers" in message.split("lower --set", 1)[1]
    # No reprojection term, no renderer: its workers are never started, so they cost nothing.
    check_step_memory(_tiny("reprojection.workers=256", "loss.weights.reprojection=0"), CPU)


def test_a_validation_batch_beyond_memory_names_its_key(monkeypatch):
    _machine_of(monkeypatch, 2 * GB)
    val = _image_bytes(32, VALIDATION_BYTES_PER_IMAGE)
    config = _tiny("validation.images=100000", "validation.batch_size=4096")
    with pytest.raises(TrainError) as error:
        check_step_memory(config, CPU)
    message = str(error.value)
    most = int((2 * GB - STEP_FIXED_BYTES) // val)
    assert message.startswith("validation.batch_size: 4096 images")
    assert f"validation.batch_size (at most {most} fits)" in message
    assert "optim.batch_size" not in message  # tiny.toml's batch of 4 fits
    # The validation batch holds no more than the validation images; validation off: none.
    check_step_memory(_tiny("validation.images=4", "validation.batch_size=4096"), CPU)
    check_step_memory(_tiny("validation.images=100000", "validation.batch_size=4096",
                            "validation.every=0"), CPU)


def test_local_processes_each_hold_their_fixed_part(monkeypatch):
    _machine_of(monkeypatch, 2 * GB)
    config = _tiny("optim.batch_size=8")
    check_step_memory(config, CPU, LaunchRanks(0, 2, 0, 1))  # one here, one elsewhere
    with pytest.raises(TrainError, match=r"on the CPU in 2 processes"):
        check_step_memory(config, CPU, LaunchRanks(0, 2, 0, 2))  # both on this machine


def test_no_check_on_cuda_or_where_memory_is_unknown(monkeypatch):
    huge = _tiny("optim.batch_size=4096", "reprojection.workers=256")
    _machine_of(monkeypatch, 2 * GB)
    with pytest.raises(TrainError):
        check_step_memory(huge, CPU)
    check_step_memory(huge, torch.device("cuda"))  # GPU memory: torch's own error says it
    _machine_of(monkeypatch, None)
    check_step_memory(huge, CPU)


# ------------------------------------------------------------------------ warm-up


def test_warmup_steps_are_bounded():
    assert _tiny("optim.warmup_steps=1000000000").optim.warmup_steps == 10**9
    with pytest.raises(ConfigError, match=r"optim\.warmup_steps"):
        _tiny("optim.warmup_steps=1000000000000000000000")


def test_cli_refuses_an_absurd_warmup(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["train", "--config", str(TINY), "--data", str(tmp_path / "data"), "--out",
                 str(out),
                 "--set", "optim.warmup_steps=1000000000000000000000"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "optim.warmup_steps" in err, err
    assert not out.exists()


def test_a_warmup_as_long_as_the_run_is_warned():
    config = _tiny("optim.warmup_steps=12", "optim.epochs=3", "optim.lr=1e-3")
    with pytest.warns(UserWarning, match=r"optim\.warmup_steps: a warm-up of 12 steps is at "
                                         r"least the run's 12 steps .*peak 0\.001"):
        warn_long_warmup(config, 4)
    with pytest.warns(UserWarning, match=r"optim\.warmup_images: a warm-up of 25 steps"):
        warn_long_warmup(_tiny("optim.warmup_images=100"), 3)  # 100 / 4 images a step
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_long_warmup(config, 5)  # 12 of 15 steps: a warm-up, then the decay


def test_training_warns_of_a_warmup_longer_than_the_run(train_dataset, tmp_path):
    config = _tiny("optim.warmup_steps=1000000", f"data.cache_dir={tmp_path / 'cache'}")
    with pytest.warns(UserWarning) as caught:
        result = train(config, train_dataset, tmp_path / "run", max_steps=0, progress=False)
    lines = [str(w.message) for w in caught if "warmup_steps" in str(w.message)]
    assert len(lines) == 1, [str(w.message) for w in caught]
    total = result.total_steps
    assert re.search(rf"the run's {total} steps \(3 epoch\(s\) of {math.ceil(total / 3)}\)",
                     lines[0]), lines[0]
    # Said once, when the run starts: not again at each --resume.
    with pytest.warns(UserWarning, match="optim.warmup_steps"):
        train(config, train_dataset, tmp_path / "run2", max_steps=1, progress=False)
    with warnings.catch_warnings(record=True) as again:
        warnings.simplefilter("always")
        train(None, train_dataset, tmp_path / "run2", resume=True, max_steps=2,
              progress=False)
    assert not [w for w in again if "warmup_steps" in str(w.message)], \
        [str(w.message) for w in again]
