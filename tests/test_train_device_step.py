"""The training step on the step's device (issue 34): the batch decoded and augmented where the
step runs, the GPU step's single read of the device, the large-batch learning-rate rule, and
``bench train``'s network-alone against full-step figures.

Tests that take ``device`` run on ``pytest --device`` (conftest.py); on the CPU the device
paths are forced where they would otherwise be chosen only on a GPU."""

from __future__ import annotations

import math
import os
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from sq_mitsuba.checks import value_checks
from sq_mitsuba.config import apply_overrides
from sq_mitsuba.training.config import OptimConfig, load_train_config

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "train" / "configs"
TINY = CONFIGS / "tiny.toml"


# ------------------------------------------------------------------------ learning rate


@pytest.mark.parametrize(("rule", "factor"), [("none", 1.0), ("linear", 8.0),
                                              ("sqrt", math.sqrt(8.0)),
                                              ("adam_sde", math.sqrt(8.0))])
def test_lr_scaling_rule_gives_the_peak_learning_rate(rule, factor):
    optim = OptimConfig(lr=1e-3, batch_size=256, lr_scaling=rule, reference_batch=32)
    assert optim.peak_lr() == pytest.approx(1e-3 * factor, rel=1e-12)
    # At the reference batch every rule is the lr as given.
    assert OptimConfig(lr=1e-3, batch_size=32, lr_scaling=rule).peak_lr() == 1e-3


def test_adam_sde_keeps_the_moments_memory_in_images_and_scales_eps():
    """adam_sde: an exponential average with decay beta remembers 1 / (1 - beta) steps; at k
    times the batch, the rescaled betas remember k times fewer steps, so as many images."""
    from sq_mitsuba.training.schedule import make_optimizer

    reference = OptimConfig(lr=1e-3, betas=(0.9, 0.999), eps=1e-5)
    large = OptimConfig(lr=1e-3, betas=(0.9, 0.999), eps=1e-5, batch_size=256,
                        reference_batch=32, lr_scaling="adam_sde")
    for small_beta, large_beta in zip(reference.adam_betas(), large.adam_betas(), strict=True):
        images_small = 32 / (1 - small_beta)
        images_large = 256 / (1 - large_beta)
        assert images_large == pytest.approx(images_small, rel=1e-9)
    assert large.adam_betas() == pytest.approx((0.2, 0.992))
    assert large.adam_eps() == pytest.approx(1e-5 / math.sqrt(8))
    group = make_optimizer(torch.nn.Linear(2, 2), large, total_steps=4)[0].param_groups[0]
    assert group["betas"] == pytest.approx((0.2, 0.992)) and group["eps"] == large.adam_eps()
    # Other rules leave them as given; a batch too large for beta1 is refused by name.
    assert OptimConfig(batch_size=256, lr_scaling="sqrt").adam_betas() == (0.9, 0.999)
    with pytest.raises(ValueError, match=r"betas\[0\].*batch_size 384"):
        OptimConfig(batch_size=384, reference_batch=32, lr_scaling="adam_sde")


def test_warm_up_in_images_follows_the_batch_and_the_optimiser_peaks_there():
    from sq_mitsuba.training.schedule import make_optimizer

    assert OptimConfig(warmup_steps=50).warmup_step_count() == 50
    assert OptimConfig(batch_size=256, warmup_steps=50,
                       warmup_images=1600).warmup_step_count() == 7  # ceil(1600 / 256)
    optim = OptimConfig(lr=1e-3, batch_size=128, lr_scaling="linear", warmup_images=256)
    model = torch.nn.Linear(2, 2)
    optimizer, scheduler = make_optimizer(model, optim, total_steps=10)
    rates = []
    for _ in range(4):
        rates.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    # Two warm-up steps (256 images of 128) up to the scaled peak, 4e-3; then the cosine.
    assert rates[0] == pytest.approx(2e-3) and rates[1] == pytest.approx(4e-3)
    assert rates[2] == pytest.approx(4e-3) and rates[3] < 4e-3


