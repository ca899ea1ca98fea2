"""`sq-mitsuba export` and the shipped model: small inference checkpoints that predict as the
training checkpoint does, with the trivial baseline stored beside the weights."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from output_checks import error_line, one_torch_thread  # noqa: F401
from PIL import Image

from sq_mitsuba.cli import main
from sq_mitsuba.evaluation.scoring import baseline_prediction
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.model.checkpoint import SHIPPED_MODEL, read_checkpoint


@pytest.fixture(scope="module")
def exported(eval_checkpoint, train_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "model.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
                 "--out", str(out), "--baseline-images", "8"]) == 0
    return out


def test_export_predicts_as_the_training_checkpoint(exported, eval_checkpoint, train_dataset):
    payload = read_checkpoint(exported)
    floats = [v for v in payload["model"].values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.float16 for v in floats)
    assert exported.stat().st_size < 0.75 * eval_checkpoint.stat().st_size
    assert payload["source"]["checkpoint"] == eval_checkpoint.name
    assert payload["source"]["step"] == 8

    original, shipped = load_model(eval_checkpoint), load_model(exported)
    images = torch.rand(4, 64, 64, generator=torch.Generator().manual_seed(0))
    a, b = original.predict(images), shipped.predict(images)
    # Half-precision weights: outputs agree, not bit for bit (measured: parameters 3.6e-4
    # apart at most, rotations 4e-6, translations 2e-4 relative; bounds 5-250 x those).
    torch.testing.assert_close(a.assembly.params, b.assembly.params, atol=2e-3, rtol=0)
    assert not torch.equal(a.assembly.params, b.assembly.params)
    torch.testing.assert_close(a.rotation, b.rotation, atol=1e-3, rtol=0)
    torch.testing.assert_close(a.translation, b.translation, rtol=1e-3, atol=1e-6)


def test_export_stores_the_baseline_of_the_exported_weights(exported, train_dataset):
    predictor = load_model(exported)
    assert predictor.baseline is not None
    raw, rotation, translation = predictor.baseline
    assert raw.shape == (1, 2, 16) and rotation.shape == (1, 3, 3) and translation.shape == (1, 3)
    # Independent recomputation with the loaded (rounded) weights.
    expected = baseline_prediction(predictor, train_dataset, 8)
    for got, want in zip((raw, rotation, translation), expected, strict=True):
        assert torch.allclose(got, want, atol=1e-5)
    assert torch.allclose(rotation[0] @ rotation[0].T, torch.eye(3, dtype=torch.float64),
                          atol=1e-5)


def test_an_exported_file_exported_again_keeps_its_record(eval_checkpoint, train_dataset,
                                                           tmp_path):
    """Exported without a baseline, then again with --data to add one: the second file keeps
    the first's record whole (the training step and checkpoint; for a real run also the
    dataset, which the check of --data against the training dataset reads)."""
    first, second = tmp_path / "first.pt", tmp_path / "second.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--out", str(first)]) == 0
    assert main(["export", "--checkpoint", str(first), "--data", str(train_dataset), "--out",
                 str(second), "--baseline-images", "4"]) == 0
    record, earlier = read_checkpoint(second)["source"], read_checkpoint(first)["source"]
    assert earlier["step"] == 8 and earlier["checkpoint"] == eval_checkpoint.name
    assert record.pop("exported_again_from") == first.name
    record.pop("baseline_data", None)  # the second export's own addition
    assert record == earlier


def test_export_refuses_bad_input_before_writing(eval_checkpoint, tmp_path, capsys):
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint")
    out = tmp_path / "out" / "model.pt"
    assert main(["export", "--checkpoint", str(corrupt), "--out", str(out)]) == 2
    assert str(corrupt) in error_line(capsys)
    assert not out.parent.exists()
    empty = tmp_path / "no_data"
    empty.mkdir()
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--data", str(empty),
                 "--out", str(out)]) == 2
    assert error_line(capsys)
    assert not out.exists()
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--start-share", "0.5",
                 "--out", str(out)]) == 2
    assert error_line(capsys).endswith("--start-share: only with --start (the share of the "
                                       "start's weights)")
    assert not out.exists()
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--baseline-images", "3",
                 "--out", str(out)]) == 2  # no --data: there is no baseline to size
    assert error_line(capsys).endswith("--baseline-images: only with --data (the baseline's "
                                       "training images)")
    assert not out.exists()


@pytest.mark.skipif(not SHIPPED_MODEL.is_file(), reason="no shipped model in this checkout")
def test_shipped_model_is_small_and_predicts_grey_and_rgb_images():
    assert SHIPPED_MODEL.stat().st_size <= 25 * 2**20
    predictor = load_model()
    assert predictor.baseline is not None
    rng = np.random.default_rng(0)
    grey = np.zeros((200, 200), np.uint8)
    grey[70:130, 40:160] = rng.integers(80, 255, (60, 120))  # a bright body on black
    rgb = np.asarray(Image.fromarray(grey).convert("RGB"))
    for image in (grey[None], rgb.mean(-1, keepdims=False)[None].astype(np.uint8)):
        prediction = predictor.predict(image)
        assert torch.isfinite(prediction.assembly.params).all()
        assert prediction.translation[0, 2] > 0  # in front of the camera


def _perturbed(eval_checkpoint, path, seed: int, change=None):
    """A second checkpoint of the tiny network: every floating-point weight moved by a seeded
    normal step (as a fine-tune of the same start would move it), ``change`` then applied."""
    from sq_mitsuba.model.checkpoint import write_checkpoint

    payload = read_checkpoint(eval_checkpoint)
    generator = torch.Generator().manual_seed(seed)
    payload["model"] = {key: value + 0.01 * torch.randn(value.shape, generator=generator)
                        if value.is_floating_point() else value
                        for key, value in payload["model"].items()}
    if change is not None:
        change(payload)
    return write_checkpoint(path, payload)


def test_export_averages_checkpoints_of_one_network(eval_checkpoint, train_dataset, tmp_path,
                                                    capsys):
    other = _perturbed(eval_checkpoint, tmp_path / "other.pt", 1)
    out = tmp_path / "soup.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), str(other), "--no-half",
                 "--data", str(train_dataset), "--baseline-images", "4", "--out",
                 str(out)]) == 0
    soup, a, b = (read_checkpoint(path)["model"] for path in (out, eval_checkpoint, other))
    for key, value in soup.items():
        if value.is_floating_point():  # the mean, element by element
            assert torch.allclose(value.double(), (a[key].double() + b[key].double()) / 2,
                                  atol=1e-6), key
        else:
            assert torch.equal(value, a[key]), key
    source = read_checkpoint(out)["source"]
    assert [entry["checkpoint"] for entry in source["averaged"]] == [eval_checkpoint.name,
                                                                     "other.pt"]
    # The baseline describes the averaged weights: recomputed with the loaded network.
    predictor = load_model(out)
    expected = baseline_prediction(predictor, train_dataset, 4)
    for got, want in zip(predictor.baseline, expected, strict=True):
        assert torch.allclose(got, want, atol=1e-5)
    # Without --data no baseline is stored, and the command says so.
    bare = tmp_path / "bare.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), str(other), "--out",
                 str(bare)]) == 0
    assert "baseline: none stored" in capsys.readouterr().out
    assert load_model(bare).baseline is None


def test_export_of_one_checkpoint_twice_predicts_as_the_checkpoint(eval_checkpoint, tmp_path,
                                                                   capsys):
    import shutil

    single, twice = tmp_path / "single.pt", tmp_path / "twice.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--no-half", "--out",
                 str(single)]) == 0
    # One file named twice is a slip (it would weigh that run double among others): refused.
    assert main(["export", "--checkpoint", str(eval_checkpoint), str(eval_checkpoint),
                 "--no-half", "--out", str(twice)]) == 2
    assert error_line(capsys).endswith(f"checkpoint {eval_checkpoint}: given twice (as "
                                       f"{eval_checkpoint}); give each run's checkpoint once")
    assert not twice.exists()
    linked = tmp_path / "linked.pt"  # a hard link is the same file under another name
    os.link(eval_checkpoint, linked)
    assert main(["export", "--checkpoint", str(eval_checkpoint), str(linked),
                 "--no-half", "--out", str(twice)]) == 2
    assert error_line(capsys).endswith(f"checkpoint {linked}: given twice (as "
                                       f"{eval_checkpoint}); give each run's checkpoint once")
    assert not twice.exists()
    copy = shutil.copy(eval_checkpoint, tmp_path / "copy.pt")  # the average of equal weights
    assert main(["export", "--checkpoint", str(eval_checkpoint), str(copy),
                 "--no-half", "--out", str(twice)]) == 0
    images = torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(2))
    a, b = load_model(single).predict(images), load_model(twice).predict(images)
    assert torch.equal(a.assembly.params, b.assembly.params)
    assert torch.equal(a.rotation, b.rotation)


def _another_depth_prior(payload):  # the same weights' shapes, another network
    payload["config"]["network"]["depth_prior"] = 2.5


def _another_camera(payload):
    import dataclasses

    from sq_mitsuba.geometry.camera import Camera

    camera = Camera.from_speed_dict(payload["camera"])  # a whole other camera, consistent
    payload["camera"] = dataclasses.replace(camera, fx=camera.fx * 1.1).to_speed_dict()


@pytest.mark.parametrize(("change", "named"), [(_another_depth_prior, "network.depth_prior"),
                                               (_another_camera, "camera differs")])
def test_export_refuses_to_average_different_networks(eval_checkpoint, tmp_path, capsys,
                                                      change, named):
    other = _perturbed(eval_checkpoint, tmp_path / "other.pt", 3, change)
    out = tmp_path / "out" / "soup.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), str(other), "--out",
                 str(out)]) == 2
    line = error_line(capsys)
    assert "other.pt" in line
    assert named in line
    assert not out.parent.exists()


def test_average_weights_names_the_weight_that_differs():
    from sq_mitsuba.model.weight_average import average_weights

    a = {"w": torch.zeros(2, 3), "steps": torch.tensor(4)}
    with pytest.raises(ValueError, match=r"b\.pt: lacks weight 'w'"):
        average_weights([a, {"steps": torch.tensor(4)}], ["a.pt", "b.pt"])
    with pytest.raises(ValueError, match=r"b\.pt: weight 'w' is torch.float32 \(3, 2\)"):
        average_weights([a, {"w": torch.zeros(3, 2), "steps": torch.tensor(4)}],
                        ["a.pt", "b.pt"])
    mean = average_weights([a, {"w": torch.ones(2, 3), "steps": torch.tensor(9)}, a],
                           ["a.pt", "b.pt", "c.pt"])
    assert torch.equal(mean["w"], torch.full((2, 3), 1 / 3))
    assert int(mean["steps"]) == 4  # integer counters: the first file's


def test_export_averages_a_file_written_before_a_network_field_existed(eval_checkpoint,
                                                                      tmp_path):
    def older(payload):  # a file from before network.depth_head: it holds the default
        payload["config"]["network"].pop("depth_head")

    other = _perturbed(eval_checkpoint, tmp_path / "older.pt", 4, older)
    assert main(["export", "--checkpoint", str(eval_checkpoint), str(other), "--out",
                 str(tmp_path / "soup.pt")]) == 0


def test_average_weights_of_half_and_single_precision_files():
    from sq_mitsuba.model.weight_average import average_weights

    single = {"w": torch.tensor([1.0, 2.0])}
    half = {"w": torch.tensor([2.0, 4.0], dtype=torch.float16)}
    mean = average_weights([single, half], ["single.pt", "half.pt"])
    assert mean["w"].dtype == torch.float32 and torch.equal(mean["w"], torch.tensor([1.5, 3.0]))
    mixed = average_weights([single, half], ["single.pt", "half.pt"], [0.75, 0.25])
    assert torch.equal(mixed["w"], torch.tensor([1.25, 2.5]))
    with pytest.raises(ValueError, match="coefficients summing to 1"):
        average_weights([single, half], ["single.pt", "half.pt"], [0.5, 0.25])
    with pytest.raises(ValueError, match=r"half\.pt: weight 'w' is torch.int64"):
        average_weights([single, {"w": torch.tensor([2, 4])}], ["single.pt", "half.pt"])


def _seeded(seed: int):
    def change(payload):  # a run's config records the seed that drew its new layers
        payload["config"]["seed"] = seed
    return change


def test_export_goes_part_way_back_to_the_start(eval_checkpoint, tmp_path, capsys):
    """--start S --start-share s: s x the start + (1 - s) x the fine-tunes' average, element
    by element (the start already the fine-tunes' network: nothing to grow), with the start
    named in the source by file and content digest."""
    import hashlib

    start = _perturbed(eval_checkpoint, tmp_path / "start.pt", 5, _seeded(7))
    a = _perturbed(eval_checkpoint, tmp_path / "a.pt", 6, _seeded(7))
    b = _perturbed(eval_checkpoint, tmp_path / "b.pt", 7, _seeded(7))
    out = tmp_path / "wise.pt"
    assert main(["export", "--checkpoint", str(a), str(b), "--start", str(start),
                 "--start-share", "0.25", "--no-half", "--out", str(out)]) == 0
    got = read_checkpoint(out)["model"]
    s, fa, fb = (read_checkpoint(path)["model"] for path in (start, a, b))
    for key, value in got.items():
        if value.is_floating_point():
            want = 0.25 * s[key].double() + 0.75 * (fa[key].double() + fb[key].double()) / 2
            assert torch.allclose(value.double(), want, atol=1e-6), key
    source = read_checkpoint(out)["source"]
    assert [entry["checkpoint"] for entry in source["averaged"]] == ["a.pt", "b.pt"]
    assert source["start"] == {"checkpoint": "start.pt", "share": 0.25, "sha256":
                               hashlib.sha256(start.read_bytes()).hexdigest()}
    # One fine-tune and its start, halfway: the start's share is what moves the weights.
    half = tmp_path / "half.pt"
    assert main(["export", "--checkpoint", str(a), "--start", str(start), "--no-half",
                 "--out", str(half)]) == 0
    weights = read_checkpoint(half)["model"]
    key = next(k for k, v in weights.items() if v.is_floating_point())
    assert torch.allclose(weights[key].double(), (s[key].double() + fa[key].double()) / 2,
                          atol=1e-6)
    assert "baseline: none stored" in capsys.readouterr().out


def test_export_with_a_start_refuses_other_seeds_and_whole_shares(eval_checkpoint, tmp_path,
                                                                  capsys):
    start = _perturbed(eval_checkpoint, tmp_path / "start.pt", 5, _seeded(7))
    a = _perturbed(eval_checkpoint, tmp_path / "a.pt", 6, _seeded(7))
    b = _perturbed(eval_checkpoint, tmp_path / "b.pt", 7, _seeded(8))
    out = tmp_path / "out" / "wise.pt"
    assert main(["export", "--checkpoint", str(a), str(b), "--start", str(start), "--out",
                 str(out)]) == 2
    line = error_line(capsys)
    assert "b.pt: config.seed is 8" in line
    assert main(["export", "--checkpoint", str(a), "--start", str(start), "--start-share",
                 "1", "--out", str(out)]) == 2
    assert "--start-share: expected a value in [0, 0.99], got 1" in error_line(capsys)
    missing = tmp_path / "no_start.pt"
    assert main(["export", "--checkpoint", str(a), "--start", str(missing), "--out",
                 str(out)]) == 2
    assert "no_start.pt" in error_line(capsys)
    assert not out.parent.exists()


def _with_existence(eval_checkpoint, path):
    """The tiny network grown to existence logits (as ``init_from`` grows it: every primitive
    present at 0.9), seed 7 recorded: the start of existence fine-tunes."""
    import dataclasses

    from sq_mitsuba.model.checkpoint import (
        checkpoint_network_config,
        load_weights,
        write_checkpoint,
    )
    from sq_mitsuba.model.network import SuperquadricNet

    payload = read_checkpoint(eval_checkpoint)
    config = dataclasses.replace(checkpoint_network_config(payload, "tiny"), existence=True,
                                 pretrained=None)
    torch.manual_seed(7)
    model = SuperquadricNet(config)
    load_weights(model, payload["model"], "tiny", partial=True)
    payload["model"] = {key: value.detach().clone() for key, value in model.state_dict().items()}
    payload["config"]["network"] = {**payload["config"]["network"], "existence": True}
    payload["config"]["seed"] = 7
    return write_checkpoint(path, payload)


def test_export_keeps_the_fine_tunes_existence_logits_when_asked(eval_checkpoint, tmp_path,
                                                                  capsys):
    """--keep-existence: the existence column of the generators' last layer is the fine-tunes'
    average, every other weight the start's share mixed in as before; without it that column
    is mixed too. Refused without --start and for a network without existence logits."""
    from sq_mitsuba.geometry.assembly import NUM_PARAMS
    from sq_mitsuba.model.weight_average import existence_keys

    start = _with_existence(eval_checkpoint, tmp_path / "start.pt")
    a = _perturbed(start, tmp_path / "a.pt", 6)
    b = _perturbed(start, tmp_path / "b.pt", 7)
    s, fa, fb = (read_checkpoint(path)["model"] for path in (start, a, b))
    keys = existence_keys(s)
    assert keys == ["sq_generator.layers.2.weight", "sq_generator.layers.2.bias"]
    outputs = {}
    for name, extra in (("kept", ["--keep-existence"]), ("mixed", [])):
        outputs[name] = tmp_path / f"{name}.pt"
        assert main(["export", "--checkpoint", str(a), str(b), "--start", str(start),
                     "--start-share", "0.75", "--no-half", "--out", str(outputs[name]),
                     *extra]) == 0
    kept, mixed = (read_checkpoint(outputs[name])["model"] for name in ("kept", "mixed"))
    for key in s:
        if not s[key].is_floating_point():
            continue
        mix = 0.75 * s[key].double() + 0.25 * (fa[key].double() + fb[key].double()) / 2
        torch.testing.assert_close(mixed[key].double(), mix, atol=1e-6, rtol=0)
        want = mix.clone()
        if key in keys:
            want[..., NUM_PARAMS] = (fa[key].double() + fb[key].double())[..., NUM_PARAMS] / 2
            assert not torch.allclose(want, mix)  # the column differs from the mix
        torch.testing.assert_close(kept[key].double(), want, atol=1e-6, rtol=0)
    assert read_checkpoint(outputs["kept"])["source"]["start"]["existence"] == \
        "the fine-tunes' average"
    # The real case: a start without existence logits, grown by the export as training grew
    # it (seed 7 draws the same column): the same file.
    grown = tmp_path / "grown.pt"
    assert main(["export", "--checkpoint", str(a), str(b), "--start", str(eval_checkpoint),
                 "--start-share", "0.75", "--no-half", "--keep-existence", "--out",
                 str(grown)]) == 0
    for key, value in read_checkpoint(grown)["model"].items():
        if value.is_floating_point():
            torch.testing.assert_close(value, kept[key], atol=1e-6, rtol=0)
    from sq_mitsuba.apps.export import ExportOptions, export_model

    with pytest.raises(ValueError, match=r"^keep_existence: only with a start"):
        export_model(a, None, tmp_path / "api.pt", ExportOptions(keep_existence=True))
    capsys.readouterr()
    assert main(["export", "--checkpoint", str(a), "--keep-existence", "--out",
                 str(tmp_path / "no_start.pt")]) == 2
    assert "--keep-existence: only with --start" in error_line(capsys)
    plain_a = _perturbed(eval_checkpoint, tmp_path / "plain_a.pt", 6, _seeded(7))
    plain_start = _perturbed(eval_checkpoint, tmp_path / "plain_start.pt", 5, _seeded(7))
    assert main(["export", "--checkpoint", str(plain_a), "--start", str(plain_start),
                 "--keep-existence", "--out", str(tmp_path / "plain.pt")]) == 2
    assert "plain_a.pt: keep_existence needs a network whose slots carry existence" in \
        error_line(capsys)
    assert not any((tmp_path / name).exists() for name in ("no_start.pt", "plain.pt", "api.pt"))


def test_export_replaces_an_exported_model_and_nothing_else(eval_checkpoint, tmp_path, capsys):
    """An existing --out is replaced only where it is an exported model (re-exporting): a
    training run's last.pt (what --resume needs), a checkpoint without an export's record and
    any other file are refused before anything is written, and kept byte for byte."""
    from sq_mitsuba.model.checkpoint import write_checkpoint

    payload = read_checkpoint(eval_checkpoint)
    run = tmp_path / "run"
    training = write_checkpoint(run / "last.pt", {
        **payload, "optimizer": {"state": {}, "param_groups": []}, "scheduler": {}})
    picture = tmp_path / "figure.png"
    Image.new("L", (4, 4), 128).save(picture)
    camera = tmp_path / "camera.json"
    camera.write_text('{"fx": 1}\n')
    for path, named in ((training, "a training checkpoint"),
                        (tmp_path / "hand.pt", "not an exported model"),
                        (picture, "not an sq_mitsuba checkpoint"),
                        (camera, "not an sq_mitsuba checkpoint")):
        if not path.exists():  # a checkpoint of this project with no export's record
            write_checkpoint(path, payload)
        before = path.read_bytes()
        assert main(["export", "--checkpoint", str(eval_checkpoint), "--out", str(path)]) == 2
        line = error_line(capsys)
        assert f"out {path}: " in line and named in line, line
        assert line.endswith("export replaces only an exported model: choose another --out")
        assert path.read_bytes() == before
    assert sorted(p.name for p in run.iterdir()) == ["last.pt"]  # no temporary left behind
    # An exported model is replaced: exported in half precision, then again in full.
    model = tmp_path / "model.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--out", str(model)]) == 0
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--no-half", "--out",
                 str(model)]) == 0
    weights = [v for v in read_checkpoint(model)["model"].values() if v.is_floating_point()]
    assert weights and all(v.dtype == torch.float32 for v in weights)


def _dataset_copy(train_dataset, path):
    """A copy of the training fixture's dataset, to damage."""
    import shutil

    return shutil.copytree(train_dataset, path)


def test_export_refuses_an_out_inside_a_dataset_folder(eval_checkpoint, train_dataset,
                                                       tmp_path, capsys):
    """Inside --data, or inside any folder holding a dataset.json: refused before writing (the
    file would become part of a dataset that export only reads)."""
    for out in (train_dataset / "model.pt", train_dataset / "new" / "model.pt"):
        assert main(["export", "--checkpoint", str(eval_checkpoint), "--out", str(out)]) == 2
        assert error_line(capsys).endswith(
            f"out {out}: inside the dataset folder {train_dataset.resolve()}, which export only "
            "reads; write outside it")
        assert not out.exists() and not (train_dataset / "new").exists()
    data = _dataset_copy(train_dataset, tmp_path / "data")
    (data / "dataset.json").unlink()  # a dataset without a manifest (the SPE3R release's)
    out = data / "model.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--data", str(data),
                 "--out", str(out)]) == 2
    assert error_line(capsys).endswith(f"out {out}: inside the dataset folder {data}, which "
                                       "export only reads; write outside it")
    assert not out.exists()


