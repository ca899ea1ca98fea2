"""``sq-mitsuba dataset render | check | preview | fit-parts``: SPE3R-layout datasets rendered by
Mitsuba, and the part targets of their training models."""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from sq_mitsuba.cli._options import (
    add_config_options,
    add_set_option,
    config_from_args,
    input_file_path,
    output_file_path,
    output_path,
)

HELP = "render, check and preview datasets in the SPE3R layout"
RENDER_DESCRIPTION = """\
Render every model of --models (a `sq-mitsuba models generate` folder) in the space scene.

OUT/dataset.json records the settings (seed, resolution, spp, exr, camera, scene) before the
first image. Running again with the same settings resumes an interrupted run; with a larger
--images-per-model it adds exactly the images a larger run would have written. Other
settings stop with an error naming them and touch nothing, unless --overwrite: that first
deletes OUT's dataset.json, camera.json, splits.csv, failures.json, preview.png, .failures/,
the model folders its dataset.json lists and the tool's temporary files (nothing else; a
non-empty OUT without a dataset.json of this tool is refused, --overwrite or not). --shard
I/N renders block I of N of the work (0 <= I < N): N shards into the same OUT, on as many
machines, in any order, equal one unsharded run byte for byte; the last to finish writes
splits.csv. A model's split is its row in the library's splits.csv or, without that file,
the one its model_card.json records (else train, with a warning). Every model's files are
read first: one that cannot be read stops the run before any work. Models that fail while
rendering are left out of splits.csv and listed with their reason in OUT/failures.json. Exit
code 1 when a model failed, 2 on bad options or a broken model (nothing written)."""

#: RenderOptions fields exposed as options.
RENDER_FLAGS = {"images_per_model": "--images-per-model", "seed": "--seed",
                "resolution": "--resolution", "spp": "--spp", "exr": "--exr",
                "camera": "--camera", "workers": "--workers", "shard": "--shard",
                "overwrite": "--overwrite", "pass_frames": "--pass-frames"}
CHECK_FLAGS = {"per_model": "--per-model", "min_iou": "--min-iou", "spp": "--spp"}
PREVIEW_FLAGS = {"count": "--count", "axis_length": "--axis-length"}


