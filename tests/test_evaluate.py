"""``sq-mitsuba eval`` end to end on the tiny trained checkpoint, then ``report`` on its output.

The numbers in the files are checked against references computed here without the
evaluation code: the network's own prediction (rotation and translation errors), scipy's
rotation mean (the baseline), numpy means (the summary) and the dataset's labels (lighting).
Bad input is a one-line error (exit code 2) with nothing written.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from output_checks import assert_picture, error_line, one_torch_thread, read_rows  # noqa: F401 (autouse fixture)
from scipy.spatial.transform import Rotation

from sq_mitsuba.cli import main
from sq_mitsuba.data.spe3r import Spe3rDataset
from sq_mitsuba.evaluation.evaluate import OUTPUT_FILES
from sq_mitsuba.evaluation.report import PAPER_TABLES
from sq_mitsuba.evaluation.scoring import METRICS
from sq_mitsuba.evaluation.tables import COLUMNS
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.model import checkpoint as checkpoint_module
from sq_mitsuba.model.checkpoint import checkpoint_payload, read_checkpoint, write_checkpoint
from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet

#: Small settings: few points (the defaults are for real evaluations) ...
SMALL_SCORES = ["--set", "surface_points=500", "--set", "volume_points=3000",
                "--set", "qualitative=2", "--set", "consistency_views=2", "--quiet"]
#: ... and, for --refine (refused without it), few refinement steps.
SMALL = ["--set", "refinement.steps=3", "--set", "refinement.patience=3",
         "--set", "search.grid=128", "--set", "search.screen_steps=2", *SMALL_SCORES]


@pytest.fixture(scope="module")
def val_eval(eval_checkpoint, train_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval") / "tiny" / "val"
    code = main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
                 "--split", "val", "--out", str(out), "--refine", "--set", "mesh_ranking=4",
                 *SMALL])
    assert code == 0
    return out


def test_eval_writes_every_file(val_eval, capsys):
    for name in OUTPUT_FILES:
        assert (val_eval / name).is_file(), name
        assert (val_eval / name).stat().st_size > 0, name
    for name in OUTPUT_FILES:
        if name.endswith(".png"):
            assert_picture(val_eval / name)
    info = json.loads((val_eval / "eval.json").read_text())
    assert info["split"] == "val" and info["images"] == 4 and info["num_primitives"] == 2
    assert info["label"] == "tiny_run"  # the checkpoint's folder: the training run
    assert info["methods"] == ["network", "search", "refined", "refined_gt", "baseline"]
    assert info["search_ms_per_image"] > 0
    assert info["images_per_second"] > 0


def test_per_image_rows_match_the_network_and_the_labels(val_eval, eval_checkpoint,
                                                          train_dataset):
    rows = read_rows(val_eval / "per_image.csv")
    assert list(rows[0]) == list(COLUMNS)
    assert len(rows) == 4 * 5  # the val split (images 4 and 9 of two models) x 5 methods
    dataset = Spe3rDataset(train_dataset, "val", image_size=64)
    predictor = load_model(eval_checkpoint)
    items = [dataset[i] for i in range(len(dataset))]
    prediction = predictor.predict(torch.stack([item["image"] for item in items]),
                                   dataset.camera.rescaled(64, 64))
    network = {(r["model"], int(r["index"])): r for r in rows if r["method"] == "network"}
    for k, item in enumerate(items):
        row = network[(item["model"], item["index"])]
        relative = prediction.rotation[k].double().T @ item["rotation"].double()
        angle = np.degrees(np.arccos(np.clip((float(torch.trace(relative)) - 1) / 2, -1, 1)))
        assert float(row["rotation_error_deg"]) == pytest.approx(angle, abs=0.05)
        assert float(row["rotation_error_sym_deg"]) <= float(row["rotation_error_deg"]) + 1e-9
        # The axes' error is the least over 24 relabellings, the half turns among them.
        assert float(row["rotation_error_axes_deg"]) <= \
            float(row["rotation_error_folded_deg"]) + 1e-9
        assert float(row["rotation_error_axes_deg"]) <= 62.81
        distance = np.linalg.norm((prediction.translation[k] - item["translation"]).numpy())
        assert float(row["translation_error_m"]) == pytest.approx(distance, rel=1e-4)
        label = json.loads((train_dataset / item["model"] / "labels.json").read_text())[
            item["index"]]
        assert row["filename"] == label["filename"]
        assert float(row["phase_angle_deg"]) == pytest.approx(label["phase_angle_deg"])
        assert row["earth_in_view"] == str(label["earth_in_view"])
        assert row["eclipse"] == str(label["eclipse"])
        assert float(row["target_visibility"]) == pytest.approx(label["target_visibility"])
        for metric in ("iou_2d", "iou_3d"):
            assert 0.0 <= float(row[metric]) <= 1.0
        assert float(row["chamfer_l1_paper"]) > float(row["chamfer_l1_occnet"]) > 0


def test_network_rows_shape_and_pose_metrics_by_brute_force(val_eval, eval_checkpoint,
                                                            train_dataset):
    """The network rows' shape, outline and SPEED columns, each recomputed here from the
    network's own prediction with numpy: brute-force nearest neighbours over the points that
    count (the assembly's samples not inside another primitive), the silhouette rendered at
    the predicted pose against the label's mask, the model's labelled volume points, and the
    SPEED score from the quaternion angle."""
    from sq_mitsuba.evaluation.scoring import volume_points
    from sq_mitsuba.evaluation.split import open_split
    from sq_mitsuba.model.losses import counted_surface_samples
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

    rows = read_rows(val_eval / "per_image.csv")
    network = {(r["model"], int(r["index"])): r for r in rows if r["method"] == "network"}
    dataset = open_split(train_dataset, "val", 64, 500)  # SMALL's surface_points
    camera = dataset.camera.rescaled(64, 64)
    items = [dataset[i] for i in range(len(dataset))]
    prediction = load_model(eval_checkpoint).predict(
        torch.stack([item["image"] for item in items]), camera)
    assembly = Assembly(prediction.assembly.params.detach().double())
    points, keep = counted_surface_samples(assembly)
    with torch.no_grad():
        silhouettes = render_assembly(assembly,
                                      prediction.rotation.double(),
                                      prediction.translation.double(),
                                      SilhouetteRenderer(camera, spp=32), 3).numpy()
    for k, item in enumerate(items):
        row = network[(item["model"], item["index"])]
        body = points[k][keep[k]].numpy()
        truth = item["surface_points"].double().numpy()
        rotation, translation = (prediction.rotation[k].double().numpy(),
                                 prediction.translation[k].double().numpy())
        true_rotation, true_translation = (item["rotation"].double().numpy(),
                                           item["translation"].double().numpy())

        def nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            distances = np.linalg.norm(a[:, None] - b[None], axis=-1)
            return distances.min(1), distances.min(0)

        forward, backward = nearest(body, truth)
        assert float(row["chamfer_l2"]) == pytest.approx(
            (forward**2).mean() + (backward**2).mean(), rel=1e-6)
        forward, backward = nearest(body @ rotation.T + translation,
                                    truth @ true_rotation.T + true_translation)
        assert float(row["camera_chamfer"]) == pytest.approx(
            0.5 * (forward.mean() + backward.mean()) / np.linalg.norm(true_translation),
            rel=2e-3)
        relative = np.linalg.norm(translation - true_translation) / np.linalg.norm(
            true_translation)
        assert float(row["translation_error_rel"]) == pytest.approx(relative, rel=1e-3)
        angle = Rotation.from_matrix(rotation.T @ true_rotation).magnitude()  # radians
        assert float(row["speed_score"]) == pytest.approx(angle + relative, abs=2e-3)
        mask = item["mask"][0].numpy() > 0.5
        drawn = silhouettes[k] > 0.5
        assert float(row["iou_2d"]) == pytest.approx(
            (drawn & mask).sum() / max((drawn | mask).sum(), 1), abs=0.02)
        cloud, inside = volume_points(train_dataset / item["model"], 3000)  # SMALL's count
        with torch.no_grad():
            held = assembly[k:k + 1].union_occupancy(cloud[None])[0]
        held, inside = held.numpy() > 0.5, inside.numpy()
        assert float(row["iou_3d"]) == pytest.approx(
            (held & inside).sum() / max((held | inside).sum(), 1), abs=0.01)


def test_mesh_ranking_ranks_each_network_prediction_among_the_splits_models(val_eval):
    info = json.loads((val_eval / "eval.json").read_text())["mesh_ranking"]
    assert info["candidates"] == 2 and info["images"] == 4  # val: the two training models
    rows = read_rows(val_eval / "mesh_ranking.csv")
    network = {(r["model"], r["index"]) for r in read_rows(val_eval / "per_image.csv")
               if r["method"] == "network"}
    assert {(r["model"], r["index"]) for r in rows} == network
    for row in rows:  # with two candidates: first iff the own mesh is at least as near
        first = float(row["own_chamfer"]) <= float(row["nearest_other_chamfer"])
        assert (row["rank"], row["beaten"]) == (("1", "1.0000") if first else ("2", "0.0000"))
    assert info["top1"] == sum(r["rank"] == "1" for r in rows) / 4


def test_baseline_is_the_mean_training_pose(val_eval, train_dataset):
    rows = [r for r in read_rows(val_eval / "per_image.csv") if r["method"] == "baseline"]
    train = Spe3rDataset(train_dataset, "train", image_size=64, num_surface=1,
                         num_occupancy=2)
    labels = [train.items[i][2] for i in range(len(train))]
    quaternions = np.array([label["q_vbs2tango_true"] for label in labels])
    mean = Rotation.from_quat(quaternions[:, [1, 2, 3, 0]]).mean()  # scipy: scalar last
    translation = np.mean([label["r_Vo2To_vbs_true"] for label in labels], axis=0)
    for row in rows:
        label = json.loads((train_dataset / row["model"] / "labels.json").read_text())[
            int(row["index"])]
        truth = Rotation.from_quat(np.roll(label["q_vbs2tango_true"], -1))
        assert float(row["rotation_error_deg"]) == pytest.approx(
            np.degrees((mean.inv() * truth).magnitude()), abs=0.01)
        assert float(row["translation_error_m"]) == pytest.approx(
            np.linalg.norm(translation - label["r_Vo2To_vbs_true"]), rel=1e-5)


def test_refinement_rows_and_summary_tables(val_eval):
    rows = read_rows(val_eval / "per_image.csv")
    for row in rows:
        if row["method"] in ("search", "refined", "refined_gt"):
            if row["search_score"]:
                assert 0 <= float(row["search_score"]) <= 1
                assert 0 <= float(row["refine_iou_after"]) <= 1
            assert row["mask_source"] == ("ground truth" if row["method"] == "refined_gt"
                                          else "segmentation")  # the tiny model has no mask head
        else:
            assert row["search_score"] == row["refine_iou_after"] == row["mask_source"] == ""
    assert all(0 <= float(r["mask_iou"]) <= 1 for r in rows
               if r["method"] in ("search", "refined"))
    # The search keeps the network's assembly: its shape metrics are the network's.
    for network, search in zip((r for r in rows if r["method"] == "network"),
                               (r for r in rows if r["method"] == "search"), strict=True):
        assert network["chamfer_l1_paper"] == search["chamfer_l1_paper"]
    summary = {(r["method"], r["metric"]): r for r in read_rows(val_eval / "summary.csv")}
    for method in ("network", "search", "refined", "refined_gt", "baseline"):
        for metric in METRICS:
            values = np.array([float(r[metric]) for r in rows if r["method"] == method])
            entry = summary[(method, metric)]
            assert float(entry["mean"]) == pytest.approx(values.mean())
            assert float(entry["std"]) == pytest.approx(values.std(), abs=1e-12)
            assert float(entry["median"]) == pytest.approx(np.median(values))
    per_model = read_rows(val_eval / "per_model.csv")
    assert {r["model"] for r in per_model} == {r["model"] for r in rows}
    markdown = (val_eval / "summary.md").read_text()
    network = summary[("network", "chamfer_l1_paper")]
    assert (f"{float(network['mean']):.3f} ± {float(network['std']):.3f} "
            f"({float(network['median']):.3f})") in markdown


def test_report_on_the_eval_output_holds_ours_and_the_papers_numbers(
        val_eval, eval_checkpoint, train_dataset, tmp_path, capsys):
    test_out = val_eval.parent / "test"
    assert main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
                 "--split", "test", "--out", str(test_out), "--limit", "3", "--no-figures",
                 *SMALL_SCORES]) == 0
    assert len(read_rows(test_out / "per_image.csv")) == 3 * 2  # network and baseline
    assert not (test_out / "qualitative.png").exists()
    capsys.readouterr()
    assert main(["report", str(val_eval), str(test_out), "--out", str(tmp_path)]) == 0
    report = (tmp_path / "report.md").read_text()
    assert PAPER_TABLES.is_file()
    assert "0.054 ± 0.026" in report  # the paper's Table 1 (a), validation Chamfer-L1
    assert "0.146 ± 0.084" in report  # ... and test
    for folder in (val_eval, test_out):
        ours = {r["metric"]: r for r in read_rows(folder / "summary.csv")
                if r["method"] == "network"}["chamfer_l1_paper"]
        assert f"{float(ours['mean']):.3f} ± {float(ours['std']):.3f}" in report
    assert "| tiny_run |" in report  # the run (the checkpoint's folder): its val and test


def test_a_rerun_stopped_among_its_writes_leaves_no_finished_evaluation(
        val_eval, eval_checkpoint, train_dataset, tmp_path, monkeypatch, capsys):
    """A second evaluation into a finished folder, interrupted after its tables but before its
    figures: the folder holds no eval.json (the mark of a finished run) that `report` could
    read the new tables under; interrupted before its first write, the first run is whole."""
    from sq_mitsuba.evaluation import figures
    from sq_mitsuba.inference.predictor import Predictor

    out = tmp_path / "val"
    shutil.copytree(val_eval, out)
    before = {name: (out / name).read_bytes() for name in OUTPUT_FILES}
    argv = ["eval", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
            "--split", "val", "--out", str(out), "--limit", "2", *SMALL_SCORES]

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    # In the loop (the network's pass): nothing written, the first run whole.
    with monkeypatch.context() as patch:
        patch.setattr(Predictor, "predict", interrupted)
        assert main(argv) == 130
    assert {name: (out / name).read_bytes() for name in OUTPUT_FILES} == before
    # Among the writes: the tables are the new run's, and no eval.json says either run's.
    monkeypatch.setattr(figures, "plot_per_model", interrupted)
    assert main(argv) == 130
    assert (out / "summary.csv").read_bytes() != before["summary.csv"]
    assert not (out / "eval.json").exists()
    capsys.readouterr()
    assert main(["report", str(out), "--out", str(tmp_path / "report")]) == 2
    assert "eval.json: missing" in capsys.readouterr().err


# ------------------------------------------------------------------------------ bad input


def test_checkpoint_of_another_config_is_one_line(eval_checkpoint, train_dataset, tmp_path,
                                                  capsys):
    payload = read_checkpoint(eval_checkpoint)
    payload["config"]["network"]["num_primitives"] = 3  # weights are for 2
    write_checkpoint(tmp_path / "other.pt", payload)
    payload = read_checkpoint(eval_checkpoint)
    payload["config"]["network"]["depth_layers"] = 4  # no such field in this version
    torch.save(payload, tmp_path / "unknown.pt")  # write_checkpoint refuses to write it
    for name, expected in (("other.pt", "do not fit config.network"),
                           ("unknown.pt", "depth_layers")):
        out = tmp_path / f"out_{name}"
        code = main(["eval", "--checkpoint", str(tmp_path / name), "--data",
                     str(train_dataset), "--out", str(out), "--quiet"])
        assert code == 2
        line = error_line(capsys)
        assert name in line and expected in line
        assert not out.exists()
    colour = SuperquadricNet(NetworkConfig(in_channels=3, image_size=64, num_primitives=2,
                                           latent_dim=8, hidden_dim=8))
    write_checkpoint(tmp_path / "rgb.pt", checkpoint_payload(colour, load_model(
        eval_checkpoint).camera))
    assert main(["eval", "--checkpoint", str(tmp_path / "rgb.pt"), "--data",
                 str(train_dataset), "--out", str(tmp_path / "rgb"), "--quiet"]) == 2
    assert "3-channel" in error_line(capsys)
    assert not (tmp_path / "rgb").exists()


def test_missing_split_and_missing_data_are_one_line(eval_checkpoint, train_dataset, tmp_path,
                                                     capsys):
    only_train = tmp_path / "only_train"
    only_train.mkdir()
    shutil.copy(train_dataset / "camera.json", only_train)
    lines = [line for line in (train_dataset / "splits.csv").read_text().splitlines()
             if line.endswith(",train")]
    (only_train / "splits.csv").write_text("\n".join(lines) + "\n")
    for line in lines:
        (only_train / line.split(",")[0]).symlink_to(train_dataset / line.split(",")[0])
    for data, split, expected in ((only_train, "test", "'test' split is empty"),
                                  (tmp_path / "nowhere", "val", "missing")):
        out = tmp_path / f"out_{split}"
        assert main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(data),
                     "--split", split, "--out", str(out), "--quiet"]) == 2
        assert expected in error_line(capsys)
        assert not out.exists()
    # The baseline needs the train split: a dataset without one says how to go on.
    only_test = _test_models_only(train_dataset, tmp_path / "only_test")
    assert main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(only_test),
                 "--split", "test", "--out", str(tmp_path / "out_base"), "--quiet"]) == 2
    assert "--no-baseline" in error_line(capsys)
    assert not (tmp_path / "out_base").exists()
    # An empty val says what val holds (a training model's images; not every n has some).
    assert main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(only_test),
                 "--split", "val", "--no-baseline", "--out", str(tmp_path / "out_val"),
                 "--quiet"]) == 2
    assert ("'val' split is empty (it holds images [0.4 n, 0.5 n) and [0.9 n, n) of each "
            "training model's n: none without training models, nor for n of 1-4, 6 or 8 "
            "(render 10 or more images a model, or evaluate --split test))") in error_line(capsys)
    assert not (tmp_path / "out_val").exists()
    # Refused before any work: the journal an interrupted run left there is not touched.
    journal = tmp_path / "out_journal" / ".eval_partial"
    journal.mkdir(parents=True)
    (journal / "run.json").write_text("{}")
    (journal / "batch_000001.pt").write_bytes(b"an interrupted run's batch")
    assert main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(only_test),
                 "--split", "test", "--out", str(journal.parent), "--quiet"]) == 2
    assert "--no-baseline" in error_line(capsys)
    assert {p.name: p.read_bytes() for p in journal.iterdir()} == {
        "run.json": b"{}", "batch_000001.pt": b"an interrupted run's batch"}
    # A mesh ranking needs two models to rank among: the test split has one. Refused up
    # front, an earlier run's ranking kept.
    ranked = tmp_path / "out_ranking"
    ranked.mkdir()
    (ranked / "mesh_ranking.csv").write_text("an earlier run's ranking\n")
    assert main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
                 "--split", "test", "--out", str(ranked), "--limit", "1", "--no-baseline",
                 "--no-figures", *SMALL_SCORES, "--set", "mesh_ranking=4"]) == 2
    line = error_line(capsys)
    assert "mesh_ranking" in line and "'test' split" in line
    assert (ranked / "mesh_ranking.csv").read_text() == "an earlier run's ranking\n"
    assert sorted(p.name for p in ranked.iterdir()) == ["mesh_ranking.csv"]
    with pytest.raises(SystemExit) as stop:  # argparse: not a choice
        main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
              "--split", "train", "--out", str(tmp_path / "x")])
    assert stop.value.code == 2


def _test_models_only(dataset: Path, folder: Path) -> Path:
    """A dataset folder holding one test model of ``dataset`` (linked) and no train split."""
    folder.mkdir()
    shutil.copy(dataset / "camera.json", folder)
    test_line = next(line for line in (dataset / "splits.csv").read_text().splitlines()
                     if line.endswith(",test"))
    (folder / "splits.csv").write_text(test_line + "\n")
    (folder / test_line.split(",")[0]).symlink_to(dataset / test_line.split(",")[0])
    return folder


def test_without_checkpoint_and_no_shipped_model_is_one_clear_line(train_dataset, tmp_path,
                                                                   monkeypatch, capsys):
    monkeypatch.setattr(checkpoint_module, "SHIPPED_MODEL", tmp_path / "absent" / "model.pt")
    assert main(["eval", "--data", str(train_dataset), "--out", str(tmp_path / "out"),
                 "--quiet"]) == 2
    line = error_line(capsys)
    assert "no trained model is shipped" in line and "sq-mitsuba train" in line
    assert not (tmp_path / "out").exists()


def test_a_dataset_of_test_models_only_is_scored_against_the_stored_baseline(
        eval_checkpoint, train_dataset, tmp_path):
    """Held-out families and real spacecraft come without a train split: the trivial baseline
    is then the checkpoint's own (the mean over its training images), not an error."""
    exported = tmp_path / "exported.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
                 "--out", str(exported), "--no-half"]) == 0
    stored = load_model(exported).baseline
    assert stored is not None
    only_test = _test_models_only(train_dataset, tmp_path / "only_test")
    model = (only_test / "splits.csv").read_text().split(",")[0]
    out = tmp_path / "out"
    assert main(["eval", "--checkpoint", str(exported), "--data", str(only_test), "--split",
                 "test", "--out", str(out), "--no-figures", "--set", "surface_points=500",
                 "--set", "volume_points=3000", "--limit", "2", "--quiet"]) == 0
    rows = [r for r in read_rows(out / "per_image.csv") if r["method"] == "baseline"]
    assert len(rows) == 2
    # The stored translation is the baseline's pose: its error against each label.
    truth = {(int(label["filename"][:6]), tuple(label["r_Vo2To_vbs_true"]))
             for label in json.loads((only_test / model / "labels.json")
                                     .read_text())}
    for row in rows:
        true_t = next(t for index, t in truth if index == int(row["index"]))
        error = float(torch.linalg.vector_norm(stored[2][0] - torch.tensor(true_t,
                                                                           dtype=torch.float64)))
        assert float(row["translation_error_m"]) == pytest.approx(error, rel=1e-6)


