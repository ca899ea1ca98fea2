"""Model library: whole processed models, stable merged splits, failures, import names,
option ranges."""

from __future__ import annotations

import json
import re
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh

from sq_mitsuba.cli import main
from sq_mitsuba.config import ConfigError
from sq_mitsuba.data.contact_sheet import ContactSheetOptions, contact_sheet
from sq_mitsuba.data.library import (
    FAILURES_FILE,
    GenerateOptions,
    ImportOptions,
    generate_library,
    import_names,
)
from sq_mitsuba.data.mesh_io import read_obj, read_tagged_obj
from sq_mitsuba.data.solids import fusion_memory_bytes, max_fusion_resolution
from sq_mitsuba.data.spacecraft import catalogue
from sq_mitsuba.data.spe3r.layout import load_model, read_splits
from sq_mitsuba.machine import available_memory
from sq_mitsuba.render.materials import MATERIALS, MTL_COLOUR

SEED = 5


@pytest.fixture(scope="module")
def library(tmp_path_factory) -> Path:
    """Three generated models (small point sets), written by :func:`generate_library`."""
    root = tmp_path_factory.mktemp("library")
    summary = generate_library(GenerateOptions(out=root, count=3, seed=SEED, points=300),
                               progress=False)
    assert summary.ok and len(summary.written) == 3
    return root


def _models(root: Path) -> list[Path]:
    return sorted(root.glob("*/models"))


def _old_style_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, tags: np.ndarray) -> None:
    """The OBJ the library wrote before: faces grouped by material with ``usemtl``."""
    lines = ["mtllib model_normalized.mtl"] + [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in vertices]
    current = -1
    for (a, b, c), tag in zip(faces + 1, tags, strict=True):
        if tag != current:
            lines.append(f"usemtl {MATERIALS[tag]}")
            current = tag
        lines.append(f"f {a} {b} {c}")
    path.write_text("\n".join(lines) + "\n")


def test_processed_models_load_as_one_watertight_mesh(library) -> None:
    """``trimesh.load(obj, force="mesh")`` with default arguments: one closed body whose
    volume is the card's, the faces those of ``face_material``."""
    for folder in _models(library):
        obj = folder / "model_normalized.obj"
        mesh = trimesh.load(obj, force="mesh")
        assert mesh.is_watertight and mesh.is_winding_consistent, folder
        assert mesh.body_count == 1
        card = json.loads((folder / "model_card.json").read_text())
        assert mesh.volume == pytest.approx(card["volume"], rel=1e-5)
        with np.load(folder / "samples.npz") as samples:
            assert len(samples["face_material"]) == len(mesh.faces) == card["faces"]
        assert "usemtl" not in obj.read_text()


def test_old_usemtl_objs_split_in_trimesh_and_still_read(library, tmp_path) -> None:
    """The problem the new format fixes: usemtl groups split trimesh's mesh at the seams. Old
    files still read, with their tags, and agree with the new files plus samples.npz."""
    folder = _models(library)[0]
    new = read_tagged_obj(folder / "model_normalized.obj")
    assert len(np.unique(new.face_material)) > 1
    old = tmp_path / "old.obj"
    _old_style_obj(old, new.vertices, new.faces, new.face_material)
    assert not trimesh.load(old, force="mesh").is_watertight
    vertices, faces, tags = read_obj(old)
    np.testing.assert_allclose(vertices, new.vertices, atol=1e-7)
    np.testing.assert_array_equal(faces, new.faces)
    np.testing.assert_array_equal(tags, new.face_material)
    # Without samples.npz beside it, the old file's own tags are used.
    assert np.array_equal(read_tagged_obj(old).face_material, new.face_material)


def test_dataset_loader_gets_per_face_tags(library) -> None:
    for folder in _models(library):
        _, faces, tags = load_model(folder.parent)
        with np.load(folder / "samples.npz") as samples:
            expected = np.asarray(MATERIALS)[samples["face_material"]]
        assert tags is not None and len(tags) == len(faces)
        np.testing.assert_array_equal(tags, expected)