def register(subparsers: argparse._SubParsersAction) -> None:
    # Imported here: these import torch, which `sq-mitsuba --help` does without.
    from sq_mitsuba.data.spe3r.check import CheckOptions
    from sq_mitsuba.data.spe3r.preview import PreviewOptions
    from sq_mitsuba.data.spe3r.render_options import RenderOptions
    from sq_mitsuba.render.scene_config import SceneConfig

    parser = subparsers.add_parser(
        "dataset", help=HELP,
        description="Physically based datasets (images, masks, pose labels) in the SPE3R layout.")
    commands = parser.add_subparsers(dest="dataset_command", metavar="ACTION", required=True)

    render = commands.add_parser(
        "render", help="path-trace images, masks and labels of every model",
        description=RENDER_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    render.add_argument("--models", type=Path, required=True, help="model library folder")
    render.add_argument("--out", type=output_path, required=True, help="dataset folder to write")
    add_config_options(render, RenderOptions, RENDER_FLAGS,
                       metavars={"camera": "JSON", "shard": "I/N"})
    render.add_argument("--scene", type=input_file_path, default=None, metavar="FILE",
                        help="scene configuration, JSON or TOML (default scenes/space.json); "
                             "fields it leaves out keep their defaults")
    add_set_option(render, "scene configuration", "sun.irradiance=1000",
                   SceneConfig)
    render.add_argument("--quiet", action="store_true", help="no progress bar")
    render.set_defaults(func=_render)

    check = commands.add_parser(
        "check", help="validate a dataset: bookkeeping, files, labels, label/mask agreement",
        description="Check the manifest and splits, look for stray files, decode every image "
                    "and mask, check every label, and re-render each model's mesh at label "
                    "poses to compare with the stored masks (pixels an edge leaves ambiguous "
                    "are left out, so the threshold holds at any resolution). Exit code 1 "
                    "when a problem is found, 2 on bad options.")
    check.add_argument("root", type=Path, help="dataset folder")
    add_config_options(check, CheckOptions, CHECK_FLAGS)
    check.add_argument("--quiet", action="store_true", help="no progress bar")
    check.set_defaults(func=_check)

    preview = commands.add_parser(
        "preview", help="contact sheet of images with mask outlines and pose axes",
        description="A contact sheet of --count images of a rendered dataset, spread over its "
                    "models: each image with its mask's outline and the body axes drawn at its "
                    "labelled pose (x red, y green, z blue), to see that labels, masks and "
                    "images agree. The dataset is only read.")
    preview.add_argument("root", type=Path, help="dataset folder")
    preview.add_argument("--out", type=output_file_path, default=None, metavar="PNG",
                         help="PNG to write (default ROOT_preview.png beside the dataset "
                              "folder, which is only read)")
    add_config_options(preview, PreviewOptions, PREVIEW_FLAGS)
    preview.set_defaults(func=_preview)

    fit_parts = commands.add_parser(
        "fit-parts", help="fit each training model's own assembly (targets of the parts term)",
        description="Fit M superquadrics to the surface of every model of the train split, "
                    "each from the network's initial layout (300 Adam steps on the Chamfer "
                    "term), and write them beside each mesh as models/part_targets.npz: the "
                    "targets of the `parts` loss term (a training config's loss.weights.parts). "
                    "Models that already have a fit made with these settings (M, --steps) are "
                    "skipped, so an interrupted run resumes; a fit made with other settings "
                    "is fitted again, and the count of those and their earlier settings are "
                    "printed. "
                    "Exit code 2 on bad options or a dataset that cannot be read.")
    fit_parts.add_argument("root", type=Path, help="dataset folder")
    fit_parts.add_argument("--primitives", type=int, default=5, metavar="M",
                           help="primitives per assembly: the network's num_primitives "
                                "(default 5)")
    fit_parts.add_argument("--steps", type=int, default=300, help="Adam steps (default 300)")
    fit_parts.add_argument("--quiet", action="store_true", help="no progress bar")
    fit_parts.set_defaults(func=_fit_parts)


def _render(args: argparse.Namespace) -> int:
    from sq_mitsuba.data.spe3r.render_options import RenderOptions
    from sq_mitsuba.data.spe3r.writer import render_dataset
    from sq_mitsuba.render.scene_config import SceneConfig

    # --scene, then --set: the scene configuration (the --set keys are the scene's fields);
    # then the render options from their flags, with that scene.
    scene = config_from_args(SceneConfig, argparse.Namespace(overrides=args.overrides),
                             base=SceneConfig.load(args.scene))
    options = config_from_args(RenderOptions, argparse.Namespace(**{**vars(args),
                                                                   "overrides": []}),
                               scene=scene)
    summary = render_dataset(args.models, args.out, options, progress=not args.quiet)
    shard = "" if options.shard_count == 1 else f"shard {options.shard}: "
    print(f"{shard}{len(summary.models_done)} models done ({summary.rendered} images rendered, "
          f"{summary.skipped} already there) in {args.out}")
    for model, reason in summary.failures.items():
        print(f"FAILED {model}: {reason}")
    if not summary.complete:
        print("the dataset is not complete yet: other shards still have work (the last to "
              "finish writes splits.csv), or failed shards must be run again")
    return 1 if summary.failures else 0


def _check(args: argparse.Namespace) -> int:
    from sq_mitsuba.data.spe3r.check import CheckOptions, check_dataset

    report = check_dataset(args.root, config_from_args(CheckOptions, args),
                           progress=not args.quiet)
    print(report.summary())
    return 0 if report.ok else 1


def _preview(args: argparse.Namespace) -> int:
    from sq_mitsuba.data.spe3r.preview import PreviewOptions, preview_dataset

    out = preview_dataset(args.root, args.out, config_from_args(PreviewOptions, args))
    print(f"wrote {out}")
    return 0


def _fit_parts(args: argparse.Namespace) -> int:
    from sq_mitsuba.cli import CLIError
    from sq_mitsuba.data.spe3r.layout import read_splits
    from sq_mitsuba.training.part_targets import fit_part_targets

    if not 1 <= args.primitives <= 64:
        raise CLIError(f"--primitives: expected 1-64, got {args.primitives}")
    if not 1 <= args.steps <= 100_000:
        raise CLIError(f"--steps: expected 1-100000, got {args.steps}")
    splits = args.root / "splits.csv"
    if not splits.is_file():
        raise CLIError(f"{splits}: missing (not a dataset folder?)")
    models = sorted(m for m, split in read_splits(splits).items() if split == "train")
    if not models:
        raise CLIError(f"{splits}: no train models")
    fits = fit_part_targets(args.root, models, args.primitives, steps=args.steps,
                            progress=not args.quiet)
    refitted = ""
    if fits.refitted:
        # Each distinct earlier setting once, with how many fits had it.
        earlier = Counter(fits.refitted.values())
        refitted = (f" ({len(fits.refitted)} of them fitted again: made with "
                    + "; ".join(f"{setting} ({n})" for setting, n in sorted(earlier.items()))
                    + ")")
    print(f"part targets of {len(models)} train models (M = {args.primitives}, steps "
          f"{args.steps}): {fits.fitted} fitted{refitted}, {len(models) - fits.fitted} already "
          f"there, in {args.root}")
    return 0