def test_turned_copies_read_the_network_row(train_dataset, tmp_path):
    """``--turns 8``: the network row is the shipped model's reading of 8 turned copies of each
    image (its rotation error that of ``predict(turns=8)``, not of one reading); the search,
    which reads its own copies, is the same as without it."""
    common = ["eval", "--data", str(train_dataset), "--split", "val", "--limit", "2",
              "--refine", "--no-baseline", "--no-figures", "--set", "refine_ground_truth=false",
              *SMALL]
    assert main([*common, "--out", str(tmp_path / "turns"), "--turns", "8"]) == 0
    assert main([*common, "--out", str(tmp_path / "once")]) == 0
    dataset = Spe3rDataset(train_dataset, "val", image_size=96)
    predictor = load_model()
    items = [dataset[i] for i in (0, len(dataset) - 1)]  # --limit 2: the first and the last
    images = torch.stack([item["image"] for item in items])
    camera = dataset.camera.rescaled(96, 96)
    turned = predictor.predict(images, camera, turns=8)
    once = predictor.predict(images, camera)

    def rows(name: str, method: str) -> dict[tuple[str, int], dict[str, str]]:
        return {(r["model"], int(r["index"])): r for r in read_rows(tmp_path / name /
                                                                    "per_image.csv")
                if r["method"] == method}
    network, search, search_once = rows("turns", "network"), rows("turns", "search"), \
        rows("once", "search")
    for k, item in enumerate(items):
        def angle(rotation: torch.Tensor, item=item) -> float:
            relative = rotation.double().T @ item["rotation"].double()
            return float(np.degrees(np.arccos(np.clip((float(torch.trace(relative)) - 1) / 2,
                                                      -1, 1))))
        key = (item["model"], item["index"])
        assert float(network[key]["rotation_error_deg"]) == pytest.approx(
            angle(turned.rotation[k]), abs=0.05)
        assert abs(angle(turned.rotation[k]) - angle(once.rotation[k])) > 0.1  # not one reading
        assert search[key]["rotation_error_deg"] == search_once[key]["rotation_error_deg"]


