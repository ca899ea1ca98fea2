"""``sq-mitsuba predict``: images in; assembly, meshes, pose and overlay per image out."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from sq_mitsuba.cli._options import (
    add_config_options,
    add_set_option,
    config_from_args,
    input_file_path,
    output_path,
    refuse_unused_settings,
)

if TYPE_CHECKING:
    from torch import Tensor

HELP = "predict superquadric assemblies and poses from images"
DESCRIPTION = """\
Predict, for each image, an assembly of superquadrics and the target's pose, and write into
--out per image <stem>: <stem>.assembly.json, <stem>.obj (merged mesh), <stem>.glb (one mesh
per primitive), <stem>.pose.json (quaternion q_vbs2tango = (w, x, y, z) and translation
r_Vo2To_vbs in metres, for a target 1 m long unless --target-size says: x_cam = R(q) x_body
+ r, OpenCV camera frame) and <stem>.overlay.png
(the network's silhouette in red; with --refine the refined one in green and the outline of
the mask fitted in yellow). Prints
the milliseconds per image.

Target: every image gets a target-present score (the mask head's most confident pixel, or
the image's segmentation for a model without a mask head; 0 for an image of noise). An image
scoring below --set min_target (0.92) shows no target (a black frame, noise, the Earth
alone): the line printed says "no target", only <stem>.pose.json is written, with "target":
false and no pose (other files of that stem are removed), and it is not refined; the command
still succeeds. pose.json records "target", "target_score" and "min_target" for every image.

Images: any size; RGB and palette images are converted to grey (luminance), an alpha channel
composites them on black, 16-bit images keep their range (12- or 10-bit data in a 16-bit file
reads dark: a warning says so), an EXIF orientation is not applied (a warning). The camera is
the checkpoint's (the dataset's), rescaled to each image, unless --camera gives the images' own
(SPEED-style camera.json). Without --camera, an image of another aspect ratio is padded with
black to the camera's (its field of view then lies across the image's longer side; pose.json
records the camera of the image's own pixels and a warning); with --camera, and for the frames
of a --sequence, it is an error naming the file.

--refine searches the pose globally (the network's rotation, or a uniform grid for a network
without a rotation distribution head, times the four half turns of the body frame, scored by
Mitsuba silhouettes; --set search.candidates=hypotheses adds its top-K hypotheses), then
refines the best few, against its --mask (one per image, same size, target bright) or,
without --mask, the network's mask head (the image's segmentation for a model without a mask
head; --set mask=segmentation forces it); the line printed and pose.json name the mask
fitted, the search's soft IoU (search_score, at search.resolution px) and the refined IoU
(iou_after, at refinement.resolution px). The refinement keeps the network's shape; for a
silhouette that follows the mask (a worse 3D shape), --set refinement.shape=free --set
refinement.steps=100 --set refinement.patience=30 (docs/inference.md).
Silhouettes cannot tell apart poses with the same outline. Every input is
checked before the first prediction (a bad one is a one-line error, exit code 2, nothing
written). Without --checkpoint the model shipped with the package is used.

