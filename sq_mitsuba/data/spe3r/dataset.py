"""A torch Dataset over an SPE3R-layout folder (ours, or the SPE3R release)."""

from __future__ import annotations

import operator
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from sq_mitsuba.checks import check_int
from sq_mitsuba.data.spe3r.layout import (
    IMAGES,
    MANIFEST,
    MASKS,
    MODELS,
    SAMPLES_FILE,
    DatasetError,
    balanced_occupancy,
    check_model_points,
    find_image,
    is_model_library,
    is_validation,
    label_problem,
    model_points,
    read_gray,
    read_labels,
    read_manifest,
    read_splits,
    resize,
)
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import quaternion_to_matrix
from sq_mitsuba.inputs import image_header

SPLITS = ("train", "val", "test")


class MissingModelWarning(UserWarning):
    """A model listed in ``splits.csv`` has no ``labels.json``: it is left out."""


def split_index(index: int, label: Any) -> int:
    """The image index that decides an image's split (:func:`is_validation`): its own, or in
    a pass dataset (labels with ``frame_in_pass``) its pass's first frame's, so that a pass
    lies whole in ``train`` or ``val`` (frames a few degrees apart on both sides would leak)."""
    frame = label.get("frame_in_pass") if isinstance(label, dict) else None
    if isinstance(frame, int) and not isinstance(frame, bool) and 0 <= frame <= index:
        return index - frame
    return index