def test_turned_copies_without_a_distribution_head_are_one_line(eval_checkpoint, train_dataset,
                                                                tmp_path, capsys):
    out = tmp_path / "refused"
    code = main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
                 "--split", "val", "--out", str(out), "--set", "turns=8", *SMALL_SCORES])
    line = error_line(capsys)
    assert code == 2 and ("turns: reading the rotation from turned copies needs a "
                          "rotation-distribution head") in line
    assert not (out / "summary.csv").exists()


def test_an_images_scores_and_rows_do_not_depend_on_its_batch(eval_checkpoint, train_dataset,
                                                              tmp_path):
    """Batches of 1 and of 3: every image's rows in one order (image by image), the baseline's
    2D IoU (the same assembly either way) equal to the last digit and the network's to its
    float rounding by batch size. Its silhouettes' samples followed the renderer's running
    sequence: batch sizes 1 and 4 moved one image's 2D IoU by up to 0.007."""
    tables = {}
    for size in (1, 3):
        out = tmp_path / f"b{size}"
        assert main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
                     "--split", "val", "--out", str(out), "--batch-size", str(size),
                     "--set", "figures=false", *SMALL_SCORES]) == 0
        tables[size] = read_rows(out / "per_image.csv")
    one, three = tables[1], tables[3]
    assert [(r["model"], r["index"], r["method"]) for r in one] == \
        [(r["model"], r["index"], r["method"]) for r in three]
    assert [r["method"] for r in one[:2]] == ["network", "baseline"]  # one image's rows
    for a, b in zip(one, three, strict=True):
        tolerance = 0 if a["method"] == "baseline" else 1e-3
        assert float(a["iou_2d"]) == pytest.approx(float(b["iou_2d"]), abs=tolerance), a