def _linear(c: float) -> float:
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def test_glb_carries_the_materials(library) -> None:
    folder = _models(library)[0]
    data = (folder / "model_normalized.glb").read_bytes()
    magic, version, length = struct.unpack("<4sII", data[:12])
    assert (magic, version, length) == (b"glTF", 2, len(data))
    mesh = read_tagged_obj(folder / "model_normalized.obj")
    counts = np.bincount(mesh.face_material, minlength=len(MATERIALS))
    scene = trimesh.load(folder / "model_normalized.glb")
    by_material = {g.visual.material.name: g for g in scene.geometry.values()}
    assert {name: len(g.faces) for name, g in by_material.items()} == {
        MATERIALS[i]: int(c) for i, c in enumerate(counts) if c}
    for name, geometry in by_material.items():
        colour = np.asarray(geometry.visual.material.baseColorFactor[:3], float) / 255
        np.testing.assert_allclose(colour, [_linear(c) for c in MTL_COLOUR[name]], atol=0.01)
        # Each material's triangles are the OBJ's triangles of that tag.
        tag = MATERIALS.index(name)
        expected = np.sort(mesh.vertices[mesh.faces[mesh.face_material == tag]].reshape(-1, 3),
                           axis=0)
        got = np.sort(geometry.vertices[geometry.faces].reshape(-1, 3), axis=0)
        np.testing.assert_allclose(got, expected, atol=1e-6)


def test_generate_merges_splits_and_records_failures(tmp_path) -> None:
    out = tmp_path / "lib"
    out.mkdir()
    (out / "splits.csv").write_text("imported_thing,train\n")
    reference = {e.name: e.split for e in catalogue(64, SEED)}
    names = [e.name for e in catalogue(3, SEED)]

    generate_library(GenerateOptions(out=out, count=2, seed=SEED, points=200), progress=False)
    assert read_splits(out / "splits.csv") == {"imported_thing": "train",
                                               **{n: reference[n] for n in names[:2]}}

    # A real failure: a file where the third model's folder must go.
    (out / names[2]).write_text("in the way\n")
    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=200),
                               progress=False)
    assert summary.written == names[:2] and list(summary.failures) == [names[2]]
    assert json.loads((out / FAILURES_FILE).read_text()).keys() == {names[2]}
    rows = (out / "splits.csv").read_text().splitlines()
    assert sorted(rows) == sorted(["imported_thing,train"] +
                                  [f"{n},{reference[n]}" for n in names[:2]])

    (out / names[2]).unlink()
    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=200),
                               progress=False)
    assert summary.ok
    assert not (out / FAILURES_FILE).exists()
    rows = (out / "splits.csv").read_text().splitlines()
    assert len(rows) == len(set(rows)) == 4  # same name, same row
    assert read_splits(out / "splits.csv") == {"imported_thing": "train",
                                               **{n: reference[n] for n in names}}


def test_workers_build_the_same_files_and_keep_failures_apart(library, tmp_path) -> None:
    """Two worker processes give the library one process gives, byte for byte, and a model
    that fails in a worker is recorded like one that fails in the main process."""
    names = [e.name for e in catalogue(3, SEED)]
    out = tmp_path / "lib"
    out.mkdir()
    (out / names[1]).write_text("in the way\n")
    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=300,
                                               workers=2), progress=False)
    assert summary.written == [names[0], names[2]] and list(summary.failures) == [names[1]]
    assert "in the way" not in summary.failures[names[1]]  # the reason, not the file's text
    assert set(read_splits(out / "splits.csv")) == {names[0], names[2]}
    for name in (names[0], names[2]):
        files = sorted(p.relative_to(library) for p in (library / name).rglob("*")
                       if p.is_file())
        assert files
        for relative in files:
            assert (out / relative).read_bytes() == (library / relative).read_bytes(), relative


