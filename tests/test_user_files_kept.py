"""Nothing the tool did not write is deleted or overwritten: a file of an output's name that no
earlier run of the command vouches for is refused before any work (predict, predict
--sequence, eval), a demo replaces only a folder a demo wrote, and a failed run removes only
what it could have written (:func:`sq_mitsuba.outputs.all_or_nothing`), never a file the user
saved into its output folder meanwhile."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from output_checks import error_line, one_torch_thread  # noqa: F401 (autouse fixture)
from PIL import Image

from sq_mitsuba.cli import main

#: Small evaluation settings (tests/test_evaluate.py's): one image, no baseline, no figures.
SMALL_EVAL = ["--split", "val", "--limit", "1", "--no-baseline", "--no-figures",
              "--set", "surface_points=500", "--set", "volume_points=3000", "--quiet"]


def _listing(root: Path) -> dict[str, bytes | None]:
    """Every entry under ``root``: a file's bytes, None for a folder."""
    return {str(p.relative_to(root)): None if p.is_dir() else p.read_bytes()
            for p in sorted(root.rglob("*"))}


def _grey(path: Path, value: int = 0) -> Path:
    Image.fromarray(np.full((64, 64), value, np.uint8)).save(path)
    return path


def _predict_pose(target: bool, sequence: bool = False) -> str:
    """A pose.json as predict writes it (the fields that mark it as predict's)."""
    from sq_mitsuba.apps.predict import POSE_CONVENTION

    pose = {"image": "x.png", "target": target, "target_score": 0.99 if target else 0.1,
            "convention": POSE_CONVENTION + ("; the body frame of sequence.assembly.json"
                                             if sequence else ""),
            "checkpoint": "model.pt"}
    if sequence:
        pose["sequence"] = {"frame": 0, "frames": 2}
    return json.dumps(pose)


# ----------------------------------------------------------------------------- predict


def test_predict_refuses_a_file_of_an_outputs_name_it_did_not_write(eval_checkpoint, tmp_path,
                                                                     capsys):
    """A user's black.obj (no pose of predict's beside it) is neither deleted (an image
    without a target) nor overwritten: refused in one line before any work."""
    image = _grey(tmp_path / "black.png")
    out = tmp_path / "out"
    out.mkdir()
    (out / "black.obj").write_text("my own mesh")
    (out / "notes.txt").write_text("mine")
    before = _listing(out)
    assert main(["predict", str(image), "--checkpoint", str(eval_checkpoint), "--out", str(out),
                 "--quiet"]) == 2
    line = error_line(capsys)
    assert str(out / "black.obj") in line and "--out" in line, line
    assert _listing(out) == before
    # A pose.json of someone else's is not predict's mark: refused, naming it.
    (out / "black.pose.json").write_text(json.dumps({"q": [1, 0, 0, 0]}))
    before = _listing(out)
    assert main(["predict", str(image), "--checkpoint", str(eval_checkpoint), "--out", str(out),
                 "--quiet"]) == 2
    assert str(out / "black.pose.json") in error_line(capsys)
    assert _listing(out) == before


