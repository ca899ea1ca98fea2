"""``sq-mitsuba fit``: fit a superquadric assembly to binary masks seen from known poses."""

from __future__ import annotations

import argparse

from sq_mitsuba.cli._options import (
    add_config_options,
    add_set_option,
    config_from_args,
    input_file_path,
    output_path,
)

HELP = "fit superquadrics to masks seen from known poses"
DESCRIPTION = """\
Fit an assembly of M superquadrics to one or more binary masks with a known camera and known
poses, by gradient descent (Adam) through Mitsuba's differentiable silhouettes; the losses of
all views are summed.

Inputs:
  --masks    PNG/JPG masks, object bright, all of one size (the camera's). Binary 8-bit gray
             is read as is; RGB and palette images are converted to gray (luminance), RGBA
             composited on black first, 16-bit kept at 16 bits; then a pixel is object when
             above half the range (> 127 of 255, > 32767 of 65535). An all-background mask
             is an error.
  --poses    SPE3R-style labels.json: a list of {"filename": ..., "q_vbs2tango_true": [w, x,
             y, z], "r_Vo2To_vbs_true": [x, y, z]}; a mask takes the entry whose filename has
             the same stem (img000001.png <- img000001.jpg). The pose maps body to camera
             (OpenCV frame: x right, y down, z forward): x_cam = R(q) x_body + r; q must be
             a unit quaternion (norm 1 within 1e-3), r in metres, in front of the camera
             and near enough for an assembly (at most 5 m across) to span the mask.
  --camera   SPEED-style camera.json (Nu, Nv, cameraMatrix in pixels); default: the project's
             default camera (SPEED field of view) at the masks' size.

Every input is checked before the fit starts (a bad one is a one-line error naming the file
and entry, exit code 2, nothing written), including the memory the --resolution needs.

Outputs in --out: assembly.json (the fitted parameters), assembly.glb (one mesh per
primitive), fit.png (masks against fitted silhouettes at the start, middle and end) and
fit_log.json (inputs, options, loss and IoU per step, final IoU per view).
"""

#: FitOptions fields exposed as options; the rest are reachable through --set.
FLAGS = {"num_primitives": "--primitives", "steps": "--steps", "resolution": "--resolution",
         "lr": "--lr", "loss": "--loss", "spp": "--spp", "seed": "--seed"}


def register(subparsers: argparse._SubParsersAction) -> None:
    # Imported here: it imports torch, which `sq-mitsuba --help` does without (see HELP).
    from sq_mitsuba.inference.fit import FitOptions

    parser = subparsers.add_parser(
        "fit", help=HELP,
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--masks", nargs="+", required=True, type=input_file_path, metavar="PNG",
                        help="mask images, one per view")
    parser.add_argument("--poses", required=True, type=input_file_path, metavar="JSON",
                        help="SPE3R-style labels.json with a pose per mask")
    parser.add_argument("--camera", type=input_file_path, metavar="JSON",
                        help="SPEED-style camera.json (default: the default camera)")
    parser.add_argument("--out", required=True, type=output_path, metavar="DIR",
                        help="output folder (created)")
    add_config_options(parser, FitOptions, FLAGS, metavars={"num_primitives": "M",
                                                            "steps": "N"})
    add_set_option(parser, "fit options", "level=4")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from sq_mitsuba.apps.fit_run import run_fit
    from sq_mitsuba.inference.fit import FitOptions

    options = config_from_args(FitOptions, args)
    run = run_fit(args.masks, args.poses, args.out, options, camera=args.camera,
                  progress=not args.quiet)
    print(run.summary())
    return 0
