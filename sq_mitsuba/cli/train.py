"""``sq-mitsuba train``: train the superquadric network on an SPE3R-layout dataset."""

from __future__ import annotations

import argparse
from pathlib import Path

from sq_mitsuba.cli import CLIError
from sq_mitsuba.cli._options import input_file_path, output_path
from sq_mitsuba.io import inside_folder
from sq_mitsuba.machine import launch_ranks

HELP = "train the network on a dataset"
DESCRIPTION = """\
Train the superquadric network (an EfficientNet encoder, M superquadrics, a pose head and
optionally a mask head, each chosen by name under [network]) on the train split of an
SPE3R-layout dataset, validating on a subset of its val split.

The run is described by a TOML config (train/configs/: the paper's Table 1 (a)-(d) and
Table 2's M = 4..8, this project's CPU recipe cpu.toml, cpu_lite0.toml with the network that
reads the pose, shipped.toml for the archetype model's first stage (the shipped model's
recipe is train/shipped_model.sh), tiny.toml for smoke tests), changed
field by field with --set (dotted names, TOML values). A config file may start from another
with a top-level  base = "other.toml".

Writes into --out: config.json, log.csv (one row per step), val.csv, curves.png (refreshed at
each validation), last.pt and best.pt (atomic checkpoints; best.pt is the last state, and the
run says so, when it stops before the first validation), tensorboard/ when tensorboard is
installed, and cache/ (the training images decoded once, and the models' symmetries, unless
data.cache_dir is set). The dataset is only read. One run at a time per --out: a second run
into a folder another run is writing stops with one line (exit code 2). On the CPU, a run
whose batch would not fit in this machine's memory (an estimate) is refused the same way,
before anything is written, naming the --set key to lower.

--resume continues the run in --out from last.pt exactly where it stopped (same config and
dataset required; the config defaults to the checkpoint's; bit for bit in one process on the
CPU, up to float rounding under torchrun). To train longer, start a new run from the last
one's weights (--set init_from=RUN/last.pt; the optimiser starts afresh). A corrupt image
stops the cache build with an error naming the file; a loss that is not finite stops training
and leaves the last checkpoint as it was.

Distributed: .venv/bin/torchrun --nproc_per_node N .venv/bin/sq-mitsuba train ... runs N
processes (gloo on the CPU, nccl on CUDA) that split each batch of optim.batch_size images.
A part of the network whose output no weighted loss term reads is refused there (a mask head
with loss.weights.mask = 0): every trained parameter needs a gradient.

Fields (--set key=value) and their defaults:
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from sq_mitsuba.config import describe
    from sq_mitsuba.training.config import TrainConfig

    parser = subparsers.add_parser(
        "train", help=HELP,
        description=DESCRIPTION + describe(TrainConfig),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=input_file_path, metavar="TOML",
                        help="training config (default: the checkpoint's with --resume, else "
                             "the defaults listed below)")
    parser.add_argument("--data", type=Path, required=True, metavar="DIR",
                        help="SPE3R-layout dataset folder")
    parser.add_argument("--out", type=output_path, required=True, metavar="RUN_DIR",
                        help="run folder (created; must not hold a run unless --resume)")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="override a config field (dotted, e.g. optim.lr=3e-4); repeatable")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last.pt")
    parser.add_argument("--max-steps", type=int, metavar="N",
                        help="stop after N steps in total (the schedule still spans every "
                             "epoch; --resume continues; 0 checks everything, builds the caches "
                             "and stops before the first step, with no checkpoint to resume "
                             "from; default: no stop before the end)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from sq_mitsuba.machine import narrow_to_local_gpu

    narrow_to_local_gpu()  # before torch starts CUDA: each torchrun process renders on its GPU
    from sq_mitsuba.config import ConfigError, apply_overrides, from_dict
    from sq_mitsuba.training.config import TrainConfig, load_train_config
    from sq_mitsuba.training.train import train

    if args.max_steps is not None and args.max_steps < 0:
        raise CLIError(f"--max-steps: expected >= 0, got {args.max_steps}")
    if inside_folder(args.out, args.data):  # the run's files would become part of the dataset
        raise CLIError(f"--out {args.out}: inside the dataset folder {args.data}, which "
                       "training only reads; choose a run folder outside it")
    config = None
    if args.config is not None:
        config = load_train_config(args.config)
    if args.overrides:
        if config is None and args.resume:
            config = _checkpoint_config(args.out, from_dict, TrainConfig)
        try:
            config = apply_overrides(config or TrainConfig(), args.overrides)
        except ConfigError as error:
            raise CLIError(f"--set {error}") from None
    result = train(config, args.data, args.out, resume=args.resume, max_steps=args.max_steps,
                   progress=not args.quiet)
    rate = "" if result.images_per_second != result.images_per_second else (
        f", {result.images_per_second:.1f} images/s")
    best = ""
    if result.validation:
        last = result.validation[-1]
        best = (f"; last validation: Chamfer-L1 {last['chamfer_l1']:.4f}, 2D IoU "
                f"{last['iou_2d']:.3f}, rotation error {last['rotation_error_deg']:.1f} deg")
    if launch_ranks().rank > 0:  # one summary for a torchrun run: rank 0's
        return 0
    if result.steps == 0 and result.last_checkpoint is None:
        # --max-steps 0, its documented use (help above): not "trained 0/N steps; wrote OUT",
        # which reads as a run to resume.
        print(f"--max-steps 0: checked the config and the dataset and built the caches, then "
              f"stopped before the first step; no checkpoint written, so nothing to --resume "
              f"(training into {result.out_dir} again starts the run)")
        return 0
    print(f"trained {result.steps}/{result.total_steps} steps{rate}{best}; wrote "
          f"{result.out_dir}")
    for note in result.notes:
        print(f"note: {note}")
    return 0


def _checkpoint_config(out: Path, from_dict: object, config_class: type) -> object:
    """The config recorded in ``out/last.pt`` (for --resume --set without --config)."""
    from sq_mitsuba.model.checkpoint import read_checkpoint

    path = out / "last.pt"
    if not path.is_file():
        raise CLIError(f"{out}: nothing to resume (no last.pt)")
    return from_dict(config_class, read_checkpoint(path)["config"])  # type: ignore[operator]
