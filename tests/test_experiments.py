"""The model card's experiment scripts under ``eval/experiments/`` run end to end (two steps on
the tiny fixture dataset), so the commands the card gives keep working."""

from __future__ import annotations

import csv
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sq_mitsuba.geometry.so3_grid import axis_turns

EXPERIMENTS = Path(__file__).resolve().parents[1] / "eval" / "experiments"


def _run_script(command: list[str]) -> subprocess.CompletedProcess:
    """``command`` (``[sys.executable, SCRIPT, *args]``) run in this process with runpy: the
    script's exit code, stdout and stderr, without a second interpreter importing torch and
    Mitsuba again. Only for scripts that change no global state but torch's thread count,
    which is put back (rotation_views.py sets it)."""
    import contextlib
    import io
    import runpy

    assert command[0] == sys.executable
    out, err = io.StringIO(), io.StringIO()
    saved_argv, saved_path = sys.argv, list(sys.path)
    sys.argv = [str(part) for part in command[1:]]
    sys.path.insert(0, str(EXPERIMENTS))  # as python puts a script's folder first
    code = 0
    threads = torch.get_num_threads()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                runpy.run_path(sys.argv[0], run_name="__main__")
            except SystemExit as exit_:
                if exit_.code is None or isinstance(exit_.code, int):
                    code = exit_.code or 0
                else:  # sys.exit("message"): the message on stderr and exit code 1, as python
                    print(exit_.code, file=sys.stderr)
                    code = 1
    finally:
        sys.argv, sys.path[:] = saved_argv, saved_path
        torch.set_num_threads(threads)
    return subprocess.CompletedProcess(command, code, out.getvalue(), err.getvalue())


@pytest.mark.filterwarnings("ignore:optim.batch_size")  # the study's batch of 32 on 12 images
# Two steps of a schedule that warms up over 50: the trainer says so, rightly, for this test.
@pytest.mark.filterwarnings("ignore:optim.warmup_steps. a warm-up of 50 steps:UserWarning")
def test_rotation_views_trains_and_scores_both_view_sets(train_dataset, tmp_path):
    """The experiment is a run of the real trainer: its log holds the pose terms alone."""
    data = tmp_path / "data"
    shutil.copytree(train_dataset, data)
    command = [sys.executable, str(EXPERIMENTS / "rotation_views.py"), str(data), "--steps", "2",
               "--views", "12", "--threads", "1"]
    result = _run_script(command)
    assert result.returncode == 0, result.stderr
    assert "12 training views" in result.stdout
    match = re.search(r"step 2: loss ([\d.]+), median E_R training views ([\d.]+) deg, "
                      r"held-out views ([\d.]+) deg", result.stdout)
    assert match, result.stdout
    assert all(0 <= float(value) <= 180 for value in match.groups()[1:])
    run = data / "rotation_views_runs" / "rotation_6d_12"
    with open(run / "log.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [int(r["step"]) for r in rows] == [1, 2]
    assert {k for k, v in rows[0].items() if v} == {"step", "epoch", "lr", "loss", "rotation_6d",
                                                    "translation", "grad_norm", "images_per_s"}
    assert abs(float(rows[-1]["loss"]) - float(match.group(1))) < 1e-3  # printed to 3 places
    # The cache a second run reads: both splits, images with their rotations and translations.
    train, val = torch.load(data / "rotation_views.pt", weights_only=True)
    for images, rotations, translations in (train, val):
        assert images.shape[1:] == (1, 96, 96) and rotations.shape == (len(images), 3, 3)
        assert translations.shape == (len(images), 3) and len(images) > 0
    assert len(train[0]) >= 12


def test_shape_capacity_fits_the_networks_assemblies_to_the_meshes(train_dataset,
                                                                   eval_checkpoint):
    """The fit is a real optimisation: 20 Adam steps on the Chamfer term bring the assembly
    nearer to every model's surface than the network's start."""
    command = [sys.executable, str(EXPERIMENTS / "shape_capacity.py"), str(train_dataset),
               "--split", "val", "--checkpoint", str(eval_checkpoint), "--steps", "20",
               "--points", "500", "--start-exponent", "0.2", "--occupancy-weight", "1"]
    result = _run_script(command)
    assert result.returncode == 0, result.stderr
    assert "2 val models" in result.stdout and "M = 2, occupancy weight 1" in result.stdout
    per_model = [line.split(" | ") for line in result.stdout.splitlines()
                 if line.startswith("sc")]
    assert len(per_model) == 2
    for _, network, fitted, _from_boxes in per_model:
        assert float(fitted) < float(network)
    totals = {line.split(" | ")[0]: line.split(" | ")[1:] for line in result.stdout.splitlines()
              if line.startswith(("network |", "fit "))}
    assert set(totals) == {"network", "fit (20 steps)", "fit from exponents 0.2"}
    for mean_chamfer, median_chamfer, mean_exponent, box_share in totals.values():
        assert float(mean_chamfer) > 0 and float(median_chamfer) > 0
        assert 0 < float(mean_exponent) < 1 and 0 <= float(box_share) <= 1


def test_shape_capacity_from_the_baseline_needs_a_checkpoint_that_stores_one(train_dataset,
                                                                            eval_checkpoint):
    """--from-baseline on a checkpoint without a trivial baseline: one line, exit 2."""
    command = [sys.executable, str(EXPERIMENTS / "shape_capacity.py"), str(train_dataset),
               "--split", "val", "--checkpoint", str(eval_checkpoint), "--steps", "2",
               "--points", "100", "--from-baseline"]
    result = _run_script(command)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1].endswith("holds no trivial baseline")


