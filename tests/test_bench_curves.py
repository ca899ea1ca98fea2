"""``sq-mitsuba bench curves``: held-out Chamfer-L1 against training time, resumable."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from sq_mitsuba.cli import main
from sq_mitsuba.config import apply_overrides
from sq_mitsuba.training.config import load_train_config

TINY = Path(__file__).resolve().parents[1] / "train" / "configs" / "tiny.toml"


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
    tiny = load_train_config(TINY)
    with pytest.raises(ValueError, match="configs: 'a b' and another label share the run "
                                         "folder 'a_b'"):
        learning_curves(tmp_path, tmp_path / "out", minutes=1, configs={"a b": tiny,
                                                                        "a, b": tiny})
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="dataset folder not found"):
        learning_curves(tmp_path / "none", tmp_path / "out", minutes=1)


def test_cli_curves_needs_data_minutes_and_out(tmp_path, capsys):
    assert main(["bench", "curves", "--minutes", "1", "--out", str(tmp_path)]) == 2
    assert "--data: required by the curves suite" in capsys.readouterr().err


_CUT_RUN = """
import os, signal, sys
import sq_mitsuba.training.train as training
from sq_mitsuba.bench.curves import learning_curves
from sq_mitsuba.config import apply_overrides
from sq_mitsuba.training.config import load_train_config

train, calls = training.train, []


def cut(*args, **kwargs):
    # The second slice trains a step past the first point (last.pt moves on), then the
    # process dies as a kill -9 would, before that slice's point is measured.
    calls.append(1)
    if len(calls) == 2:
        train(*args, **{**kwargs, "max_seconds": 1e-3})
        os.kill(os.getpid(), signal.SIGKILL)
    return train(*args, **kwargs)


training.train = cut
config = apply_overrides(load_train_config(sys.argv[4]), ["optim.epochs=1000"])
learning_curves(sys.argv[1], sys.argv[2], minutes=float(sys.argv[3]), points=2, val_images=2,
                progress=False, configs={"tiny": config})
