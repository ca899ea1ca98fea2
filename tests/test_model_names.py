"""Model names users give folders: read back as written, or refused in one line up front.

``splits.csv`` is CSV: a name holding a comma or a double quote is quoted on write and reads
back as itself (it was written unquoted, so such a model could not be read back, and a
leading space was stripped on read, which silently dropped a model from training). Names
with white space around them, or with bytes that are no UTF-8, are refused before any work;
one mesh file given twice to ``models import`` is refused; a folder and its row that differ
only in Unicode normalisation are named as such. Rendering at tiny sizes (16 px, spp 1).
"""

from __future__ import annotations

import os
import re
import unicodedata
from pathlib import Path

import pytest
import trimesh

from sq_mitsuba.cli import main
from sq_mitsuba.data.library import ImportOptions, import_models
from sq_mitsuba.data.spe3r.layout import (
    DatasetError,
    model_name_problem,
    read_splits,
    splits_text,
    write_splits,
)

#: Names a user's folder can have that CSV must quote, or that look like CSV syntax.
AWKWARD_NAMES = ["twin, wing", '"q" cube', 'a"b', 'say "hi"', "a,b,c", "café ü 日本 🚀",
                 "line\u2028sep", "x'y", "train", "test,train"]


def test_awkward_names_round_trip_through_splits_csv(tmp_path) -> None:
    """Before: written unquoted, 'twin, wing' came back as three fields (refused) and
    '"q" cube' as 'q cube' (another model)."""
    rows = [(name, "train" if i % 2 else "test") for i, name in enumerate(AWKWARD_NAMES)]
    assert all(model_name_problem(name) is None for name, _ in rows)
    path = write_splits(tmp_path, rows)
    assert read_splits(path) == dict(rows)
    assert path.read_text(encoding="utf-8") == splits_text(rows)
    # Plain names keep the bytes older versions wrote (a dataset is not rewritten for it).
    assert splits_text([("sc000_twin-wing.v2", "train"), ("b", "test")]) == \
        "sc000_twin-wing.v2,train\nb,test\n"


def test_files_of_older_versions_read_where_that_is_safe(tmp_path) -> None:
    path = tmp_path / "splits.csv"
    # Unquoted names with commas (the only reading of such a row), a space or CRLF around
    # the split, a quote inside a name: as before.
    path.write_bytes(b'twin, wing,train\r\na"b, test\nc,train \n\n')
    assert read_splits(path) == {"twin, wing": "train", 'a"b': "test", "c": "train"}
    # A leading quote was written bare: CSV would read '"q" cube' as 'q cube', another
    # model. Refused, naming the line, rather than read as another name.
    path.write_text('a,train\n"q" cube,test\n', encoding="utf-8")
    with pytest.raises(DatasetError, match=rf"^{re.escape(str(path))}:2: not a CSV row "
                                           r"\(',' expected after '\"'\): '\"q\" cube,test'; "):
        read_splits(path)
    path.write_text('"unclosed,train\n', encoding="utf-8")
    with pytest.raises(DatasetError, match=rf"^{re.escape(str(path))}:1: not a CSV row"):
        read_splits(path)


@pytest.mark.parametrize("name", [" cube", "cube ", "\xa0cube", "cube\u3000", " "])
def test_a_name_with_white_space_around_it_is_refused(tmp_path, name) -> None:
    """' twin2' was read as 'twin2' (stripped): that folder does not exist, and train
    dropped the model with a warning. Now refused naming the line, and never written."""
    assert model_name_problem(name) == "starts or ends with white space"
    path = tmp_path / "splits.csv"
    path.write_text(f"twin,train\n{name},train\n", encoding="utf-8")
    shown = repr(name) if name.strip() else "''"  # a blank cell is an empty name
    problem = "starts or ends with white space" if name.strip() else "empty"
    with pytest.raises(DatasetError, match=re.escape(
            f"{path}:2: model name {shown} is not a plain folder name ({problem}); refused")):
        read_splits(path)
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(DatasetError, match="is not a plain folder name"):
        write_splits(out, [("twin", "train"), (name, "test")])
    assert not (out / "splits.csv").exists()


def test_a_name_that_is_not_utf8_is_refused() -> None:
    """A folder name with a raw byte 0xff reaches Python as a surrogate escape."""
    name = os.fsdecode(b"caf\xff")
    assert model_name_problem(name) == "not valid UTF-8 (a raw byte of the file system's name)"
    assert model_name_problem("café") is None


def _mesh(path: Path, extents: tuple[float, float, float]) -> Path:
    trimesh.creation.box(extents).export(path)
    return path


@pytest.fixture(scope="module")
def two_models(tmp_path_factory) -> Path:
    """A library of two imported boxes, ``a`` (train) and ``b`` (test)."""
    tmp = tmp_path_factory.mktemp("two")
    root = tmp / "lib"
    for name, extents, split in (("a", (1.0, 0.5, 0.25), "train"),
                                 ("b", (0.4, 1.0, 0.6), "test")):
        summary = import_models([_mesh(tmp / f"{name}.obj", extents)],
                                ImportOptions(out=root, points=200, split=split),
                                progress=False)
        assert summary.ok
    return root


