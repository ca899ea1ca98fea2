"""Names and sizes that come with downloaded data are checked where they are read.

A library's or dataset's ``splits.csv`` and ``dataset.json`` name models, and each name
becomes a folder path: only one plain path component is accepted. A ``samples.npz`` member
is sized from its ``.npy`` header before it is read (a small archive can expand to
gigabytes). ``train`` deletes only the tool's own temporary files. All without rendering.
"""

from __future__ import annotations

import io
import json
import os
import re
import zipfile
from pathlib import Path

import numpy as np
import pytest

from sq_mitsuba.data.mesh_io import read_npz, read_tagged_obj
from sq_mitsuba.data.spe3r.layout import (
    MANIFEST_FORMAT,
    DatasetError,
    load_model,
    read_manifest,
    read_samples,
    read_splits,
)
from sq_mitsuba.data.spe3r.writer import find_models
from sq_mitsuba.training.run.folder import remove_stale_temporaries

#: Model names that would lead a reader or writer outside its folder, or onto a hidden entry
#: of the tool's own, with what the refusal says of them.
BAD_NAMES = {
    "/abs/path/to/some_model": "an absolute path",
    "../x": "contains a path separator",
    "..": "not a folder name",
    ".": "not a folder name",
    "a/b": "contains a path separator",
    "a\\b": "contains a path separator",
    ".failures": "starts with '.'",
    "a\x00b": "contains a control character",
    "a\x1b[31mb": "contains a control character",
}


@pytest.mark.parametrize("name", list(BAD_NAMES))
def test_splits_refuse_a_model_name_that_is_not_one_folder_name(tmp_path, name):
    """A row ``/abs/path,train`` made ``dataset render`` delete that folder and write into it;
    ``../x,train`` made render, eval and fit-parts reach outside their folders."""
    path = tmp_path / "splits.csv"
    path.write_text(f"good,train\n{name},test\n", encoding="utf-8")
    with pytest.raises(DatasetError) as caught:
        read_splits(path)
    message = str(caught.value)
    assert message == (f"{path}:2: model name {name!r} is not a plain folder name "
                       f"({BAD_NAMES[name]}); refused")
    assert "\n" not in message


def test_an_empty_model_name_is_refused(tmp_path):
    from sq_mitsuba.data.spe3r.layout import model_name_problem

    path = tmp_path / "splits.csv"
    path.write_text(" ,train\n", encoding="utf-8")
    with pytest.raises(DatasetError, match=re.escape(f"{path}:1: model name '' is not a plain "
                                                     "folder name (empty); refused")):
        read_splits(path)
    assert model_name_problem("sc000_twin-wing.v2") is None  # dots and dashes inside are fine


@pytest.mark.parametrize("name", ["../outside_model", "/tmp/victim", ".progress"])
def test_a_manifest_listing_a_model_name_that_is_not_one_folder_name_is_refused(tmp_path,
                                                                                  name):
    manifest = {"format": MANIFEST_FORMAT, "settings": {}, "images_per_model": 1,
                "models": {"good": {}, name: {"split": "train"}}}
    (tmp_path / "dataset.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match=re.escape(
            f"{tmp_path / 'dataset.json'}: models: model name {name!r} is not a plain folder "
            "name (")):
        read_manifest(tmp_path)


def _library_model(root: Path, name: str) -> Path:
    """A model folder with a mesh (no points: find_models needs the mesh alone)."""
    folder = root / name / "models"
    folder.mkdir(parents=True)
    (folder / "model_normalized.obj").write_text(TETRAHEDRON)
    return folder.parent


def test_a_library_model_folder_of_a_bad_name_or_through_a_link_is_refused(tmp_path):
    """find_models names folders as well as rows: a folder whose name holds a control
    character, and a model folder that is a link to another place, are refused."""
    library = tmp_path / "library"
    _library_model(library, "good")
    odd = _library_model(library, "bad\x1bname")
    with pytest.raises(DatasetError, match="model name 'bad\\\\x1bname' is not a plain folder "
                                           r"name \(contains a control character\)"):
        find_models(library)
    odd.rename(tmp_path / "elsewhere")
    assert find_models(library) == ["good"]
    (library / "linked").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(DatasetError, match=re.escape(
            f"{library / 'linked'}: a symbolic link (to {tmp_path / 'elsewhere'}); a model's "
            f"files are read and written inside {library} only, not through links: refused")):
        find_models(library)


# ------------------------------------------------------------------------ samples.npz sizes


TETRAHEDRON = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def _npz_claiming(path: Path, key: str, shape: tuple[int, ...], dtype: str,
                  **arrays: np.ndarray) -> None:
    """An archive of ``arrays`` plus a member ``key`` whose ``.npy`` header claims ``shape``
    while only 64 bytes of data follow: read in full it fails as truncated, so a refusal that
    names the size shows that the header alone was read."""
    np.savez(path, **arrays)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {
        "descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False,
        "shape": shape})
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr(f"{key}.npy", header.getvalue() + bytes(64))


