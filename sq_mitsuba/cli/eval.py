"""``sq-mitsuba eval``: score a trained model on a dataset split; tables, charts and figures."""

from __future__ import annotations

import argparse
from pathlib import Path

from sq_mitsuba.cli._options import (
    add_config_options,
    add_set_option,
    config_from_args,
    input_file_path,
    output_path,
    refuse_unused_settings,
)

HELP = "evaluate a trained model on a dataset split (metrics, tables, figures)"
DESCRIPTION = """\
Run the network over the val or test split of an SPE3R-layout dataset (`sq-mitsuba dataset
render`) and score every image: Chamfer-L1 (the paper's and the occnet convention), Chamfer-L2,
2D IoU at the predicted pose, 3D IoU, rotation error (raw, over the model's symmetries, over
the four half turns of the body frame, and over the 24 turns of its axes: which is x, y or z),
translation error, SPEED score and a camera-frame Chamfer. The trivial baseline (the mean
training assembly at the mean training pose) is scored beside it. --refine adds render and
compare: a global pose search (the network's rotation, or a uniform grid for a network without
a rotation distribution head, times the four half turns, scored by Mitsuba silhouettes; --set
search.candidates=hypotheses adds its top-K hypotheses; row 'search') and the search followed
by refinement (row 'refined'), both against the mask read from the image (the network's mask
head, or the threshold segmentation for a model without one; column mask_source), and the same
against the ground-truth mask as an upper bound (row 'refined_gt'). Silhouettes cannot tell
apart poses with the same outline.

Outputs in --out: per_image.csv (every metric and the label's lighting: phase angle, Earth in
view, eclipse, visibility; on the search and refined rows the search's score, the refinement's
IoU and mask_iou, the fitted mask's IoU with the true mask), per_model.{csv,md},
summary.{csv,md} (mean ± std and median), per_model.png (bars per model, as the paper's
Fig. 10), qualitative.png (Fig. 12), consistency.png (Fig. 11) and eval.json (settings,
images/s); with --set mesh_ranking=256, mesh_ranking.csv: for 256 network predictions (spread
evenly), the rank of the image's own model among every model of the split by Chamfer-L1 (is
the shape read from the image?; a split of one model is refused).
`sq-mitsuba report` collates eval folders into the paper's tables.

Without --checkpoint the model shipped with the package is used. A checkpoint that does not
fit this version's network, an empty split, a samples.npz that lacks an array or holds NaN,
images of another size than camera.json says, an unwritable --out or one inside --data (the
dataset is only read), or an --out another run is writing into, is a one-line error before
any work (exit code 2); so is the baseline on a dataset without a train split whose checkpoint
stores none. Rerunning into an earlier --out removes the outputs this run does not write (e.g.
the figures after --no-figures) and a lighting breakdown of the earlier per_image.csv
(lighting.*, `sq-mitsuba study illumination --eval`). Each finished batch is kept in
--out/.eval_partial until eval.json is written: after an interrupt (Ctrl-C, a killed run),
the same command with --resume computes only the batches left and writes the same files as
an uninterrupted run (timings aside); a journal of other settings, another checkpoint,
other data (labels, model files) or another sq-mitsuba version is refused in one line naming
what differs, and a run without --resume starts afresh. Other settings:
--set key=value on the eval options, e.g.
--set refinement.steps=20 --set search.grid=576 --set mask=segmentation
--set refinement.shape=free --set refinement.depth=fixed --set volume_points=20000
--set mesh_ranking=256. The refinement that fits the outline rather than keeping the shape
(OUTLINE_REFINEMENT: a higher 2D IoU, a worse 3D shape; docs/inference.md):
--set refinement.shape=free --set refinement.steps=100 --set refinement.patience=30."""

#: EvalOptions fields exposed as options; the rest are reachable through --set.
FLAGS = {"split": "--split", "turns": "--turns", "refine": "--refine", "limit": "--limit",
         "batch_size": "--batch-size", "baseline": "--baseline",
         "baseline_images": "--baseline-images", "figures": "--figures", "fast": "--fast"}


def register(subparsers: argparse._SubParsersAction) -> None:
    # Imported here: it imports torch, which `sq-mitsuba --help` does without (see HELP).
    from sq_mitsuba.evaluation.evaluate import EvalOptions

    parser = subparsers.add_parser("eval", help=HELP, description=DESCRIPTION,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=input_file_path, default=None, metavar="PT",
                        help="checkpoint file (default: the model shipped with the package)")
    parser.add_argument("--data", type=Path, required=True, metavar="DIR",
                        help="dataset folder in the SPE3R layout")
    parser.add_argument("--out", type=output_path, required=True, metavar="DIR",
                        help="output folder (created)")
    parser.add_argument("--label", default=None,
                        help="name of the run in eval.json and the report (default: the "
                             "checkpoint's folder name)")
    add_config_options(parser, EvalOptions, FLAGS, metavars={"limit": "N"})
    add_set_option(parser, "eval options", "refinement.steps=20")
    parser.add_argument("--resume", action="store_true",
                        help="continue the interrupted evaluation in --out: the batches its "
                             "journal (--out/.eval_partial) holds are not computed again; "
                             "refused when the settings, checkpoint or data differ")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from sq_mitsuba.evaluation.evaluate import EvalOptions, evaluate_checkpoint

    if args.label is not None and (not args.label.strip() or set(args.label) & set("|\n\r")):
        from sq_mitsuba.cli import CLIError

        raise CLIError(f"--label {args.label!r}: expected one line without '|' (it names a "
                       "row of report.md's tables)")
    options = config_from_args(EvalOptions, args)
    if not options.refine:  # they would act on nothing (the API takes them and says nothing)
        refuse_unused_settings(args, ("mask", "search", "refinement", "refine_ground_truth"),
                               "--refine")
    result = evaluate_checkpoint(args.checkpoint, args.data, args.out, options,
                                 progress=not args.quiet, label=args.label,
                                 resume=args.resume)
    print(result.describe())
    return 0