"""


def _same(a, b) -> bool:
    """Curves equal, a NaN images/s equal to a NaN."""
    nan = math.isnan(a.images_per_second) and math.isnan(b.images_per_second)
    return (nan and dataclasses.replace(a, images_per_second=0.0) == \
        dataclasses.replace(b, images_per_second=0.0)) or a == b


@pytest.mark.slow
def test_a_curve_cut_between_points_continues_from_its_last_point(train_dataset, tmp_path):
    """A run killed (SIGKILL) a step into training towards its second point: the rerun keeps
    the first point as recorded, starts again from that point's checkpoint, and measures the
    second (beside a second config's curve drawn from nothing, plotted and reported); a rerun
    of the finished curves trains nothing."""
    import torch

    from sq_mitsuba.bench.curves import (
        CURVE_FILE,
        curves_report,
        learning_curves,
        plot_learning_curves,
    )

    out, minutes = tmp_path / "runs", 2 / 60  # a second a slice: a step or more each
    log = tmp_path / "child.log"
    with open(log, "wb") as stderr:
        code = subprocess.run([sys.executable, "-c", _CUT_RUN, str(train_dataset), str(out),
                               str(minutes), str(TINY)], stderr=stderr, timeout=600).returncode
    record = out / "tiny" / CURVE_FILE
    assert code == -signal.SIGKILL and record.is_file(), (code, log.read_text()[-2000:])
    first = json.loads(record.read_text())
    assert len(first["seconds"]) == 1 and not first["finished"]
    cut = torch.load(out / "tiny" / "last.pt", weights_only=True)
    assert cut["step"] > first["steps"][0]  # training past the point, to be done again
    # The rerun also draws a second curve from nothing (its own folder): two configs side by
    # side, plotted and reported, as `bench curves` does.
    tiny = apply_overrides(load_train_config(TINY), ["optim.epochs=1000"])
    long = {"tiny": tiny,
            "tiny, no augmentation": apply_overrides(tiny, ["augment.probability=0"])}
    threads = torch.get_num_threads()
    torch.set_num_threads(cut["torch_threads"])  # the cut run's: its steps repeat bit for bit
    try:
        curves = learning_curves(train_dataset, out, minutes=minutes, points=2, val_images=2,
                                 progress=False, configs=long)
    finally:
        torch.set_num_threads(threads)
    assert [c.label for c in curves] == list(long)
    for each in curves:
        assert 1 <= len(each.seconds) <= 2
        assert each.seconds == sorted(each.seconds) and each.seconds[0] > 0
        assert each.steps == sorted(each.steps) and each.steps[0] >= 1
        assert all(math.isfinite(v) and v > 0 for v in each.chamfer_l1)
    assert (out / "tiny_no_augmentation" / "last.pt").is_file()
    png = plot_learning_curves(curves, tmp_path / "curves.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = curves_report(curves, minutes, train_dataset, png)
    rows = [line for line in table.splitlines() if line.startswith("| tiny")]
    assert len(rows) == sum(len(c.seconds) for c in curves)
    curve = curves[0]
    assert curve.finished and len(curve.seconds) == 2
    assert curve.seconds[0] == first["seconds"][0] and curve.steps[0] == first["steps"][0]
    assert curve.chamfer_l1[0] == first["chamfer_l1"][0]
    assert curve.steps[1] > curve.steps[0] and curve.seconds[1] > curve.seconds[0]
    assert sorted(p.name for p in (out / "tiny").glob("point_*.pt")) == ["point_2.pt"]
    stamps = [os.stat(out / name / "last.pt").st_mtime_ns
              for name in ("tiny", "tiny_no_augmentation")]
    again = learning_curves(train_dataset, out, minutes=minutes, points=2, val_images=2,
                            progress=False, configs=long)
    assert all(_same(a, b) for a, b in zip(again, curves, strict=True))
    assert [os.stat(out / name / "last.pt").st_mtime_ns
            for name in ("tiny", "tiny_no_augmentation")] == stamps


def test_a_run_folder_of_other_settings_is_refused_before_any_training(train_dataset,
                                                                      tmp_path):
    from sq_mitsuba.bench.curves import CURVE_FILE, learning_curves

    tiny = {"tiny": load_train_config(TINY)}
    out = tmp_path / "runs"
    (out / "tiny").mkdir(parents=True)
    (out / "tiny" / "last.pt").write_bytes(b"a run of its own")
    with pytest.raises(ValueError, match=r"runs/tiny: holds a run that is not this curve's"):
        learning_curves(train_dataset, out, minutes=1, points=2, val_images=2,
                        progress=False, configs=tiny)
    assert sorted(p.name for p in (out / "tiny").iterdir()) == ["last.pt"]
    # A curve of other settings (another budget) is not continued either.
    (out / "tiny" / CURVE_FILE).write_text(json.dumps({"settings": {"minutes": 2}}))
    with pytest.raises(ValueError, match=r"runs/tiny: holds a run that is not this curve's"):
        learning_curves(train_dataset, out, minutes=1, points=2, val_images=2,
                        progress=False, configs=tiny)


def test_an_out_inside_the_dataset_is_refused_before_any_training(train_dataset, tmp_path,
                                                                   capsys):
    """An --out in the dataset folder (or one that cannot be written) is refused at once,
    naming --out: nothing trained, nothing left in the dataset (the first evaluation used to
    refuse it only after a slice of training, its logs and caches left there)."""
    import shutil

    from sq_mitsuba.bench.curves import learning_curves
    from sq_mitsuba.cli import main

    data = shutil.copytree(train_dataset, tmp_path / "data")  # the fixture's stays clean
    before = sorted(data.rglob("*"))
    with pytest.raises(ValueError, match=rf"^out {data / 'bc'}: inside the dataset folder "
                                         rf"{data}, which the curves only read"):
        learning_curves(data, data / "bc", minutes=0.001, points=1, val_images=2,
                        progress=False, configs={"tiny": load_train_config(TINY)})
    for out in (data / "bc", data):
        assert main(["bench", "curves", "--data", str(data), "--minutes", "0.001",
                     "--configs", "cpu", "--out", str(out)]) == 2
        assert capsys.readouterr().err.strip() == (
            f"sq-mitsuba bench: error: --out {out}: inside the dataset folder {data}, which "
            "the curves only read; choose a folder outside it")
    assert sorted(data.rglob("*")) == before
    blocked = tmp_path / "file"
    blocked.write_text("mine")
    assert main(["bench", "curves", "--data", str(data), "--minutes", "0.001", "--configs",
                 "cpu", "--out", str(blocked / "bc")]) == 2
    assert capsys.readouterr().err.strip() == (f"sq-mitsuba bench: error: --out {blocked}/bc: "
                                               f"{blocked} is a file, not a folder")
    assert blocked.read_text() == "mine"
