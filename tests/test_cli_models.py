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
    captured = capsys.readouterr()
    err = captured.err
    assert "2 failed" in err and "empty.obj" in err and "nan.obj" in err
    # Only the written import is reported with its name; the failed ones only as failures.
    assert "good.stl -> good" in captured.out and "empty.obj ->" not in captured.out
    assert "nan.obj ->" not in captured.out
    assert sorted(p.name for p in out.iterdir()) == ["good", "splits.csv"]
    assert (out / "splits.csv").read_text() == "good,test\n"  # rows of the written alone
    card = json.loads((out / "good" / "models" / "model_card.json").read_text())
    assert card["extents"] == [1.0, 0.66666667, 0.33333333]


def test_a_folder_given_as_a_mesh_is_named_a_folder(tmp_path, capsys) -> None:
    folder = tmp_path / "meshes.obj"
    folder.mkdir()
    assert main(["models", "import", str(folder), "--out", str(tmp_path / "lib")]) != 0
    assert "is a folder" in capsys.readouterr().err


def test_bad_arguments_exit_2(tmp_path) -> None:
    assert main(["models", "generate", "--count", "0", "--out", str(tmp_path)]) == 2
    assert main(["models", "preview", str(tmp_path)]) == 2


def test_composed_generator_keeps_the_held_out_families_apart(tmp_path) -> None:
    from sq_mitsuba.data.spacecraft import HELD_OUT_FAMILIES

    training, held_out = tmp_path / "training", tmp_path / "held_out"
    for out, families in ((training, "training"), (held_out, "held-out")):
        assert main(["models", "generate", "--generator", "composed", "--families", families,
                     "--count", "5", "--seed", "3", "--points", "500", "--out", str(out)]
                    ) == 0
    rows = {path: [line.split(",") for line in (path / "splits.csv").read_text().split()]
            for path in (training, held_out)}
    family = {name: name.split("_", 1)[1] for rows_ in rows.values() for name, _ in rows_}
    assert len(rows[training]) == len(rows[held_out]) == 5
    assert all(name.startswith("cs") for name in family)
    assert not any(family[name] in HELD_OUT_FAMILIES for name, _ in rows[training])
    assert all(family[name] in HELD_OUT_FAMILIES and split == "test"
               for name, split in rows[held_out])
    # The archetype catalogue has no held-out families to choose.
    assert main(["models", "generate", "--families", "held-out", "--count", "2",
                 "--out", str(tmp_path / "x")]) == 2


def test_graph_generator_writes_part_graphs(tmp_path) -> None:
    out = tmp_path / "graphs"
    assert main(["models", "generate", "--generator", "graph", "--count", "2", "--seed", "3",
                 "--points", "500", "--out", str(out)]) == 0
    rows = [line.split(",") for line in (out / "splits.csv").read_text().split()]
    assert [name for name, _ in rows] == ["pg00000_part_graph", "pg00001_part_graph"]
    assert (out / "pg00001_part_graph" / "models" / "model_normalized.obj").is_file()
    # Part graphs belong to no family: none to hold out.
    assert main(["models", "generate", "--generator", "graph", "--families", "training",
                 "--count", "2", "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()


def test_a_machine_too_small_for_the_imports_default_still_runs_every_other_models_command(
        tmp_path, capsys, monkeypatch) -> None:
    """The parser took its defaults from an ImportOptions(), whose own check measures depth
    fusion's memory (about 2.3 GiB at the default resolution): on a machine of 1 GiB every
    `models` command, --help included, failed with a traceback. Only an import refuses now."""
    from sq_mitsuba import machine
    from sq_mitsuba.data import library

    for module in (machine, library):  # the library holds its own name of it
        monkeypatch.setattr(module, "available_memory", lambda: 2**30)
    out = tmp_path / "lib"
    assert main(["models", "generate", "--count", "1", "--out", str(out), "--points", "200"]) == 0
    capsys.readouterr()
    box = tmp_path / "box.stl"
    trimesh.creation.box([1.0, 2.0, 3.0]).export(box)
    assert main(["models", "import", str(box), "--out", str(tmp_path / "imported")]) == 2
    error = capsys.readouterr().err.strip()
    assert "resolution" in error and "memory" in error and "\n" not in error, error
    assert not (tmp_path / "imported").exists()
