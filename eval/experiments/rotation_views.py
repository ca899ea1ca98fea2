"""Does the rotation generalise to new views of one model, and how does that grow with views?

The "views per model" test of eval/experiments/README.md: ``cpu.toml`` trained by the real trainer
(:func:`sq_mitsuba.training.train.train`) on the pose loss alone (the rotation term ``--term``
and the translation term, weight 1 each; no shape term, no augmentation, no validation) on the
first ``--views`` training images of a one-model dataset, and scored by the median rotation
error on the first 400 training images used and on every val image (new views of the same
model). Chance is 132 deg (the median angle of a uniformly random rotation).

Make the dataset first (one model of a library; 2,400 images give 1,920 train and 480 val)::

    mkdir -p views/models && ln -s $PWD/data/shipped/models/sc005_single_wing views/models/
    sq-mitsuba dataset render --models views/models --out views/data \\
        --images-per-model 2400 --resolution 96 --spp 16 --workers 2
    python eval/experiments/rotation_views.py views/data --term rotation_6d --steps 1200 \\
        --views 160

It prints the two errors every 200 steps (the run resumes between checks, one schedule over
``--steps``). The run goes to ``DATA/rotation_views_runs/TERM_VIEWS`` (replaced on each
call); the scored images and labels are cached in ``DATA/rotation_views.pt`` after the first
run.
"""

from __future__ import annotations

import argparse
import math
import shutil
import time
from pathlib import Path

import torch

from sq_mitsuba.config import apply_overrides
from sq_mitsuba.data.spe3r import Spe3rDataset
from sq_mitsuba.geometry.metrics import rotation_error_deg
from sq_mitsuba.model.checkpoint import read_checkpoint
from sq_mitsuba.model.network import SuperquadricNet
from sq_mitsuba.training.config import load_train_config
from sq_mitsuba.training.train import train

CONFIG = Path(__file__).resolve().parents[2] / "train" / "configs" / "cpu.toml"
ROTATION_TERMS = ("rotation_6d", "rotation")
CHECK_EVERY = 200


def load_split(root: Path, split: str, size: int) -> tuple[torch.Tensor, torch.Tensor,
                                                          torch.Tensor]:
    """(images (N, 1, S, S), rotations (N, 3, 3), translations (N, 3)) of one split."""
    dataset = Spe3rDataset(root, split, image_size=size, num_surface=1, num_occupancy=2)
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
    return float(rotation_error_deg(predicted, rotations).median())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="a one-model dataset folder")
    parser.add_argument("--term", choices=ROTATION_TERMS, default="rotation_6d",
                        help="rotation loss term (default: rotation_6d)")
    parser.add_argument("--steps", type=int, default=1200)
    parser.add_argument("--views", type=int, default=1920,
                        help="training images used: the first VIEWS of the train split")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    weights = f"{{{args.term} = 1.0, translation = 1.0}}"
    config = apply_overrides(load_train_config(CONFIG), [
        f"loss.weights={weights}", f"data.train_images={args.views}",
        "augment.probability=0.0", "validation.every=0", "checkpoint_every=0",
        "optim.epochs=1", "seed=0"])
    size = config.network.image_size
    cache = args.data / "rotation_views.pt"
    if cache.is_file():
        train_split, val = torch.load(cache, weights_only=True)
    else:
        train_split, val = load_split(args.data, "train", size), load_split(args.data, "val",
                                                                           size)
        torch.save((train_split, val), cache)
    images, rotations = (tensor[:args.views] for tensor in train_split[:2])
    # One schedule over --steps: an epoch is ceil(views / batch) steps.
    per_epoch = math.ceil(min(args.views, len(train_split[0])) / config.optim.batch_size)
    config = apply_overrides(config, [f"optim.epochs={math.ceil(args.steps / per_epoch)}"])
    camera = Spe3rDataset(args.data, "val", image_size=size, num_surface=1,
                          num_occupancy=2).camera.rescaled(size, size).matrix()
    print(f"{len(images)} training views, {len(val[0])} held-out views", flush=True)

    run = args.data / "rotation_views_runs" / f"{args.term}_{args.views}"
    shutil.rmtree(run, ignore_errors=True)
    start = time.time()
    done = 0
    while done < args.steps:
        result = train(config, args.data, run, resume=done > 0, progress=False,
                       max_steps=min(args.steps, done + CHECK_EVERY))
        done = result.steps
        model = SuperquadricNet(config.network)
        model.load_state_dict(read_checkpoint(run / "last.pt")["model"])
        seen = median_error_deg(model, images[:400], rotations[:400], camera)
        held_out = median_error_deg(model, val[0], val[1], camera)
        print(f"step {done}: loss {result.losses[-1]:.3f}, median E_R training views "
              f"{seen:.1f} deg, held-out views {held_out:.1f} deg "
              f"({time.time() - start:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