def _summary(folder: Path, rows: dict[tuple[str, str], tuple[float, float]]) -> None:
    folder.mkdir(parents=True)
    lines = ["method,metric,mean,std,median,images"]
    lines += [f"{m},{k},{mean},0,{median},10" for (m, k), (mean, median) in rows.items()]
    (folder / "summary.csv").write_text("\n".join(lines) + "\n")


def test_generalisation_row_reads_the_four_evaluations(tmp_path):
    """The row's margin and ratio are computed from the summaries (0.12 against 0.15: 20 %
    below; 0.05 against 0.1: 0.5 x); a missing evaluation prints as '-'."""
    _summary(tmp_path / "m_heldout", {
        ("network", "chamfer_l1_paper"): (0.12, 0.11),
        ("baseline", "chamfer_l1_paper"): (0.15, 0.1),
        ("network", "camera_chamfer"): (0.05, 0.0), ("baseline", "camera_chamfer"): (0.1, 0.0),
        ("network", "iou_2d"): (0.5, 0.5), ("network", "rotation_error_folded_deg"): (40, 41.25)})
    _summary(tmp_path / "m_heldout_refined", {("refined", "iou_2d"): (0.6, 0.6),
                                              ("search", "rotation_error_folded_deg"): (30, 33.5)})
    result = subprocess.run([sys.executable, str(EXPERIMENTS / "generalisation_row.py"),
                             str(tmp_path), "m"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    row = result.stdout.strip().splitlines()[-1]
    assert row == ("| m | 0.1200 (20.0 % below 0.150) | 0.0500 (0.50 x) | 0.500 / 0.600 | "
                   "41.2 / 33.5 deg | - / - / - / - deg |")
    missing = subprocess.run([sys.executable, str(EXPERIMENTS / "generalisation_row.py"),
                              str(tmp_path / "absent"), "m"], capture_output=True, text=True)
    assert missing.returncode == 2 and "not a folder" in missing.stderr
    # A checkpoint exported without --data stores no baseline: its figures without a margin.
    _summary(tmp_path / "n_heldout", {
        ("network", "chamfer_l1_paper"): (0.12, 0.11), ("network", "camera_chamfer"): (0.05, 0.0),
        ("network", "iou_2d"): (0.5, 0.5), ("network", "rotation_error_folded_deg"): (40, 41.25)})
    bare = subprocess.run([sys.executable, str(EXPERIMENTS / "generalisation_row.py"),
                           str(tmp_path), "n"], capture_output=True, text=True, timeout=60)
    assert bare.returncode == 0, bare.stderr
    assert bare.stdout.strip().splitlines()[-1].startswith(
        "| n | 0.1200 (no baseline) | 0.0500 (no baseline) | 0.500 / - |")


def test_generalisation_script_refuses_bad_arguments_before_any_work(tmp_path,
                                                                    eval_checkpoint):
    """A wrong argument count, a missing checkpoint, or one that stores no trivial baseline (a
    training run's, not exported): one line, exit 2, no test set made; the same checkpoint
    with a baseline gets past the check. (An unreadable file takes the check's other exit, the
    reader's one-line error: ``read_checkpoint``'s own tests.)"""
    from sq_mitsuba.model.checkpoint import (
        checkpoint_network_config,
        read_checkpoint,
        write_checkpoint,
    )

    script = str(EXPERIMENTS / "generalisation.sh")
    env = {**os.environ, "PY": sys.executable}
    for argv, message in (([str(tmp_path / "work")], "usage:"),
                          ([str(tmp_path / "work"), str(tmp_path / "absent.pt"), "x"],
                           "checkpoint not found"),
                          ([str(tmp_path / "work"), str(eval_checkpoint), "x"],
                           "stores no trivial baseline")):
        result = subprocess.run(["bash", script, *argv], capture_output=True, text=True,
                                timeout=60, env=env)
        assert result.returncode == 2 and message in result.stderr, result.stderr
        assert result.stderr.strip().count("\n") == 0
        assert not (tmp_path / "work").exists()
    payload = read_checkpoint(eval_checkpoint)
    primitives = checkpoint_network_config(payload, "eval_checkpoint").num_primitives
    payload["baseline"] = {"raw": torch.zeros(1, primitives, 16),
                           "rotation": torch.eye(3)[None], "translation": torch.zeros(1, 3)}
    exported = write_checkpoint(tmp_path / "exported.pt", payload)
    # SQ=false: the first step after the checks (making the test sets) fails at once.
    result = subprocess.run(["bash", script, str(tmp_path / "work"), str(exported), "x"],
                            capture_output=True, text=True, timeout=60,
                            env={**env, "SQ": "false"})
    assert result.returncode not in (0, 2) and (tmp_path / "work" / "eval").is_dir(), \
        result.stderr


def test_body_frame_limits_scores_the_reading_five_ways(train_dataset, eval_checkpoint):
    """The best of the 24 axis rotations (``so3_grid.axis_turns``, 24 distinct proper
    rotations) includes the identity, so it is never worse than the reading as it is."""
    turns = axis_turns()
    assert turns.shape == (24, 3, 3)
    assert torch.allclose(torch.linalg.det(turns), torch.ones(24, dtype=turns.dtype))
    assert len({tuple(t.flatten().tolist()) for t in turns}) == 24
    command = [sys.executable, str(EXPERIMENTS / "body_frame_limits.py"), "--checkpoint",
               str(eval_checkpoint), "--data", str(train_dataset), "--images", "4"]
    result = _run_script(command)
    assert result.returncode == 0, result.stderr
    means = {line.split()[0]: float(line.split()[3]) for line in result.stdout.splitlines()
             if "Chamfer-L1 mean" in line}
    assert set(means) == {"read", "axes_sorted", "oriented_box", "best_of_24", "true_pose"}
    assert 0 < means["best_of_24"] <= means["read"] + 1e-12
    assert "4 images of" in result.stdout


def test_training_fit_scores_training_models_as_a_test_split(train_dataset, eval_checkpoint,
                                                             tmp_path):
    """The script's eval reads exactly the training models it picked (none of the test split);
    asking for more training models than the dataset has is a one-line error before any work."""
    train_models = [line.split(",")[0] for line in
                    (train_dataset / "splits.csv").read_text().splitlines()
                    if line.endswith(",train")]
    prefix = train_models[0][:2]
    out = tmp_path / "fit"
    env = {"SQ": f"{sys.executable} -m sq_mitsuba", "PATH": "/usr/bin:/bin"}
    script = str(EXPERIMENTS / "training_fit.sh")
    result = subprocess.run(["bash", script, str(train_dataset), str(eval_checkpoint), str(out),
                             f"{prefix}:2", "--", "--no-baseline", "--set", "surface_points=500",
                             "--set", "volume_points=2000"],  # which models, not their scores
                            capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr
    with (out / "per_image.csv").open() as handle:
        scored = {row["model"] for row in csv.DictReader(handle)}
    assert scored == set(train_models)
    for pick, message in ((f"{prefix}:9", "asked for 9"), (f"{prefix}:2:2", "asked for 2 every 2"),
                          (f"{prefix}:0", "expected PREFIX:COUNT")):
        failed = subprocess.run(["bash", script, str(train_dataset), str(eval_checkpoint),
                                 str(tmp_path / "refused"), pick],
                                capture_output=True, text=True, timeout=60, env=env)
        assert failed.returncode == 2, pick
        assert failed.stderr.strip().count("\n") == 0 and message in failed.stderr, pick
        assert not list(tmp_path.glob("refused*")), pick


def test_reading_spread_ranks_each_reading_against_every_model(train_dataset, eval_checkpoint):
    """The rank is one more than the models strictly nearer (checked on a small matrix by
    hand), and the script reports ranks within the set and spreads on the fixture."""
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        from reading_spread import own_model_ranks
    finally:
        sys.path.remove(str(EXPERIMENTS))
    distances = np.array([[0.1, 0.3, 0.2], [0.5, 0.4, 0.6], [0.2, 0.2, 0.9]])
    assert own_model_ranks(distances, np.array([0, 0, 1])).tolist() == [1, 2, 1]
    command = [sys.executable, str(EXPERIMENTS / "reading_spread.py"), "--checkpoint",
               str(eval_checkpoint), "--data", str(train_dataset), "--images"]
    one = _run_script([*command, "6"])
    assert one.returncode != 0 and "one model" in one.stderr  # the test split: one model
    result = _run_script([*command, "8", "--split", "train"])
    assert result.returncode == 0, result.stderr
    models = int(re.search(r"8 images of (\d+) models", result.stdout).group(1))
    assert models == 2
    spread = re.search(r"readings (\S+) against the truths' (\S+)", result.stdout)
    # Two different spacecraft lie apart; the fixture's two-step network may read them alike.
    assert float(spread.group(1)) >= 0 and float(spread.group(2)) > 0
    median = float(re.search(r"rank: median (\S+),", result.stdout).group(1))
    assert 1 <= median <= models


def test_half_turn_hedge_measures_asymmetry_and_the_folded_ends(train_dataset, eval_checkpoint):
    """A cloud the half turns leave unchanged has asymmetry 0, a one-sided one does not; a
    truth turned by a half turn is matched exactly once the ends are folded, and its
    symmetric hull contains it (so the hull's distance is the hull's excess only). Then the
    script on the fixture."""
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        from half_turn_hedge import HALF_TURNS, asymmetry, distance, folded
    finally:
        sys.path.remove(str(EXPERIMENTS))
    generator = torch.Generator().manual_seed(0)
    blob = torch.rand(1, 200, 3, generator=generator, dtype=torch.float64) - 0.5
    symmetric = torch.cat([blob[0]] + [blob[0] * turn for turn in HALF_TURNS])[None]
    assert asymmetry(symmetric) < 1e-12
    one_sided = blob + torch.tensor([0.6, 0.0, 0.0], dtype=torch.float64)
    assert asymmetry(one_sided) > 0.3
    turned = one_sided * HALF_TURNS[2]  # a half turn about z flips x: the far side
    assert distance(turned, one_sided) > 0.3
    assert folded(turned, one_sided) < 1e-12
    command = [sys.executable, str(EXPERIMENTS / "half_turn_hedge.py"), "--checkpoint",
               str(eval_checkpoint), "--data", str(train_dataset), "--images", "4"]
    result = _run_script(command)
    assert result.returncode == 0, result.stderr
    read, truth = (float(x) for x in re.search(r"readings (\S+), truths (\S+)",
                                                 result.stdout).groups())
    assert read >= 0 and truth > 0
    as_read, ends = (float(x) for x in re.search(r"as read (\S+), ends folded (\S+)",
                                                   result.stdout).groups())
    assert 0 < ends <= as_read + 1e-9



def test_depth_error_scales_a_reading_without_changing_its_image(train_dataset,
                                                                 eval_checkpoint):
    """unit_scaled makes the longest body-frame side 1 and moves every camera-frame point
    along its ray (the projections are unchanged); then the script on the fixture."""
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        from depth_error import longest_side, unit_scaled
    finally:
        sys.path.remove(str(EXPERIMENTS))
    from sq_mitsuba.geometry.assembly import Assembly
    from sq_mitsuba.geometry.rotation import random_rotations
    from sq_mitsuba.model.losses import counted_surface_samples

    generator = torch.Generator().manual_seed(3)
    assembly = Assembly.from_raw(torch.randn(2, 4, 16, generator=generator,
                                             dtype=torch.float64))
    rotation = random_rotations(2, generator, dtype=torch.float64)
    translation = torch.tensor([[0.2, -0.1, 4.0], [0.0, 0.3, 6.0]], dtype=torch.float64)
    scaled, moved = unit_scaled(assembly, translation)
    torch.testing.assert_close(longest_side(scaled), torch.ones(2, dtype=torch.float64))

    def projected(a: Assembly, t: torch.Tensor) -> torch.Tensor:
        points, _ = counted_surface_samples(a, 2)
        camera = points @ rotation.transpose(1, 2) + t[:, None]
        return camera[..., :2] / camera[..., 2:]

    torch.testing.assert_close(projected(scaled, moved), projected(assembly, translation))
    command = [sys.executable, str(EXPERIMENTS / "depth_error.py"), "--checkpoint",
               str(eval_checkpoint), "--data", str(train_dataset), "--images", "4"]
    result = _run_script(command)
    assert result.returncode == 0, result.stderr
    as_read = re.search(r"as read: camera-frame Chamfer (\S+), translation (\S+) \(depth (\S+),"
                        r" across (\S+),", result.stdout)
    camera, total, depth, across = (float(x) for x in as_read.groups())
    assert camera > 0 and total > 0
    assert max(depth, across) <= total + 1e-9 <= depth + across + 1e-9  # the triangle
    at_true, across_true = (float(x) for x in re.search(
        r"as read: .* at the true position (\S+) \(across the line of sight (\S+)\)",
        result.stdout).groups())
    assert 0 < across_true <= at_true + 1e-9  # nearest in x, y: never farther than in 3D


def test_input_detail_cuts_the_detail_above_its_side(train_dataset, eval_checkpoint):
    """degraded leaves an image at its own side unchanged, keeps a constant image constant,
    turns a one-pixel checkerboard cut to half its side into its mean grey, and keeps a pattern
    coarser than the side; then the script on the fixture prints a line per side."""
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        from input_detail import degraded
    finally:
        sys.path.remove(str(EXPERIMENTS))
    images = torch.rand(2, 1, 16, 16, generator=torch.Generator().manual_seed(4))
    assert torch.equal(degraded(images, 16), images)
    torch.testing.assert_close(degraded(torch.full((1, 1, 16, 16), 0.3), 8),
                               torch.full((1, 1, 16, 16), 0.3))
    checker = (torch.arange(16)[:, None] + torch.arange(16)[None]) % 2
    torch.testing.assert_close(degraded(checker[None, None].float(), 8),
                               torch.full((1, 1, 16, 16), 0.5))
    halves = torch.zeros(1, 1, 16, 16)
    halves[..., 8:] = 1.0  # left half black, right half white: coarser than 8 px
    cut = degraded(halves, 8)
    assert cut[..., :6].max() == 0 and cut[..., 10:].min() == 1
    command = [sys.executable, str(EXPERIMENTS / "input_detail.py"), "--checkpoint",
               str(eval_checkpoint), "--data", str(train_dataset), "--images", "3"]
    result = _run_script(command)
    assert result.returncode == 0, result.stderr
    lines = re.findall(r"detail (\d+) px: body-frame Chamfer-L1 (\S+),", result.stdout)
    assert len(lines) == 4 and all(float(value) > 0 for _, value in lines)


def _per_image(folder: Path, values: dict[tuple[str, int], float]) -> Path:
    folder.mkdir(parents=True)
    lines = ["model,index,method,chamfer_l1_paper"]
    lines += [f"{model},{index},network,{value}" for (model, index), value in values.items()]
    lines += [f"{model},{index},baseline,9" for (model, index) in values]  # never compared
    (folder / "per_image.csv").write_text("\n".join(lines) + "\n")
    return folder


def test_paired_difference_averages_per_model_and_resamples_models(tmp_path):
    """The mean difference is the mean of the per-model means (by hand: model m0's two images
    differ by -0.02 and +0.04, m1's by -0.04, so (0.01 - 0.04) / 2); a difference the same on
    every model has an interval of that one value; no common image is a one-line error."""
    sys.path.insert(0, str(EXPERIMENTS))
    from paired_difference import paired_difference, read_scores

    a = _per_image(tmp_path / "a", {("m0", 0): 0.10, ("m0", 1): 0.16, ("m1", 0): 0.20})
    b = _per_image(tmp_path / "b", {("m0", 0): 0.12, ("m0", 1): 0.12, ("m1", 0): 0.24,
                                    ("m2", 0): 0.5})  # m2: B alone, left out
    result = paired_difference(read_scores(a, "network", "chamfer_l1_paper"),
                               read_scores(b, "network", "chamfer_l1_paper"), 2000)
    assert result["mean"] == pytest.approx(-0.015)
    assert result["models"] == 2 and result["images"] == 3 and result["lower_share"] == 0.5
    assert -0.04 - 1e-12 <= result["low"] <= result["mean"] <= result["high"] <= 0.01 + 1e-12
    same = {(f"m{k}", 0): 0.1 for k in range(5)}
    shifted = {key: value + 0.03 for key, value in same.items()}
    flat = paired_difference(same, shifted, 500)
    assert flat["low"] == pytest.approx(-0.03) and flat["high"] == pytest.approx(-0.03)
    run = subprocess.run([sys.executable, str(EXPERIMENTS / "paired_difference.py"), str(a),
                          str(b), "--metric", "chamfer_l1_paper"],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert "-0.0150" in run.stdout and "within noise" in run.stdout
    other = _per_image(tmp_path / "c", {("x", 0): 0.1})
    refused = subprocess.run([sys.executable, str(EXPERIMENTS / "paired_difference.py"),
                              str(a), str(other)], capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1


def test_library_coverage_ranks_a_library_as_the_exact_distances_do(train_dataset,
                                                                    eval_checkpoint, tmp_path):
    """The coarse-then-exact ranking finds the exact nearest cloud (brute force over random
    clouds), the trees' distance is spread_images.distance, and on images whose own models
    are in the library the oracle row is the smallest and near zero."""
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        from library_coverage import Cloud, nearest_by_size, rough_distances, to_library
        from spread_images import distance
    finally:
        sys.path.remove(str(EXPERIMENTS))
    rng = np.random.default_rng(3)
    clouds = [torch.from_numpy(rng.normal(size=(1, 600, 3)) * rng.uniform(0.2, 1.0, 3))
              for _ in range(20)]
    library = [Cloud(c) for c in clouds]
    for probe in clouds[:4]:
        probe = probe + torch.from_numpy(rng.normal(scale=0.05, size=probe.shape))
        exact = np.array([distance(probe, c) for c in clouds])
        ranked = to_library(Cloud(probe), library)
        assert ranked.argmin() == exact.argmin()
        assert ranked.min() == pytest.approx(exact.min(), rel=1e-12)
    # Nested random subsets of the library, against brute force over each subset.
    probes = [Cloud(c + torch.from_numpy(rng.normal(scale=0.05, size=c.shape)))
              for c in clouds[::3]]
    rough = np.array([rough_distances(p, library) for p in probes])
    by_size = nearest_by_size(probes, library, rough, [5, 12, 20], seed=1)
    order = np.random.default_rng(1).permutation(len(library))
    for size, found in by_size.items():
        brute = [min(p.distance(library[j]) for j in order[:size]) for p in probes]
        assert found == pytest.approx(brute, rel=1e-12), size
    assert np.all(by_size[5] >= by_size[12]) and np.all(by_size[12] >= by_size[20])
    command = [sys.executable, str(EXPERIMENTS / "library_coverage.py"), "--checkpoint",
               str(eval_checkpoint), "--data", str(train_dataset), "--split", "train",
               "--library", str(train_dataset), "--images", "6", "--library-images", "6"]
    result = _run_script([*command, "--turns", "--sizes", "2", "1"])
    assert result.returncode == 0, result.stderr
    rows = dict(re.findall(r"^\| ([a-z][^|]*?) \| (\S+) \|", result.stdout, re.MULTILINE))
    assert set(rows) == {"reading", "library constant", "feature look-up", "reading look-up",
                         "nearest in the library (oracle)",
                         "nearest in the library, any axis turn (oracle)",
                         "nearest among 1 of the library (oracle)",
                         "nearest among 2 of the library (oracle)"}
    # The library's 2 training spacecraft: the larger subset is the whole library.
    assert rows.pop("nearest among 2 of the library (oracle)") == rows[
        "nearest in the library (oracle)"]
    assert float(rows.pop("nearest among 1 of the library (oracle)")) >= float(
        rows["nearest in the library (oracle)"])
    # The turns include the identity: turned, the truth finds its own model again or nearer.
    turned = float(rows.pop("nearest in the library, any axis turn (oracle)"))
    oracle = float(rows.pop("nearest in the library (oracle)"))
    assert turned <= oracle < 0.05 and all(oracle <= float(v) for v in rows.values())
    refused = _run_script([*command[:-1], "0"])
    assert refused.returncode != 0 and "--library-images" in refused.stderr
    drawn = _run_script([*command, "--sizes", "1", "2", "--size-draws", "3", "--plot",
                         str(tmp_path / "sizes.png")])
    assert drawn.returncode == 0, drawn.stderr
    spread_rows = {m[0]: [float(v) for v in m[1:]] for m in re.findall(
        r"^\| (\d+) \| (\S+) \| (\S+) \| (\S+) \|$", drawn.stdout, re.MULTILINE)}
    # The whole library is the same in every order; each mean lies in its range.
    assert spread_rows["2"] == [oracle] * 3
    mean, low, high = spread_rows["1"]
    assert low <= mean <= high
    assert (tmp_path / "sizes.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    refused = _run_script([*command, "--sizes", "3"])
    assert refused.returncode != 0 and "--sizes: the library holds 2" in refused.stderr


def test_structure_axes_reads_the_axes_from_the_visible_normals(train_dataset,
                                                                 eval_checkpoint):
    """With their best axis order told, the network's rotation and the frame of the true
    visible normals are never further from the truth than as read, nor than the cube group's
    covering radius."""
    command = [sys.executable, str(EXPERIMENTS / "structure_axes.py"), "--checkpoint",
               str(eval_checkpoint), "--data", str(train_dataset), "--images", "2", "--edges"]
    result = _run_script(command)
    assert result.returncode == 0, result.stderr
    medians = {line.split()[0]: float(line.split()[1]) for line in result.stdout.splitlines()
               if line.startswith("  ") and "images:" not in line}
    assert set(medians) == {"network", "network_oracle", "true_normals", "true_normals_oracle",
                            "true_depth_oracle", "edges_oracle"}
    assert all(0 <= value <= 180 for value in medians.values())
    # Per image the best order is never worse than the one read, so neither is the median.
    assert medians["true_normals_oracle"] <= medians["true_normals"] + 1e-9
    assert medians["network_oracle"] <= medians["network"] + 1e-9
    assert all(medians[k] <= 62.81 for k in medians if k.endswith("_oracle"))
    assert "over 2 images" in result.stdout


def test_depth_normals_and_edge_frame_read_a_known_plane_and_rectangle() -> None:
    """The normals of a tilted plane's depth map are its analytic normal; a bright rectangle
    drawn along the image axes is explained by the identity's axes and not by a turn of
    30 deg about the line of sight, and the edge frame found on a grid lies on the image axes
    (up to the axes' order and signs)."""
    import math

    sys.path.insert(0, str(EXPERIMENTS))
    try:
        from structure_axes import depth_normals, edge_agreement, edge_frame, edge_pixels
    finally:
        sys.path.remove(str(EXPERIMENTS))
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.geometry.rotation import axis_angle_to_matrix
    from sq_mitsuba.geometry.so3_grid import so3_grid

    camera = Camera.default(96)
    # The plane z = 3 + 0.2 x - 0.1 y seen through the stride-4 cell centres.
    rows, cols = torch.meshgrid(torch.arange(24), torch.arange(24), indexing="ij")
    x = (cols.double().add(0.5).mul(4) - camera.cx) / camera.fx
    y = (rows.double().add(0.5).mul(4) - camera.cy) / camera.fy
    depth = 3.0 / (1.0 - 0.2 * x + 0.1 * y)  # z of each ray's hit: z = 3 + 0.2 xz - 0.1 yz
    normals = depth_normals(depth - 3.0, torch.ones(24, 24, dtype=torch.bool), 3.0, camera)
    expected = torch.nn.functional.normalize(torch.tensor([0.2, -0.1, -1.0],
                                                          dtype=torch.float64), dim=0)
    assert normals.shape == (23 * 23, 3)
    assert torch.allclose(normals, expected.expand_as(normals), atol=1e-6)

    image = np.zeros((96, 96), np.uint8)
    image[30:60, 20:76] = 200
    mask = (image > 0).astype(np.uint8)
    edges = edge_pixels(image, mask, camera, count=10_000)
    assert 300 < len(edges[0]) < 1000  # the outline's pixels only, not the flat ones
    assert torch.allclose(edges[0].norm(dim=1), torch.ones(len(edges[0]), dtype=torch.float64))
    turned = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(30.0)],
                                               dtype=torch.float64))
    upright = edge_agreement(torch.eye(3, dtype=torch.float64)[None], *edges)[0]
    assert upright > 0.9 > 0.2 > edge_agreement(turned[None], *edges)[0]
    frame = edge_frame(*edges, so3_grid(500), steps=20)
    # Two of its axes on the image's u and v axes, whichever they are.
    in_image = frame[:2].abs().amax(dim=0).sort(descending=True).values
    assert bool((in_image[:2] > math.cos(math.radians(5.0))).all())


def test_visible_surface_fit_scores_depth_maps_against_the_truth():
    """A head that reads the true visible depth and a reading that is the truth score 0, a
    head 0.1 m off scores 0.1, and a flat map the true map's mean absolute depth
    (``visible_depth_map`` itself is checked by brute force in test_surface_depth.py)."""
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        from visible_surface_fit import depth_errors
    finally:
        sys.path.remove(str(EXPERIMENTS))
    from sq_mitsuba.geometry.assembly import Assembly
    from sq_mitsuba.model.losses import counted_surface_samples
    from sq_mitsuba.model.surface_depth import visible_depth_map

    params = torch.zeros(1, 2, 16)
    params[0, :, 0:3] = torch.tensor([[0.5, 0.2, 0.2], [0.15, 0.3, 0.1]])
    params[0, :, 3:5] = torch.tensor([[0.3, 0.3], [1.0, 1.0]])
    params[0, :, 5:8] = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.25]])
    params[0, :, 8:14] = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])  # identity rotations
    read = Assembly(params)
    samples, keep = counted_surface_samples(read, 3)
    truth = samples[0][keep[0]].detach()
    rotation, translation = torch.eye(3), torch.tensor([0.0, 0.0, 3.0])
    k = torch.tensor([[60.0, 0.0, 24.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    depth, valid = visible_depth_map(truth[None], rotation[None], translation[None], k, 48, 4)
    errors = depth_errors(depth[0], read, truth, rotation, translation, k, 48, 4)
    assert errors["depth_head"] == pytest.approx(0.0, abs=1e-6)
    assert errors["depth_head_both"] == pytest.approx(0.0, abs=1e-6)
    assert errors["depth_reading_both"] == pytest.approx(0.0, abs=1e-6)
    assert errors["depth_flat"] == pytest.approx(float(depth[valid].abs().mean()), rel=1e-6)
    assert errors["depth_flat"] > 0.05
    shifted = depth_errors(depth[0] + 0.1, read, truth, rotation, translation, k, 48, 4)
    assert shifted["depth_head"] == pytest.approx(0.1, abs=1e-5)


def test_visible_surface_fit_keeps_one_point_per_cell_and_runs(train_dataset,
                                                                eval_checkpoint):
    """The visible points are the nearest of each cell by brute force; the script prints a
    finite body-frame Chamfer-L1 for every fit."""
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        from visible_surface_fit import nearest_per_cell
    finally:
        sys.path.remove(str(EXPERIMENTS))
    from sq_mitsuba.model.surface_depth import cells_at_pose

    generator = torch.Generator().manual_seed(0)
    points = torch.rand(400, 3, generator=generator) - 0.5 + torch.tensor([0.0, 0.0, 3.0])
    k = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]])
    # The camera at the body origin: the points are their own camera-frame coordinates.
    _, flat, side = cells_at_pose(points[None], torch.eye(3)[None], torch.zeros(1, 3), k, 32, 4)
    assert side == 8
    cells = flat[0]
    kept = nearest_per_cell(points, cells, 8)
    for cell in cells.unique().tolist():
        members = (cells == cell).nonzero()[:, 0]
        if cell == 64:  # outside the grid
            assert not bool(kept[members].any())
            continue
        assert kept[members].tolist() == (points[members, 2] == points[members, 2].min()
                                          ).tolist()
    command = [sys.executable, str(EXPERIMENTS / "visible_surface_fit.py"), "--checkpoint",
               str(eval_checkpoint), "--data", str(train_dataset), "--images", "2",
               "--steps", "2", "--pose-steps", "1"]
    result = _run_script(command)
    assert result.returncode == 0, result.stderr
    means = {line.split()[0]: float(line.split()[1]) for line in result.stdout.splitlines()
             if line.startswith("  ")}
    assert {"read", "visible", "visible_at_reading", "registered"} <= set(means)
    assert all(0 < value < 10 for name, value in means.items() if "folded" not in name)


