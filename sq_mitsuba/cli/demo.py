"""``sq-mitsuba demo``: unseen spacecraft in, superquadric assemblies and poses out, as a page."""

from __future__ import annotations

import argparse
from pathlib import Path

from sq_mitsuba.cli import CLIError
from sq_mitsuba.cli._options import (
    add_config_options,
    add_set_option,
    config_from_args,
    input_file_path,
    output_path,
    refuse_unused_settings,
)

HELP = "the front door: predict unseen spacecraft from single images, as a web page"
DESCRIPTION = """\
One image in, a superquadric assembly and a pose out, on spacecraft the model never saw.

Generates a few procedural spacecraft from catalogue seed --seed (default 20261122; the
shipped model trains on catalogue seed 0, so these are new to it), path-traces images of each
in the default space scene, predicts every image with the model, searches its pose globally
and refines it at test time through Mitsuba silhouettes against the mask read from the image
(the network's mask head, or the threshold segmentation for a model without one; the page
names it), and scores the network, the searched and refined prediction and the trivial
baseline (the mean training assembly at the mean training pose, as stored with the
checkpoint; without one, computed over the demo's own images) with the metrics of
`sq-mitsuba eval`. Then it renders a pass of a few frames of the first spacecraft (the target
tumbling while the camera approaches) and predicts one assembly and every frame's pose from
them at once (`predict --sequence`), scored per frame beside each frame alone.

Writes --out (default demo_output): index.html and its Markdown twin index.md (input, the
silhouettes before and after refinement, the predicted assembly with one colour per primitive
beside the true mesh, metrics per image, a summary table against the baseline, links to each
assembly's JSON and GLB, and the pass: its shared assembly from six sides, an overlay per
frame, its metrics), per_image.csv and summary.csv, the generated models (models/), the
rendered dataset (data/) and the pass (pass/: its frames, the files of predict --sequence,
per_frame.csv). The folder is replaced as a whole, only once the new demo is
complete; it must be absent, empty or an earlier demo.

Sizes (--size):
{sizes}
The default size takes about a minute and a half on 2 CPU cores with the shipped model
(measured: 61-93 s wall on AVX2-only VMs, of which 5-19 s the pass of 8 frames; on the
slower runs 34-39 s predicting, refining and scoring 15 images), a few minutes with a network that
takes 128 px or more.

--train first trains a small model from scratch (a small library of the training catalogue,
a small dataset, train/configs/tiny.toml with the overrides of --set training.overrides;
measured: 2.6-5.8 minutes in all on 2 cores, by CPU) and demonstrates that model, with its training
curves on the page. It needs the repository's train/configs/ (an editable install).

Without --checkpoint the model shipped with the package is used; when there is none, or the
checkpoint is missing or unusable, or --out is unusable, the command stops with a one-line
error before any work (exit code 2)."""

#: DemoOptions fields exposed as options (--size is checked here: one line on a bad value).
FLAGS = {"seed": "--seed", "train": "--train"}


def register(subparsers: argparse._SubParsersAction) -> None:
    # Imported here: it imports torch, which `sq-mitsuba --help` does without (see HELP).
    from sq_mitsuba.apps.demo_options import SIZES, DemoOptions, describe_sizes
    from sq_mitsuba.config import field_docs

    parser = subparsers.add_parser(
        "demo", help=HELP, description=DESCRIPTION.format(sizes=describe_sizes()),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    # A plain string, checked in _run: argparse's own choices error takes two lines.
    # Default None: only a --size typed counts as given (--set size=... is then the one).
    parser.add_argument("--size", default=None, metavar="{" + ",".join(SIZES) + "}",
                        help=" ".join(field_docs(DemoOptions)["size"].split()).rstrip(".")
                        + f" (default: {DemoOptions().size})")
    parser.add_argument("--out", type=output_path, default=Path("demo_output"), metavar="DIR",
                        help="output folder, replaced as a whole (default: demo_output)")
    parser.add_argument("--checkpoint", type=input_file_path, default=None, metavar="PT",
                        help="checkpoint file (default: the model shipped with the package)")
    add_config_options(parser, DemoOptions, FLAGS)
    add_set_option(parser, "demo options", "silhouette_spp=64")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from sq_mitsuba.apps.demo import run_demo
    from sq_mitsuba.apps.demo_options import SIZES, DemoOptions

    if args.size is not None and args.size not in SIZES:
        raise CLIError(f"--size: expected one of {', '.join(SIZES)}, got {args.size!r}")
    extra = {} if args.size is None else {"size": args.size}
    options = config_from_args(DemoOptions, args, **extra)
    if not options.train:  # they would act on nothing
        refuse_unused_settings(args, ("training",), "--train")
    result = run_demo(options, args.out, args.checkpoint, progress=not args.quiet)
    print(result.describe())
    return 0
