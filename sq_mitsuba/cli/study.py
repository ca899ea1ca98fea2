"""``sq-mitsuba study illumination``: metrics against the sun's phase angle, Earth and eclipse."""

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
)

HELP = ("studies of a trained model (illumination: phase angle, Earth, eclipse; passes: one "
        "assembly from N frames)")
ILLUMINATION = """\
Two ways to see how lighting changes the results:

  study illumination --models LIB --out DIR [--checkpoint PT] [--poses N] [--step 15]
    Render fixed poses of the library's models under a sweep of sun phase angles (0 to 180
    degrees in steps of --step), each with and without the Earth in view, plus eclipse
    frames, with the dataset renderer (one dataset per sweep point, scene overrides
    sun.phase_deg, earth.probability_in_view, eclipse.probability); evaluate each: the
    network, the pose search and search + refinement against the image's own mask; write
    per_image.csv, illumination.{csv,md,png} (every metric against the phase angle, one line
    per background, shaded ± std) and study.json. A rerun into the same --out resumes the renders
    and skips the sweep points already evaluated with the same settings, checkpoint and data
    (an interrupted point's evaluation continues from its journal).

  study illumination --eval EVAL_DIR [--out DIR] [--step 15]
    Break a regular `sq-mitsuba eval` folder down by the lighting recorded in its
    per_image.csv: phase-angle bins of --step degrees, Earth in view or not, eclipses apart;
    writes lighting.{csv,md,png} (into EVAL_DIR by default).

Renderer and evaluation settings go through --set, e.g. --set render.resolution=128
--set render.spp=32 --set evaluation.refinement.steps=20 --set evaluation.refine=false; the
study sets render.images_per_model (--poses), render.shard, render.overwrite,
evaluation.split and evaluation.baseline itself (given, they are refused). A rerun with
other render settings into one --out is refused (delete the folder to start over); one with
other evaluation settings reuses the renders and evaluates every point again, replacing
evals/. A run that fails other than on bad input (out of memory, a disk error) keeps its
renders and evaluations for the rerun; bad input (a model that cannot be rendered) leaves
nothing."""
DESCRIPTION = f"""\
`study illumination --help`: metrics against the sun's phase angle, the Earth and eclipses.
`study passes --help`: one assembly from N frames of a pass against each frame alone.

{ILLUMINATION}"""

FLAGS = {"poses": "--poses", "step": "--step", "split": "--split",
         "max_models": "--max-models"}