def test_predicts_own_files_are_told_by_the_pose_beside_them(tmp_path):
    from sq_mitsuba.apps.predict import check_own_files, is_pass_pose

    out = tmp_path
    check_own_files(out, ["a"])  # nothing there: nothing to refuse
    (out / "a.pose.json").write_text(_predict_pose(target=True))
    for suffix in (".obj", ".glb", ".assembly.json", ".overlay.png"):
        (out / f"a{suffix}").write_text("an earlier run's")
    check_own_files(out, ["a"])  # predict's own: replaced
    # Predict writes a pose alone for an image without a target: an obj beside it is not its.
    (out / "b.pose.json").write_text(_predict_pose(target=False))
    check_own_files(out, ["b"])
    (out / "b.obj").write_text("mine")
    with pytest.raises(ValueError, match=r"b\.obj: b\.pose\.json is of an image without a "):
        check_own_files(out, ["b"])
    # A pass's frame vouches for its overlay (and, a pass stopped part-way, its stem's files).
    (out / "c.pose.json").write_text(_predict_pose(target=False, sequence=True))
    (out / "c.overlay.png").write_text("the pass's")
    check_own_files(out, ["c"])
    assert is_pass_pose(out / "c.pose.json") and not is_pass_pose(out / "a.pose.json")
    # Neither a decoy with a "sequence" entry nor a JSON nested too deep is predict's.
    (out / "d.pose.json").write_text(json.dumps({"sequence": {}}))
    (out / "d.glb").write_text("mine")
    assert not is_pass_pose(out / "d.pose.json")
    with pytest.raises(ValueError, match=r"d\.pose\.json: not a pose file sq-mitsuba predict"):
        check_own_files(out, ["d"])
    (out / "d.pose.json").write_text("[" * 100_000)
    with pytest.raises(ValueError, match=r"d\.pose\.json: not a pose file"):
        check_own_files(out, ["d"])
    # No pose at all, but this package's assembly file: a run of predict stopped among the
    # stem's files (the pose goes first, comes back last); a rerun takes them up.
    from sq_mitsuba.geometry.assembly import JSON_FORMAT

    (out / "e.obj").write_text("the stopped run's")
    with pytest.raises(ValueError, match=r"e\.obj: no pose file of sq-mitsuba predict"):
        check_own_files(out, ["e"])
    (out / "e.assembly.json").write_text(json.dumps({"format": JSON_FORMAT, "version": 1}))
    check_own_files(out, ["e"])


def test_a_pass_replaces_only_what_predict_wrote(eval_checkpoint, train_dataset, tmp_path,
                                                 capsys):
    """predict --sequence: a user's sequence.png (no pass in the folder) or a frame's
    overlay without predict's pose beside it is refused before any work."""
    model = next(line.split(",")[0] for line in
                 (train_dataset / "splits.csv").read_text().splitlines()
                 if line.endswith(",test"))
    # Two copies of one image that shows its target (as tests/test_predict.py's passes).
    frames = [Path(shutil.copy(train_dataset / model / "images" / "000002.png",
                               tmp_path / f"f{k}.png")) for k in range(2)]
    out = tmp_path / "out"
    out.mkdir()
    for name in ("sequence.png", "f1.overlay.png"):  # a pass's file, a frame's
        (out / name).write_bytes(b"mine")
        before = _listing(out)
        assert main(["predict", *map(str, frames), "--sequence", "--checkpoint",
                     str(eval_checkpoint), "--out", str(out), "--quiet"]) == 2
        assert str(out / name) in error_line(capsys)
        assert _listing(out) == before
        (out / name).unlink()
    # A folder holding a pass predict wrote: its files are the pass's, replaced.
    (out / "old.pose.json").write_text(_predict_pose(target=True, sequence=True))
    (out / "colmap").mkdir()
    for name in ("sequence.png", "sequence.glb", "colmap/images.txt"):
        (out / name).write_text("an earlier pass's")
    from sq_mitsuba.apps.predict_sequence import check_pass_files

    check_pass_files(out, ["f0", "f1"])


# ----------------------------------------------------------------------------- demo


def test_the_demo_replaces_only_a_folder_a_demo_wrote(tmp_path, monkeypatch, capsys):
    """A decoy demo.json (``{}``) does not make a thesis folder a demo's; nor does a real
    one make a folder holding something else one; the working folder and those above it are
    refused. All before any work: the checkpoint (absent) is not even looked at."""
    from sq_mitsuba.apps.demo import check_demo_folder
    from sq_mitsuba.apps.demo_files import MANIFEST

    missing = ["--checkpoint", str(tmp_path / "absent.pt"), "--size", "tiny", "--quiet"]
    thesis = tmp_path / "thesis"
    thesis.mkdir()
    (thesis / MANIFEST).write_text("{}")
    (thesis / "chapter1.tex").write_text("months of work")
    before = _listing(tmp_path)
    assert main(["demo", "--out", str(thesis), *missing]) == 2
    line = error_line(capsys)
    assert f"{MANIFEST} no demo wrote" in line and "absent.pt" not in line, line
    assert _listing(tmp_path) == before
    # A demo's own record, but a file a demo does not write beside it: named.
    from sq_mitsuba.apps.demo_files import DEMO_FORMAT

    (thesis / MANIFEST).write_text(json.dumps({"format": DEMO_FORMAT}))
    before = _listing(tmp_path)
    assert main(["demo", "--out", str(thesis), *missing]) == 2
    assert "holds chapter1.tex, which the demo does not write" in error_line(capsys)
    assert _listing(tmp_path) == before
    # A previous demo (its record and its own entries only) is taken.
    (thesis / "chapter1.tex").unlink()
    (thesis / "images").mkdir()
    check_demo_folder(thesis)
    # The working folder, and one above it: refused up front (it cannot be renamed away).
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    for out in (".", str(work), ".."):
        assert main(["demo", "--out", out, *missing]) == 2
        line = error_line(capsys)
        assert "working" in line and "absent.pt" not in line, line
    assert _listing(work) == {}
    # A link to a folder: the demo swapped a folder in for the link, its target left empty.
    target = tmp_path / "target"
    target.mkdir()
    (tmp_path / "link").symlink_to(target)
    assert main(["demo", "--out", str(tmp_path / "link"), *missing]) == 2
    assert "a link (to " in error_line(capsys)
    assert (tmp_path / "link").is_symlink() and _listing(target) == {}


