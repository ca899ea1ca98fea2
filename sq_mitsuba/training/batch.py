"""The training batch: what the data stream hands the training step, documented once."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["TrainingBatch"]


@dataclass
class TrainingBatch:
    """One process's share of a training step's batch: B images with their labels and the
    ground truth the loss terms compare against (after augmentation, which changes image,
    mask and pose together; the body-frame points are unchanged by it).

    Convention: rotations map body to camera (OpenCV frame), ``x_cam = R x_body + t``; points
    are in the body frame of the model, in metres.
    """

    image: Tensor
    "(B, C, S, S) float32 in [0, 1]: the network's input, S = ``network.image_size``."
    mask: Tensor
    "(B, 1, S, S) float32 in [0, 1]: the target's silhouette."
    rotation: Tensor
    "(B, 3, 3) float32: the true body-to-camera rotation."
    translation: Tensor
    "(B, 3) float32: the true body-to-camera translation, metres."
    model_index: Tensor
    "(B,) int64: each image's model (its row in the dataset's model list)."
    surface_points: Tensor
    "(B, K, 3) float32: points on the model's mesh, K = ``data.num_surface``."
    occupancy_points: Tensor
    "(B, N, 3) float32: labelled points around the model, N = ``data.num_occupancy``."
    occupancy_labels: Tensor
    "(B, N) float32 in {0, 1}: 1 where the point lies inside the model."
    symmetries: Tensor
    """(B, S, 3, 3) float32: body-frame rotations that map each model onto itself (the
    identity among them; shorter sets padded with identities)."""
    surface_normals: Tensor | None = None
    """(B, K, 3) float32: the unit outward normals at ``surface_points`` (body frame; zero
    where the dataset holds none), or None."""

    def __len__(self) -> int:
        return int(self.image.shape[0])

    def to(self, device: torch.device | str) -> TrainingBatch:
        """The batch with every tensor on ``device`` (dtypes kept)."""
        return TrainingBatch(**{f.name: None if getattr(self, f.name) is None
                                else getattr(self, f.name).to(device)
                                for f in dataclasses.fields(self)})