class Spe3rDataset(torch.utils.data.Dataset):
    """A torch Dataset over an SPE3R-layout folder (ours, or the SPE3R release).

    Each item is a dict: ``image`` (1, S, S) float in [0, 1]; ``mask`` (1, S, S) float in
    {0, 1}; ``quaternion`` (4,), ``rotation`` (3, 3) and ``translation`` (3,), the pose body ->
    camera; ``camera`` (3, 3) intrinsics for S x S pixels; ``model`` (str) and ``model_index``;
    ``surface_points`` (num_surface, 3); ``occupancy_points`` (num_occupancy, 3) with
    ``occupancy_labels`` (num_occupancy,), half inside and half outside where the model has
    enough of each; ``index`` of the image within its model.

    Convention: a model listed in ``splits.csv`` whose folder or ``labels.json`` is missing is
    skipped with a :class:`MissingModelWarning` naming it (a dataset with one model gone stays
    usable, and says so); a ``labels.json`` that exists but cannot be read, or holds a bad
    entry (NaN, wrong length, not a unit quaternion), is a one-line :class:`DatasetError` naming
    the file and the entry. Images and masks are decoded completely when an item is read: a
    corrupt or truncated file, or a mask of another size than its image, is a
    :class:`DatasetError` naming the file.

    Args:
        root: dataset folder.
        split: "train", "val" (images [0.4 n, 0.5 n) and [0.9 n, n) of each train model with n
            its image count: SPE3R's 400-499 and 900-999 at n = 1000) or "test".
        image_size: S, the side of the square images and masks are resized to (default
            128; None: ``camera.json``'s width, the images as rendered when they are square;
            a W x H camera's images are stretched to W x W, the intrinsics with them).
        num_surface, num_occupancy: points per item (2,500 and 10,000 by default).
        seed: makes the point subsets reproducible (item i uses seed + i).
    """

    def __init__(self, root: str | Path, split: str = "train", image_size: int | None = 128,
                 num_surface: int = 2500, num_occupancy: int = 10_000, seed: int = 0):
        if split not in SPLITS:
            raise ValueError(f"split: expected 'train', 'val' or 'test', got {split!r}")
        if image_size is not None:
            image_size = check_int("image_size", image_size)
        num_surface = check_int("num_surface", num_surface)
        num_occupancy = check_int("num_occupancy", num_occupancy)
        seed = check_int("seed", seed, 0)  # item i draws its points with seed + i
        self.root = Path(root)
        for required in ("camera.json", "splits.csv"):
            if not (self.root / required).is_file():
                library = required == "camera.json" and is_model_library(self.root)
                unfinished = required == "splits.csv" and _rendering(self.root)
                raise DatasetError(f"{self.root / required}: missing" + (
                    f"; {self.root} is a model library, not a dataset: render one with "
                    f"sq-mitsuba dataset render --models {self.root} --out DATA" if library
                    else "; its rendering has not finished (dataset.json says so): run the "
                    "render command again" if unfinished else ""))
        if _rendering(self.root):  # a finished dataset being extended: splits.csv is the
            # smaller run's, and the models hold labels and images of neither run
            raise DatasetError(f"{self.root / MANIFEST}: says its rendering has not finished "
                               "(an interrupted run, or one still going): run the render "
                               "command again, or wait for it")
        try:
            self.camera = Camera.load(self.root / "camera.json")
        except ValueError as error:
            path = self.root / "camera.json"
            raise DatasetError(str(error) if str(path) in str(error) else f"{path}: {error}") \
                from None
        self.image_size = self.camera.width if image_size is None else image_size
        self.seed = seed
        self.num_surface, self.num_occupancy = num_surface, num_occupancy
        splits = read_splits(self.root / "splits.csv")
        wanted = "test" if split == "test" else "train"
        self.models: list[str] = []
        self.skipped: list[str] = []
        self.items: list[tuple[int, int, dict[str, Any]]] = []
        for model in sorted(m for m, s in splits.items() if s == wanted):
            labels_path = self.root / model / "labels.json"
            if not labels_path.is_file():
                warnings.warn(f"{labels_path}: missing; model {model} left out of the "
                              f"{split} split", MissingModelWarning, stacklevel=2)
                self.skipped.append(model)
                continue
            labels = read_labels(labels_path)
            for index, label in enumerate(labels):
                problem = label_problem(label)
                if problem is not None:
                    name = label.get("filename") if isinstance(label, dict) else None
                    entry = f"entry {index}" + (f" ({name})" if isinstance(name, str) else "")
                    raise DatasetError(f"{labels_path}: {entry}: {problem}")
            model_index = len(self.models)
            self.models.append(model)
            for index, label in enumerate(labels):
                if split == "test" or (split == "val") == is_validation(
                        split_index(index, label), len(labels)):
                    self.items.append((model_index, index, label))
        self._points: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.items)

    def _item(self, item: Any) -> int:
        """``item`` as an index into :attr:`items` (an integer of any kind, negative from the
        end, as a list's); a one-line IndexError naming it when there is no such item."""
        try:
            index = operator.index(item)  # int, numpy integers, one-element integer tensors
        except TypeError:
            raise TypeError(f"item: expected an integer, got {type(item).__name__}") from None
        if not -len(self.items) <= index < len(self.items):
            raise IndexError(f"item: {index} out of range for the {len(self.items)} items of "
                             f"{self.root}")
        return index % len(self.items)

    def _image_path(self, model: str, folder: str, filename: str) -> Path:
        path = find_image(self.root, model, folder, filename)
        if not path.is_file():
            raise DatasetError(f"{path}: missing")
        return path

    def check(self, points: bool = True) -> None:
        """Refuse, before any work, what would stop a run over this split part-way: an image
        of another size than ``camera.json`` describes (the first image of each model, read
        from its header) and, with ``points``, a model whose points cannot be read
        (``samples.npz`` missing an array, holding NaN, unreadable; see
        :func:`~sq_mitsuba.data.spe3r.layout.read_samples`). One-line :class:`DatasetError`
        naming the file. Reads each samples file once and keeps nothing."""
        first: dict[int, dict[str, Any]] = {}
        for model_index, _, label in self.items:
            first.setdefault(model_index, label)
        sampled: list[Path] = []  # models whose points come from their mesh
        for model_index, label in sorted(first.items()):
            model = self.models[model_index]
            path = self._image_path(model, IMAGES, label["filename"])
            try:
                with image_header(path) as image:
                    width, height = image.size
            except (OSError, SyntaxError, ValueError) as error:  # PIL's kinds of bad file
                raise DatasetError(f"{path}: cannot read image ({error})") from None
            if (width, height) != (self.camera.width, self.camera.height):
                raise DatasetError(
                    f"{self.root / 'camera.json'}: describes {self.camera.width} x "
                    f"{self.camera.height} px images, but {path} is {width} x {height} px "
                    "(a camera.json of another resolution?)")
            if points:
                check_model_points(self.root / model)
                if not (self.root / model / MODELS / SAMPLES_FILE).is_file():
                    sampled.append(self.root / model / MODELS / SAMPLES_FILE)
        if sampled and (self.root / MANIFEST).is_file():
            # The SPE3R release has no samples: sampling its meshes is the way. A dataset
            # rendered here has them, and its scores are on them: said, not silent.
            warnings.warn(f"{sampled[0]}: missing ({len(sampled)} model(s) of {self.root}, a "
                          "dataset sq-mitsuba rendered): their points are sampled from the "
                          "mesh instead, so the Chamfer and 3D IoU are not the dataset's own "
                          "(`sq-mitsuba dataset check` lists them)", stacklevel=2)

    def release_points(self) -> None:
        """Forget the model points read so far (a cache built from them holds its own copy);
        :meth:`model_points` reads them again if asked."""
        self._points.clear()

    def model_points(self, model_index: int) -> dict[str, np.ndarray]:
        """Surface and labelled occupancy points of a model (from samples.npz, or the mesh)."""
        if model_index not in self._points:
            self._points[model_index] = model_points(self.root / self.models[model_index])
        return self._points[model_index]

    def image_file(self, item: int) -> Path:
        """The file of ``item``'s image (``images/<filename>``, whatever its extension)."""
        item = self._item(item)
        model_index, _, label = self.items[item]
        return self._image_path(self.models[model_index], IMAGES, label["filename"])

    def read_pair(self, item: int) -> tuple[np.ndarray, np.ndarray]:
        """Image and mask (H, W) uint8 of ``item`` at their stored size, decoded completely;
        a mask of another size than its image is a DatasetError naming the mask."""
        item = self._item(item)
        model_index, _, label = self.items[item]
        model = self.models[model_index]
        image_path = self._image_path(model, IMAGES, label["filename"])
        mask_path = self._image_path(model, MASKS, label["filename"])
        image, mask = read_gray(image_path), read_gray(mask_path)
        if mask.shape != image.shape and mask.shape == (self.camera.height, self.camera.width):
            # The image is the odd one out (the release's images may be smaller than its
            # camera.json's, but each the size of its mask).
            raise DatasetError(f"{image_path}: {image.shape[1]} x {image.shape[0]} px, but "
                               f"its mask and camera.json {self.camera.width} x "
                               f"{self.camera.height} px")
        if mask.shape != image.shape:
            raise DatasetError(f"{mask_path}: mask is {mask.shape[1]} x {mask.shape[0]} px, "
                               f"its image {image_path.name} is {image.shape[1]} x "
                               f"{image.shape[0]} px")
        return image, mask

    def pixel_item(self, item: int) -> dict[str, Any]:
        """The item of :meth:`__getitem__` without its model's points: image, mask, pose,
        camera and names (what a cache of images keeps; the model's points are not read)."""
        item = self._item(item)
        model_index, index, label = self.items[item]
        size = self.image_size
        image, mask = self.read_pair(item)
        image = resize(image, size, Image.BILINEAR)
        # The mask by area (its share of each output pixel, then >= half): nearest-neighbour
        # picked one corner of each block, a quarter pixel off the image at half size.
        mask = resize(mask, size, Image.BOX)
        quaternion = torch.tensor(label["q_vbs2tango_true"], dtype=torch.float32)
        return {
            "image": torch.from_numpy(image.astype(np.float32) / 255.0)[None],
            "mask": torch.from_numpy((mask >= 128).astype(np.float32))[None],
            "quaternion": quaternion,
            "rotation": quaternion_to_matrix(quaternion),
            "translation": torch.tensor(label["r_Vo2To_vbs_true"], dtype=torch.float32),
            "camera": self.camera.rescaled(size, size).matrix(),
            "model": self.models[model_index],
            "model_index": model_index,
            "index": index,
        }

    def __getitem__(self, item: int) -> dict[str, Any]:
        item = self._item(item)
        sample = self.pixel_item(item)
        points = self.model_points(sample["model_index"])
        rng = np.random.default_rng(self.seed + item)
        surface = points["surface"][rng.choice(len(points["surface"]), self.num_surface,
                                               replace=len(points["surface"]) < self.num_surface)]
        occupancy, labels = balanced_occupancy(points["points"], points["inside"],
                                                self.num_occupancy, rng)
        return {
            **sample,
            "surface_points": torch.from_numpy(surface.astype(np.float32)),
            "occupancy_points": torch.from_numpy(occupancy.astype(np.float32)),
            "occupancy_labels": torch.from_numpy(labels.astype(np.float32)),
        }


def _rendering(root: Path) -> bool:
    """Whether ``root``'s manifest says its rendering has not finished (the last model to
    finish writes splits.csv): False where there is none or it cannot be read."""
    try:
        manifest = read_manifest(root)
    except DatasetError:
        return False
    return manifest is not None and manifest.get("state") == "rendering"
