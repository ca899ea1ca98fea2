"""What the per-image diagnostics share (body_frame_limits.py, reading_spread.py): the
command line (--checkpoint, --data, --split, --images) and the checkpoint, the split and the
indices of IMAGES images spread evenly over it."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sq_mitsuba.data.spe3r import Spe3rDataset
from sq_mitsuba.evaluation.split import open_split
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.inference.predictor import Predictor


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


def open_spread_images(description: str, min_images: int = 1) -> SpreadImages:
    """Parse the command line (argparse's one-line errors, exit 2), then open the checkpoint
    and the split."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split", default="test")
    parser.add_argument("--images", type=int, default=96)
    args = parser.parse_args()
    if args.images < min_images:
        parser.error(f"--images: need at least {min_images}")
    predictor = load_model(args.checkpoint)
    dataset = open_split(args.data, args.split, predictor.image_size, 2000)
    camera = dataset.camera.rescaled(predictor.image_size, predictor.image_size)
    chosen = np.linspace(0, len(dataset) - 1, min(args.images, len(dataset))).round()
    return SpreadImages(args, predictor, dataset, camera, chosen)