def test_export_without_training_images_says_to_leave_data_out(eval_checkpoint, train_dataset,
                                                               tmp_path, capsys):
    """A --data whose train split is empty (its labels gone): the way out is export's own
    (leave --data out), not eval's --no-baseline, and each model left out is said once; with
    one train model left the baseline is computed, the other's warning said once too."""
    data = _dataset_copy(train_dataset, tmp_path / "data")
    train_models = [line.split(",")[0] for line in (data / "splits.csv").read_text().split()
                    if line.endswith(",train")]
    assert len(train_models) == 2
    (data / train_models[0] / "labels.json").unlink()
    out = tmp_path / "out" / "model.pt"
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--data", str(data),
                 "--baseline-images", "2", "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(
        f"{data / train_models[0] / 'labels.json'}: missing; model {train_models[0]} left out "
        "of the train split"), err
    out.unlink()
    (data / train_models[1] / "labels.json").unlink()
    assert main(["export", "--checkpoint", str(eval_checkpoint), "--data", str(data),
                 "--out", str(out)]) == 2
    *warned, error = capsys.readouterr().err.strip().splitlines()
    assert len(warned) == 2 and len(set(warned)) == 2, warned
    assert error.endswith(f"{data}: no images for the baseline (its 'train' split is empty); "
                          "give the training dataset as --data, or leave --data out to store "
                          "no baseline")
    assert not out.exists()


def test_an_out_that_ends_in_a_separator_is_a_folder_not_a_file(eval_checkpoint, train_dataset,
                                                                tmp_path, capsys):
    """``--out newdir/`` wrote a file named newdir (exit 0): refused, nothing written."""
    out = f"{tmp_path / 'newdir'}/"
    with pytest.raises(SystemExit) as exited:  # argparse's own refusal of the argument
        main(["export", "--checkpoint", str(eval_checkpoint), "--data", str(train_dataset),
              "--out", out])
    assert exited.value.code == 2
    assert "ends in a separator, a folder; give the file to write in it" in error_line(capsys)
    assert not (tmp_path / "newdir").exists()
