"""What the per-image diagnostics share (body_frame_limits.py, reading_spread.py,
half_turn_hedge.py): the command line (--checkpoint, --data, --split, --images) and the
checkpoint, the split and the indices of IMAGES images spread evenly over it; and, for those
that compare clouds, each image's body-frame reading and true surface thinned to POINTS."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sq_mitsuba.data.spe3r import Spe3rDataset
from sq_mitsuba.evaluation.split import collate, open_split
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.metrics import chamfer_l1, rotation_error_deg
from sq_mitsuba.geometry.so3_grid import axis_turns, half_turns
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.inference.predictor import Predictor
from sq_mitsuba.model.losses import counted_surface_samples

#: Points kept per cloud (readings and truths alike), so that every pair costs the same.
POINTS = 1500


@dataclass
class SpreadImages:
    """A diagnostic's inputs, opened."""

    args: argparse.Namespace
    predictor: Predictor
    dataset: Spe3rDataset
    camera: Camera
    "The dataset's camera at the network's input size."
    chosen: np.ndarray
    "Dataset indices of the images, evenly spread, first and last included."


def open_spread_images(description: str, min_images: int = 1,
                       add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
                       surface_points: int = 2000) -> SpreadImages:
    """Parse the command line (argparse's one-line errors, exit 2; ``add_arguments`` adds a
    script's own options), then open the checkpoint and the split (``surface_points`` per
    item)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split", default="test")
    parser.add_argument("--images", type=int, default=96)
    if add_arguments is not None:
        add_arguments(parser)
    args = parser.parse_args()
    if args.images < min_images:
        parser.error(f"--images: need at least {min_images}")
    predictor = load_model(args.checkpoint)
    dataset = open_split(args.data, args.split, predictor.image_size, surface_points)
    camera = dataset.camera.rescaled(predictor.image_size, predictor.image_size)
    chosen = np.linspace(0, len(dataset) - 1, min(args.images, len(dataset))).round()
    return SpreadImages(args, predictor, dataset, camera, chosen)


def folded_error_deg(rotation: torch.Tensor, truth: torch.Tensor) -> float:
    """The rotation error (3, 3) against (3, 3) up to the four half turns of the body frame,
    degrees, as ``sq-mitsuba eval``'s folded rotation."""
    return float(rotation_error_deg(rotation[None].double(), truth[None].double(),
                                    half_turns())[0])


def axes_error_deg(rotation: torch.Tensor, truth: torch.Tensor) -> float:
    """The rotation error (3, 3) against (3, 3) up to the 24 turns of the body axes (which
    is called x, y or z and their ends), degrees, as ``sq-mitsuba eval``'s axes error: the
    folded error with the axes' best order told."""
    return float(rotation_error_deg(rotation[None].double(), truth[None].double(),
                                    axis_turns())[0])


def back_projected(depth: torch.Tensor, cells: torch.Tensor, depth_origin: float,
                   camera: Camera, stride: int) -> torch.Tensor:
    """(V, 3) camera-frame points, float64, of a depth map (h, w; relative to the body
    origin's depth ``depth_origin``) at the centres of the stride-``stride`` cells ``cells``
    (h, w bool) of the camera's image."""
    rows, cols = torch.nonzero(cells, as_tuple=True)
    centres = torch.stack([cols, rows], -1).double().add(0.5).mul(stride)
    return camera.unproject(centres, depth[rows, cols].double() + depth_origin)


def thinned(cloud: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    """(1, <= POINTS, 3) float64: an evenly drawn subset of a (P, 3) cloud."""
    keep = rng.choice(len(cloud), min(POINTS, len(cloud)), replace=False)
    return cloud[torch.from_numpy(np.sort(keep))].double()[None]


def distance(a: torch.Tensor, b: torch.Tensor) -> float:
    """Chamfer-L1 (the paper's) between two (1, P, 3) clouds."""
    return float(chamfer_l1(a, b, "paper")[0])


def readings_and_truths(spread: SpreadImages, rng: np.random.Generator
                        ) -> Iterator[tuple[str, torch.Tensor, torch.Tensor]]:
    """For each chosen image, in order: its model's name, the network's body-frame reading
    (the kept primitives' surface samples) and the model's true surface points, both thinned
    (the reading drawn first)."""
    for start in range(0, len(spread.chosen), 16):
        batch = collate([spread.dataset[int(i)] for i in spread.chosen[start:start + 16]])
        prediction = spread.predictor.predict(batch["image"], spread.camera)
        for k, model in enumerate(batch["model"]):
            assembly = Assembly(prediction.assembly.params[k:k + 1].detach().double())
            samples, keep = counted_surface_samples(assembly, 3)
            reading = thinned(samples[0][keep[0]], rng)
            yield model, reading, thinned(batch["surface_points"][k], rng)