def test_cli_count_6_splits_are_those_of_count_64(tmp_path) -> None:
    out = tmp_path / "lib"
    assert main(["models", "generate", "--count", "6", "--seed", "0", "--out", str(out),
                 "--points", "200"]) == 0
    reference = {e.name: e.split for e in catalogue(64, 0)}
    splits = read_splits(out / "splits.csv")
    assert len(splits) == 6 and all(reference[name] == s for name, s in splits.items())
    card = json.loads((out / next(iter(splits)) / "models" / "model_card.json").read_text())
    assert card["catalogue_seed"] == 0


def test_import_gives_every_file_its_own_folder(tmp_path, capsys) -> None:
    box, sphere = tmp_path / "a.obj", tmp_path / "a.glb"
    trimesh.creation.box([1.0, 0.5, 0.25]).export(box)
    trimesh.Scene({"s": trimesh.creation.icosphere(subdivisions=2)}).export(sphere)
    out = tmp_path / "lib"
    assert main(["models", "import", str(box), str(sphere), "--out", str(out),
                 "--points", "200"]) == 0
    printed = capsys.readouterr().out
    assert f"{box} -> a\n" in printed and f"{sphere} -> a_2\n" in printed
    cards = {n: json.loads((out / n / "models" / "model_card.json").read_text())
             for n in ("a", "a_2")}
    assert cards["a"]["source"] == str(box) and cards["a_2"]["source"] == str(sphere)
    before = (out / "a" / "models" / "model_normalized.obj").read_bytes()
    # Importing again never overwrites: the next free number.
    assert main(["models", "import", str(box), "--out", str(out), "--points", "200"]) == 0
    assert f"{box} -> a_3\n" in capsys.readouterr().out
    assert (out / "a" / "models" / "model_normalized.obj").read_bytes() == before
    assert sorted(p.name for p in out.iterdir()) == ["a", "a_2", "a_3", "splits.csv"]
    assert import_names([box, sphere, tmp_path / "b.stl"], out) == ["a_4", "a_5", "b"]
    # Each model gets its row, test unless told: a library `dataset render` takes as it is.
    assert read_splits(out / "splits.csv") == {"a": "test", "a_2": "test", "a_3": "test"}
    assert main(["models", "import", str(box), "--out", str(out), "--points", "200",
                 "--split", "train"]) == 0
    assert read_splits(out / "splits.csv")["a_4"] == "train"
    # A split that is neither: one line naming the option, before any model is imported.
    with pytest.raises(SystemExit) as stop:  # argparse's one line, exit 2
        main(["models", "import", str(box), "--out", str(out), "--points", "200",
              "--split", "val"])
    assert stop.value.code == 2 and "--split: invalid choice: 'val'" in capsys.readouterr().err
    assert not (out / "a_5").exists()
    # A file named like a library's or dataset's own file gets another name.
    assert import_names([tmp_path / "splits.csv.obj", tmp_path / "camera.json.stl"],
                        tmp_path / "empty") == ["splits.csv_2", "camera.json_2"]
    # Letters of any script are kept (they were dropped: "日本.obj" became "model"), in
    # their composed form; what is no letter or digit becomes "_".
    assert import_names([tmp_path / "Satellit_ü.obj", tmp_path / "Satellit_u\u0308 2.obj",
                         tmp_path / "日本 衛星.stl", tmp_path / "🚀.obj"],
                        tmp_path / "empty") == ["Satellit_ü", "Satellit_ü_2", "日本_衛星",
                                                "model"]


def test_import_missing_file_is_an_error_before_any_work(tmp_path, capsys) -> None:
    good = tmp_path / "good.stl"
    trimesh.creation.box([1.0, 2.0, 3.0]).export(good)
    out = tmp_path / "lib"
    assert main(["models", "import", str(good), str(tmp_path / "nope.obj"),
                 "--out", str(out)]) == 2
    assert "nope.obj: no such file" in capsys.readouterr().err
    assert not out.exists()