def register(subparsers: argparse._SubParsersAction) -> None:
    from sq_mitsuba.evaluation.study import StudyOptions

    parser = subparsers.add_parser("study", help=HELP, description=DESCRIPTION,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    studies = parser.add_subparsers(dest="study", metavar="STUDY", required=True)
    illumination = studies.add_parser(
        "illumination", help="metrics against the sun phase angle, with and without the "
                             "Earth, and in eclipse", description=ILLUMINATION,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    source = illumination.add_mutually_exclusive_group(required=True)
    source.add_argument("--models", type=Path, metavar="DIR",
                        help="model library to render (a `sq-mitsuba models` folder)")
    source.add_argument("--eval", type=Path, dest="eval_dir", metavar="EVAL_DIR",
                        help="break down this evaluation folder by its recorded lighting")
    illumination.add_argument("--checkpoint", type=input_file_path, default=None, metavar="PT",
                              help="checkpoint file (default: the model shipped with the "
                                   "package)")
    illumination.add_argument("--out", type=output_path, default=None, metavar="DIR",
                              help="output folder (required with --models; default with "
                                   "--eval: EVAL_DIR)")
    add_config_options(illumination, StudyOptions, FLAGS, metavars={"max_models": "N"})
    add_set_option(illumination, "study options", "render.resolution=128")
    illumination.add_argument("--quiet", action="store_true", help="no progress bar")
    illumination.set_defaults(func=_illumination)
    _register_passes(studies)


PASSES_DESCRIPTION = """\
Quality against the number of frames N: on a dataset of passes (`sq-mitsuba dataset render
--pass-frames F`: each model seen in passes of F frames in order, the target tumbling while
the camera closes in), score the first N frames of every pass, for each N of --counts, with
every metric of `sq-mitsuba eval`, per frame, for three methods: the network's reading of each
frame ("network"), each frame alone through the search and refinement ("single", the shipped
`predict --refine`), and one assembly with N poses (`predict --sequence`, "sequence", N >= 2).
Each row also holds the error of the rotation between consecutive frames. Frames are read
and scored at the dataset's own resolution.

Outputs in --out: per_frame.csv, summary.{csv,md} (mean ± std and median per N and method),
quality_vs_frames.png (body- and camera-frame Chamfer, 2D IoU, folded and relative rotation
against N) and passes.json (the settings and the seconds per frame: the tables hold no timing,
so that two runs of the same settings write them alike). A rerun into the same --out takes up
where an interrupted one stopped (the passes scored already, with the same settings, weights
and data, are read back from --out/.passes_partial). With --no-ordered a dataset of independent
images (`dataset render` without --pass-frames) is scored too, each model's images as one
unordered set of views in their order. A dataset of independent images without --no-ordered, a
pass shorter than the largest N, an --out inside --data or one another run writes into is a
one-line error before any work (exit code 2). Settings through --set, e.g. --set
sequence.steps=80 --set sequence.motion=free --set refinement.steps=10."""

#: PassOptions fields exposed as options; the rest are reachable through --set.
PASS_FLAGS = {"split": "--split", "counts": "--counts", "passes": "--passes",
              "ordered": "--ordered", "fast": "--fast"}


def _register_passes(studies: argparse._SubParsersAction) -> None:
    from sq_mitsuba.evaluation.passes import PassOptions

    passes = studies.add_parser(
        "passes", help="one assembly from N frames of a pass against each frame alone, as N "
                       "grows", description=PASSES_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    passes.add_argument("--data", type=Path, required=True, metavar="DIR",
                        help="dataset of passes (dataset render --pass-frames F), or "
                             "with --no-ordered of independent images")
    passes.add_argument("--checkpoint", type=input_file_path, default=None, metavar="PT",
                        help="checkpoint file (default: the model shipped with the package)")
    passes.add_argument("--out", type=output_path, required=True, metavar="DIR",
                        help="output folder (created)")
    add_config_options(passes, PassOptions, PASS_FLAGS, metavars={"counts": "N", "passes": "K"},
                       helps={"ordered": "the frames are read in the order they were taken (a "
                                         "pass, kept on one constant-rate turn); "
                                         "--no-ordered: as an unordered set, and a dataset of "
                                         "independent images is scored too, each model's "
                                         "images as one set of views"})
    add_set_option(passes, "pass options", "sequence.steps=80")
    passes.add_argument("--quiet", action="store_true", help="no progress bar")
    passes.set_defaults(func=_passes)


def _passes(args: argparse.Namespace) -> int:
    from sq_mitsuba.evaluation.evaluate import check_data_folder
    from sq_mitsuba.evaluation.passes import PassOptions, evaluate_passes
    from sq_mitsuba.inference.loading import load_model

    options = config_from_args(PassOptions, args)
    check_data_folder(args.data)  # before the model loads (seconds)
    result = evaluate_passes(load_model(args.checkpoint), args.data, args.out, options,
                             progress=not args.quiet)
    print(result.describe())
    return 0


def _illumination(args: argparse.Namespace) -> int:
    from sq_mitsuba.evaluation.study import (
        STUDY_SET,
        StudyOptions,
        illumination_study,
        lighting_breakdown,
    )

    options = config_from_args(StudyOptions, args)
    if args.eval_dir is not None:
        if args.checkpoint is not None:
            raise CLIError("--checkpoint: not used with --eval (the evaluation is done)")
        unused = [flag for name, flag in FLAGS.items() if name != "step" and hasattr(args, name)]
        unused += [f"--set {s}" for s in getattr(args, "overrides", None) or []
                   if s.split("=", 1)[0].strip() != "step"]
        if unused:  # they choose what to render and score: the evaluation has done both
            raise CLIError(f"{unused[0]}: not used with --eval (the evaluation is done; only "
                           "--step applies)")
        result = lighting_breakdown(args.eval_dir, args.out, options.step)
    else:
        if args.out is None:
            raise CLIError("--out: required with --models")
        for given in getattr(args, "overrides", None) or []:  # the study would not use them
            key = given.split("=", 1)[0].strip()
            if key in STUDY_SET:
                hint = f"; give {STUDY_SET[key]}" if STUDY_SET[key] else ""
                raise CLIError(f"--set {given}: set by the study itself{hint}")
        result = illumination_study(args.checkpoint, args.models, args.out, options,
                                    progress=not args.quiet)
    print(result.describe())
    return 0
