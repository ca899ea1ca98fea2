"""``sq-mitsuba models``: generate procedural spacecraft, import meshes, preview a library."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sq_mitsuba.cli._options import add_config_options, config_from_args, input_file_path

EXIT_BATCH_FAILED = 1
# Listed by `sq-mitsuba --help` without importing the library (numpy, trimesh: ~0.25 s).
HELP = "spacecraft model library: generate, import, preview"

GENERATE_DESCRIPTION = """\
Generate the first COUNT models of the seeded procedural catalogue into OUT/<model>/models/.
A model's train/test split depends only on its name and the seed (7 test models in every 64,
at least one in any catalogue of two or more), so --count 6 and --count 64 agree on the
first six. Generating into an existing library merges: OUT/splits.csv keeps the rows of
other models and gets one row per model written; models that fail are listed with their
reason in OUT/failures.json (removed again when they succeed) and get no row. A model is
never replaced by another spacecraft of the same name (catalogues of other seeds reuse names
such as sc000_twin_wing): such a batch is refused before any work, naming the folder. One
batch at a time per OUT: a second one started while another writes there stops at once.
A rerun resumes: a model already complete in OUT (every file there, this catalogue's
spacecraft, the same --points) is kept, not built again, and counted as "already there";
--rebuild builds every model again. Temporary folders a killed run left in OUT's model
folders are removed first.
With --generator composed the models come from the compositional families (Earth observers,
relays, deep-space and solar-electric probes, observatories, small satellites, stations...),
named cs<i:05d>_<family>; three families are held out of training for good
(planetary_orbiter, infrared_observatory, module_stack): --families training leaves them out,
--families held-out makes only them (all marked test), for a leave-family-out evaluation.
With --generator graph the models are free-form part graphs (a core body and a random tree
of bodies, booms, arrays, dishes, panels and instruments, no family's layout), named
pg<i:05d>_part_graph.
OUT must not be a rendered dataset (a folder holding dataset.json or camera.json).
Exit code 1 when some model failed, 2 on bad options (nothing written)."""

IMPORT_DESCRIPTION = """\
Import mesh files, each into its own new folder OUT/<name>/models/: the name is the file's
stem, or <stem>_2, <stem>_3, ... when that name is already in OUT, was given to an earlier
file of the batch or is a library's own file (splits.csv, ...); nothing is overwritten, and
each file's name is printed. Each model imported gets its row in OUT/splits.csv: --split
test (the default: spacecraft a model has not seen, for `eval --split test`) or train. OUT
must not be a rendered dataset (holding dataset.json or camera.json). One batch at a time per
OUT. Exit code 1 when some file failed, 2 on bad options or missing files (nothing
written)."""

PREVIEW_DESCRIPTION = """\
Render every model of a library (ROOT/<model>/models/model_normalized.obj, with the per-face
materials of its samples.npz) with Mitsuba, one grey tile per model from a fixed three-quarter
view, labelled with the model's name, into one grid image: ROOT/contact_sheet.png, or --out
(PNG, JPEG, TIFF or BMP, as its suffix says). --limit renders the first models by name. The
options and the sheet's size are checked before anything is rendered (exit code 2)."""


def register(subparsers: argparse._SubParsersAction) -> None:
    from sq_mitsuba.data.contact_sheet import ContactSheetOptions
    from sq_mitsuba.data.library import GenerateOptions, ImportOptions

    parser = subparsers.add_parser(
        "models", help=HELP,
        description="Procedural spacecraft and imported meshes, processed as in the paper "
                    "(watertight, unit size, centred on the centre of mass, aligned).")
    sub = parser.add_subparsers(dest="models_command", metavar="ACTION", required=True)

    gen = sub.add_parser("generate", help="generate seeded procedural spacecraft",
                         description=GENERATE_DESCRIPTION,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    add_config_options(gen, GenerateOptions, {"count": "--count", "seed": "--seed",
                                              "out": "--out", "points": "--points",
                                              "generator": "--generator",
                                              "families": "--families",
                                              "workers": "--workers",
                                              "rebuild": "--rebuild"},
                       metavars={"out": "DIR"})
    gen.set_defaults(func=_generate)

    imp = sub.add_parser("import", help="import and process mesh files",
                         description=IMPORT_DESCRIPTION,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    imp.add_argument("meshes", nargs="+", type=input_file_path, metavar="MESH",
                     help="OBJ, PLY, STL, OFF, GLB or GLTF files")
    add_config_options(imp, ImportOptions, {"out": "--out", "method": "--method",
                                            "align": "--align", "resolution": "--resolution",
                                            "points": "--points", "split": "--split"},
                       metavars={"out": "DIR"})
    imp.set_defaults(func=_import)

    pre = sub.add_parser("preview", help="contact sheet of a model library, rendered with Mitsuba",
                         description=PREVIEW_DESCRIPTION)
    pre.add_argument("root", type=Path, help="library root (holds <model>/models/)")
    add_config_options(pre, ContactSheetOptions, {"out": "--out", "size": "--size",
                                                  "spp": "--spp", "columns": "--columns",
                                                  "limit": "--limit"},
                       metavars={"out": "PNG"})
    pre.set_defaults(func=_preview)


def _report(summary) -> int:
    print(summary.text())
    if not summary.ok:
        print(summary.failure_text(), file=sys.stderr)
        return EXIT_BATCH_FAILED
    return 0


def _generate(args: argparse.Namespace) -> int:
    from sq_mitsuba.data.library import GenerateOptions, generate_library

    return _report(generate_library(config_from_args(GenerateOptions, args)))


def _import(args: argparse.Namespace) -> int:
    from sq_mitsuba.data.library import ImportOptions, import_models

    return _report(import_models(args.meshes, config_from_args(ImportOptions, args)))


def _preview(args: argparse.Namespace) -> int:
    from sq_mitsuba.data.contact_sheet import ContactSheetOptions, contact_sheet

    sheet = contact_sheet(args.root, config_from_args(ContactSheetOptions, args),
                          progress=True)
    print(f"contact sheet of {sheet.models} model(s) written to {sheet.path}")
    return 0
