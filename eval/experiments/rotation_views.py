"""Does the rotation generalise to new views of one model, and how does that grow with views?

The model card's "views per model" test: the network of ``cpu.toml`` (from scratch, 96 px),
trained on the pose loss alone (rotation + translation terms, no shape) on the first
``--views`` training images of a one-model dataset, and scored by the median rotation error
on the first 400 training images used and on every val image (new views of the same model).
Chance is 132 deg (the median angle of a uniformly random rotation).

Make the dataset first (one model of a library; 2,400 images give 1,920 train and 480 val)::

    mkdir -p views/models && ln -s $PWD/data/shipped/models/sc005_single_wing views/models/
    sq-mitsuba dataset render --models views/models --out views/data \\
        --images-per-model 2400 --resolution 96 --spp 16 --workers 2
    python eval/experiments/rotation_views.py views/data --form 6d --steps 1200 --views 160

It prints the two errors every 200 steps. Images and labels are cached in
``DATA/rotation_views.pt`` after the first run.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from sq_mitsuba.data.spe3r import Spe3rDataset
from sq_mitsuba.geometry.rotation import rotation_angle
from sq_mitsuba.learning.losses import ROTATION_FORMS, pose_loss
from sq_mitsuba.learning.network import SuperquadricNet
from sq_mitsuba.learning.train_config import TrainConfig

IMAGE_SIZE = 96
BATCH = 32


def load_split(root: Path, split: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(images (N, 1, S, S), rotations (N, 3, 3), translations (N, 3)) of one split."""
    dataset = Spe3rDataset(root, split, image_size=IMAGE_SIZE, num_surface=1, num_occupancy=2)
    items = [dataset[i] for i in range(len(dataset))]
    return (torch.stack([item["image"] for item in items]),
            torch.stack([item["rotation"] for item in items]).float(),
            torch.stack([item["translation"] for item in items]).float())


def median_error_deg(model: SuperquadricNet, images: torch.Tensor, rotations: torch.Tensor,
                     camera: torch.Tensor) -> float:
    """Median rotation error (degrees) of the model in eval mode."""
    model.eval()
    with torch.no_grad():
        predicted = torch.cat([model(images[i:i + 128], camera).rotation
                               for i in range(0, len(images), 128)])
    model.train()
    return float(torch.rad2deg(rotation_angle(predicted, rotations)).median())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="a one-model dataset folder")
    parser.add_argument("--form", choices=ROTATION_FORMS, default="6d",
                        help="rotation form of the pose loss (default: 6d)")
    parser.add_argument("--steps", type=int, default=1200)
    parser.add_argument("--views", type=int, default=1920,
                        help="training images used: the first VIEWS of the train split")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    cache = args.data / "rotation_views.pt"
    if cache.is_file():
        train, val = torch.load(cache, weights_only=True)
    else:
        train, val = load_split(args.data, "train"), load_split(args.data, "val")
        torch.save((train, val), cache)
    camera = Spe3rDataset(args.data, "val", image_size=IMAGE_SIZE, num_surface=1,
                          num_occupancy=2).camera.rescaled(IMAGE_SIZE, IMAGE_SIZE).matrix()
    images, rotations, translations = (tensor[:args.views] for tensor in train)
    print(f"{len(images)} training views, {len(val[0])} held-out views", flush=True)

    torch.manual_seed(0)
    model = SuperquadricNet(TrainConfig().network).to(memory_format=torch.channels_last)
    optimiser = torch.optim.AdamW(model.parameters(), lr=1e-3, eps=1e-8, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, 1e-3, total_steps=args.steps,
                                                   pct_start=0.05)
    generator = torch.Generator().manual_seed(1)
    start = time.time()
    for step in range(1, args.steps + 1):
        batch = torch.randint(0, len(images), (BATCH,), generator=generator)
        output = model(images[batch].contiguous(memory_format=torch.channels_last), camera)
        rotation_term, translation_term = pose_loss(
            output.rotation, output.translation, rotations[batch], translations[batch],
            rotation_form=args.form, pred_rotation_6d=output.rotation_6d)
        loss = rotation_term.mean() + translation_term.mean()
        optimiser.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimiser.step()
        schedule.step()
        if step % 200 == 0 or step == args.steps:
            seen = median_error_deg(model, images[:400], rotations[:400], camera)
            held_out = median_error_deg(model, val[0], val[1], camera)
            print(f"step {step}: loss {loss.item():.3f}, median E_R training views "
                  f"{seen:.1f} deg, held-out views {held_out:.1f} deg "
                  f"({time.time() - start:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