def test_hypotheses_coverage_takes_the_best_of_the_first_k(train_dataset):
    """``best_of_first`` is the running minimum along the hypotheses; the script on the
    fixture with the shipped model (a distribution head, 8 hypotheses): the best of more
    hypotheses is never farther, and the first alone is the reading's own rotation."""
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        from hypotheses_coverage import best_of_first
        from spread_images import folded_error_deg
    finally:
        sys.path.remove(str(EXPERIMENTS))
    errors = np.array([[30.0, 10.0, 20.0, 5.0], [1.0, 50.0, 2.0, 0.5]])
    assert best_of_first(errors).tolist() == [[30, 10, 10, 5], [1, 1, 1, 0.5]]
    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.evaluation.split import collate
    from sq_mitsuba.inference.loading import load_model
    from sq_mitsuba.model.checkpoint import SHIPPED_MODEL

    command = [sys.executable, str(EXPERIMENTS / "hypotheses_coverage.py"), "--checkpoint",
               str(SHIPPED_MODEL), "--data", str(train_dataset), "--images", "4", "--turns", "2"]
    result = _run_script(command)
    assert result.returncode == 0, result.stderr
    medians = {int(k): float(m) for k, m in
               re.findall(r"first (\d+): median (\S+) deg", result.stdout)}
    assert sorted(medians) == [1, 2, 4, 8]
    assert all(medians[a] >= medians[b] for a, b in ((1, 2), (2, 4), (4, 8)))
    predictor = load_model(SHIPPED_MODEL)
    dataset = Spe3rDataset(train_dataset, "test", image_size=predictor.image_size,
                           num_surface=10, num_occupancy=2)
    chosen = np.linspace(0, len(dataset) - 1, min(4, len(dataset))).round()
    batch = collate([dataset[int(i)] for i in chosen])
    camera = dataset.camera.rescaled(predictor.image_size, predictor.image_size)
    reading = predictor.predict(batch["image"], camera, turns=2)
    first = [folded_error_deg(r, t) for r, t in zip(reading.rotation, batch["rotation"],
                                                     strict=True)]
    assert medians[1] == pytest.approx(float(np.median(first)), abs=0.051)



def test_hypotheses_coverage_refuses_turns_a_network_cannot_read(train_dataset,
                                                                 eval_checkpoint):
    command = [sys.executable, str(EXPERIMENTS / "hypotheses_coverage.py"), "--checkpoint",
               str(eval_checkpoint), "--data", str(train_dataset), "--images", "2",
               "--turns", "8"]
    result = _run_script(command)
    assert result.returncode == 1 and result.stdout == ""
    assert "turns" in result.stderr and len(result.stderr.strip().splitlines()) == 1
