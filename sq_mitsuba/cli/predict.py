"""``sq-mitsuba predict``: images in; assembly, meshes, pose and overlay per image out."""

from __future__ import annotations

import argparse
from pathlib import Path

from sq_mitsuba.cli._options import add_config_options, add_set_option, config_from_args

HELP = "predict superquadric assemblies and poses from images"
DESCRIPTION = """\
Predict, for each image, an assembly of superquadrics and the target's pose, and write into
--out per image <stem>: <stem>.assembly.json, <stem>.obj (merged mesh), <stem>.glb (one mesh
per primitive), <stem>.pose.json (quaternion q_vbs2tango = (w, x, y, z) and translation
r_Vo2To_vbs in metres: x_cam = R(q) x_body + r, OpenCV camera frame) and <stem>.overlay.png
(the network's silhouette in red; refined, in green; the mask's outline in yellow). Prints
the milliseconds per image.

Images: any size; RGB and palette images are converted to grey (luminance), an alpha channel
composites them on black, 16-bit images keep their range. The camera is the checkpoint's
(the dataset's), rescaled to each image, unless --camera gives the images' own (SPEED-style
camera.json). Without --camera, an image of another aspect ratio is padded with black to the
camera's (its field of view then lies across the image's longer side; pose.json records the
camera of the image's own pixels and a warning); with --camera it is an error naming the file.

--refine searches the pose globally (the network's rotation, or a uniform grid for a network
without a rotation distribution head, times the four half turns of the body frame, scored by
Mitsuba silhouettes; --set search.candidates=hypotheses adds its top-K hypotheses), then refines the
best few, against its --mask (one per image, same size, target bright) or, without masks, the
mask the network predicts (a mask segmented from the image for a model without a mask head;
--set mask=segmentation forces it); the line printed and pose.json name the mask fitted.
Silhouettes cannot tell apart poses with the same outline. Every input is
checked before the first prediction (a bad one is a one-line error, exit code 2, nothing
written). Without --checkpoint the model shipped with the package is used."""

FLAGS = {"refine": "--refine", "level": "--level", "fast": "--fast"}


def register(subparsers: argparse._SubParsersAction) -> None:
    from sq_mitsuba.apps.predict import PredictOptions

    parser = subparsers.add_parser("predict", help=HELP, description=DESCRIPTION,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="input images")
    parser.add_argument("--checkpoint", type=Path, default=None, metavar="PT",
                        help="checkpoint file (default: the model shipped with the package)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output folder (created)")
    parser.add_argument("--camera", type=Path, default=None, metavar="JSON",
                        help="SPEED-style camera.json of the images (default: the "
                             "checkpoint's camera, rescaled to each image)")
    parser.add_argument("--mask", nargs="+", type=Path, default=None, metavar="MASK",
                        help="with --refine: one mask per image, in the same order "
                             "(default: the network's mask, or one segmented from each image "
                             "for a model without a mask head)")
    add_config_options(parser, PredictOptions, FLAGS)
    add_set_option(parser, "predict options", "refinement.steps=20")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from sq_mitsuba.apps.predict import PredictOptions, predict_images

    options = config_from_args(PredictOptions, args)
    records = predict_images(args.images, args.out, args.checkpoint, args.camera, args.mask,
                             options, progress=not args.quiet)
    for record in records:
        print(record.describe())
    network = sum(r.network_ms for r in records) / len(records)
    line = f"{len(records)} image(s): network {network:.1f} ms per image"
    if options.refine:
        line += (f", search {sum(r.search_ms for r in records) / len(records):.0f} ms, search + "
                 f"refinement {sum(r.refine_ms for r in records) / len(records):.0f} ms")
    print(f"{line}; wrote {len(records) * 5} files to {args.out}")
    return 0
