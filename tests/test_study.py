"""``sq-mitsuba study illumination``: the sweep through the dataset renderer (fixed poses, the
lighting asked for, eclipse frames), evaluated with and without refinement; and the breakdown
of a regular evaluation by its recorded lighting."""

from __future__ import annotations

import json

import numpy as np
import pytest
from output_checks import assert_picture, error_line, one_torch_thread, read_rows  # noqa: F401 (autouse fixture)

from sq_mitsuba.cli import main
from sq_mitsuba.evaluation.evaluate import EvalOptions, evaluate
from sq_mitsuba.evaluation.scoring import METRICS
from sq_mitsuba.evaluation.study import sweep_points
from sq_mitsuba.inference.loading import load_model


def test_sweep_points():
    points = sweep_points(15)
    angles = sorted({p.phase_deg for p in points if p.phase_deg is not None})
    assert angles == [15.0 * k for k in range(13)]
    assert len(points) == 2 * 13 + 1 and points[-1].name == "eclipse"
    assert "sun.phase_deg=[30.0,30.0]" in points[4].overrides
    assert {p.background for p in points} == {"space", "earth", "eclipse"}
    assert len({p.name for p in points}) == len(points)


def test_illumination_study_end_to_end(eval_checkpoint, train_dataset, tmp_path, capsys):
    out = tmp_path / "study"
    # The training dataset doubles as a model library (<model>/models/, splits.csv): its one
    # test model, 2 poses, phase angles 0, 90 and 180 deg.
    code = main(["study", "illumination", "--checkpoint", str(eval_checkpoint), "--models",
                 str(train_dataset), "--out", str(out), "--poses", "2", "--step", "90",
                 "--set", "render.resolution=64", "--set", "render.spp=4",
                 "--set", "evaluation.refinement.steps=2",
                 "--set", "evaluation.refinement.patience=2",
                 "--set", "evaluation.search.grid=64",
                 "--set", "evaluation.surface_points=500",
                 "--set", "evaluation.volume_points=2000", "--quiet"])
    assert code == 0, capsys.readouterr().err
    for name in ("per_image.csv", "illumination.csv", "illumination.md", "study.json"):
        assert (out / name).stat().st_size > 0
    assert_picture(out / "illumination.png")
    points = sweep_points(90)
    rows = read_rows(out / "per_image.csv")
    assert len(rows) == len(points) * 2 * 3  # 2 poses, network, search, search + refinement
    assert {r["method"] for r in rows} == {"network", "search", "refined"}
    poses = set()
    for point in points:
        labels = [label for folder in (out / "renders" / point.name).iterdir()
                  if (folder / "labels.json").is_file()
                  for label in json.loads((folder / "labels.json").read_text())]
        assert len(labels) == 2
        poses.add(json.dumps([(lb["q_vbs2tango_true"], lb["r_Vo2To_vbs_true"])
                              for lb in labels]))
        for label in labels:
            if point.background == "eclipse":
                assert label["eclipse"] is True
            else:
                assert label["earth_in_view"] is (point.background == "earth")
                if not label["eclipse"]:
                    assert label["phase_angle_deg"] == pytest.approx(point.phase_deg, abs=1e-4)
        mine = [r for r in rows if r["point"] == point.name]
        assert {r["phase_angle_deg"] for r in mine} == \
            {str(round(lb["phase_angle_deg"], 6)) for lb in labels}
    assert len(poses) == 1  # the same poses under every lighting
    # Each model's symmetries detected once, in the study's copy, and rendered along with it.
    model = next(p.parent.parent.name for p in (out / "models").glob("*/models/*.obj"))
    for folder in (out / "models", *(out / "renders" / p.name for p in points)):
        assert (folder / model / "models" / "symmetries.json").is_file(), folder
    table = read_rows(out / "illumination.csv")
    groups = {(r["background"], r["method"]) for r in table}
    assert ("eclipse", "network") in groups and ("earth", "refined") in groups
    network_at_0 = [float(r["chamfer_l1_paper"]) for r in rows
                    if r["point"] == "phase_000_space" and r["method"] == "network"]
    entry = next(r for r in table if r["background"] == "space" and float(r["phase_deg"]) == 0
                 and r["method"] == "network" and r["metric"] == "chamfer_l1_paper")
    assert float(entry["mean"]) == pytest.approx(np.mean(network_at_0))
    assert int(entry["images"]) == 2
    # A rerun of other settings into the same folder: refused in the study's terms (it has
    # no --overwrite), the renders as they were.
    for changed, said in ((["--set", "render.spp=8", "--poses", "2"], "spp 4 (this run: 8)"),
                          (["--set", "render.spp=4", "--poses", "1"],
                           "--poses 1 is below the dataset's 2")):
        assert main(["study", "illumination", "--checkpoint", str(eval_checkpoint), "--models",
                     str(train_dataset), "--out", str(out), "--step", "90",
                     "--set", "render.resolution=64", *changed, "--quiet"]) == 2
        message = error_line(capsys)
        assert said in message and "--overwrite" not in message, message
        assert message.endswith(f"a study of other settings: delete {out} to start over, or "
                                "give another --out)")


