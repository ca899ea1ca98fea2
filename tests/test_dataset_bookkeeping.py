"""Dataset bookkeeping: the manifest, refusing other settings, overwrite, growth, shards,
failures, splits and bounded options.

Datasets here are tiny (2 models x 4 images, 32 px, 1 spp, a lighter mask pass) and built once
per session where they can be shared; every comparison is against an unsharded, uninterrupted
render of the same settings.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from output_checks import error_line

from sq_mitsuba.cli import main
from sq_mitsuba.config import apply_overrides, config_hash
from sq_mitsuba.data.library import generate_model
from sq_mitsuba.data.spacecraft import catalogue
from sq_mitsuba.data.spe3r import (
    DatasetError,
    MissingModelWarning,
    RenderOptions,
    Spe3rDataset,
    check_dataset,
    is_validation,
    render_dataset,
    render_options,
)
from sq_mitsuba.data.spe3r import writer as spe3r_writer
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.render.scene_config import SceneConfig

IMAGES = 4
#: A lighter mask pass (4 samples per pixel at 256 px: 256 at 32 px) keeps renders fast.
SCENE_SET = ["mask.spp=4"]
SCENE = apply_overrides(SceneConfig.load(), SCENE_SET)
TINY = {"images_per_model": IMAGES, "seed": 11, "resolution": 32, "spp": 1, "exr": True,
        "scene": SCENE}
CLI_TINY = ["--images-per-model", str(IMAGES), "--seed", "11", "--resolution", "32", "--spp",
            "1", "--exr", "--quiet", *[a for s in SCENE_SET for a in ("--set", s)]]


@pytest.fixture(scope="session")
def library(tmp_path_factory) -> Path:
    """Two generated spacecraft (small point sets), one train and one test."""
    root = tmp_path_factory.mktemp("bookkeeping_models")
    entries = catalogue(2, 9)
    for entry in entries:
        generate_model(entry, root, points=2000)
    (root / "splits.csv").write_text(f"{entries[0].name},train\n{entries[1].name},test\n")
    return root


@pytest.fixture(scope="session")
def reference(library, tmp_path_factory) -> Path:
    """The unsharded, uninterrupted render every other run is compared with."""
    out = tmp_path_factory.mktemp("bookkeeping_reference") / "data"
    summary = render_dataset(library, out, RenderOptions(**TINY), progress=False)
    assert summary.complete and not summary.failures and summary.rendered == 2 * IMAGES
    return out


def tree(root: Path) -> dict[str, bytes | None]:
    """Every file (bytes) and folder (None) under ``root``, by relative path."""
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(root.rglob("*"))}


def digests(root: Path) -> dict[str, str | None]:
    return {name: (hashlib.sha256(data).hexdigest() if data is not None else None)
            for name, data in tree(root).items()}


def render_cli(library: Path, out: Path, *extra: str) -> int:
    return main(["dataset", "render", "--models", str(library), "--out", str(out), *CLI_TINY,
                 *extra])


# ------------------------------------------------------------------------ manifest


def test_manifest_records_how_the_dataset_was_made(reference, library):
    manifest = json.loads((reference / "dataset.json").read_text())
    camera = Camera.default(32)
    assert manifest["format"] == "sq-mitsuba-dataset/1"
    assert manifest["settings"] == {
        "seed": 11, "resolution": 32, "spp": 1, "exr": True,
        "camera": json.loads(json.dumps(camera.to_speed_dict())),
        "scene_hash": config_hash(SCENE), "pass_frames": 1}
    assert manifest["tool"]["name"] == "sq-mitsuba" and manifest["tool"]["version"]
    assert manifest["images_per_model"] == IMAGES and manifest["state"] == "complete"
    assert SceneConfig.load() != SCENE and manifest["scene"]["mask"]["spp"] == 4
    splits = dict(line.split(",") for line in (library / "splits.csv").read_text().split())
    assert {m: e["split"] for m, e in manifest["models"].items()} == splits
    for model, entry in manifest["models"].items():
        labels = (reference / model / "labels.json").read_bytes()
        assert entry["images"] == len(json.loads(labels)) == IMAGES
        assert entry["labels_sha256"] == hashlib.sha256(labels).hexdigest()
    assert json.loads((reference / "camera.json").read_text()) == camera.to_speed_dict()
    assert not (reference / "failures.json").exists()
    assert not (reference / ".failures").exists()


def test_a_manifest_from_before_passes_resumes_as_independent_images(reference, library,
                                                                     tmp_path):
    """Datasets rendered before ``pass_frames`` existed recorded no such setting: they were
    independent images, and resuming them with the default renders nothing new."""
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    manifest = json.loads((out / "dataset.json").read_text())
    del manifest["settings"]["pass_frames"]
    (out / "dataset.json").write_text(json.dumps(manifest))
    assert render_cli(library, out) == 0
    assert render_cli(library, out, "--pass-frames", "2") == 2  # another dataset


def test_a_pass_dataset_of_an_earlier_framing_is_not_resumed(library, tmp_path, capsys):
    """A pass dataset records how its passes were placed; one placed by an earlier version (a
    turned frame could cut the target at the image's edge) is refused, not grown with frames
    placed another way."""
    out = tmp_path / "passes"
    assert render_cli(library, out, "--pass-frames", "2") == 0
    manifest = json.loads((out / "dataset.json").read_text())
    assert manifest["settings"]["pass_frames"] == 2 and manifest["settings"]["pass_framing"] == 2
    assert render_cli(library, out, "--pass-frames", "2") == 0  # the same framing resumes
    del manifest["settings"]["pass_framing"]
    (out / "dataset.json").write_text(json.dumps(manifest))
    before = tree(out)
    capsys.readouterr()
    assert render_cli(library, out, "--pass-frames", "2") == 2
    error = capsys.readouterr().err
    assert "passes placed by an earlier framing (1; this run: 2" in error
    assert error.count("\n") == 1 and tree(out) == before


def test_passes_that_do_not_divide_the_images_are_refused_before_any_work(library, tmp_path,
                                                                          capsys):
    """3 images in passes of 2 would end in a pass of 1, which study passes then refuses."""
    out = tmp_path / "short"
    assert render_cli(library, out, "--images-per-model", "3", "--pass-frames", "2") == 2
    assert capsys.readouterr().err.strip().endswith(
        "pass_frames (--pass-frames) 2 does not divide images_per_model (--images-per-model) "
        "3: the last pass would be short; give a multiple, e.g. 2")
    assert not out.exists()


@pytest.mark.parametrize("extra, named", [
    (["--resolution", "40"], "resolution 32 (this run: 40)"),
    (["--seed", "12"], "seed 11 (this run: 12)"),
    (["--spp", "2"], "spp 1 (this run: 2)"),
    (["--no-exr"], "exr true (this run: false)"),
    (["--set", "sun.irradiance=1000"], "sun.irradiance 1361.0, now 1000.0"),
    (["--camera", "CAMERA"], "camera 32 x 32 px"),
    (["--images-per-model", "2"], "grows but does not shrink"),
])

def test_other_settings_stop_before_touching_any_file(reference, library, tmp_path, capsys,
                                                      extra, named):
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    before = digests(out)
    if "CAMERA" in extra:
        camera = Camera.from_fov(50.0, 32, 32)
        (tmp_path / "camera.json").write_text(json.dumps(camera.to_speed_dict()))
        extra = [tmp_path / "camera.json" if a == "CAMERA" else a for a in extra]
    code = render_cli(library, out, *map(str, extra))
    err = capsys.readouterr().err
    assert code == 2 and named in err and "dataset.json" in err
    assert len(err.strip().splitlines()) == 1
    assert digests(out) == before


@pytest.mark.parametrize("manifest", ["none", "another tool's"])
def test_a_folder_without_a_manifest_of_this_tool_is_not_rendered_into_nor_cleared(
        reference, library, tmp_path, capsys, manifest):
    """A folder that is not empty and holds no valid dataset.json is refused, with or
    without --overwrite (which deleted every child folder holding images/, masks/, exr/,
    labels.json or .progress): the message says what is there and suggests another --out,
    never --overwrite."""
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    if manifest == "none":
        (out / "dataset.json").unlink()
    else:
        (out / "dataset.json").write_text(json.dumps({"format": "other-tool/3", "models": {}}))
    (out / "photos" / "images").mkdir(parents=True)
    (out / "photos" / "images" / "holiday.png").write_bytes(b"not ours")
    (out / "photos" / "labels.json").write_text("[]")
    before = digests(out)
    for extra in ((), ("--overwrite",)):
        assert render_cli(library, out, *extra) == 2
        line = capsys.readouterr().err.strip()
        assert "\n" not in line and "--overwrite to" not in line, line
        assert "another --out" in line or (not extra and manifest != "none"), line
        if manifest == "none":
            first = sorted(p.parent.name for p in out.glob("*/models"))[0]
            assert line.endswith(
                f"{out}: not empty (camera.json, photos/, {first}/, ...) and holds no "
                "dataset.json of this tool, so nothing there is known to be its own; nothing "
                "was changed: choose another --out (a new or empty folder)"), line
        else:
            assert "not a dataset manifest of this version" in line, line
        assert digests(out) == before


def test_overwrite_starts_clean_and_keeps_other_files(reference, library, tmp_path):
    """--overwrite deletes the tool's files and the models its manifest lists, nothing else:
    not a folder of images the manifest does not list, not a user's hidden file whose name
    holds ".tmp" (only the tool's temporary files, sq_mitsuba.outputs.TEMPORARY_NAME)."""
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    (out / "notes.txt").write_text("mine")
    (out / ".notes.tmp.txt").write_text("mine too")
    (out / ".camera.abcd1234.tmp.json").write_text("a killed write's")
    (out / "preview.png").write_bytes(b"old preview")
    (out / "stray_model" / "images").mkdir(parents=True)
    (out / "other" / "models").mkdir(parents=True)
    assert render_cli(library, out, "--overwrite", "--images-per-model", "1",
                      "--seed", "12") == 0
    manifest = json.loads((out / "dataset.json").read_text())
    assert manifest["settings"]["seed"] == 12 and manifest["images_per_model"] == 1
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / ".notes.tmp.txt").read_text() == "mine too"
    assert not (out / ".camera.abcd1234.tmp.json").exists()
    assert not (out / "preview.png").exists()
    assert (out / "stray_model" / "images").is_dir() and (out / "other" / "models").is_dir()
    for model in manifest["models"]:
        assert sorted(p.name for p in (out / model / "images").iterdir()) == ["000000.png"]
        assert len(json.loads((out / model / "labels.json").read_text())) == 1


def test_overwrite_checks_everything_it_deletes_before_deleting_anything(
        reference, library, tmp_path, capsys):
    """A listed model folder that is a link (and a folder named as one of the dataset's
    files) made --overwrite stop half-way, dataset.json, camera.json and splits.csv deleted,
    with "Cannot call rmtree on a symbolic link"; now it is refused whole, before any
    deletion, and the link's target is untouched."""
    out = Path(shutil.copytree(reference, tmp_path / "data"))
    model = sorted(json.loads((out / "dataset.json").read_text())["models"])[-1]
    victim = tmp_path / "victim"
    (out / model).rename(victim)
    (out / model).symlink_to(victim)
    before, victim_before = digests(out), digests(victim)
    assert render_cli(library, out, "--overwrite", "--seed", "12") == 2
    line = capsys.readouterr().err.strip()
    assert line.endswith(f"{out / model}: a symbolic link (to {victim}); a model's files are "
                         f"read and written inside {out} only, not through links: refused")
    assert digests(out) == before and digests(victim) == victim_before
    (out / model).unlink()
    victim.rename(out / model)
    (out / "preview.png").mkdir()  # a folder where the tool writes a file: not its own
    before = digests(out)
    assert render_cli(library, out, "--overwrite", "--seed", "12") == 2
    assert capsys.readouterr().err.strip().endswith(
        f"{out / 'preview.png'}: not a file (a folder) where this tool writes a file, so not "
        "the tool's to delete; nothing was changed (--overwrite): move it away, or choose "
        "another --out")
    assert digests(out) == before


@pytest.mark.parametrize("where", ["dataset", "library"])
def test_a_model_folder_that_is_a_link_is_refused_before_any_work(reference, library,
                                                                  tmp_path, capsys, where):
    """Through a linked model folder `dataset render` wrote images and rewrote labels.json
    in another place (in the dataset), or read a model from one (in the library)."""
    out = Path(shutil.copytree(reference, tmp_path / "data"))
    models = Path(shutil.copytree(library, tmp_path / "models"))
    model = sorted(json.loads((out / "dataset.json").read_text())["models"])[-1]
    root = out if where == "dataset" else models
    victim = tmp_path / "victim"
    (root / model).rename(victim)
    (root / model).symlink_to(victim)
    if where == "dataset":  # an image to render again: written through the link before
        (victim / "images" / "000000.png").unlink()
    before, victim_before = digests(out), digests(victim)
    assert render_cli(models, out) == 2
    assert capsys.readouterr().err.strip().endswith(
        f"{root / model}: a symbolic link (to {victim}); a model's files are read and written "
        f"inside {root} only, not through links: refused")
    assert digests(out) == before and digests(victim) == victim_before


def test_a_folder_the_manifest_does_not_list_is_not_rendered_into(reference, library,
                                                                  tmp_path, capsys):
    """A library model whose folder is in the output but not in its dataset.json: the folder
    is not the tool's (nothing the tool did not create is written into)."""
    out = Path(shutil.copytree(reference, tmp_path / "data"))
    manifest = json.loads((out / "dataset.json").read_text())
    model = sorted(manifest["models"])[-1]
    del manifest["models"][model]
    (out / "dataset.json").write_text(json.dumps(manifest))
    (out / "splits.csv").write_text("".join(
        line + "\n" for line in (out / "splits.csv").read_text().splitlines()
        if not line.startswith(f"{model},")))
    before = digests(out)
    assert render_cli(library, out) == 2
    assert capsys.readouterr().err.strip().endswith(
        f"{out / model}: exists, but dataset.json does not list the model, so the folder is "
        "not this tool's; nothing was changed: move it away, or choose another --out")
    assert digests(out) == before


@pytest.mark.parametrize("row", ["absolute", "../victim"])
def test_a_model_name_reaching_outside_the_library_is_refused_before_any_work(
        library, tmp_path, capsys, row):
    """A library's splits.csv row ``/abs/path,train`` made `dataset render` delete that folder
    (rmtree of .failures/<model>, an absolute path) and write images into it; ``../x,train``
    wrote into a sibling folder."""
    models = Path(shutil.copytree(library, tmp_path / "models"))
    victim = tmp_path / "victim"
    shutil.copytree(next(models.glob("*/models")), victim / "models")
    (victim / "mine.txt").write_text("precious")
    name = str(victim) if row == "absolute" else row
    with open(models / "splits.csv", "a") as splits:
        splits.write(f"{name},train\n")
    victim_before = digests(victim)
    out = tmp_path / "data"
    assert render_cli(models, out) == 2
    line = capsys.readouterr().err.strip()
    assert line.endswith(f"{models / 'splits.csv'}:3: model name {name!r} is not a plain "
                         "folder name (" + ("an absolute path" if row == "absolute" else
                                            "contains a path separator") + "); refused"), line
    assert digests(victim) == victim_before and not out.exists()


def test_a_dataset_whose_splits_name_a_model_outside_it_is_refused_by_its_readers(
        reference, tmp_path):
    """``../x,train`` in a dataset's splits.csv made eval read a model outside --data."""
    out = Path(shutil.copytree(reference, tmp_path / "data"))
    with open(out / "splits.csv", "a") as splits:
        splits.write("../outside_model,train\n")
    message = (f"{out / 'splits.csv'}:3: model name '../outside_model' is not a plain folder "
               "name (contains a path separator); refused")
    with pytest.raises(DatasetError, match=re.escape(message) + "$"):
        Spe3rDataset(out)
    assert message in check_dataset(out, per_model=0, progress=False).problems


# ------------------------------------------------------------------------ growth


def test_growing_gives_exactly_the_larger_run(reference, library, tmp_path, monkeypatch):
    out = tmp_path / "data"
    small = RenderOptions(**{**TINY, "images_per_model": 2})
    assert render_dataset(library, out, small, progress=False).complete
    first_camera = (out / "camera.json").read_bytes()
    seen = []
    real_render_image = spe3r_writer.render_image

    def watching(scene, vertices, options, model, index, model_out):
        # What the folder says when the first new image is rendered.
        if not seen:
            seen.append(json.loads((out / "dataset.json").read_text()))
        real_render_image(scene, vertices, options, model, index, model_out)

    monkeypatch.setattr(spe3r_writer, "render_image", watching)
    summary = render_dataset(library, out, RenderOptions(**TINY), progress=False)
    assert summary.complete and (summary.rendered, summary.skipped) == (4, 4)
    assert seen[0]["images_per_model"] == IMAGES and seen[0]["state"] == "rendering"
    assert {e["images"] for e in seen[0]["models"].values()} == {2}
    assert (out / "camera.json").read_bytes() == first_camera
    assert tree(out) == tree(reference)


# ------------------------------------------------------------------------ shards


def test_shards_in_any_order_equal_one_unsharded_run(reference, library, tmp_path):
    """3 shards of 8 images: blocks [0, 2), [2, 5), [5, 8), so both models are split
    between two shards; finished last to first."""
    out = tmp_path / "data"
    for shard, last in (("2/3", False), ("0/3", False), ("1/3", True)):
        summary = render_dataset(library, out, RenderOptions(**TINY, shard=shard),
                                 progress=False)
        assert summary.complete is last and not summary.failures
        assert (out / "splits.csv").exists() is last
    assert tree(out) == tree(reference)
    # A shard run again later finds its work done and changes nothing.
    summary = render_dataset(library, out, RenderOptions(**TINY, shard="1/3"), progress=False)
    assert summary.rendered == 0 and summary.complete
    assert tree(out) == tree(reference)


@pytest.mark.slow
def test_two_shards_at_once_into_one_folder(reference, library, tmp_path):
    """Two processes at the same time, as a job array would run them."""
    out = tmp_path / "data"
    command = [sys.executable, "-m", "sq_mitsuba", "dataset", "render", "--models",
               str(library), "--out", str(out), *CLI_TINY]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    processes = [subprocess.Popen([*command, "--shard", f"{i}/2"], env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
                 for i in range(2)]
    for process in processes:
        _, err = process.communicate(timeout=300)
        assert process.returncode == 0, err.decode()
    assert tree(out) == tree(reference)


def test_shard_work_is_a_partition():
    models = ["a", "b", "c"]
    for shards in (1, 2, 5, 7, 40):
        pairs = [(m, i) for s in range(shards)
                 for m, r in spe3r_writer._shard_work(models, 10, f"{s}/{shards}").items()
                 for i in r]
        assert sorted(pairs) == [(m, i) for m in models for i in range(10)]
        assert len(pairs) == len(set(pairs))


# ------------------------------------------------------------------------ kills and strays


def test_rerun_after_a_kill_cleans_stray_temporary_files(reference, library, tmp_path):
    """The state a kill leaves while image 1 of a model is being written: its image written,
    its EXR a 0-byte temporary file, no label; image 0 finished (its label in .progress)."""
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    model = json.loads((out / "dataset.json").read_text())["models"].popitem()[0]
    labels = json.loads((out / model / "labels.json").read_text())
    (out / model / "labels.json").unlink()
    (out / model / ".progress").mkdir()
    (out / model / ".progress" / "000000.json").write_text(json.dumps(labels[0]))
    for index in (2, 3):
        for folder, suffix in (("images", "png"), ("masks", "png"), ("exr", "exr")):
            (out / model / folder / f"00000{index}.{suffix}").unlink()
    (out / model / "exr" / "000001.exr").unlink()
    (out / model / "exr" / ".000001.k2j4x9.tmp.exr").write_bytes(b"")
    (out / model / "masks" / ".000001.q8w1e3.tmp.png").write_bytes(b"\x89PNG")
    report = check_dataset(out, per_model=1, progress=False)
    problems = "\n".join(report.problems)
    assert f"{model}/exr/.000001.k2j4x9.tmp.exr: stray temporary file" in problems
    assert f"{model}/masks/.000001.q8w1e3.tmp.png: stray temporary file" in problems
    assert f"{model}/.progress/: unfinished model" in problems
    summary = render_dataset(library, out, RenderOptions(**TINY), progress=False)
    assert summary.rendered == 3 and summary.complete
    assert tree(out) == tree(reference)


def test_a_rerun_renders_again_the_images_of_a_finished_model_deleted_or_cut_short(
        reference, library, tmp_path):
    """A finished model whose image was deleted and whose mask was cut short since (by hand,
    a full disk elsewhere): the rerun renders those two images again, not "already there",
    and the dataset is the reference again, byte for byte."""
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    model = sorted(json.loads((out / "dataset.json").read_text())["models"])[0]
    (out / model / "images" / "000001.png").unlink()
    cut = out / model / "masks" / "000002.png"
    cut.write_bytes(cut.read_bytes()[:-20])  # its end lost
    summary = render_dataset(library, out, RenderOptions(**TINY), progress=False)
    assert summary.rendered == 2 and summary.complete
    assert tree(out) == tree(reference)



def test_a_model_of_the_same_name_from_another_library_is_refused_before_any_work(
        reference, library, tmp_path, capsys):
    """Rendering another library into a finished dataset adds its models; one whose name the
    dataset holds but whose mesh differs is refused (its images are of the other model),
    before any file changes. A card that differs beside the same mesh is the same model."""
    out, other = tmp_path / "data", tmp_path / "other"
    shutil.copytree(reference, out)
    shutil.copytree(library, other)
    model = sorted(json.loads((out / "dataset.json").read_text())["models"])[0]
    card = other / model / "models" / "model_card.json"
    card.write_text(card.read_text() + "\n")
    before = tree(out)
    assert render_cli(other, out) == 0  # the card alone: nothing to render
    assert tree(out) == before
    mesh = other / model / "models" / "model_normalized.obj"
    mesh.write_text(mesh.read_text() + "# generated again\n")
    capsys.readouterr()
    assert render_cli(other, out) == 2
    error = capsys.readouterr().err
    assert error.strip().endswith(f"{out / model / 'models' / 'model_normalized.obj'}: differs "
                                  f"from {mesh}, the model the dataset's images of {model} were "
                                  "rendered from; render into another folder, or use --overwrite")
    assert tree(out) == before


# ------------------------------------------------------------------------ failures, splits


def test_failed_models_are_left_out_of_the_splits(reference, library, tmp_path):
    """A model that fails while the others render (here its labels.json damaged since: a
    broken library model is refused before any work instead) is listed in failures.json, left
    out of splits.csv and recorded with no images; repaired, running again renders it."""
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    failed = sorted(json.loads((out / "dataset.json").read_text())["models"])[1]
    (out / failed / "labels.json").write_text("[{")
    summary = render_dataset(library, out, RenderOptions(**TINY), progress=False)
    assert summary.complete and set(summary.failures) == {failed}
    failures = json.loads((out / "failures.json").read_text())
    assert set(failures) == {failed} and "labels.json: not valid JSON" in failures[failed]
    assert failed not in (out / "splits.csv").read_text()
    assert (out / "splits.csv").read_text() in (reference / "splits.csv").read_text()
    manifest = json.loads((out / "dataset.json").read_text())
    assert manifest["models"][failed]["images"] == 0
    report = check_dataset(out, per_model=1, progress=False)
    assert report.ok, report.summary()
    assert any(f"{failed}: failed" in note for note in report.notes)
    # Repaired as the failure says (its folder deleted): rendered again, the same bytes.
    shutil.rmtree(out / failed)
    summary = render_dataset(library, out, RenderOptions(**TINY), progress=False)
    assert not summary.failures and not (out / "failures.json").exists()
    assert tree(out) == tree(reference)


def _delete_mesh(model: Path) -> None:
    (model / "models" / "model_normalized.obj").unlink()


def _text_samples(model: Path) -> None:
    (model / "models" / "samples.npz").write_text("not an archive\n")


def _nan_point(model: Path) -> None:
    path = model / "models" / "samples.npz"
    with np.load(path) as samples:
        arrays = {key: samples[key] for key in samples.files}
    arrays["surface_points"] = arrays["surface_points"].copy()
    arrays["surface_points"][0, 0] = np.nan
    np.savez(path, **arrays)


def _delete_folder(model: Path) -> None:
    shutil.rmtree(model)  # its row in splits.csv stays: listed but missing


#: Damage to one library model -> what the one-line refusal says after the model file's path.
BROKEN_MODELS = {"mesh deleted": (_delete_mesh, "model_normalized.obj: missing"),
                 "samples.npz a text file": (_text_samples, "samples.npz: corrupt or "
                                             "truncated: not a valid .npz file"),
                 "NaN point": (_nan_point, "samples.npz: surface_points: 1 of 2000 points "
                               "hold NaN or infinite values"),
                 "listed folder missing": (_delete_folder, "model_normalized.obj: missing")}


@pytest.mark.parametrize("case", BROKEN_MODELS)
def test_a_broken_library_model_is_refused_before_any_work(library, tmp_path, capsys, case):
    """A model whose files cannot be read stops the render before any file is written, in one
    line naming the file (exit 2; it was a failed model after the others' images, and a
    partial dataset). A samples.npz that is no archive is not met with numpy's advice to load
    it "unsafely" with allow_pickle."""
    damage, said = BROKEN_MODELS[case]
    models = tmp_path / "models"
    shutil.copytree(library, models)
    model = sorted(p.name for p in models.iterdir() if p.is_dir())[1]
    damage(models / model)
    out = tmp_path / "data"
    capsys.readouterr()
    assert render_cli(models, out) == 2
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and f"{models / model / 'models'}/" in error, error
    assert error.endswith(said) and "allow_pickle" not in error, error
    assert not out.exists()


def test_reader_skips_a_listed_model_that_is_missing(reference, tmp_path):
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    train_model, test_model = sorted(json.loads((out / "dataset.json").read_text())["models"])
    shutil.rmtree(out / test_model)
    with pytest.warns(MissingModelWarning, match=test_model):
        test = Spe3rDataset(out, "test", image_size=16, num_surface=10, num_occupancy=10)
    assert len(test) == 0 and test.skipped == [test_model]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        train = Spe3rDataset(out, "train", image_size=16, num_surface=10, num_occupancy=10)
    assert train.models == [train_model] and len(train) == IMAGES


@pytest.fixture(scope="session")
def forty(library, tmp_path_factory) -> Path:
    """The train model alone, 40 images (32 px, 1 spp)."""
    models = tmp_path_factory.mktemp("forty_models")
    model = (library / "splits.csv").read_text().split(",")[0]
    shutil.copytree(library / model, models / model)
    (models / "splits.csv").write_text(f"{model},train\n")
    out = tmp_path_factory.mktemp("forty") / "data"
    options = RenderOptions(**{**TINY, "images_per_model": 40, "exr": False})
    assert render_dataset(models, out, options, progress=False).complete
    return out


def test_every_size_of_dataset_has_a_validation_split(forty):
    kwargs = {"image_size": 16, "num_surface": 10, "num_occupancy": 10}
    train, val = Spe3rDataset(forty, "train", **kwargs), Spe3rDataset(forty, "val", **kwargs)
    train_ids = {(m, i) for m, i, _ in train.items}
    val_ids = {(m, i) for m, i, _ in val.items}
    assert [i for _, i in sorted(val_ids)] == [16, 17, 18, 19, 36, 37, 38, 39]
    assert not train_ids & val_ids and train_ids | val_ids == {(0, i) for i in range(40)}
    assert val[0]["index"] == 16 and val[0]["image"].shape == (1, 16, 16)
    # SPE3R's own split at 1000 images per model, and the sizes in between.
    assert [i for i in range(1000) if is_validation(i, 1000)] == [*range(400, 500),
                                                                  *range(900, 1000)]
    for count in range(10, 300):
        val_count = sum(is_validation(i, count) for i in range(count))
        assert val_count >= 2 and abs(val_count - 0.2 * count) <= 2


# ------------------------------------------------------------------------ bounded options


@pytest.mark.parametrize("argv, message", [
    (["render", "--seed", "-1"], "--seed: expected a value in [0, 4294967295], got -1"),
    (["render", "--seed", "4294967296"], "--seed"),
    (["render", "--images-per-model", "0"], "--images-per-model"),
    (["render", "--resolution", "7"], "--resolution"),
    (["render", "--resolution", "60000"], "1 rendering process(es), each 768 MiB + 160 bytes a "
     "pixel) needs about 537 GiB of memory"),
    (["render", "--spp", "0"], "--spp"),
    (["render", "--workers", "0"], "--workers"),
    (["render", "--shard", "2/2"], "--shard: expected I/N with 0 <= I < N"),
    (["render", "--shard", "1/2", "--overwrite"], "overwrite: not with shard N > 1"),
    (["render", "--set", "mask.spp=0"], "--set mask.spp"),
    (["check", "ROOT", "--per-model", "-3"], "--per-model"),
    (["check", "ROOT", "--min-iou", "2"], "--min-iou: expected a value in [0, 1], got 2"),
    (["check", "ROOT", "--spp", "0"], "--spp"),
    (["preview", "ROOT", "--count", "0"], "--count"),
    (["preview", "ROOT", "--axis-length", "0"], "--axis-length"),
])
def test_numeric_options_are_checked_before_any_work(reference, library, tmp_path, capsys,
                                                     argv, message):
    out = tmp_path / "new"
    if argv[0] == "render":
        argv = [*argv, "--models", str(library), "--out", str(out), "--quiet"]
    root = tmp_path / "data"
    shutil.copytree(reference, root)
    before = digests(root)
    argv = [str(root) if a == "ROOT" else a for a in argv]
    assert main(["dataset", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and digests(root) == before


def test_resolution_is_bounded_by_memory():
    options = RenderOptions(resolution=4096)
    need = render_options.estimate_render_memory(4096, 4096)
    assert 2.5 * 2**30 < need < 3.5 * 2**30  # 0.75 GiB + 160 B x 16.8 Mpx
    render_options.check_render_resources(options.dataset_camera(), options, memory=need)
    with pytest.raises(DatasetError, match=r"^resolution: 4096 x 4096 px \(1 rendering "
                                          r"process\(es\), .*\) needs about 3\.25 GiB of memory, "
                                          r"more than the 3\.25 GiB this process may use"):
        render_options.check_render_resources(options.dataset_camera(), options,
                                              memory=need - 1)
    assert RenderOptions(seed=2**32 - 1).seed == 2**32 - 1


def test_the_scenes_textures_count_in_the_memory_estimate():
    """A star map 16384 texels wide took 9.4 GB a process for 64 px images while the estimate
    said 0.75 GiB, so two or three rendering processes passed the check and were killed:
    the textures beyond the default scene's are counted, and named when they are the cause."""
    import dataclasses

    scene = SceneConfig.load()
    assert render_options.texture_memory(scene) == 0  # the default scene's are in the base
    stars = dataclasses.replace(scene, stars=dataclasses.replace(scene.stars,
                                                                 envmap_width=16384))
    extra = render_options.texture_memory(stars)
    assert 8 * 2**30 < extra < 10 * 2**30  # 70 B a texel over 134 M texels, less the default's
    options = RenderOptions(resolution=64, workers=2, scene=stars)
    need = render_options.estimate_render_memory(64, 64, scene=stars)
    assert need == render_options.estimate_render_memory(64, 64) + extra
    render_options.check_render_resources(options.dataset_camera(), options, memory=2 * need)
    with pytest.raises(DatasetError, match=r"^the scene's textures \(stars.envmap_width 16384, "
                                          r"earth.texture 1024 x 512: 8\.\d+ GiB a process, 2 "
                                          r"rendering process\(es\)\) needs about .*; lower "
                                          r"--set stars.envmap_width"):
        render_options.check_render_resources(options.dataset_camera(), options,
                                              memory=2 * need - 1)


def test_a_render_that_cannot_fit_on_its_disk_is_refused_before_any_work(library, tmp_path,
                                                                           capsys):
    """Ten million 2048 px images a model started on a disk of 53 GB without a word: refused
    when even the fewest bytes an image takes would not fit, before any file is written."""
    out = tmp_path / "new" / "data"
    if 10_000_000 * 4096**2 * render_options.MIN_DISK_BYTES_PER_PIXEL <= \
            shutil.disk_usage(tmp_path).free:
        pytest.skip("a disk this large holds even that")
    assert main(["dataset", "render", "--models", str(library), "--out", str(out),
                 "--images-per-model", "10000000", "--resolution", "4096", "--spp", "1",
                 "--quiet"]) == 2
    line = error_line(capsys)
    assert re.search(r"images_per_model: [\d,]+ images of 4096 x 4096 px need at least .* on "
                     r"disk, more than the .* free under .*; lower --images-per-model", line), line
    assert not out.exists() and not out.parent.exists()
    render_options.check_disk_room(out, Camera.default(256), 1)  # a small one fits


def test_a_model_folder_without_a_row_in_the_librarys_splits_is_refused(library, tmp_path):
    """A library whose splits.csv lacks a model folder (an interrupted parallel `models
    generate`): its split is not guessed as train (a held-out model would silently train);
    the render stops before any work, naming it."""
    models = tmp_path / "models"
    shutil.copytree(library, models)
    rows = (models / "splits.csv").read_text().splitlines()
    dropped = rows[-1].split(",")[0]
    (models / "splits.csv").write_text("\n".join(rows[:-1]) + "\n")
    out = tmp_path / "data"
    with pytest.raises(DatasetError, match=rf"splits.csv: no row for 1 model folder\(s\) "
                                           rf"\({dropped}\)"):
        render_dataset(models, out, RenderOptions(**TINY), progress=False)
    assert not out.exists()


def test_a_library_without_splits_takes_each_models_split_from_its_card(library, tmp_path):
    """Without the library's splits.csv a model's split is the one its model_card.json
    records (a test model rendered as train would silently train); only a model whose card
    says none is a train model, said once in one warning counting them."""
    models = tmp_path / "models"
    shutil.copytree(library, models)
    (models / "splits.csv").unlink()
    cards = {path.parent.parent.name: json.loads(path.read_text())
             for path in sorted(models.glob("*/models/model_card.json"))}
    assert sorted(card["split"] for card in cards.values()) == ["test", "train"]
    one = dict(TINY, images_per_model=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every split known: nothing to warn about
        render_dataset(models, tmp_path / "data", RenderOptions(**one), progress=False)
    assert (tmp_path / "data" / "splits.csv").read_text() == \
        "".join(f"{name},{card['split']}\n" for name, card in sorted(cards.items()))
    test_model = next(name for name, card in cards.items() if card["split"] == "test")
    card_path = models / test_model / "models" / "model_card.json"
    card_path.write_text(json.dumps({**cards[test_model], "split": None}))
    with pytest.warns(UserWarning) as caught:
        render_dataset(models, tmp_path / "guessed", RenderOptions(**one), progress=False)
    assert [str(w.message) for w in caught] == [
        f"{models}: no splits.csv and no split in the model card of 1 model(s) ({test_model}): "
        "rendered as train models"]
    assert f"{test_model},train" in (tmp_path / "guessed" / "splits.csv").read_text()


def test_reading_a_dataset_whose_rendering_has_not_finished_says_so(reference, tmp_path):
    """splits.csv is written when the last model finishes: a reader of a dataset stopped
    before that says why it is missing, from the manifest's state."""
    from sq_mitsuba.data.spe3r.dataset import Spe3rDataset

    out = tmp_path / "data"
    shutil.copytree(reference, out)
    (out / "splits.csv").unlink()
    manifest = json.loads((out / "dataset.json").read_text())
    manifest["state"] = "rendering"
    (out / "dataset.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match=re.escape(
            f"{out / 'splits.csv'}: missing; its rendering has not finished (dataset.json says "
            "so): run the render command again") + "$"):
        Spe3rDataset(out)
    # A finished dataset being extended (more images a model) keeps its splits.csv while its
    # models hold labels and images of neither run: refused too (train and eval took it).
    (out / "splits.csv").write_bytes((reference / "splits.csv").read_bytes())
    with pytest.raises(DatasetError, match=re.escape(
            f"{out / 'dataset.json'}: says its rendering has not finished (an interrupted run, "
            "or one still going): run the render command again, or wait for it") + "$"):
        Spe3rDataset(out)


def test_a_manifest_with_nan_in_its_settings_is_named(reference, library, tmp_path, capsys):
    """Python's json reads NaN: a manifest whose settings hold one is named by dataset check
    and refused by a rerun, touching no file."""
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    text = (out / "dataset.json").read_text()
    (out / "dataset.json").write_text(re.sub(r'"spp": \d+', '"spp": NaN', text, count=1))
    report = check_dataset(out, per_model=0, progress=False)
    assert f"{out / 'dataset.json'}: settings.spp: not a finite number" in report.problems
    before = tree(out)
    assert render_cli(library, out) == 2
    assert capsys.readouterr().err.strip().endswith("settings.spp: not a finite number")
    assert tree(out) == before


def test_a_dataset_is_not_rendered_into_or_inside_its_library(library, tmp_path, capsys):
    """Inside the library, the dataset's folder would be read as one of its models."""
    models = Path(shutil.copytree(library, tmp_path / "models"))
    before = sorted(p.relative_to(models) for p in models.rglob("*"))
    for out, where in ((models, "the model library"),
                       (models / "sub", f"inside the model library {models}")):
        capsys.readouterr()
        assert render_cli(models, out) == 2
        assert capsys.readouterr().err.strip().endswith(
            f"{out}: the output folder is {where}; render into another folder")
    assert sorted(p.relative_to(models) for p in models.rglob("*")) == before


def test_a_radiance_image_holding_nan_is_a_problem(reference, tmp_path):
    """dataset check decoded each EXR and let NaN through (a radiance image is finite)."""
    import OpenEXR

    from sq_mitsuba.data.spe3r.layout import write_exr

    out = Path(shutil.copytree(reference, tmp_path / "data"))
    model = sorted(json.loads((out / "dataset.json").read_text())["models"])[0]
    path = sorted((out / model / "exr").glob("*.exr"))[0]
    with OpenEXR.File(str(path)) as exr:
        channels = {name: np.array(channel.pixels, np.float32)
                    for name, channel in exr.channels().items()}
    first = sorted(channels)[0]
    channels[first][0, :3] = np.nan
    write_exr(path, channels)
    problems = check_dataset(out, per_model=0, progress=False).problems
    assert problems == [f"{model}/exr/{path.name}: 3 value(s) NaN or infinite"], problems


def test_an_exr_of_another_size_than_the_camera_is_a_problem_not_decoded(reference, tmp_path):
    """dataset check decoded an EXR of any size (an 8192 x 8192 one of zeros, 0.8 MB, took
    2.8 GB) and found it fine on a 32 px dataset: the size is read from the header's
    dataWindow, and another than camera.json's is a problem."""
    from sq_mitsuba.data.spe3r.layout import write_exr

    out = Path(shutil.copytree(reference, tmp_path / "data"))
    model = sorted(json.loads((out / "dataset.json").read_text())["models"])[0]
    path = sorted((out / model / "exr").glob("*.exr"))[0]
    zeros = np.zeros((48, 64), np.float32)  # finite values: fine but for their size
    write_exr(path, {"Y": zeros, "Z": zeros, "A": zeros})
    problems = check_dataset(out, per_model=0, progress=False).problems
    assert problems == [f"{model}/exr/{path.name}: 64 x 48 px, camera.json says 32 x 32 (not "
                        "decoded)"], problems
