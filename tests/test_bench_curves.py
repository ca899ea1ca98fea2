"""``sq-mitsuba bench curves``: held-out Chamfer-L1 against training time, resumable."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sq_mitsuba.cli import main
from sq_mitsuba.config import apply_overrides
from sq_mitsuba.training.config import load_train_config

TINY = Path(__file__).resolve().parents[1] / "train" / "configs" / "tiny.toml"


def test_learning_curves_on_the_tiny_dataset(train_dataset, tmp_path):
    from sq_mitsuba.bench.curves import (
        curves_report,
        learning_curves,
        plot_learning_curves,
    )

    tiny = load_train_config(TINY)
    configs = {"tiny": tiny, "tiny, no augmentation": apply_overrides(
        tiny, ["augment.probability=0"])}
    curves = learning_curves(train_dataset, tmp_path / "runs", minutes=2 / 60, points=2,
                             val_images=2, progress=False, configs=configs)
    assert [c.label for c in curves] == list(configs)
    for curve in curves:
        assert 1 <= len(curve.seconds) <= 2
        assert curve.seconds == sorted(curve.seconds) and curve.seconds[0] > 0
        assert curve.steps == sorted(curve.steps) and curve.steps[0] >= 1
        assert all(math.isfinite(v) and v > 0 for v in curve.chamfer_l1)
    assert (tmp_path / "runs" / "tiny_no_augmentation" / "last.pt").is_file()
    png = plot_learning_curves(curves, tmp_path / "curves.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = curves_report(curves, 2 / 60, train_dataset, png)
    rows = [line for line in table.splitlines() if line.startswith("| tiny")]
    assert len(rows) == sum(len(c.seconds) for c in curves)


def test_only_a_recorded_run_draws_the_repository_figure(tmp_path):
    from sq_mitsuba.bench.curves import CURVES_PNG, curves_figure_path

    assert curves_figure_path(tmp_path, write=False) == tmp_path / "learning_curves.png"
    assert curves_figure_path(tmp_path, write=True) == CURVES_PNG
    assert CURVES_PNG.parent.name == "figures" and CURVES_PNG.parent.parent.name == "eval"


def test_learning_curves_refuse_bad_input(tmp_path):
    from sq_mitsuba.bench.curves import learning_curves

    with pytest.raises(ValueError, match="minutes"):
        learning_curves(tmp_path, tmp_path / "out", minutes=0)
    with pytest.raises(ValueError, match="unknown 'b'"):
        learning_curves(tmp_path, tmp_path / "out", minutes=1, labels=["b"])
    with pytest.raises(ValueError, match="dataset folder not found"):
        learning_curves(tmp_path / "none", tmp_path / "out", minutes=1)


def test_cli_curves_needs_data_minutes_and_out(tmp_path, capsys):
    assert main(["bench", "curves", "--minutes", "1", "--out", str(tmp_path)]) == 2
    assert "--data: required by the curves suite" in capsys.readouterr().err


_CUT_RUN = """
import sys
from sq_mitsuba.bench.curves import learning_curves
from sq_mitsuba.config import apply_overrides
from sq_mitsuba.training.config import load_train_config
config = apply_overrides(load_train_config(sys.argv[4]), ["optim.epochs=1000"])
learning_curves(sys.argv[1], sys.argv[2], minutes=float(sys.argv[3]), points=2, val_images=2,
                progress=False, configs={"tiny": config})
"""


@pytest.mark.slow
def test_a_curve_cut_between_points_continues_from_its_last_point(train_dataset, tmp_path):
    """A run killed (SIGKILL) while training towards its second point: the rerun keeps the
    first point as recorded, starts again from that point's checkpoint, and measures the
    second; a rerun of the finished curve trains nothing."""
    from sq_mitsuba.bench.curves import CURVE_FILE, learning_curves

    out, minutes = tmp_path / "runs", 0.3  # 9 s a point: the kill lands inside the second
    record = out / "tiny" / CURVE_FILE
    child = subprocess.Popen([sys.executable, "-c", _CUT_RUN, str(train_dataset), str(out),
                              str(minutes), str(TINY)], stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 300
        while not record.is_file() and child.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
    first = json.loads(record.read_text())
    assert len(first["seconds"]) == 1 and not first["finished"]
    long = {"tiny": apply_overrides(load_train_config(TINY), ["optim.epochs=1000"])}
    curves = learning_curves(train_dataset, out, minutes=minutes, points=2, val_images=2,
                             progress=False, configs=long)
    curve = curves[0]
    assert curve.finished and len(curve.seconds) == 2
    assert curve.seconds[0] == first["seconds"][0] and curve.steps[0] == first["steps"][0]
    assert curve.chamfer_l1[0] == first["chamfer_l1"][0]
    assert curve.steps[1] > curve.steps[0] and curve.seconds[1] > curve.seconds[0]
    # Training after the first point counted once: the second slice's time is one slice's.
    assert curve.seconds[1] - curve.seconds[0] < 60 * minutes
    stamp = os.stat(out / "tiny" / "last.pt").st_mtime_ns
    again = learning_curves(train_dataset, out, minutes=minutes, points=2, val_images=2,
                            progress=False, configs=long)
    assert again == curves
    assert os.stat(out / "tiny" / "last.pt").st_mtime_ns == stamp


def test_a_run_folder_of_other_settings_is_refused_before_any_training(train_dataset,
                                                                      tmp_path):
    from sq_mitsuba.bench.curves import learning_curves

    tiny = {"tiny": load_train_config(TINY)}
    out = tmp_path / "runs"
    (out / "tiny").mkdir(parents=True)
    (out / "tiny" / "last.pt").write_bytes(b"a run cut before its first point")
    with pytest.raises(ValueError, match=r"runs/tiny: holds a run that is not this curve's"):
        learning_curves(train_dataset, out, minutes=1, points=2, val_images=2,
                        progress=False, configs=tiny)
    assert sorted(p.name for p in (out / "tiny").iterdir()) == ["last.pt"]