def test_generate_and_import_refuse_a_dataset_as_out(library, tmp_path, capsys) -> None:
    """A rendered dataset holds a copy of each model and a splits.csv: generating or
    importing into it rewrote them silently. Refused in one line before any work (exit 2),
    as `dataset render` refuses the library as its output; the dataset byte for byte kept."""
    from sq_mitsuba.data.spe3r import RenderOptions, render_dataset

    data = tmp_path / "data"
    one = tmp_path / "one"
    name = _models(library)[0].parent.name
    shutil.copytree(library / name, one / name)
    (one / "splits.csv").write_text(f"{name},test\n")
    render_dataset(one, data, RenderOptions(images_per_model=1, resolution=16, spp=1),
                   progress=False)
    before = {p: p.read_bytes() for p in sorted(data.rglob("*")) if p.is_file()}
    box = tmp_path / "box.stl"
    trimesh.creation.box([1.0, 0.5, 0.25]).export(box)
    for argv in (["generate", "--count", "1", "--seed", str(SEED), "--points", "300"],
                 ["import", str(box), "--points", "200"]):
        capsys.readouterr()
        assert main(["models", *argv, "--out", str(data)]) == 2
        assert capsys.readouterr().err.strip() == (
            f"sq-mitsuba models: error: {data}: the output folder is a dataset (it holds "
            "dataset.json), not a model library; write the models into another folder")
        assert {p: p.read_bytes() for p in sorted(data.rglob("*")) if p.is_file()} == before


@pytest.mark.parametrize("argv, flag", [
    (["generate", "--seed", "-1"], "--seed"),
    (["generate", "--seed", str(2**32)], "--seed"),
    (["generate", "--count", "0"], "--count"),
    (["generate", "--count", "10001"], "--count"),
    (["generate", "--points", "0"], "--points"),
    (["generate", "--points", "2000001"], "--points"),
    (["import", "MESH", "--resolution", "100000"], "--resolution"),
    (["import", "MESH", "--resolution", "8"], "--resolution"),
    (["import", "MESH", "--points", "-5"], "--points"),
    (["preview", "ROOT", "--size", "8"], "--size"),
    (["preview", "ROOT", "--size", "5000"], "--size"),
    (["preview", "ROOT", "--spp", "0"], "--spp"),
    (["preview", "ROOT", "--spp", "100000"], "--spp"),
    (["preview", "ROOT", "--columns", "0"], "--columns"),
    (["preview", "ROOT", "--columns", "1000"], "--columns"),
    (["preview", "ROOT", "--limit", "0"], "--limit"),
])
def test_numeric_options_are_range_checked_before_any_work(tmp_path, capsys, monkeypatch,
                                                            argv, flag) -> None:
    # The work of each command (the library calls behind it) must never start: each records
    # its call and fails (a command that reached them exits 1, not 2).
    from sq_mitsuba.data import contact_sheet as sheet_module
    from sq_mitsuba.data import library as library_module

    started = []
    for module, name in ((library_module, "generate_library"),
                         (library_module, "import_models"), (sheet_module, "contact_sheet")):
        def work(*args, _name=name, **kwargs):
            started.append(_name)
            raise RuntimeError(f"{_name} started")

        monkeypatch.setattr(module, name, work)
    mesh = tmp_path / "box.stl"
    trimesh.creation.box([1.0, 2.0, 3.0]).export(mesh)
    out = tmp_path / "out"
    argv = [str(mesh) if a == "MESH" else str(tmp_path) if a == "ROOT" else a for a in argv]
    if argv[0] != "preview":
        argv += ["--out", str(out)]
    else:
        argv += ["--out", str(out / "sheet.png")]
    assert main(["models", *argv]) == 2
    assert started == []  # refused at once, not after (or during) the work
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"error: {flag}:" in err, err
    if flag == "--resolution" and argv[2] == "100000":
        assert "(depth fusion) needs about" in err and "GiB of memory" in err
    assert not out.exists()


