"""``sq-mitsuba export``: a training checkpoint in, a small inference checkpoint out."""

from __future__ import annotations

import argparse
from pathlib import Path

from sq_mitsuba.cli._options import (
    add_config_options,
    config_from_args,
    input_file_path,
    output_file_path,
)

HELP = "export a training checkpoint for inference (what the package ships)"
DESCRIPTION = """\
Write an inference checkpoint from a training checkpoint (RUN/best.pt): the config, the
dataset camera and the weights (half precision unless --no-half), the trivial baseline
computed with those weights over training images of --data (skipped without --data; a
baseline the checkpoint stores already is kept, and --data then refused), and a record of
the run it came from; no optimiser, scheduler or RNG state. A --data that is not the dataset
the checkpoint was trained on (by the fingerprint it records) is said in one line. The
shipped model (sq_mitsuba/model/weights/model.pt) is such a file. Written atomically; a corrupt or
mismatched checkpoint, or a dataset without training images, is a one-line error (exit 2)
before anything is written. An existing --out is replaced only where it is an exported model
(exporting again); a training checkpoint (a run's last.pt) or any other file there is refused,
as is an --out inside a dataset folder (--data, or any folder holding dataset.json).

Several checkpoints (--checkpoint A.pt B.pt ...) of one network, fine-tuned from one start
(e.g. each on a different library), export as the average of their
weights: a "model soup", which can read data unlike the training data better than each
(docs/training.md). Their network configuration, camera and weights must match (else a
one-line error naming what differs); the baseline is computed over --data. With --start
(the file they were fine-tuned from, their init_from), the weights go part way back to
it: --start-share x the start + the rest x the fine-tunes' average, which keeps more of what
the start read well (WiSE-FT; docs/training.md); --keep-existence leaves the existence column
of the generators' last layer at the fine-tunes' average, so that the count of primitives they
learned survives the mix."""

FLAGS = {"half": "--half", "baseline_images": "--baseline-images",
         "start_share": "--start-share", "keep_existence": "--keep-existence"}


def register(subparsers: argparse._SubParsersAction) -> None:
    from sq_mitsuba.apps.export import ExportOptions

    parser = subparsers.add_parser("export", help=HELP, description=DESCRIPTION,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=input_file_path, required=True, nargs="+",
                        metavar="PT",
                        help="training checkpoint (e.g. RUN/best.pt); several of one network: "
                             "their weights averaged")
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="the training dataset, for the baseline (default: no baseline)")
    parser.add_argument("--out", type=output_file_path, required=True, metavar="PT",
                        help="inference checkpoint to write")
    parser.add_argument("--start", type=input_file_path, default=None, metavar="PT",
                        help="the checkpoint the --checkpoint files were fine-tuned from "
                             "(their init_from): the export goes --start-share of the way "
                             "back to it (default: none, the average alone)")
    add_config_options(parser, ExportOptions, FLAGS, helps={
        "start_share": "With --start: its share of the exported weights, the fine-tunes' "
                       "average the rest",
        "keep_existence": "With --start, for a network with existence logits: the existence "
                          "column of the generators' last layer is the fine-tunes' average "
                          "alone, not mixed back (the start's grown column would keep every "
                          "primitive)",
        "half": "Store floating-point weights in half precision: half the file size; the "
                "network's outputs change by about 1e-3 relative, below what the metrics "
                "resolve"})
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from sq_mitsuba.apps.export import ExportOptions, export_model
    from sq_mitsuba.cli import CLIError

    if hasattr(args, "start_share") and args.start is None:
        raise CLIError("--start-share: only with --start (the share of the start's weights)")
    if hasattr(args, "baseline_images") and args.data is None:  # it would be ignored
        raise CLIError("--baseline-images: only with --data (the baseline's training images)")
    if getattr(args, "keep_existence", False) and args.start is None:
        raise CLIError("--keep-existence: only with --start (without one the existence column "
                       "is the average already)")
    notes: list[str] = []
    checkpoint = args.checkpoint[0] if len(args.checkpoint) == 1 else args.checkpoint
    path = export_model(checkpoint, args.data, args.out,
                        config_from_args(ExportOptions, args), notes=notes, start=args.start)
    for note in notes:
        print(f"note: {note}")
    print(f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB)")
    return 0
