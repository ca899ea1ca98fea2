"""A torch Dataset over an SPE3R-layout folder (ours, or the SPE3R release)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from sq_mitsuba.data.spe3r.layout import (
    IMAGES,
    MASKS,
    VALIDATION_INDICES,
    DatasetError,
    balanced_occupancy,
    model_points,
    read_gray,
    read_splits,
)
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import quaternion_to_matrix
from sq_mitsuba.io import read_json


def _resize(array: np.ndarray, size: int, resample: int) -> np.ndarray:
    if array.shape == (size, size):
        return array
    return np.asarray(Image.fromarray(array).resize((size, size), resample))


class Spe3rDataset(torch.utils.data.Dataset):
    """A torch Dataset over an SPE3R-layout folder (ours, or the SPE3R release).

    Each item is a dict: ``image`` (1, S, S) float in [0, 1]; ``mask`` (1, S, S) float in
    {0, 1}; ``quaternion`` (4,), ``rotation`` (3, 3) and ``translation`` (3,), the pose body ->
    camera; ``camera`` (3, 3) intrinsics for S x S pixels; ``model`` (str) and ``model_index``;
    ``surface_points`` (num_surface, 3); ``occupancy_points`` (num_occupancy, 3) with
    ``occupancy_labels`` (num_occupancy,), half inside and half outside where the model has
    enough of each; ``index`` of the image within its model.

    Args:
        root: dataset folder.
        split: "train", "val" (images 400-499 and 900-999 of the train models) or "test".
        image_size: S, the side images and masks are resized to (default 128).
        num_surface, num_occupancy: points per item (2,500 and 10,000 by default).
        seed: makes the point subsets reproducible (item i uses seed + i).
    """

    def __init__(self, root: str | Path, split: str = "train", image_size: int = 128,
                 num_surface: int = 2500, num_occupancy: int = 10_000, seed: int = 0):
        if split not in ("train", "val", "test"):
            raise ValueError(f"split: expected 'train', 'val' or 'test', got {split!r}")
        self.root = Path(root)
        for required in ("camera.json", "splits.csv"):
            if not (self.root / required).is_file():
                raise DatasetError(f"{self.root / required}: missing")
        self.camera = Camera.load(self.root / "camera.json")
        self.image_size, self.seed = image_size, seed
        self.num_surface, self.num_occupancy = num_surface, num_occupancy
        splits = read_splits(self.root / "splits.csv")
        wanted = "test" if split == "test" else "train"
        self.models = sorted(m for m, s in splits.items() if s == wanted)
        self.items: list[tuple[int, int, dict[str, Any]]] = []
        for model_index, model in enumerate(self.models):
            labels_path = self.root / model / "labels.json"
            try:
                labels = read_json(labels_path)
            except FileNotFoundError:
                raise DatasetError(f"{labels_path}: missing") from None
            except ValueError as error:
                raise DatasetError(str(error)) from None
            for index, label in enumerate(labels):
                in_val = index in VALIDATION_INDICES
                if split == "test" or (split == "val") == in_val:
                    self.items.append((model_index, index, label))
        self._points: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.items)

    def _image_path(self, model: str, folder: str, filename: str) -> Path:
        path = self.root / model / folder / filename
        if path.is_file():
            return path
        for suffix in (".png", ".jpg", ".jpeg"):
            candidate = path.with_suffix(suffix)
            if candidate.is_file():
                return candidate
        raise DatasetError(f"{path}: missing")

    def model_points(self, model_index: int) -> dict[str, np.ndarray]:
        """Surface and labelled occupancy points of a model (from samples.npz, or the mesh)."""
        if model_index not in self._points:
            self._points[model_index] = model_points(self.root / self.models[model_index])
        return self._points[model_index]

    def __getitem__(self, item: int) -> dict[str, Any]:
        model_index, index, label = self.items[item]
        model = self.models[model_index]
        size = self.image_size
        image = _resize(read_gray(self._image_path(model, IMAGES, label["filename"])), size,
                        Image.BILINEAR)
        mask = _resize(read_gray(self._image_path(model, MASKS, label["filename"])), size,
                       Image.NEAREST)
        quaternion = torch.tensor(label["q_vbs2tango_true"], dtype=torch.float32)
        camera = self.camera.rescaled(size, size)
        points = self.model_points(model_index)
        rng = np.random.default_rng(self.seed + item)
        surface = points["surface"][rng.choice(len(points["surface"]), self.num_surface,
                                               replace=len(points["surface"]) < self.num_surface)]
        occupancy, labels = balanced_occupancy(points["points"], points["inside"],
                                                self.num_occupancy, rng)
        return {
            "image": torch.from_numpy(image.astype(np.float32) / 255.0)[None],
            "mask": torch.from_numpy((mask >= 128).astype(np.float32))[None],
            "quaternion": quaternion,
            "rotation": quaternion_to_matrix(quaternion),
            "translation": torch.tensor(label["r_Vo2To_vbs_true"], dtype=torch.float32),
            "camera": camera.matrix(),
            "model": model,
            "model_index": model_index,
            "index": index,
            "surface_points": torch.from_numpy(surface.astype(np.float32)),
            "occupancy_points": torch.from_numpy(occupancy.astype(np.float32)),
            "occupancy_labels": torch.from_numpy(labels.astype(np.float32)),
        }