def test_resolution_bound_is_the_memory_estimate() -> None:
    for memory in (4 * 2**30, 16 * 2**30, 64 * 2**30):
        r = max_fusion_resolution(memory)
        assert fusion_memory_bytes(r) <= memory < fusion_memory_bytes(r + 1)
    limit = max_fusion_resolution(available_memory())
    assert ImportOptions(resolution=min(limit, 128)).resolution == min(limit, 128)
    with pytest.raises(ValueError,
                       match=rf"resolution: {limit + 1} \(depth fusion\) needs about .* GiB"):
        ImportOptions(resolution=limit + 1)


def test_help_shows_the_library_defaults(capsys) -> None:
    for action, config, fields in (("generate", GenerateOptions(), ("count", "seed", "points")),
                                   ("import", ImportOptions(), ("resolution", "method")),
                                   ("preview", ContactSheetOptions(), ("size", "spp"))):
        with pytest.raises(SystemExit):
            main(["models", action, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        for name in fields:
            assert f"(default: {getattr(config, name)})" in text, (action, name)


def test_contact_sheet_size_checked_before_rendering(library, tmp_path) -> None:
    options = ContactSheetOptions(out=tmp_path / "sheet.png", size=1024, columns=256)
    with pytest.raises(ValueError, match="size: 3 models of 1024 px in 256 columns"):
        contact_sheet(library, options)
    with pytest.raises(ConfigError, match="spp"):
        contact_sheet(library, ContactSheetOptions(spp=0))
    assert not (tmp_path / "sheet.png").exists()


OUT_FOLDER_CASES = {"under a file": ("a_file/sheet.png", "/a_file is a file, not a folder"),
                    "in /proc": ("/proc/sheet.png", "cannot write in /proc")}


@pytest.mark.parametrize("case", OUT_FOLDER_CASES)
def test_a_contact_sheet_out_that_cannot_be_written_is_refused_before_rendering(
        library, tmp_path, capsys, case) -> None:
    """An --out whose folder cannot take the sheet rendered every model, then failed naming
    the temporary file of the atomic write; now one line naming --out, before any render
    (no progress bar)."""
    where, reason = OUT_FOLDER_CASES[case]
    if where.startswith("/proc") and not Path("/proc/self").is_dir():
        pytest.skip("no /proc here")
    (tmp_path / "a_file").write_text("a file, not a folder")
    out = Path(where) if where.startswith("/") else tmp_path / where
    assert main(["models", "preview", str(library), "--out", str(out), "--size", "16",
                 "--spp", "1"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err  # no progress bar: nothing was rendered
    assert err.startswith(f"sq-mitsuba models: error: out {out}: ") and reason in err, err
    assert ".tmp" not in err and not out.exists()


def test_a_model_in_both_splits_is_refused_naming_the_line(tmp_path):
    from sq_mitsuba.data.spe3r.layout import DatasetError

    path = tmp_path / "splits.csv"
    path.write_text("a,train\nb,test\na,train\n")  # a repeat in the same split is harmless
    assert read_splits(path) == {"a": "train", "b": "test"}
    path.write_text("a,train\nb,test\na,test\n")
    with pytest.raises(DatasetError, match=rf"^{re.escape(str(path))}:3: 'a' is listed as "
                                           "train above and as test here$"):
        read_splits(path)
    # Bytes that are not text name the file (they came out as a bare UnicodeDecodeError).
    path.write_bytes(b"a,train\nb\xff,test\n")
    with pytest.raises(DatasetError, match=rf"^{re.escape(str(path))}: not UTF-8 text "
                                           r"\(invalid start byte at byte 9\)$"):
        read_splits(path)


def _identity(folder: Path) -> int:
    """The inode of a model's ``models/`` folder: write_model replaces the folder, so a model
    built again gets a new one."""
    return (folder / "models").stat().st_ino


def test_a_rerun_keeps_complete_models_and_rebuilds_the_rest(tmp_path, capsys) -> None:
    """Run again into the same --out (after an interrupt), a batch builds only what is not
    there complete: not a model whose files are all there with the same --points."""
    names = [e.name for e in catalogue(3, SEED)]
    out = tmp_path / "lib"
    generate_library(GenerateOptions(out=out, count=2, seed=SEED, points=200), progress=False)
    before = {name: _identity(out / name) for name in names[:2]}
    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=200),
                               progress=False)
    assert summary.ok and summary.written == names
    assert {name: _identity(out / name) for name in names[:2]} == before  # not built again
    assert summary.kept == names[:2]
    assert f"3 model(s) in {out}: 1 built, 2 already there" in summary.text()
    # A model missing one of its files is built again, as is every model at other --points.
    (out / names[1] / "models" / "model_normalized.glb").unlink()
    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=200),
                               progress=False)
    assert summary.kept == [names[0], names[2]]
    assert (out / names[1] / "models" / "model_normalized.glb").is_file()
    # So is one whose files were cut short or emptied since: the same files again.
    files = {name: (out / names[k] / "models" / name).read_bytes() for k, name in
             ((0, "model_normalized.obj"), (1, "model_normalized.glb"), (2, "samples.npz"))}
    for k, name in enumerate(files):  # the OBJ cut inside its last face: its counts hold
        (out / names[k] / "models" / name).write_bytes(
            files[name][:-4] if k == 0 else files[name][:len(files[name]) // 2])
    (out / names[1] / "models" / "model_normalized.glb").write_bytes(b"")
    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=200),
                               progress=False)
    assert summary.kept == [] and summary.written == names
    assert {k: (out / names[i] / "models" / k).read_bytes()
            for i, k in enumerate(files)} == files
    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=150),
                               progress=False)
    assert summary.ok and summary.kept == []
    card = json.loads((out / names[0] / "models" / "model_card.json").read_text())
    assert card["samples"]["surface"] == 150
    # --rebuild builds every model again; the CLI line says how many were already there.
    kept = _identity(out / names[0])
    assert main(["models", "generate", "--count", "3", "--seed", str(SEED), "--out", str(out),
                 "--points", "150"]) == 0
    assert "3 model(s) in " in capsys.readouterr().out  # ...: 0 built, 3 already there
    assert _identity(out / names[0]) == kept
    assert main(["models", "generate", "--count", "3", "--seed", str(SEED), "--out", str(out),
                 "--points", "150", "--rebuild"]) == 0
    assert "already there" not in capsys.readouterr().out
    assert _identity(out / names[0]) != kept