--sequence: the images are N >= 2 frames of one spacecraft (one size; --ordered when in the
order they were taken): one assembly and every pose (Predictor.predict_sequence: each frame
by the --refine path, the half turns resolved across frames, then one shape and N poses
fitted to every frame's mask at once). Writes sequence.assembly.json, sequence.glb,
sequence.png (the assembly from six sides) and per frame <stem>.pose.json (its pose of that
assembly) and <stem>.overlay.png (its own fit in red, the shared assembly in green), and
colmap/ (every pose as a COLMAP sparse model, text format: the start of structure from
motion, e.g. colmap point_triangulator --input_path DIR/colmap; not written, with a warning,
for frames whose file names hold white space).
--mask gives each frame's mask (one per image, in their order) in place of the network's;
a frame the network sees no target in (its score below --set min_target) is refused unless
masks are given. A pass takes --level, --target-size and three --set fields: min_target,
level and overlay_spp (its overlays' and GLB's meshes and samples).
--relative-rotations FILE gives the rotations between the frames when they are known (e.g.
from the servicer's navigation, for a target that holds its attitude): a JSON list of one
quaternion [w, x, y, z] per image, in their order, each the target's rotation into that
frame's camera up to one rotation common to every frame (only the rotations between frames
are used); they take the place of the pass's own motion.

Units: the network reads every target at the dataset's unit size (its longest side 1), so
translations are metres for a target 1 m long; one camera cannot tell a larger target farther
away. --target-size METRES (the target's longest side, when known) scales the assembly and
every translation written to it (the overlays are the same); pose.json records it."""

FLAGS = {"refine": "--refine", "turns": "--turns", "level": "--level", "fast": "--fast",
         "target_size": "--target-size"}


def register(subparsers: argparse._SubParsersAction) -> None:
    from sq_mitsuba.apps.predict import PredictOptions

    parser = subparsers.add_parser("predict", help=HELP, description=DESCRIPTION,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    # "*", checked in _run: after "--mask A B" argparse gives every path to --mask, and
    # "IMAGE is required" would not say why.
    parser.add_argument("images", nargs="*", type=input_file_path, metavar="IMAGE",
                        help="input images (at least one; before --mask, which takes every "
                             "path after it)")
    parser.add_argument("--checkpoint", type=input_file_path, default=None, metavar="PT",
                        help="checkpoint file (default: the model shipped with the package)")
    parser.add_argument("--out", type=output_path, required=True, metavar="DIR",
                        help="output folder (created)")
    parser.add_argument("--camera", type=input_file_path, default=None, metavar="JSON",
                        help="SPEED-style camera.json of the images (default: the "
                             "checkpoint's camera, rescaled to each image)")
    parser.add_argument("--mask", nargs="+", type=input_file_path, default=None, metavar="MASK",
                        help="with --refine or --sequence: one mask per image, in the same order "
                             "(default, without --mask: the network's mask head, or the "
                             "image's segmentation for a model without one; --set "
                             "mask=segmentation forces the segmentation)")
    parser.add_argument("--sequence", action="store_true",
                        help="the images are frames of one spacecraft: one assembly, every "
                             "pose (default: each image alone)")
    parser.add_argument("--ordered", action="store_true",
                        help="with --sequence: the frames are in the order they were taken, "
                             "equally spaced in time: they are kept on one constant-rate turn "
                             "(default: any order)")
    parser.add_argument("--relative-rotations", type=input_file_path, default=None, metavar="JSON",
                        help="with --sequence: one quaternion [w, x, y, z] per image (a JSON "
                             "list), each frame's rotation up to one common to all: the "
                             "rotations between frames, when known (default: read from the "
                             "images)")
    parser.add_argument("--fit", dest="fit_overrides", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="with --sequence: override a field of the joint fit's options "
                             "(SequenceOptions: steps=80 for a longer fit, grow=2 to grow "
                             "primitives where the silhouettes miss); repeatable. Fields: "
                             + _sequence_fields())
    add_config_options(parser, PredictOptions, FLAGS, metavars={"target_size": "METRES"})
    add_set_option(parser, "predict options", "refinement.steps=20")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=_run)


def _sequence_fields() -> str:
    from sq_mitsuba.cli._options import settable_fields
    from sq_mitsuba.inference.sequence import SequenceOptions

    return settable_fields(SequenceOptions)


def _run(args: argparse.Namespace) -> int:
    from sq_mitsuba.apps.predict import PredictOptions, predict_images
    from sq_mitsuba.cli import CLIError

    if not args.images:
        if args.mask:
            raise CLIError(f"IMAGE: none given; --mask took every path after it "
                           f"({', '.join(map(str, args.mask[:3]))}"
                           f"{', ...' if len(args.mask) > 3 else ''}): give the images first, "
                           "then --mask and the masks")
        raise CLIError("IMAGE: at least one image is required")
    if args.ordered and not args.sequence:
        raise CLIError("--ordered: only with --sequence")
    if args.fit_overrides and not args.sequence:
        raise CLIError("--fit: only with --sequence (--set changes a single image's options)")
    if args.relative_rotations is not None and not args.sequence:
        raise CLIError("--relative-rotations: only with --sequence")
    if args.sequence:
        return _run_sequence(args)
    options = config_from_args(PredictOptions, args)
    if not options.refine:  # the fit's settings would be ignored: refused here (the API
        # takes them without --refine and leaves them unused)
        refuse_unused_settings(args, ("mask", "search", "refinement"), "--refine")
    records = predict_images(args.images, args.out, args.checkpoint, args.camera, args.mask,
                             options, progress=not args.quiet)
    for record in records:
        print(record.describe())
    network = sum(r.network_ms for r in records) / len(records)
    line = f"{len(records)} image(s): network {network:.1f} ms per image"
    refined = [r for r in records if r.iou_before is not None]  # not the no-target images
    if options.refine and refined:
        line += (f", search {sum(r.search_ms for r in refined) / len(refined):.0f} ms, search + "
                 f"refinement {sum(r.refine_ms for r in refined) / len(refined):.0f} ms per "
                 f"refined image")
    absent = sum(not r.target for r in records)
    if absent:
        line += f"; {absent} without a target"
    print(f"{line}; wrote {sum(len(r.files) for r in records)} files to {args.out}")
    return 0


SEQUENCE_SETTINGS = ("min_target", "level", "overlay_spp")
"""The single image's settings (``--set``) that a pass (``--sequence``) uses too."""


def _run_sequence(args: argparse.Namespace) -> int:
    from sq_mitsuba.apps.predict import PredictOptions
    from sq_mitsuba.apps.predict_sequence import check_frame_files, predict_sequence_files
    from sq_mitsuba.cli import CLIError
    from sq_mitsuba.config import ConfigError, apply_overrides
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.inference.loading import load_model
    from sq_mitsuba.inference.sequence import SequenceOptions

    # A pass refines every frame, on the fast path: the single image's fit options would be
    # silently ignored. What applies: --target-size, --level and the overlays' samples (--set
    # overlay_spp), and the threshold on the target-present score (--set min_target), below
    # which a frame is refused.
    overrides = [override for override in getattr(args, "overrides", None) or []
                 if override.split("=", 1)[0].strip() not in SEQUENCE_SETTINGS]
    unused = [flag for flag, given in (("--refine", hasattr(
        args, "refine")), ("--turns", hasattr(args, "turns")),
        ("--fast / --no-fast", hasattr(args, "fast")),
        (f"--set {overrides[0] if overrides else ''}", overrides)) if given]
    if unused:
        raise CLIError(f"{unused[0]}: not used with --sequence (every frame is refined, on the "
                       "fast path; --fit sets the joint fit; --set takes "
                       f"{', '.join(SEQUENCE_SETTINGS)} only)")
    try:
        options = apply_overrides(SequenceOptions(), args.fit_overrides)
    except ConfigError as error:
        raise CLIError(f"--fit {error}") from None
    single = config_from_args(PredictOptions, args)
    check_frame_files(args.images, args.mask)  # before the counts below and the model's load
    camera = Camera.load(args.camera) if args.camera is not None else None
    relative = None
    if args.relative_rotations is not None:
        relative = _relative_rotations(args.relative_rotations, len(args.images))
    inputs = [path for path in (args.checkpoint, args.camera, args.relative_rotations)
              if path is not None]
    predictor = load_model(args.checkpoint, min_target=single.min_target)
    record = predict_sequence_files(args.images, args.out, predictor, camera,
                                    relative_rotations=relative, options=options,
                                    ordered=args.ordered, other_inputs=inputs,
                                    masks=args.mask, progress=not args.quiet,
                                    target_size=single.target_size, level=single.level,
                                    overlay_spp=single.overlay_spp)
    removed = f" (and removed {record.removed} of an earlier pass)" if record.removed else ""
    print(f"{record.describe()}; wrote {len(record.files)} files to {args.out}{removed}")
    return 0


def _relative_rotations(path: Path, count: int) -> Tensor:
    """(N, 3, 3) ``Q_j = A_j A_0^T`` from a file of N quaternions ``A_j`` (each frame's
    rotation up to one common to all, so ``Q_j = R_j R_0^T`` whatever it is), float64."""
    import torch

    from sq_mitsuba.geometry.rotation import quaternion_to_matrix
    from sq_mitsuba.inputs import check_quaternions
    from sq_mitsuba.io import read_json

    quaternions = check_quaternions(read_json(path), count, "image", str(path))
    attitudes = quaternion_to_matrix(torch.tensor(quaternions, dtype=torch.float64))
    return attitudes @ attitudes[0].T