# ----------------------------------------------------------------------------- eval


def test_eval_leaves_files_of_a_folder_that_held_no_evaluation(eval_checkpoint, train_dataset,
                                                              tmp_path, capsys):
    """Figures, a mesh ranking and a lighting breakdown of those names in a folder that held
    no evaluation are someone else's: an evaluation that does not write them leaves them; one
    of the files it writes there is refused before any work."""
    out = tmp_path / "mine"
    out.mkdir()
    theirs = ["qualitative.png", "consistency.png", "per_model.png", "mesh_ranking.csv",
              "lighting.png", "lighting.csv", "lighting.md", "notes.txt"]
    for name in theirs:
        (out / name).write_text(f"my {name}")
    run = ["eval", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
           "--out", str(out), *SMALL_EVAL]
    assert main(run) == 0
    for name in theirs:
        assert (out / name).read_text() == f"my {name}", name
    assert (out / "eval.json").is_file()
    # Where there is no evaluation, a file named as one of the run's outputs is refused.
    other = tmp_path / "other"
    other.mkdir()
    (other / "summary.csv").write_text("my table")
    assert main([*run[:-len(SMALL_EVAL) - 2], "--out", str(other), *SMALL_EVAL]) == 2
    assert str(other / "summary.csv") in error_line(capsys)
    assert _listing(other) == {"summary.csv": b"my table"}
    # Where an evaluation is, its stale files go: a breakdown of the old per_image.csv.
    (out / "lighting.csv").write_text("a breakdown of the first run's per_image.csv")
    assert main(run) == 0
    assert not (out / "lighting.csv").exists() and (out / "notes.txt").is_file()


# ----------------------------------------------------------------------------- all or nothing


def test_a_failed_run_removes_only_what_it_could_have_written(tmp_path):
    from sq_mitsuba.cli import OUTPUT_NAMES
    from sq_mitsuba.outputs import all_or_nothing

    # A folder the run made (with a parent): the user saves a file and a folder into it
    # meanwhile. The run's files go; the user's stay, with the folders holding them.
    out = tmp_path / "new" / "eval"
    with pytest.warns(UserWarning, match=r"left 2 entries it did not write"), \
            pytest.raises(ValueError), all_or_nothing(out, outputs=OUTPUT_NAMES["eval"]):
        (out / ".eval_partial").mkdir()
        (out / ".eval_partial" / "run.json").write_text("{}")
        (out / "per_image.csv").write_text("partial")
        (out / ".summary.abcd1234.tmp.csv").write_text("a temporary")
        (out / "thesis").mkdir()
        (out / "thesis" / "chapter.tex").write_text("months of work")
        (out / "notes.txt").write_text("mine")
        (tmp_path / "new" / "beside.txt").write_text("mine too")
        raise ValueError("bad input found late")
    assert _listing(tmp_path / "new") == {
        "beside.txt": b"mine too", "eval": None, "eval/notes.txt": b"mine",
        "eval/thesis": None, "eval/thesis/chapter.tex": b"months of work"}
    # A folder of the run's (colmap/) holding a file of the user's: only the run's files go.
    shutil.rmtree(tmp_path / "new")
    out = tmp_path / "pass"
    with pytest.warns(UserWarning, match="left 1 entry"), pytest.raises(MemoryError), \
            all_or_nothing(out, outputs=OUTPUT_NAMES["predict"]):
        (out / "colmap").mkdir(parents=True)
        (out / "colmap" / "images.txt").write_text("the run's")
        (out / "colmap" / "my.db").write_text("the user's")
        (out / "a.pose.json").write_text("the run's")
        raise MemoryError
    assert _listing(out) == {"colmap": None, "colmap/my.db": b"the user's"}
    # Nothing of the user's: the run's folders go whole, silently, as before.
    out = tmp_path / "clean" / "study"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError), all_or_nothing(out, outputs=OUTPUT_NAMES["study"]):
            (out / "renders" / "phase_000_space" / "images").mkdir(parents=True)
            (out / "renders" / "phase_000_space" / "images" / "000000.png").write_text("x")
            (out / "study.json").write_text("{}")
            raise ValueError("late")
    assert not (tmp_path / "clean").exists()