def _dead_write(folder: Path, name: str, source: Path) -> Path:
    """What a write killed by SIGKILL leaves: the model's files in a hidden folder."""
    path = folder / name
    shutil.copytree(source, path)
    return path


def test_a_killed_runs_temporary_folders_are_ignored_then_removed(tmp_path) -> None:
    """Leftovers of writes killed outright: readers never list them, and the next generate
    removes them (an old model with no new one beside it is put back, and kept)."""
    from sq_mitsuba.data.contact_sheet import library_models
    from sq_mitsuba.data.spe3r.writer import find_models

    names = [e.name for e in catalogue(3, SEED)]
    out = tmp_path / "lib"
    generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=200), progress=False)
    model = out / names[0] / "models"
    leftovers = [
        _dead_write(out / names[0], ".models.k1ll3d_x", model),   # a rewrite, killed
        _dead_write(out / names[1], ".models.old.4242", model),   # cut after its renames
        _dead_write(out / "sc099_first", ".models.abcd_123", model),  # a first write, killed
    ]
    (out / ".splits.a1b2c3d4.tmp.csv").write_text("half a line")
    leftovers.append(out / ".splits.a1b2c3d4.tmp.csv")
    # Cut between its two renames: the model is aside, no models/ in its place.
    old = out / names[2] / ".models.old.4343"
    (out / names[2] / "models").rename(old)
    inode = old.stat().st_ino

    assert find_models(out) == sorted(names)  # the orphan is not a model, nor the hidden ones
    assert library_models(out) == [out / n / "models" / "model_normalized.obj"
                                   for n in names[:2]]

    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=200),
                               progress=False)
    assert not any(path.exists() for path in leftovers)
    assert not (out / "sc099_first").exists() and not old.exists()
    assert list(out.rglob(".models*")) == []
    assert sorted(p.name for p in out.iterdir()) == sorted([*names, "splits.csv"])
    assert summary.ok and summary.kept == names  # the old model came back complete
    assert (out / names[2] / "models").stat().st_ino == inode


