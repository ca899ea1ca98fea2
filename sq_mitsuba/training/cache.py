"""The fast data path of training: a split decoded once into memory-mapped arrays.

Decoding PNGs (and resizing them) for every item of every step costs more than a network step
on a small CPU, so training reads a cache instead:

- :class:`ImageCache`: the images and masks of a split (or a subset of it) at the training
  resolution S, as uint8 memory maps (``images.u8`` (N, S, S), ``masks.u8`` (N, S, ceil(S / 8))
  bit-packed along the rows), with each item's pose, model and visibility in ``items.npz``;
- :class:`PointCache`: each model's surface samples and labelled occupancy points, concatenated
  into float32 / uint8 memory maps with per-model offsets (loaded once, shared by all items
  and, through the page cache, by all processes of a distributed run).

A cache folder is named by what it holds (split, size, a digest of the dataset fingerprint and
the subset) and written atomically: built in a temporary sibling, ``meta.json`` last, then
renamed. A folder whose ``meta.json`` matches is reused; anything else is rebuilt. The
dataset fingerprint (:func:`dataset_fingerprint`) hashes the dataset manifest
(``dataset.json``) where there is one, ``camera.json``, ``splits.csv`` and every
``labels.json``: a re-rendered or edited dataset gets a new cache; the point cache's key also
holds each model's ``samples.npz`` size and time (a model made again gets new points).

Beside them, ``symmetries/`` keeps each training model's half-turn symmetries
(:func:`sq_mitsuba.data.symmetry.model_symmetries` with ``cache_dir``, one record per model
and content digest): the dataset itself is only read.

Decoding goes through :class:`~sq_mitsuba.data.spe3r.Spe3rDataset` itself (same resize), so the
cache holds exactly the pixels the dataset would give. A corrupt or missing image stops the
build with the dataset's one-line error naming the file; nothing is left half-written.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import socket
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.data.spe3r.layout import MODELS, SAMPLES_FILE, DatasetError, read_splits
from sq_mitsuba.io import atomic_write_json
from sq_mitsuba.processes import process_alive

__all__ = ["CACHE_VERSION", "ImageCache", "PointCache", "dataset_fingerprint", "decode_pixels",
           "manifest_hash", "open_image_cache", "open_point_cache"]

CACHE_VERSION = 3  # 3: masks resized by area (were nearest-neighbour)
MANIFEST = "dataset.json"


def dataset_fingerprint(root: str | Path) -> str:
    """sha256 (hex) of what a dataset holds: its manifest ``dataset.json`` where there is one
    (how it was made, image counts, a hash of each model's labels), ``camera.json``,
    ``splits.csv`` and every listed model's ``labels.json``.

    The labels are hashed too, not only the manifest's record of them, so a dataset edited by
    hand (or the SPE3R release, which has no manifest) also gets a new fingerprint. Images are
    not hashed (too slow): re-rendered images always come with a new manifest and labels.
    """
    root = Path(root)
    digest = hashlib.sha256()
    manifest = root / MANIFEST
    if manifest.is_file():
        digest.update(b"manifest\0" + manifest.read_bytes())
    for name in ("camera.json", "splits.csv"):
        path = root / name
        if not path.is_file():
            raise DatasetError(f"{path}: missing")
        digest.update(name.encode() + b"\0" + path.read_bytes())
    for model in sorted(read_splits(root / "splits.csv")):
        labels = root / model / "labels.json"
        if labels.is_file():
            digest.update(model.encode() + b"\0" + labels.read_bytes())
    return digest.hexdigest()


def manifest_hash(root: str | Path) -> str | None:
    """sha256 (hex) of the dataset manifest ``dataset.json``, or None where there is none."""
    path = Path(root) / MANIFEST
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None


# ------------------------------------------------------------------------ atomic folders


def _key_digest(*parts: Any) -> str:
    text = json.dumps(parts, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _read_meta(folder: Path) -> dict[str, Any] | None:
    try:
        return json.loads((folder / "meta.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _publish(tmp: Path, folder: Path) -> None:
    """Rename a finished temporary folder onto ``folder``; another process may have won."""
    try:
        os.replace(tmp, folder)
    except OSError:
        if _read_meta(folder) is None:  # an incomplete folder (should not exist): replace it
            shutil.rmtree(folder, ignore_errors=True)
            os.replace(tmp, folder)
        else:
            shutil.rmtree(tmp, ignore_errors=True)


def _temporary(folder: Path) -> Path:
    """A fresh temporary sibling of ``folder`` for this process, named by its machine and
    process id; those of this machine's processes no longer alive (a build killed by SIGKILL
    or for memory: their memory maps can be gigabytes) are removed, a live one's (another run
    building into a shared cache) and other machines' (a shared disk) kept."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    prefix = f".{folder.name}.tmp-{socket.gethostname()}-"
    for stale in folder.parent.glob(f"{prefix}*"):
        owner = stale.name[len(prefix):]
        if owner.isdigit() and int(owner) != os.getpid() and not process_alive(int(owner)):
            shutil.rmtree(stale, ignore_errors=True)
    tmp = folder.with_name(f"{prefix}{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    return tmp


# ------------------------------------------------------------------------ images


class ImageCache:
    """Images, masks and poses of N dataset items at S x S pixels, memory-mapped read-only.

    Attributes:
        folder: the cache folder.
        size: S.
        images: (N, S, S) uint8 memory map.
        masks: (N, S, ceil(S / 8)) uint8 memory map, bit-packed along the last axis.
        quaternions (N, 4), rotations (N, 3, 3), translations (N, 3): float64 poses, body to
            camera.
        model_index (N,): index into :attr:`models`; image_index (N,): index of the image
            within its model; dataset_index (N,): the item's index in the split.
        visibility (N,): the label's ``target_visibility`` (NaN where the label has none).
        models: model names of the split, sorted (the dataset's ``models``).
    """

    def __init__(self, folder: Path) -> None:
        meta = _read_meta(folder)
        if meta is None:
            raise DatasetError(f"{folder}: not a finished image cache (no meta.json)")
        self.folder = folder
        self.meta = meta
        self.size = int(meta["size"])
        count = int(meta["count"])
        packed = (self.size + 7) // 8
        self.images = np.memmap(folder / "images.u8", np.uint8, "r",
                                shape=(count, self.size, self.size))
        self.masks = np.memmap(folder / "masks.u8", np.uint8, "r",
                               shape=(count, self.size, packed))
        with np.load(folder / "items.npz") as items:
            self.quaternions = items["quaternions"]
            self.rotations = items["rotations"]
            self.translations = items["translations"]
            self.model_index = items["model_index"]
            self.image_index = items["image_index"]
            self.dataset_index = items["dataset_index"]
            self.visibility = items["visibility"]
        self.models: list[str] = list(meta["models"])

    def __len__(self) -> int:
        return len(self.model_index)

    def __repr__(self) -> str:
        return f"ImageCache({len(self)} items, {self.size} px, {self.folder})"

    def batch(self, indices: Sequence[int] | np.ndarray) -> dict[str, Tensor]:
        """Collated items: ``image`` (B, 1, S, S) float32 in [0, 1] (exactly the dataset's
        values, k / 255), ``mask`` (B, 1, S, S) float32 in {0, 1}, ``quaternion`` (B, 4),
        ``rotation`` (B, 3, 3), ``translation`` (B, 3) float32, ``model_index`` (B,) int64."""
        items = self.raw_batch(indices)
        image, mask = decode_pixels(items.pop("image_u8"), items.pop("mask_packed"), self.size)
        return {"image": image, "mask": mask, **items}

    def raw_batch(self, indices: Sequence[int] | np.ndarray) -> dict[str, Tensor]:
        """:meth:`batch` before its pixels are decoded (what a GPU step copies, a quarter of
        the float32 bytes): ``image_u8`` (B, S, S) uint8, ``mask_packed`` (B, S, ceil(S / 8))
        uint8 bit-packed, and the poses and model indices of :meth:`batch`; decoded by
        :func:`decode_pixels` on any device."""
        idx = np.asarray(indices, dtype=np.int64)
        return {
            "image_u8": torch.from_numpy(np.ascontiguousarray(self.images[idx])),
            "mask_packed": torch.from_numpy(np.ascontiguousarray(self.masks[idx])),
            "quaternion": torch.from_numpy(self.quaternions[idx]).to(torch.float32),
            "rotation": torch.from_numpy(self.rotations[idx]).to(torch.float32),
            "translation": torch.from_numpy(self.translations[idx]).to(torch.float32),
            "model_index": torch.from_numpy(self.model_index[idx]).to(torch.int64),
        }


def decode_pixels(images: Tensor, packed_masks: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Cached pixels decoded on their own device: images (B, S, S) uint8 -> (B, 1, S, S)
    float32 k / 255; bit-packed masks (B, S, ceil(S / 8)) uint8 (``np.packbits`` order, most
    significant bit first) -> (B, 1, S, S) float32 in {0, 1}. Equal, bit for bit, on every
    device (one correctly rounded division; the masks exact)."""
    image = (images.to(torch.float32) / 255.0)[:, None]
    shifts = torch.arange(7, -1, -1, dtype=torch.uint8, device=packed_masks.device)
    bits = (packed_masks[..., None] >> shifts) & 1  # (B, S, P, 8)
    mask = bits.flatten(-2)[..., :size].to(torch.float32)[:, None]
    return image, mask


def _label_of(dataset: Any, item: int) -> dict[str, Any]:
    """The label record of a dataset item (empty when the dataset does not expose it)."""
    entries = getattr(dataset, "items", None)
    if entries is None:
        return {}
    entry = entries[item]
    if isinstance(entry, tuple) and entry and isinstance(entry[-1], dict):
        return entry[-1]
    return entry if isinstance(entry, dict) else {}


def _decode(dataset: Any, item: int) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    # The pixels alone where the dataset can give them: its models' points are not read (for
    # a release without samples.npz each would be sampled from its mesh again).
    sample = dataset.pixel_item(item) if hasattr(dataset, "pixel_item") else dataset[item]
    image = np.rint(sample["image"][0].numpy() * 255.0).astype(np.uint8)
    mask = (sample["mask"][0].numpy() > 0.5).astype(np.uint8)
    return image, mask, sample


def open_image_cache(dataset: Any, split: str, cache_root: str | Path, fingerprint: str,
                     indices: Sequence[int] | None = None, progress: bool = False,
                     workers: int | None = None) -> ImageCache:
    """The :class:`ImageCache` of ``dataset`` (a Spe3rDataset) at its ``image_size``, built on
    first use under ``cache_root``.

    Args:
        dataset: the split to cache; its ``image_size`` is the cache's S.
        split: the split's name (part of the cache's key and name).
        cache_root: folder of cache folders (created).
        fingerprint: :func:`dataset_fingerprint` of the dataset root.
        indices: cache only these items of the split (default: all), in this order.
        progress: show a progress bar while decoding.
        workers: decoding threads (PIL releases the GIL while decoding); default: CPU count.

    Raises:
        DatasetError: a missing or corrupt image or label, naming the file.
    """
    size = int(dataset.image_size)
    chosen = list(range(len(dataset))) if indices is None else [int(i) for i in indices]
    key = {"version": CACHE_VERSION, "fingerprint": fingerprint, "split": split,
           "size": size, "items": _key_digest(chosen)}
    folder = Path(cache_root) / f"images-{split}-{size}px-{_key_digest(key)}"
    meta = _read_meta(folder)
    if meta is not None and meta.get("key") == key:
        return ImageCache(folder)
    if meta is not None:  # same name, other content (a digest collision): rebuild
        shutil.rmtree(folder, ignore_errors=True)

    tmp = _temporary(folder)
    try:
        count, packed = len(chosen), (size + 7) // 8
        images = np.memmap(tmp / "images.u8", np.uint8, "w+", shape=(max(count, 1), size, size))
        masks = np.memmap(tmp / "masks.u8", np.uint8, "w+", shape=(max(count, 1), size, packed))
        quaternions = np.zeros((count, 4))
        rotations = np.zeros((count, 3, 3))
        translations = np.zeros((count, 3))
        model_index = np.zeros(count, dtype=np.int64)
        image_index = np.zeros(count, dtype=np.int64)
        visibility = np.full(count, np.nan)

        def work(position: int) -> tuple[int, np.ndarray, np.ndarray, dict[str, Any]]:
            return (position, *_decode(dataset, chosen[position]))

        bar = None
        if progress:
            from sq_mitsuba.progress import progress_bar

            bar = progress_bar(total=count, unit="img", desc=f"cache {split} {size}px", leave=False)
        threads = workers or min(8, os.cpu_count() or 1)
        with ThreadPoolExecutor(max_workers=threads) as pool:
            for position, image, mask, sample in pool.map(work, range(count)):
                images[position] = image
                masks[position] = np.packbits(mask, axis=-1)
                quaternions[position] = sample["quaternion"].numpy()
                rotations[position] = sample["rotation"].numpy()
                translations[position] = sample["translation"].numpy()
                model_index[position] = int(sample["model_index"])
                image_index[position] = int(sample["index"])
                label = _label_of(dataset, chosen[position])
                value = label.get("target_visibility")
                if isinstance(value, int | float) and not isinstance(value, bool):
                    visibility[position] = float(value)
                if bar is not None:
                    bar.update(1)
        if bar is not None:
            bar.close()
        images.flush()
        masks.flush()
        del images, masks
        np.savez(tmp / "items.npz", quaternions=quaternions, rotations=rotations,
                 translations=translations, model_index=model_index, image_index=image_index,
                 dataset_index=np.asarray(chosen, dtype=np.int64), visibility=visibility)
        atomic_write_json(tmp / "meta.json", {
            "key": key, "size": size, "count": count, "split": split,
            "root": str(getattr(dataset, "root", "")), "models": list(dataset.models),
        })
        _publish(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        _release_points(dataset)
    return ImageCache(folder)


# ------------------------------------------------------------------------ points


class PointCache:
    """Surface and labelled occupancy points of every model of a split, memory-mapped.

    :meth:`sample` draws an item's points as :class:`~sq_mitsuba.data.spe3r.Spe3rDataset`
    does: ``num_surface`` surface points (with replacement only when the model has fewer), and
    ``num_occupancy`` occupancy points, half inside and half outside where the model has enough
    inside points (the rest outside).
    """

    def __init__(self, folder: Path) -> None:
        meta = _read_meta(folder)
        if meta is None:
            raise DatasetError(f"{folder}: not a finished point cache (no meta.json)")
        self.folder, self.meta = folder, meta
        self.models: list[str] = list(meta["models"])
        self.surface_offsets = np.asarray(meta["surface_offsets"], dtype=np.int64)
        self.point_offsets = np.asarray(meta["point_offsets"], dtype=np.int64)
        self.surface = np.memmap(folder / "surface.f32", np.float32, "r",
                                 shape=(max(int(self.surface_offsets[-1]), 1), 3))
        self.normals = np.memmap(folder / "normals.f32", np.float32, "r",
                                 shape=(max(int(self.surface_offsets[-1]), 1), 3))
        self.points = np.memmap(folder / "points.f32", np.float32, "r",
                                shape=(max(int(self.point_offsets[-1]), 1), 3))
        self.inside = np.memmap(folder / "inside.u8", np.uint8, "r",
                                shape=(max(int(self.point_offsets[-1]), 1),))

    def __repr__(self) -> str:
        return f"PointCache({len(self.models)} models, {self.folder})"

    def model_surface(self, model_index: int) -> np.ndarray:
        """All surface samples (n, 3) of a model."""
        a, b = self.surface_offsets[model_index], self.surface_offsets[model_index + 1]
        return self.surface[a:b]

    def _inside_outside(self, model_index: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the model's inside and outside occupancy points. Found again at every call,
        not kept: 0.06-0.3 ms a model of 40,000 points, against about 1 ms for the draw, where
        keeping them cost 0.64 MB a model in every process (1.3 GB for 2,000 models)."""
        a, b = self.point_offsets[model_index], self.point_offsets[model_index + 1]
        inside = np.asarray(self.inside[a:b]).astype(bool)
        return a + np.flatnonzero(inside), a + np.flatnonzero(~inside)

    def sample(self, model_index: int, rng: np.random.Generator, num_surface: int,
               num_occupancy: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(surface (num_surface, 3), occupancy points (num_occupancy, 3), labels
        (num_occupancy,) in {0, 1}, the surface points' normals (num_surface, 3)) of one item,
        float32, drawn from ``rng``."""
        surface = self.model_surface(model_index)
        chosen = rng.choice(len(surface), num_surface, replace=len(surface) < num_surface)
        inside_idx, outside_idx = self._inside_outside(model_index)
        want_in = min(num_occupancy // 2, len(inside_idx))
        want_out = num_occupancy - want_in
        if len(outside_idx) == 0:
            raise DatasetError(f"{self.models[model_index]}: no outside occupancy points")
        rows = np.concatenate([
            rng.choice(inside_idx, want_in, replace=False) if want_in else
            np.empty(0, np.int64),
            rng.choice(outside_idx, want_out, replace=len(outside_idx) < want_out)])
        labels = np.concatenate([np.ones(want_in, np.float32), np.zeros(want_out, np.float32)])
        first = self.surface_offsets[model_index]
        return (np.asarray(surface[chosen]), np.asarray(self.points[rows]), labels,
                np.asarray(self.normals[first + chosen]))


def _point_cache_folder(root: Path, models: Sequence[str], cache_root: str | Path,
                        fingerprint: str) -> tuple[Path, dict[str, Any]]:
    """The folder and key of the point cache of ``models`` of the dataset at ``root``: its
    fingerprint (labels, not points) and each model's ``samples.npz`` size and time, so that
    a model made again keeps no stale points (a stat a model, not a read)."""
    samples = []
    for model in models:
        path = Path(root) / model / MODELS / SAMPLES_FILE
        stat = path.stat() if path.is_file() else None
        samples.append(None if stat is None else [stat.st_size, stat.st_mtime_ns])
    key = {"version": CACHE_VERSION, "fingerprint": fingerprint, "models": list(models),
           "samples": samples}
    return Path(cache_root) / f"points-{_key_digest(key)}", key


def point_cache_ready(root: str | Path, models: Sequence[str], cache_root: str | Path,
                      fingerprint: str) -> bool:
    """Whether ``cache_root`` holds the finished :class:`PointCache` of these models of the
    dataset at ``root`` with this fingerprint, their samples as they are now: their points
    were then read, and checked, when it was built, and training reads them from it, not
    from the models' files."""
    folder, key = _point_cache_folder(Path(root), models, cache_root, fingerprint)
    meta = _read_meta(folder)
    return meta is not None and meta.get("key") == key


def open_point_cache(dataset: Any, cache_root: str | Path, fingerprint: str,
                     progress: bool = False) -> PointCache:
    """The :class:`PointCache` of every model of ``dataset`` (``dataset.model_points``),
    built on first use under ``cache_root``."""
    models = list(dataset.models)
    folder, key = _point_cache_folder(Path(dataset.root), models, cache_root, fingerprint)
    meta = _read_meta(folder)
    if meta is not None and meta.get("key") == key:
        return PointCache(folder)
    if meta is not None:
        shutil.rmtree(folder, ignore_errors=True)
    tmp = _temporary(folder)
    try:
        surface_offsets, point_offsets = [0], [0]
        iterator: Any = range(len(models))
        if progress:
            from sq_mitsuba.progress import progress_bar

            iterator = progress_bar(iterator, unit="model", desc="cache points", leave=False)
        with open(tmp / "surface.f32", "wb") as surface_file, \
                open(tmp / "normals.f32", "wb") as normals_file, \
                open(tmp / "points.f32", "wb") as points_file, \
                open(tmp / "inside.u8", "wb") as inside_file:
            for model_index in iterator:
                try:
                    points = dataset.model_points(model_index)
                except DatasetError:
                    raise
                except (OSError, ValueError, KeyError) as error:
                    raise DatasetError(f"{dataset.root / models[model_index]}: cannot read "
                                       f"model points ({error})") from None
                surface = np.ascontiguousarray(points["surface"], dtype=np.float32)
                normals = np.ascontiguousarray(points["normals"], dtype=np.float32)
                cloud = np.ascontiguousarray(points["points"], dtype=np.float32)
                inside = np.ascontiguousarray(points["inside"], dtype=bool).astype(np.uint8)
                if surface.ndim != 2 or surface.shape[1] != 3 or len(surface) == 0 or \
                        cloud.ndim != 2 or cloud.shape[1] != 3 or len(cloud) != len(inside) \
                        or normals.shape != surface.shape:
                    raise DatasetError(f"{dataset.root / models[model_index]}: malformed "
                                       "model points")
                surface_file.write(surface.tobytes())
                normals_file.write(normals.tobytes())
                points_file.write(cloud.tobytes())
                inside_file.write(inside.tobytes())
                surface_offsets.append(surface_offsets[-1] + len(surface))
                point_offsets.append(point_offsets[-1] + len(cloud))
            for handle in (surface_file, normals_file, points_file, inside_file):
                if handle.tell() == 0:  # a memory map of an empty file is an error
                    handle.write(b"\0" * 12)
        atomic_write_json(tmp / "meta.json", {
            "key": key, "models": models, "surface_offsets": surface_offsets,
            "point_offsets": point_offsets})
        _publish(tmp, folder)
    finally:
        with contextlib.suppress(OSError):
            shutil.rmtree(tmp, ignore_errors=True)
        _release_points(dataset)
    return PointCache(folder)


def _release_points(dataset: Any) -> None:
    """Let the dataset forget the model points it read while a cache was built: the cache
    holds them now, and 2,000 models' points would keep about 10 GB for the whole run."""
    release = getattr(dataset, "release_points", None)
    if release is not None:
        release()
