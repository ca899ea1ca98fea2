"""``sq-mitsuba models``: generate, import (with failures), preview."""

from __future__ import annotations

import json

import numpy as np
import trimesh
from PIL import Image

from sq_mitsuba.cli import main


def test_generate_writes_layout_splits_and_cards(tmp_path) -> None:
    out = tmp_path / "lib"
    assert main(["models", "generate", "--count", "3", "--seed", "5", "--out", str(out),
                 "--points", "500"]) == 0
    rows = (out / "splits.csv").read_text().splitlines()
    assert len(rows) == 3 and all(r.split(",")[1] in ("train", "test") for r in rows)
    assert sum(r.endswith(",test") for r in rows) == 1
    for row in rows:
        folder = out / row.split(",")[0] / "models"
        card = json.loads((folder / "model_card.json").read_text())
        assert all(card["checks"].values())
        assert card["source"] == "procedural" and card["archetype"] in row
        samples = np.load(folder / "samples.npz")
        assert samples["near_points"].shape == (500, 3)
        assert (folder / "model_normalized.obj").stat().st_size > 0
    sheet = out / "sheet.png"
    assert main(["models", "preview", str(out), "--out", str(sheet), "--size", "32",
                 "--spp", "2"]) == 0
    with Image.open(sheet) as image:
        assert image.size[0] == 2 * 32
        tile = np.asarray(image)[:32, :32]
    # Black background (the ambient light is hidden from the camera), a lit model in the middle.
    border = np.concatenate([tile[0], tile[-1], tile[:, 0], tile[:, -1]])
    assert border.max() == 0
    assert tile[8:24, 8:24].max() > 100


def test_import_batch_continues_past_bad_files(tmp_path, capsys) -> None:
    good = tmp_path / "good.stl"
    trimesh.creation.box([1.0, 2.0, 3.0]).export(good)
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    out = tmp_path / "lib"
    code = main(["models", "import", str(empty), str(good), str(nan), "--out", str(out),
                 "--points", "500"])
    assert code == 1
    err = capsys.readouterr().err
    assert "2 failed" in err and "empty.obj" in err and "nan.obj" in err
    assert sorted(p.name for p in out.iterdir()) == ["good"]
    card = json.loads((out / "good" / "models" / "model_card.json").read_text())
    assert card["extents"] == [1.0, 0.66666667, 0.33333333]


def test_bad_arguments_exit_2(tmp_path) -> None:
    assert main(["models", "generate", "--count", "0", "--out", str(tmp_path)]) == 2
    assert main(["models", "preview", str(tmp_path)]) == 2