def test_leftovers_are_removed_only_under_the_librarys_lock(tmp_path) -> None:
    from sq_mitsuba.data.library import remove_dead_writes
    from sq_mitsuba.outputs import output_lock

    leftover = tmp_path / "lib" / "m" / ".models.abcdefgh"
    leftover.mkdir(parents=True)
    assert remove_dead_writes(tmp_path / "lib") == []  # no lock held: maybe another run's
    assert leftover.is_dir()
    with output_lock(tmp_path / "lib"):
        assert remove_dead_writes(tmp_path / "lib") == [leftover]
    assert not (tmp_path / "lib" / "m").exists()


def test_import_frees_a_name_a_killed_import_left_taken(tmp_path, capsys) -> None:
    box = tmp_path / "a.obj"
    trimesh.creation.box([1.0, 0.5, 0.25]).export(box)
    out = tmp_path / "lib"
    (out / "a" / ".models.abcdefgh").mkdir(parents=True)
    (out / "a" / ".models.abcdefgh" / "model_normalized.obj").write_text("v 0 0 0\n")
    assert main(["models", "import", str(box), "--out", str(out), "--points", "200"]) == 0
    assert f"{box} -> a\n" in capsys.readouterr().out
    assert sorted(p.name for p in (out / "a").iterdir()) == ["models"]


def test_a_model_put_back_from_a_killed_rewrite_is_never_replaced(tmp_path) -> None:
    """A model aside as ``.models.old.<pid>`` (a rewrite killed between its renames) is a
    model of the library: another spacecraft of its name is refused, as for ``models/``."""
    name = catalogue(1, SEED)[0].name
    out = tmp_path / "lib"
    generate_library(GenerateOptions(out=out, count=1, seed=SEED, points=200), progress=False)
    card_path = out / name / "models" / "model_card.json"
    card = json.loads(card_path.read_text())
    card_path.write_text(json.dumps({**card, "seed": card["seed"] + 1}))  # another spacecraft
    (out / name / "models").rename(out / name / ".models.old.77")
    with pytest.raises(ValueError, match="holds another spacecraft of this name"):
        generate_library(GenerateOptions(out=out, count=1, seed=SEED, points=200),
                         progress=False)
    assert json.loads(card_path.read_text())["seed"] == card["seed"] + 1


def test_a_model_card_of_another_catalogue_is_built_again(library, tmp_path) -> None:
    """A complete model whose card names another catalogue seed, or another split, is not
    kept by a rerun: it is built again and its card says this catalogue's values."""
    reference = {e.name: e.split for e in catalogue(64, SEED)}
    names = [e.name for e in catalogue(3, SEED)]
    out = tmp_path / "lib"
    shutil.copytree(library, out)
    cards = {name: out / name / "models" / "model_card.json" for name in names[:2]}
    card = json.loads(cards[names[0]].read_text())
    cards[names[0]].write_text(json.dumps({**card, "catalogue_seed": SEED + 1}))
    card = json.loads(cards[names[1]].read_text())
    other = {"train": "test", "test": "train"}[reference[names[1]]]
    cards[names[1]].write_text(json.dumps({**card, "split": other}))
    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=300),
                               progress=False)
    assert summary.ok and summary.written == names and summary.kept == [names[2]]
    for name in names[:2]:
        card = json.loads(cards[name].read_text())
        assert (card["catalogue_seed"], card["split"]) == (SEED, reference[name]), name