def _points(count: int = 10) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {"surface_points": rng.normal(size=(count, 3)),
            "uniform_points": rng.normal(size=(count, 3)),
            "uniform_inside": np.zeros(count, bool),
            "near_points": rng.normal(size=(count, 3)),
            "near_inside": np.zeros(count, bool)}


@pytest.mark.parametrize("key, shape", [("near_points", (20_000_000, 3)),
                                        ("uniform_inside", (2**40,)),
                                        ("surface_normals", (10**9, 3))])
def test_a_samples_member_beyond_the_bound_is_refused_from_its_header(tmp_path, key, shape):
    """A 1 MB samples.npz held a member that expanded to gigabytes, read in full before its
    shape was checked."""
    path = tmp_path / "samples.npz"
    arrays = {k: v for k, v in _points().items() if k != key}
    _npz_claiming(path, key, shape, "<f8" if key.endswith(("points", "normals")) else "|b1",
                  **arrays)
    count = int(np.prod(shape))
    bound = 10_000_000 if key == "uniform_inside" else 30_000_000
    with pytest.raises(DatasetError, match=re.escape(
            f"{path}: {key}: {count:,} values (shape {shape}), more than the {bound:,} this "
            "tool reads; refused before reading it") + "$"):
        read_samples(path, optional=("surface_normals",))


def test_face_material_longer_than_the_mesh_is_refused_from_its_header(tmp_path):
    """face_material holds one tag per face: a member claiming more is not read (by the
    model loader, the tagged-mesh reader and the library check's reader alike)."""
    model = tmp_path / "model"
    (model / "models").mkdir(parents=True)
    (model / "models" / "model_normalized.obj").write_text(TETRAHEDRON)
    samples = model / "models" / "samples.npz"
    _npz_claiming(samples, "face_material", (2**31,), "<i2", **_points())
    with pytest.raises(DatasetError, match=re.escape(
            f"{samples}: face_material: 2,147,483,648 values (shape (2147483648,)), more than "
            "the 4 this tool reads; refused before reading it") + "$"):
        load_model(model)
    with pytest.raises(ValueError, match="more than the 4 this tool reads"):
        read_tagged_obj(model / "models" / "model_normalized.obj")
    with pytest.raises(ValueError, match="more than the 30,000,000 this tool reads"):
        read_npz(samples, ["face_material"])
    # An archive within the bounds reads as before.
    np.savez(samples, face_material=np.zeros(4, np.int16), **_points())
    assert load_model(model)[2] is not None
    assert len(read_samples(samples)["near_points"]) == 10


# ------------------------------------------------------------------------ train's clean-up


def test_train_deletes_only_the_tools_own_temporary_files(tmp_path):
    """``train`` deleted every hidden file with ".tmp" in its name at the top of --out; the
    tool's temporary files are ``.<stem>.<8 random>.tmp<suffix>``
    (sq_mitsuba.outputs.TEMPORARY_NAME), and only those go."""
    mine = [tmp_path / ".notes.tmp.txt", tmp_path / ".cache.tmpdir", tmp_path / ".x.tmp"]
    ours = [tmp_path / ".last.abcd1234.tmp.pt", tmp_path / ".log.k2j4h5g6.tmp.csv"]
    for path in mine + ours:
        path.write_text("x")
    os.symlink(tmp_path / ".notes.tmp.txt", tmp_path / ".link.abcdefgh.tmp.pt")
    assert remove_stale_temporaries(tmp_path) == sorted(ours)
    assert all(path.is_file() for path in mine)
    assert (tmp_path / ".link.abcdefgh.tmp.pt").is_symlink()


def test_the_readers_beyond_read_samples_size_an_array_from_its_header(tmp_path):
    """The evaluation's volume points and the part targets read samples.npz and
    part_targets.npz themselves: their arrays too are sized from the header first."""
    from sq_mitsuba.evaluation.scoring import volume_points
    from sq_mitsuba.training.part_targets import PartTargetError, load_part_targets

    model = tmp_path / "data" / "m"
    (model / "models").mkdir(parents=True)
    arrays = {k: v for k, v in _points().items() if k != "uniform_points"}
    _npz_claiming(model / "models" / "samples.npz", "uniform_points", (20_000_000, 3), "<f8",
                  **arrays)
    with pytest.raises(DatasetError, match="uniform_points: 60,000,000 values"):
        volume_points(model, 100)
    _npz_claiming(model / "models" / "part_targets.npz", "raw", (10**6, 16), "<f8")
    with pytest.raises(PartTargetError, match=r"raw: 16,000,000 values .* refused before"):
        load_part_targets(tmp_path / "data", ["m"], 5)