def test_shipped_b256_is_the_shipped_recipe_at_batch_256():
    import dataclasses

    shipped = load_train_config(CONFIGS / "shipped.toml")
    large = load_train_config(CONFIGS / "shipped_b256.toml")
    assert large.optim.batch_size == 256 and large.optim.lr_scaling == "sqrt"
    assert large.optim.peak_lr() == pytest.approx(shipped.optim.lr * math.sqrt(8))
    # The same number of warm-up images as shipped.toml's 50 steps of 32.
    assert large.optim.warmup_images == 50 * 32 == shipped.optim.warmup_steps * 32
    assert dataclasses.replace(large, optim=shipped.optim) == shipped
    assert shipped.optim.peak_lr() == shipped.optim.lr  # the default rule changes nothing


# ------------------------------------------------------------------------ the batch


def test_pixels_decode_on_the_device_as_on_the_host(device):
    from sq_mitsuba.training.cache import decode_pixels

    rng = np.random.default_rng(0)
    size = 21  # not a multiple of 8: the last packed byte is part padding
    masks = rng.integers(0, 2, (3, size, size), dtype=np.uint8)
    images = rng.integers(0, 256, (3, size, size), dtype=np.uint8)
    packed = torch.from_numpy(np.packbits(masks, axis=-1))
    image, mask = decode_pixels(torch.from_numpy(images).to(device), packed.to(device), size)
    assert image.shape == mask.shape == (3, 1, size, size) and image.device.type == device.type
    assert torch.equal(mask.cpu()[:, 0], torch.from_numpy(masks).float())
    assert torch.equal(image.cpu(), (torch.from_numpy(images).float() / 255.0)[:, None])


@pytest.fixture(scope="module")
def stream(train_dataset, tmp_path_factory):
    """A :class:`TrainingStream` of tiny.toml (augmentation on) over ``train_dataset``."""
    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.training.cache import dataset_fingerprint, open_image_cache, open_point_cache
    from sq_mitsuba.training.data_stream import TrainingStream

    config = load_train_config(TINY)
    dataset = Spe3rDataset(train_dataset, "train", image_size=config.network.image_size,
                           num_surface=1, num_occupancy=2)
    root, fingerprint = tmp_path_factory.mktemp("stream_cache"), dataset_fingerprint(
        train_dataset)
    images = open_image_cache(dataset, "train", root, fingerprint, workers=2)
    points = open_point_cache(dataset, root, fingerprint)
    camera = dataset.camera.rescaled(config.network.image_size, config.network.image_size)
    symmetries = torch.eye(3).repeat(len(dataset.models), 2, 1, 1)
    return TrainingStream(images, points, np.arange(len(images)), config, camera, symmetries)


def _reference_batch(stream, step):
    """Step ``step``'s batch as the stream made it item by item before issue 34: decoded and
    augmented on the host."""
    from sq_mitsuba.training.augment import augment_batch
    from sq_mitsuba.training.random_streams import STREAMS, seed_of

    cfg = stream.config
    rows = stream.rows(step)
    cached = stream.images.batch(rows)
    generators = [np.random.default_rng(seed_of(cfg.seed, STREAMS["item"], step, j))
                  for j in range(len(rows))]
    drawn = [stream.points.sample(int(m), generators[k], cfg.data.num_surface,
                                  cfg.data.num_occupancy)
             for k, m in enumerate(cached["model_index"].tolist())]
    image, mask, rotation, translation = augment_batch(
        cached["image"], cached["mask"], cached["rotation"], cached["translation"],
        cfg.augment, generators, stream.camera)
    return {"image": image, "mask": mask, "rotation": rotation, "translation": translation,
            "surface_points": torch.from_numpy(np.stack([d[0] for d in drawn])),
            "occupancy_points": torch.from_numpy(np.stack([d[1] for d in drawn])),
            "occupancy_labels": torch.from_numpy(np.stack([d[2] for d in drawn])),
            "model_index": cached["model_index"]}