def test_a_kept_model_missing_from_splits_gets_its_row_back(library, tmp_path) -> None:
    """Killed between publishing a model and writing splits.csv: the rerun keeps the model
    and writes its row."""
    reference = {e.name: e.split for e in catalogue(64, SEED)}
    names = [e.name for e in catalogue(3, SEED)]
    out = tmp_path / "lib"
    shutil.copytree(library, out)
    rows = (out / "splits.csv").read_text().splitlines()
    (out / "splits.csv").write_text("".join(f"{row}\n" for row in rows
                                            if not row.startswith(f"{names[1]},")))
    assert set(read_splits(out / "splits.csv")) == {names[0], names[2]}
    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=300),
                               progress=False)
    assert summary.ok and summary.kept == names
    assert read_splits(out / "splits.csv") == {name: reference[name] for name in names}


def test_a_killed_cleanups_folder_is_removed_by_the_next_generate(library, tmp_path) -> None:
    """``<model>/.models.removing.<pid>.<x>/``: a dead write's removal, itself killed; the
    next generate removes it (and a model folder left with nothing else)."""
    names = [e.name for e in catalogue(3, SEED)]
    out = tmp_path / "lib"
    shutil.copytree(library, out)
    model = out / names[0] / "models"
    beside = _dead_write(out / names[1], ".models.removing.4242.k1ll3d_x", model)
    alone = _dead_write(out / "sc099_first", ".models.removing.4343.abcd_123", model)
    summary = generate_library(GenerateOptions(out=out, count=3, seed=SEED, points=300),
                               progress=False)
    assert summary.ok and summary.kept == names
    assert not beside.exists() and not alone.exists() and not (out / "sc099_first").exists()
    assert sorted(p.name for p in (out / names[1]).iterdir()) == ["models"]
    assert sorted(p.name for p in out.iterdir()) == sorted([*names, "splits.csv"])


def test_importing_into_a_library_imported_without_rows_keeps_its_models_training(
        tmp_path) -> None:
    """Imports once kept no splits.csv, and `dataset render` took such models for training
    ones: the next import writes them that row beside its own, so the library still
    renders; a name a row holds is not reused even when its folder is gone."""
    from sq_mitsuba.data.library import RESERVED_NAMES, import_models
    from sq_mitsuba.data.spe3r.writer import OVERWRITE_DELETES, find_models

    box = tmp_path / "box.obj"
    trimesh.creation.box([1.0, 0.5, 0.25]).export(box)
    out = tmp_path / "lib"
    import_models([box], ImportOptions(out=out, points=200), progress=False)
    (out / "splits.csv").unlink()  # as an import before rows were kept left it
    import_models([box], ImportOptions(out=out, points=200), progress=False)
    assert read_splits(out / "splits.csv") == {"box": "train", "box_2": "test"}
    assert find_models(out) == ["box", "box_2"]
    shutil.rmtree(out / "box_2")
    assert import_names([box], out, taken=read_splits(out / "splits.csv")) == ["box_3"]
    assert set(OVERWRITE_DELETES) <= RESERVED_NAMES  # the two lists kept together


def test_an_imported_mesh_in_separate_pieces_is_kept_and_said(tmp_path) -> None:
    """A panel floating beside its bus (a lost strut or node transform) imports as it is,
    with a one-line warning naming the file and the count; one body says nothing."""
    import warnings

    from sq_mitsuba.data.library import import_model

    bus = trimesh.creation.box([1.0, 1.0, 1.0])
    panel = trimesh.creation.box([2.0, 0.05, 1.0])
    panel.apply_translation([2.5, 0.0, 0.0])
    trimesh.util.concatenate([bus, panel]).export(tmp_path / "apart.obj")
    bus.export(tmp_path / "bus.obj")
    with pytest.warns(UserWarning, match=r"apart.obj: 2 separate pieces: parts that do not "
                                         r"touch in the file stay apart"):
        assert import_model(tmp_path / "apart.obj", tmp_path / "lib", points=200).is_dir()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        import_model(tmp_path / "bus.obj", tmp_path / "lib", points=200)