def test_breakdown_of_an_evaluation_by_recorded_lighting(eval_checkpoint, train_dataset,
                                                        tmp_path, capsys):
    folder = tmp_path / "eval"
    evaluate(load_model(eval_checkpoint), train_dataset, folder,
             EvalOptions(split="test", baseline=False, figures=False, surface_points=300,
                         volume_points=1000), progress=False)
    rows = read_rows(folder / "per_image.csv")
    assert main(["study", "illumination", "--eval", str(folder), "--step", "30"]) == 0
    for name in ("lighting.csv", "lighting.md"):
        assert (folder / name).stat().st_size > 0
    assert_picture(folder / "lighting.png")
    table = read_rows(folder / "lighting.csv")
    expected: dict[tuple[str, float], list[float]] = {}
    eclipses = [float(r["phase_angle_deg"]) for r in rows if r["eclipse"] == "True"]
    for row in rows:  # the grouping, done here from the recorded lighting
        if row["eclipse"] == "True":  # eclipses: one group, at their mean phase angle
            key = ("eclipse", float(np.mean(eclipses)))
        else:
            key = ("earth" if row["earth_in_view"] == "True" else "space",
                   15.0 + 30.0 * min(int(float(row["phase_angle_deg"]) // 30), 5))
        expected.setdefault(key, []).append(float(row["iou_2d"]))
    got = {(r["background"], round(float(r["phase_deg"]), 2)): r for r in table
           if r["metric"] == "iou_2d" and r["method"] == "network"}
    assert set(got) == {(b, round(round(p, 3), 2)) for b, p in expected}
    for (background, phase), values in expected.items():
        key = (background, round(round(phase, 3), 2))
        assert int(got[key]["images"]) == len(values)
        assert float(got[key]["mean"]) == pytest.approx(np.mean(values))
    assert {r["metric"] for r in table} == set(METRICS)
    # A step that does not divide 180: the last bin, [100, 180] (the recorded phases reach
    # past 100 deg), is drawn at its centre, 140 (it was drawn at 150).
    assert max(float(r["phase_angle_deg"]) for r in rows) > 100
    assert main(["study", "illumination", "--eval", str(folder), "--step", "100"]) == 0
    centres = {float(r["phase_deg"]) for r in read_rows(folder / "lighting.csv")
               if r["background"] != "eclipse"}
    assert 140.0 in centres and centres <= {50.0, 140.0}, centres
    # An unfinished evaluation (no eval.json: interrupted) is not broken down.
    record = (folder / "eval.json").read_bytes()
    (folder / "eval.json").unlink()
    capsys.readouterr()
    assert main(["study", "illumination", "--eval", str(folder), "--step", "30"]) == 2
    assert error_line(capsys).endswith(f"{folder}: an unfinished evaluation (no eval.json: "
                                       "interrupted, or still running); finish it with the "
                                       "same eval command and --resume first")
    (folder / "eval.json").write_bytes(record)
    # Another evaluation into the folder: its per_image.csv is new, so the breakdown of the
    # earlier one goes (study illumination --eval makes this one's).
    evaluate(load_model(eval_checkpoint), train_dataset, folder,
             EvalOptions(split="test", limit=1, baseline=False, figures=False,
                         surface_points=300, volume_points=1000), progress=False)
    assert len(read_rows(folder / "per_image.csv")) == 1
    assert not [p.name for p in folder.iterdir() if p.name.startswith("lighting.")]


def test_bad_study_input_is_one_line(eval_checkpoint, train_dataset, tmp_path, capsys):
    assert main(["study", "illumination", "--eval", str(tmp_path)]) == 2
    assert "per_image.csv: missing" in error_line(capsys)
    for extra in (["--poses", "4"], ["--max-models", "2"], ["--split", "all"],
                  ["--set", "render.resolution=64"]):  # what --models renders: the eval's done
        assert main(["study", "illumination", "--eval", str(tmp_path), *extra]) == 2
        named = " ".join(extra) if extra[0] == "--set" else extra[0]
        assert error_line(capsys).endswith(f"{named}: not used with --eval (the evaluation is "
                                           "done; only --step applies)")
    assert main(["study", "illumination", "--models", str(train_dataset),
                 "--checkpoint", str(eval_checkpoint)]) == 2
    assert "--out: required" in error_line(capsys)
    assert main(["study", "illumination", "--models", str(tmp_path / "nowhere"),
                 "--checkpoint", str(eval_checkpoint), "--out", str(tmp_path / "o")]) == 2
    assert "nowhere" in error_line(capsys)
    assert main(["study", "illumination", "--models", str(train_dataset), "--checkpoint",
                 str(eval_checkpoint), "--out", str(tmp_path / "o"), "--step", "0.5"]) == 2
    assert "--step" in error_line(capsys)
    assert main(["study", "illumination", "--models", str(train_dataset), "--checkpoint",
                 str(eval_checkpoint), "--out", str(tmp_path / "o"),
                 "--set", "render.scene.sun.irradiance=-1"]) == 2
    assert "irradiance" in error_line(capsys)
    inside = train_dataset / "study"  # its folders would be read as the library's models
    assert main(["study", "illumination", "--models", str(train_dataset), "--checkpoint",
                 str(eval_checkpoint), "--out", str(inside)]) == 2
    assert error_line(capsys).endswith(f"out {inside}: inside the model library "
                                       f"{train_dataset}; write the study outside it")
    assert not inside.exists()
    # A mesh ranking among the study's one model: refused before the first render.
    assert main(["study", "illumination", "--models", str(train_dataset), "--checkpoint",
                 str(eval_checkpoint), "--out", str(tmp_path / "o"), "--poses", "1",
                 "--step", "180", "--set", "render.resolution=64", "--set", "render.spp=4",
                 "--set", "evaluation.refine=false", "--set", "evaluation.mesh_ranking=4",
                 "--quiet"]) == 2
    assert "evaluation.mesh_ranking 4" in error_line(capsys)
    assert not (tmp_path / "o").exists()
    # Fields the study sets itself would be ignored: refused, naming them.
    for field, value, said in (("render.shard", "1/2", ""),
                               ("render.images_per_model", "7", "; give --poses"),
                               ("evaluation.baseline", "true", ""),
                               ("evaluation.split", "val", "")):
        assert main(["study", "illumination", "--models", str(train_dataset), "--checkpoint",
                     str(eval_checkpoint), "--out", str(tmp_path / "o"),
                     "--set", f"{field}={value}", "--quiet"]) == 2
        assert error_line(capsys).endswith(f"--set {field}={value}: set by the study "
                                           f"itself{said}")
    assert not (tmp_path / "o").exists()