def test_stream_batch_made_on_the_device_equals_the_host_batch(stream, device):
    """The batch decoded and augmented on ``device`` equals the host's, item by item: bit for
    bit on the CPU, to float rounding on a GPU (bilinear resampling, blur, powers)."""
    from sq_mitsuba.training.distributed import World

    for step in (0, 1, 5):
        expected = _reference_batch(stream, step)
        got = stream.batch(step, World(), device)
        assert got.image.device.type == device.type
        for name, value in expected.items():
            actual = getattr(got, name).cpu()
            assert actual.dtype == value.dtype, name
            if device.type == "cpu":
                assert torch.equal(actual, value), name
            else:
                torch.testing.assert_close(actual, value, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("workers", [0, 2])
def test_prefetched_batches_equal_the_streams_own(stream, device, workers):
    """The prefetch thread (``workers = 0``) or worker processes hand out, bit for bit, the
    batch the stream makes on demand: in step order (each prefetched behind the last), after
    a jump (the stale prefetch dropped), past the planned steps, and with the stream's own
    batch interleaved."""
    from sq_mitsuba.training.distributed import World
    from sq_mitsuba.training.prefetch import BatchPrefetcher, prefetch_enabled

    assert prefetch_enabled(None, "cpu") is False and prefetch_enabled(None, "cuda") is True
    assert prefetch_enabled(True, "cpu") is True
    with BatchPrefetcher(stream, World(), device, end_step=7, workers=workers) as prefetcher:
        for step in (0, 1, 2, 5, 6, 7, 3):
            got = prefetcher.batch(step)
            expected = stream.batch(step, World(), device)
            for name in ("image", "mask", "rotation", "translation", "model_index",
                         "surface_points", "occupancy_points", "occupancy_labels",
                         "symmetries"):
                assert torch.equal(getattr(got, name), getattr(expected, name)), (step, name)
        if workers == 0:
            assert prefetcher._pending is not None and prefetcher._pending.result().step == 4
        else:
            assert prefetcher._loader is not None and prefetcher._next == 4
    assert not prefetcher.enabled  # closed: the workers are gone
    assert torch.equal(BatchPrefetcher(stream, World(), device, 7, enabled=False).batch(1).image,
                       stream.batch(1, World(), device).image)


@pytest.mark.parametrize("workers", [0, 1])
def test_prefetching_leaves_the_global_random_state_alone(stream, workers):
    """The encoder's stochastic depth draws from torch's global generator, which a resumed
    run restores before it makes its prefetcher again: making the workers' loader must not
    draw from it (it took one draw for its base seed), or a run and its resume part ways."""
    from sq_mitsuba.training.distributed import World
    from sq_mitsuba.training.prefetch import BatchPrefetcher

    torch.manual_seed(3)
    before = torch.get_rng_state()
    with BatchPrefetcher(stream, World(), "cpu", end_step=4, workers=workers) as prefetcher:
        prefetcher.batch(0)
        prefetcher.batch(2)  # a jump: the loader made again
    assert torch.equal(torch.get_rng_state(), before)


@pytest.mark.parametrize("workers", [0, 2])
def test_a_prefetch_error_comes_back_as_raised(stream, workers, monkeypatch):
    """An error met while making a batch ahead reaches the training process as it was raised
    (type and one-line message), not wrapped in a worker's traceback."""
    from sq_mitsuba.data.spe3r import DatasetError
    from sq_mitsuba.training.distributed import World
    from sq_mitsuba.training.prefetch import BatchPrefetcher

    made = stream.host_batch

    def host_batch(step, world, pin=False):
        if step == 2:
            raise DatasetError("model x: no outside occupancy points")
        return made(step, world, pin)

    monkeypatch.setattr(stream, "host_batch", host_batch)
    with BatchPrefetcher(stream, World(), "cpu", end_step=5, workers=workers) as prefetcher:
        prefetcher.batch(0)
        prefetcher.batch(1)
        with pytest.raises(DatasetError) as raised:
            prefetcher.batch(2)
    assert str(raised.value) == "model x: no outside occupancy points"


# ------------------------------------------------------------------------ the step


def _config(*overrides: str):
    return apply_overrides(load_train_config(TINY), ["loss.weights.reprojection=0",
                                                     "optim.eps=1e-5", *overrides])


def test_the_gpu_step_forced_on_the_cpu_equals_the_cpu_step():
    """:func:`training_step`'s device path (one read of the device, checks after the backward
    pass), run on the CPU, updates the network exactly as the CPU path and reads back the same
    values."""
    from sq_mitsuba.bench.train import StepBench
    from sq_mitsuba.training import step as step_module
    from sq_mitsuba.training.distributed import World

    config = _config()
    with step_module.mitsuba_for(torch.device("cpu"), True):
        cpu, forced = StepBench(config, batch=4), StepBench(config, batch=4)
    for index in range(2):
        batch = cpu.data.batch(index)
        a = step_module.training_step(cpu.model, cpu.optimizer, batch, cpu.k_matrix,
                                      cpu.context(index), config.optim.grad_clip)
        b = step_module._device_step(forced.model, forced.optimizer, batch, forced.k_matrix,
                                     forced.context(index), config.optim.grad_clip, World())
        assert a.values == b.values and a.grad_norm == b.grad_norm
        assert set(a.values) == {"loss", *config.loss.enabled()}
        assert a.values["loss"] == float(a.loss)
    for p, q in zip(cpu.model.parameters(), forced.model.parameters(), strict=True):
        assert torch.equal(p, q)


def test_both_step_paths_clip_the_gradient_and_log_its_norm_before():
    """With ``grad_clip`` the gradient the optimiser applies has that norm, each parameter's
    the unclipped one scaled alike; the logged norm is the unclipped gradient's."""
    from sq_mitsuba.bench.train import StepBench
    from sq_mitsuba.training import step as step_module
    from sq_mitsuba.training.distributed import World

    config = _config()
    clip = 1e-3

    def step(path: str, grad_clip: float | None) -> tuple[float, list[torch.Tensor]]:
        with step_module.mitsuba_for(torch.device("cpu"), True):
            bench = StepBench(config, batch=4)
        args = (bench.model, bench.optimizer, bench.data.batch(0), bench.k_matrix,
                bench.context(0), grad_clip)
        result = (step_module.training_step(*args) if path == "cpu"
                  else step_module._device_step(*args, World()))
        return result.grad_norm, [p.grad.detach().clone() for p in bench.model.parameters()
                                  if p.grad is not None]

    free_norm, free = step("cpu", None)
    assert free_norm > 10 * clip  # else this clip would not bite
    assert free_norm == pytest.approx(float(torch.linalg.vector_norm(
        torch.stack([g.norm() for g in free]))), rel=1e-5)
    for path in ("cpu", "device"):
        norm, clipped = step(path, clip)
        assert norm == pytest.approx(free_norm, rel=1e-5)  # logged before clipping
        total = torch.linalg.vector_norm(torch.stack([g.norm() for g in clipped]))
        assert float(total) == pytest.approx(clip, rel=1e-4)
        for g, h in zip(clipped, free, strict=True):
            torch.testing.assert_close(g, h * (clip / free_norm), rtol=1e-4, atol=1e-12)


def test_a_non_finite_network_is_refused_by_both_step_paths(monkeypatch):
    """A NaN network: the CPU path stops before the loss terms; the device path runs them
    (with the GPU's dense search, which takes NaN) and refuses the update after."""
    from sq_mitsuba.bench.train import StepBench
    from sq_mitsuba.geometry import nearest
    from sq_mitsuba.training import step as step_module
    from sq_mitsuba.training.distributed import World

    config = _config()
    with step_module.mitsuba_for(torch.device("cpu"), True):
        bench = StepBench(config, batch=4)
    with torch.no_grad():
        next(bench.model.parameters()).fill_(float("nan"))
    before = [p.detach().clone() for p in bench.model.parameters()]
    batch = bench.data.batch(0)
    with value_checks(False):
        assert not step_module.outputs_finite(bench.model(batch.image, bench.k_matrix))
    with pytest.raises(step_module.NotFiniteError, match="non-finite network output"):
        step_module.training_step(bench.model, bench.optimizer, batch, bench.k_matrix,
                                  bench.context(0), 1.0)
    monkeypatch.setattr(nearest, "nearest_method", lambda device, method=None: "dense")
    with pytest.raises(step_module.NotFiniteError, match="not finite"):
        step_module._device_step(bench.model, bench.optimizer, batch, bench.k_matrix,
                                 bench.context(0), 1.0, World())
    for p, q in zip(before, bench.model.parameters(), strict=True):  # no update applied
        assert torch.equal(p, q) or bool(torch.isnan(p).all())


def test_bench_step_ratio_times_both_on_the_step_device(device):
    from sq_mitsuba.bench.train import step_ratio

    samples = step_ratio(_config(f'device="{device.type}"'), 4, device, repeats=2, warmup=1)
    assert set(samples) == {"network", "step"}
    assert all(len(v) == 2 and all(s > 0 for s in v) for v in samples.values())


def test_gpu_step_check_script_parses_and_documents_its_dry_run():
    script = ROOT / "train" / "gpu_step_check.sh"
    assert subprocess.run(["bash", "-n", str(script)], check=False).returncode == 0
    text = script.read_text()
    assert "DEVICE=cpu" in text and "shipped_b256.toml" in text and "timeout" in text


def test_gpu_recipe_script_parses_and_names_what_it_trains():
    """train/gpu_recipe.sh (dry-run on the CPU with DEVICE=cpu and tiny sizes, as its usage
    says) parses, trains a config that exists, and keeps each run within a time limit."""
    script = ROOT / "train" / "gpu_recipe.sh"
    assert subprocess.run(["bash", "-n", str(script)], check=False).returncode == 0
    text = script.read_text()
    config = re.search(r"^config=(\S+)$", text, re.MULTILINE)
    assert config and (ROOT / config.group(1)).is_file()
    assert "DEVICE=cpu" in text and "timeout" in text and "--workers" in text


def test_gpu_recipe_script_refuses_an_unknown_pair_before_any_work(tmp_path):
    """PAIR names the one change between the two runs; anything else is one line and exit 2,
    before a model is generated (the output folder gets only its empty summary)."""
    script = ROOT / "train" / "gpu_recipe.sh"
    env = {**os.environ, "PAIR": "longer", "WORK": str(tmp_path / "work")}
    result = subprocess.run(["bash", str(script), str(tmp_path / "out")], env=env,
                            capture_output=True, text=True, check=False, timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip() == \
        "PAIR: expected schedule, start, chamfer or shards, got 'longer'"
    assert not (tmp_path / "work" / "models").exists()


@pytest.mark.parametrize(("setting", "message"), [
    ({"SHARDS": "1"}, "SHARDS: expected a whole number >= 2, got '1'"),
    ({"SHARD_SETS": "split half"}, "SHARD_SETS: expected split, keep or all, got 'half'"),
])
def test_gpu_recipe_script_refuses_bad_shards_before_any_work(tmp_path, setting, message):
    """PAIR=shards: a shard count below 2 or an unknown set of runs is one line and exit 2,
    before a model is generated."""
    script = ROOT / "train" / "gpu_recipe.sh"
    env = {**os.environ, "PAIR": "shards", "WORK": str(tmp_path / "work"), **setting}
    result = subprocess.run(["bash", str(script), str(tmp_path / "out")], env=env,
                            capture_output=True, text=True, check=False, timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip() == message
    assert not (tmp_path / "work" / "models").exists()


def test_gpu_recipe_script_refuses_a_missing_start_before_any_work(tmp_path):
    """INIT naming no file is one line and exit 2 before anything is made, not even the
    output folder."""
    script = ROOT / "train" / "gpu_recipe.sh"
    env = {**os.environ, "INIT": "/nowhere/start.pt", "WORK": str(tmp_path / "work")}
    result = subprocess.run(["bash", str(script), str(tmp_path / "out")], env=env,
                            capture_output=True, text=True, check=False, timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip() == f"{script}: INIT /nowhere/start.pt: no such file"
    assert not (tmp_path / "out").exists() and not (tmp_path / "work").exists()
