"""Part targets: the per-primitive costs against a brute-force loop, the Hungarian pairing
against every permutation, the matched loss's gradient against finite differences (float64),
a fit that recovers a known assembly's surface, the files' round trip and one-line errors, and
the ``parts`` term training two steps."""

from __future__ import annotations

import itertools
import re
import shutil

import numpy as np
import pytest
import torch

from sq_mitsuba.cli import main
from sq_mitsuba.config import apply_overrides
from sq_mitsuba.data.spe3r.layout import read_splits
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.model.losses import surface_chamfer_loss
from sq_mitsuba.model.network import SuperquadricNet, initial_raw, sphere_directions
from sq_mitsuba.model.network_config import NetworkConfig
from sq_mitsuba.model.part_targets import (
    fit_to_surface,
    matched_part_loss,
    part_costs,
    part_matching,
)
from sq_mitsuba.training.config import load_train_config
from sq_mitsuba.training.part_targets import (
    PartTargetError,
    fit_part_targets,
    load_part_targets,
    part_targets_path,
)
from sq_mitsuba.training.train import TrainError, train
from tests.test_loss_terms import TINY


def _random_assembly(items: int, count: int, seed: int) -> Assembly:
    generator = torch.Generator().manual_seed(seed)
    return Assembly.from_raw(torch.randn(items, count, 16, generator=generator,
                                         dtype=torch.float64))


def test_part_costs_equal_a_loop_over_pairs_of_primitives():
    pred, target = _random_assembly(2, 3, 0), _random_assembly(2, 3, 1)
    costs = part_costs(pred, target, level=1)
    a, b = pred.surface_points(1), target.surface_points(1)
    for item, i, j in itertools.product(range(2), range(3), range(3)):
        d = ((a[item, i][:, None] - b[item, j][None]) ** 2).sum(-1)
        expected = d.min(1).values.mean() + d.min(0).values.mean()
        assert float(costs[item, i, j]) == pytest.approx(float(expected), rel=1e-9)