def test_a_failed_export_removes_its_file_not_the_folder_the_user_wrote_into(tmp_path):
    from sq_mitsuba.outputs import all_or_nothing

    out = tmp_path / "exports" / "model.pt"
    with pytest.raises(OSError), all_or_nothing(out, file=True):
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(b"half a model")
        (out.parent / "notes.txt").write_text("mine")
        raise OSError(28, "No space left on device")
    assert _listing(tmp_path) == {"exports": None, "exports/notes.txt": b"mine"}


def test_the_commands_output_names_cover_what_they_write():
    """OUTPUT_NAMES (the CLI) against the modules' own lists of what they write."""
    from sq_mitsuba.apps.colmap_model import COLMAP_FILES
    from sq_mitsuba.apps.fit_run import OUTPUT_FILES as FIT_FILES
    from sq_mitsuba.apps.predict import OUTPUT_SUFFIXES
    from sq_mitsuba.apps.predict_sequence import PASS_FILES
    from sq_mitsuba.cli import ALL_OR_NOTHING, OUTPUT_NAMES
    from sq_mitsuba.evaluation.evaluate import LIGHTING_FILES, MESH_RANKING_FILE, OUTPUT_FILES
    from sq_mitsuba.evaluation.journal import JOURNAL, RUN_FILE
    from sq_mitsuba.evaluation.passes import OUTPUT_FILES as PASS_EVAL_FILES
    from sq_mitsuba.evaluation.passes import PARTIAL
    from sq_mitsuba.outputs import is_output

    assert {c for c, kind in ALL_OR_NOTHING.items() if kind == "folder"} == set(OUTPUT_NAMES)
    written = {
        "eval": [*OUTPUT_FILES, MESH_RANKING_FILE, f"{JOURNAL}/{RUN_FILE}",
                 f"{JOURNAL}/batch_000001.pt"],
        "predict": [*(f"img_001{suffix}" for suffix in OUTPUT_SUFFIXES), *PASS_FILES,
                    *(f"colmap/{name}" for name in COLMAP_FILES)],
        "fit": list(FIT_FILES),
        "report": ["report.md", "report.csv"],
        "study": [*PASS_EVAL_FILES, f"{PARTIAL}/{RUN_FILE}", f"{PARTIAL}/sc000__2.json",
                  "models/splits.csv", "renders/eclipse/sc000/images/000000.png",
                  "evals/eclipse/eval.json", "per_image.csv", "study.json",
                  *(f"illumination{name.removeprefix('lighting')}" for name in LIGHTING_FILES),
                  *LIGHTING_FILES],
    }
    for command, paths in written.items():
        for path in paths:
            assert is_output(path, OUTPUT_NAMES[command]), (command, path)
    # Not everything: a user's files in the same folders.
    for command, path in (("eval", "notes.txt"), ("predict", "colmap/my.db"),
                          ("predict", "sub/a.obj"), ("study", "thesis/ch1.tex")):
        assert not is_output(path, OUTPUT_NAMES[command]), (command, path)
    assert is_output("colmap", OUTPUT_NAMES["predict"], folder=True)
    assert not is_output("thesis", OUTPUT_NAMES["predict"], folder=True)
