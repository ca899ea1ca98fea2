"""The training cache holds exactly what the dataset gives, is reused, keyed, and atomic."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from sq_mitsuba.data.spe3r import DatasetError, Spe3rDataset
from sq_mitsuba.training.cache import dataset_fingerprint, open_image_cache, open_point_cache


def _dataset(root: Path, split: str = "train", size: int = 32) -> Spe3rDataset:
    return Spe3rDataset(root, split, image_size=size, num_surface=1, num_occupancy=2)


def test_image_cache_equals_dataset_items(train_dataset, tmp_path, monkeypatch):
    dataset = _dataset(train_dataset)
    fingerprint = dataset_fingerprint(train_dataset)
    with monkeypatch.context() as patch:  # pixels alone: no model's points are read for it
        patch.setattr(Spe3rDataset, "model_points", lambda *args: pytest.fail("points read"))
        cache = open_image_cache(dataset, "train", tmp_path, fingerprint, workers=2)
    assert len(cache) == len(dataset) > 0
    batch = cache.batch(np.arange(len(cache)))
    for i in range(len(dataset)):
        item = dataset[i]
        assert torch.equal(batch["image"][i], item["image"])
        assert torch.equal(batch["mask"][i], item["mask"])
        assert torch.equal(batch["rotation"][i], item["rotation"])
        assert torch.equal(batch["translation"][i], item["translation"])
        assert int(batch["model_index"][i]) == item["model_index"]
        assert int(cache.image_index[i]) == item["index"]
    # Reused: the same folder, not rewritten.
    stamp = (cache.folder / "images.u8").stat().st_mtime_ns
    again = open_image_cache(dataset, "train", tmp_path, fingerprint)
    assert again.folder == cache.folder
    assert (again.folder / "images.u8").stat().st_mtime_ns == stamp
    # Keyed by size, split and subset.
    other = open_image_cache(_dataset(train_dataset, size=48), "train", tmp_path, fingerprint)
    assert other.folder != cache.folder and other.images.shape[1:] == (48, 48)
    subset = open_image_cache(dataset, "train", tmp_path, fingerprint, indices=[3, 1])
    assert subset.folder != cache.folder
    assert torch.equal(subset.batch([0])["image"][0], dataset[3]["image"])
    assert list(subset.dataset_index) == [3, 1]


def test_point_cache_samples_like_the_dataset(train_dataset, tmp_path):
    dataset = _dataset(train_dataset)
    points = open_point_cache(dataset, tmp_path, dataset_fingerprint(train_dataset))
    assert points.models == dataset.models
    assert not dataset._points  # the cache holds them: the dataset does not keep a copy
    for model_index in range(len(dataset.models)):
        reference = dataset.model_points(model_index)
        rng = np.random.default_rng(0)
        surface, occupancy, labels, normals = points.sample(model_index, rng, 500, 400)
        assert surface.shape == normals.shape == (500, 3) and occupancy.shape == (400, 3)
        assert labels.sum() == 200  # balanced: half inside
        # Every sampled point is one of the model's, with the model's own label.
        lookup = {tuple(p): bool(inside) for p, inside in
                  zip(reference["points"].astype(np.float32), reference["inside"], strict=True)}
        assert all(lookup[tuple(p)] == bool(lab) for p, lab in zip(occupancy, labels,
                                                                   strict=True))
        # Every sampled surface point is one of the model's, with that point's own normal.
        normal_of = {tuple(p): tuple(n) for p, n in zip(
            reference["surface"].astype(np.float32), reference["normals"].astype(np.float32),
            strict=True)}
        assert all(normal_of[tuple(p)] == tuple(n) for p, n in zip(surface, normals,
                                                                     strict=True))
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-4)


def test_point_cache_keeps_nothing_per_model(train_dataset, tmp_path):
    """Drawing from every model leaves the cache as large as it was (it kept each model's
    inside and outside rows, 0.64 MB a model of 40,000 points in every training process),
    and the same generator draws the same points."""
    import tracemalloc

    points = open_point_cache(_dataset(train_dataset), tmp_path,
                              dataset_fingerprint(train_dataset))
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for model_index in range(len(points.models)):
            points.sample(model_index, np.random.default_rng(model_index), 50, 40)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grown < 4096, f"{grown} bytes kept after drawing from every model"
    first, repeat = ([points.sample(m, np.random.default_rng(m), 50, 40)
                      for m in range(len(points.models))] for _ in range(2))
    for a, b in zip(first, repeat, strict=True):
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_fingerprint_follows_the_content(train_dataset, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(train_dataset, root)
    first = dataset_fingerprint(root)
    assert first == dataset_fingerprint(train_dataset)
    model = _dataset(root).models[0]
    labels_path = root / model / "labels.json"
    labels = json.loads(labels_path.read_text())
    labels[0]["r_Vo2To_vbs_true"][2] += 0.5
    labels_path.write_text(json.dumps(labels))
    second = dataset_fingerprint(root)
    assert second != first  # edited labels, manifest untouched
    manifest = root / "dataset.json"
    assert manifest.is_file()
    manifest.write_text(manifest.read_text().replace('"spp": 4', '"spp": 5'))
    assert dataset_fingerprint(root) not in (first, second)
    manifest.unlink()  # the SPE3R release has none: labels, splits and camera still count
    assert dataset_fingerprint(root) not in (first, second)


def test_corrupt_image_names_the_file_and_leaves_nothing(train_dataset, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(train_dataset, root)
    dataset = _dataset(root)
    model = dataset.models[1]
    victim = sorted((root / model / "images").glob("*.png"))[2]
    victim.write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    cache_root = tmp_path / "cache"
    with pytest.raises(DatasetError, match=victim.name) as info:
        open_image_cache(dataset, "train", cache_root, dataset_fingerprint(root))
    assert "\n" not in str(info.value) and str(victim) in str(info.value)
    assert not any(cache_root.iterdir())  # no half-written cache folder


def test_a_ready_point_cache_spares_reading_the_models_points_again(train_dataset, tmp_path):
    """Training refuses a model whose points cannot be read, before any work, unless the
    point cache of this dataset is already built (its points were read and checked then, and
    training reads them from it): a start or resume then skips reading every samples.npz."""
    from sq_mitsuba.training.cache import point_cache_ready
    from sq_mitsuba.training.config import TrainConfig
    from sq_mitsuba.training.data_stream import open_datasets

    root = tmp_path / "data"
    shutil.copytree(train_dataset, root)
    config = TrainConfig(optim=dataclasses.replace(TrainConfig().optim, batch_size=4))
    fingerprint, cache = dataset_fingerprint(root), tmp_path / "cache"
    dataset = _dataset(root)
    samples = root / dataset.models[0] / "models" / "samples.npz"
    good = samples.read_bytes()
    samples.write_bytes(b"not an archive")
    for arguments in ((), (cache, fingerprint)):
        with pytest.raises(DatasetError, match=r"samples\.npz"):
            open_datasets(config, root, *arguments)

    samples.write_bytes(good)
    assert not point_cache_ready(root, dataset.models, cache, fingerprint)
    open_point_cache(dataset, cache, fingerprint)
    assert point_cache_ready(root, dataset.models, cache, fingerprint)
    assert not point_cache_ready(root, dataset.models, cache, "another dataset")
    assert not point_cache_ready(root, dataset.models[1:], cache, fingerprint)
    # The models' files are not read again: a damaged file of the same size and time (the
    # key's stat of it) is not noticed.
    stat = samples.stat()
    samples.write_bytes(b"x" * len(good))
    os.utime(samples, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert open_datasets(config, root, cache, fingerprint).train_set.models == dataset.models
    with pytest.raises(DatasetError, match=r"samples\.npz"):
        open_datasets(config, root, cache, "another dataset")
    # A model made again (another samples.npz) gets new points, not the cache's stale ones.
    samples.write_bytes(good)
    assert not point_cache_ready(root, dataset.models, cache, fingerprint)


def test_a_killed_builds_temporary_folder_goes_with_the_next_build(tmp_path):
    """A build killed by SIGKILL (or for memory) left its temporary folder, memory maps and
    all, for ever: the next build on this machine removes those of dead processes and keeps
    a live one's and other machines' (a cache on a shared disk)."""
    import socket
    import subprocess
    import sys

    from sq_mitsuba.training.cache import _temporary

    folder = tmp_path / "images-train-32px-abc"
    host = socket.gethostname()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    stale = tmp_path / f".{folder.name}.tmp-{host}-{dead}"
    live = tmp_path / f".{folder.name}.tmp-{host}-{os.getppid()}"
    elsewhere = tmp_path / f".{folder.name}.tmp-another-machine-{dead}"
    for path in (stale, live, elsewhere):
        (path / "images.u8").parent.mkdir()
        (path / "images.u8").write_bytes(b"partial")
    mine = _temporary(folder)
    assert mine.name == f".{folder.name}.tmp-{host}-{os.getpid()}" and mine.is_dir()
    assert not stale.exists() and live.exists() and elsewhere.exists()