def test_the_pairing_is_the_cheapest_of_every_permutation():
    costs = torch.rand(6, 4, 4, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    pairs = part_matching(costs)
    for item in range(6):
        assert sorted(pairs[item].tolist()) == [0, 1, 2, 3]
        chosen = sum(float(costs[item, i, pairs[item, i]]) for i in range(4))
        best = min(sum(float(costs[item, i, p[i]]) for i in range(4))
                   for p in itertools.permutations(range(4)))
        assert chosen == pytest.approx(best, rel=1e-12)


def test_the_matched_loss_is_zero_for_the_target_in_any_order_and_positive_otherwise():
    target = _random_assembly(3, 5, 4)
    shuffled = Assembly(target.params[:, torch.tensor([3, 0, 4, 1, 2])])
    assert float(matched_part_loss(shuffled, target)) == pytest.approx(0.0, abs=1e-12)
    assert float(matched_part_loss(_random_assembly(3, 5, 5), target)) > 1e-3
    with pytest.raises(ValueError, match="differ in shape"):
        matched_part_loss(_random_assembly(3, 4, 5), target)


def test_the_matched_loss_gradient_matches_finite_differences():
    raw = torch.randn(1, 3, 16, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    target = _random_assembly(1, 3, 7)
    # Pairing fixed in a neighbourhood of a generic point: the loss is smooth there.
    assert torch.autograd.gradcheck(
        lambda r: matched_part_loss(Assembly.from_raw(r), target, level=1),
        (raw.requires_grad_(True),), eps=1e-6, atol=1e-5)


def test_the_initial_layout_is_the_networks_own_first_reading():
    raw = initial_raw(4, spread=0.25)
    assembly = Assembly.from_raw(raw)
    assert torch.allclose(assembly.translation[0], 0.25 * sphere_directions(4), atol=1e-12)
    torch.manual_seed(0)
    network = SuperquadricNet(NetworkConfig(num_primitives=4, image_size=64, latent_dim=16,
                                            hidden_dim=16, pretrained=None))
    bias = network.sq_generator.layers[2].bias.detach().double()
    assert torch.allclose(bias[:, :16], raw[0], atol=1e-6)


def test_a_fit_from_the_initial_layout_recovers_a_known_assemblys_surface():
    truth = Assembly.from_values(size=torch.tensor([[[0.25, 0.08, 0.08], [0.06, 0.06, 0.2]]]),
                                 shape=torch.tensor([[[0.3, 0.3], [0.8, 0.8]]]),
                                 translation=torch.tensor([[[0.05, 0.0, 0.0],
                                                            [-0.15, 0.0, 0.1]]]))
    target = truth.surface_points(3).reshape(1, -1, 3).double()
    start = surface_chamfer_loss(Assembly.from_raw(initial_raw(2)), target, 2)
    raw, final = fit_to_surface(target, 2, steps=300)
    assert raw.shape == (1, 2, 16) and final.shape == (1,)
    assert float(final[0]) < 0.05 * float(start)
    assert float(final[0]) == pytest.approx(
        float(surface_chamfer_loss(Assembly.from_raw(raw), target, 2)), rel=1e-9)


def test_part_target_files_round_trip_and_bad_ones_are_one_line_errors(train_dataset, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(train_dataset, data)
    models = sorted(p.name for p in data.iterdir() if (p / "labels.json").is_file())
    with pytest.raises(PartTargetError, match=r"missing .*dataset fit-parts") as missing:
        load_part_targets(data, models, 2)
    assert "\n" not in str(missing.value)
    assert fit_part_targets(data, models[:2], 2, steps=5, progress=False).fitted == 2
    assert fit_part_targets(data, models[:2], 2, steps=5, progress=False).fitted == 0  # resumes
    table = load_part_targets(data, models[:2], 2)
    assert table.shape == (2, 2, 16) and torch.isfinite(table).all()
    with np.load(part_targets_path(data, models[0])) as archive:
        assert np.allclose(archive["raw"], table[0].double().numpy(), atol=1e-6)
        assert int(archive["steps"]) == 5
    with pytest.raises(PartTargetError, match="the network has 3"):
        load_part_targets(data, models[:2], 3)
    part_targets_path(data, models[1]).write_bytes(b"not an archive")
    with pytest.raises(PartTargetError, match="cannot read part targets"):
        load_part_targets(data, models[:2], 2)
    np.savez(part_targets_path(data, models[1]), raw=np.full((2, 16), np.nan))
    with pytest.raises(PartTargetError, match="NaN"):
        load_part_targets(data, models[:2], 2)
    # A file cut in half (a zip archive without its directory) is refused naming it, and
    # fit-parts fits that model again instead of stopping.
    path = part_targets_path(data, models[0])
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    with pytest.raises(PartTargetError, match=f"{re.escape(str(path))}: cannot read"):
        load_part_targets(data, models[:1], 2)
    assert fit_part_targets(data, models[:1], 2, steps=5, progress=False).fitted == 1
    assert load_part_targets(data, models[:1], 2).shape == (1, 2, 16)


def test_the_parts_term_trains_once_the_targets_are_fitted(train_dataset, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(train_dataset, data)
    config = apply_overrides(load_train_config(TINY), ["loss.weights.parts=1.0",
                                                       "validation.every=0"])
    with pytest.raises(TrainError, match=r"loss\.weights\.parts: .*missing"):
        train(config, data, tmp_path / "refused", progress=False, max_steps=1)
    assert not (tmp_path / "refused").exists()
    primitives = config.network.num_primitives
    assert main(["dataset", "fit-parts", str(data), "--primitives", str(primitives),
                 "--steps", "5", "--quiet"]) == 0
    assert "part targets of 2 train models" in capsys.readouterr().out
    result = train(config, data, tmp_path / "run", progress=False, max_steps=2)
    assert result.steps == 2
    rows = (tmp_path / "run" / "log.csv").read_text().splitlines()
    header = rows[0].split(",")
    values = [float(v) for v in rows[-1].split(",")[header.index("parts"):][:1]]
    assert values[0] > 0


def test_a_rerun_with_other_settings_fits_again_and_says_so(train_dataset, tmp_path, capsys):
    """`fit-parts --steps 7` after a 3-step run replaces the 3-step fits (it kept them
    silently), naming the earlier setting; the same settings again keep every fit."""
    data = tmp_path / "data"
    shutil.copytree(train_dataset, data)
    fit_parts = ["dataset", "fit-parts", str(data), "--primitives", "2", "--quiet"]
    paths = [part_targets_path(data, model) for model, split
             in read_splits(data / "splits.csv").items() if split == "train"]
    assert len(paths) == 2
    assert main([*fit_parts, "--steps", "3"]) == 0
    assert "2 fitted, 0 already there" in capsys.readouterr().out
    assert main([*fit_parts, "--steps", "7"]) == 0
    out = capsys.readouterr().out
    assert "2 fitted (2 of them fitted again: made with --steps 3 (2)), 0 already there" in out
    for path in paths:
        with np.load(path) as archive:
            assert (int(archive["steps"]), int(archive["points"])) == (7, 1000)
    assert main([*fit_parts, "--steps", "7"]) == 0
    assert "0 fitted, 2 already there" in capsys.readouterr().out


def test_a_fit_without_a_record_of_its_settings(train_dataset, tmp_path):
    """A file from before `points` was recorded counts as made with the 1,000 points every
    fit drew then (kept); one without `steps` (never written by fit-parts) is fitted again."""
    data = tmp_path / "data"
    shutil.copytree(train_dataset, data)
    models = sorted(p.name for p in data.iterdir() if (p / "labels.json").is_file())[:2]
    assert fit_part_targets(data, models, 2, steps=3, progress=False).fitted == 2
    for model, keep in zip(models, (("raw", "chamfer", "steps"), ("raw", "chamfer")),
                           strict=True):
        path = part_targets_path(data, model)
        with np.load(path) as archive:
            arrays = {k: archive[k] for k in keep}
        np.savez(path, **arrays)
    fits = fit_part_targets(data, models, 2, steps=3, progress=False)
    assert fits.fitted == 1 and fits.refitted == {models[1]: "--steps not recorded"}
    fits = fit_part_targets(data, models, 2, steps=3, points=500, progress=False)
    assert fits.refitted == {models[0]: "points 1000", models[1]: "points 1000"}
    fits = fit_part_targets(data, models, 3, steps=3, points=500, progress=False)
    assert fits.refitted == {model: "--primitives 2" for model in models}


@pytest.mark.parametrize("argv, message", [
    (["--primitives", "0"], "--primitives: expected 1-64"),
    (["--steps", "0"], "--steps: expected 1-100000"),
])
def test_fit_parts_refuses_bad_options_in_one_line(train_dataset, capsys, argv, message):
    assert main(["dataset", "fit-parts", str(train_dataset), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_fit_parts_refuses_a_folder_that_is_not_a_dataset(tmp_path, capsys):
    assert main(["dataset", "fit-parts", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "splits.csv: missing" in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_fit_to_surface_refuses_wrong_shapes():
    with pytest.raises(ValueError, match="target"):
        fit_to_surface(torch.zeros(2, 10, 2), 3, steps=1)
    with pytest.raises(ValueError, match="start"):
        fit_to_surface(torch.zeros(2, 10, 3), 3, steps=1, start=initial_raw(4))


def test_a_fit_made_with_more_steps_than_asked_is_fitted_again(train_dataset, tmp_path):
    """Other settings means other, either way: a 7-step fit is not kept by a 3-step run."""
    data = tmp_path / "data"
    shutil.copytree(train_dataset, data)
    models = sorted(p.name for p in data.iterdir() if (p / "labels.json").is_file())[:2]
    assert fit_part_targets(data, models, 2, steps=7, progress=False).fitted == 2
    fits = fit_part_targets(data, models, 2, steps=3, progress=False)
    assert fits.fitted == 2 and fits.refitted == {model: "--steps 7" for model in models}
    for model in models:
        with np.load(part_targets_path(data, model)) as archive:
            assert int(archive["steps"]) == 3