def _library(tmp_path: Path, two_models: Path, names: dict[str, str],
             splits: list[tuple[str, str]] | None) -> Path:
    """A copy of ``two_models`` whose folders ``a`` and ``b`` are renamed as ``names`` says,
    with ``splits`` as its rows (written as a user's file; None: rows of the new names)."""
    import shutil

    root = tmp_path / "lib"
    for old, new in names.items():
        shutil.copytree(two_models / old, root / new)
    old_splits = read_splits(two_models / "splits.csv")
    rows = splits if splits is not None else [(names[m], s) for m, s in old_splits.items()]
    (root / "splits.csv").write_text(splits_text(rows), encoding="utf-8")
    return root


def test_a_library_of_awkward_names_renders_and_reads_back(tmp_path, two_models) -> None:
    """Before: `dataset render` exited 0 with a splits.csv that check, train, eval and
    preview all refused."""
    from sq_mitsuba.data.spe3r import RenderOptions, render_dataset
    from sq_mitsuba.data.spe3r.dataset import Spe3rDataset

    library = _library(tmp_path, two_models, {"a": "twin, wing", "b": '"q" cube'}, None)
    data = tmp_path / "data"
    summary = render_dataset(library, data, RenderOptions(images_per_model=2, resolution=16,
                                                          spp=1), progress=False)
    assert summary.complete and not summary.failures
    assert read_splits(data / "splits.csv") == {"twin, wing": "train", '"q" cube': "test"}
    train = Spe3rDataset(data, "train", image_size=16, num_surface=10, num_occupancy=10)
    test = Spe3rDataset(data, "test", image_size=16, num_surface=10, num_occupancy=10)
    assert (train.models, test.models) == (["twin, wing"], ['"q" cube'])
    assert not train.skipped and not test.skipped
    assert test[0]["model"] == '"q" cube' and len(train) == 2


def test_import_keeps_a_quoted_row_readable(tmp_path) -> None:
    """A user's quoted row was rewritten unquoted by the next import, and the import after
    that refused the library."""
    box = _mesh(tmp_path / "box.obj", (1.0, 0.5, 0.25))
    out = tmp_path / "lib"
    out.mkdir()
    (out / "splits.csv").write_text('"twin, wing",train\n', encoding="utf-8")
    for _ in range(2):
        assert import_models([box], ImportOptions(out=out, points=200), progress=False).ok
    assert read_splits(out / "splits.csv") == {"twin, wing": "train", "box": "test",
                                               "box_2": "test"}


@pytest.mark.parametrize("bad", [" cube", os.fsdecode(b"caf\xff")])
def test_render_refuses_a_bad_folder_name_before_any_work(tmp_path, two_models, capsys,
                                                          bad) -> None:
    """Before: ' cube' rendered (a dataset nothing could read); 'caf\\xff' failed that model
    after the others and left dataset.json, failures.json and more behind."""
    library = _library(tmp_path, two_models, {"a": "good", "b": bad}, [("good", "train")])
    (library / "splits.csv").unlink()  # the folder itself, not a row, brings the name
    out = tmp_path / "data"
    assert main(["dataset", "render", "--models", str(library), "--out", str(out),
                 "--images-per-model", "1", "--resolution", "16", "--spp", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"sq-mitsuba dataset: error: {library}: model name {bad!r} is not a "
                          "plain folder name (") and "\n" not in err
    assert not out.exists()


def test_import_refuses_one_file_given_twice(tmp_path, capsys, monkeypatch) -> None:
    """`box.obj box.obj ./box.obj` made three models of one spacecraft (possibly in both
    splits once one is moved to train)."""
    box = _mesh(tmp_path / "box.obj", (1.0, 0.5, 0.25))
    other = _mesh(tmp_path / "other.obj", (0.4, 1.0, 0.6))
    (tmp_path / "link.obj").symlink_to(box)
    os.link(box, tmp_path / "hard.obj")
    out = tmp_path / "lib"
    for second in ("box.obj", "./box.obj", "link.obj", "hard.obj"):
        with pytest.raises(ValueError, match=r"^meshes: .*given twice; give each mesh once"):
            import_models([box, other, Path(tmp_path / second)],
                          ImportOptions(out=out, points=200), progress=False)
        assert not out.exists()
    capsys.readouterr()
    monkeypatch.chdir(tmp_path)
    assert main(["models", "import", "box.obj", "other.obj", "link.obj", "--out", "lib",
                 "--points", "200"]) == 2
    assert capsys.readouterr().err.strip() == (
        "sq-mitsuba models: error: meshes: box.obj and link.obj are the same file, given "
        "twice; give each mesh once (each file becomes its own model)")
    assert not out.exists()


def test_a_row_in_another_unicode_normalisation_is_named_as_such(tmp_path, two_models) -> None:
    """'café' as a folder (NFD, as macOS writes it) and 'café' as its row (NFC) look the
    same; the refusal said only "no row for 1 model folder(s) (café)"."""
    from sq_mitsuba.data.spe3r import RenderOptions, render_dataset

    nfd, nfc = unicodedata.normalize("NFD", "café"), unicodedata.normalize("NFC", "café")
    assert nfd != nfc
    library = _library(tmp_path, two_models, {"a": nfd}, [(nfc, "train")])
    out = tmp_path / "data"
    with pytest.raises(DatasetError, match=re.escape(
            f"no row for 1 model folder(s) ({nfd}), so their split is not known (folder "
            r"'cafe\u0301' and row 'caf\xe9' look alike but differ in Unicode normalisation")):
        render_dataset(library, out, RenderOptions(images_per_model=1, resolution=16, spp=1),
                       progress=False)
    assert not out.exists()
