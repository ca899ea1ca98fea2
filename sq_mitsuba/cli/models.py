"""``sq-mitsuba models``: generate procedural spacecraft, import meshes, preview a library."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sq_mitsuba.cli import CLIError
from sq_mitsuba.data.spacecraft.generator import DEFAULT_CATALOGUE_COUNT, DEFAULT_CATALOGUE_SEED

EXIT_BATCH_FAILED = 1


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "models", help="spacecraft model library: generate, import, preview",
        description="Procedural spacecraft and imported meshes, processed as in the paper "
                    "(watertight, unit size, centred on the centre of mass, aligned).")
    sub = parser.add_subparsers(dest="models_command", metavar="ACTION", required=True)

    gen = sub.add_parser("generate", help="generate seeded procedural spacecraft")
    gen.add_argument("--count", type=int, default=DEFAULT_CATALOGUE_COUNT,
                     help=f"number of models (default {DEFAULT_CATALOGUE_COUNT})")
    gen.add_argument("--seed", type=int, default=DEFAULT_CATALOGUE_SEED,
                     help=f"catalogue seed (default {DEFAULT_CATALOGUE_SEED})")
    gen.add_argument("--out", type=Path, default=Path("data/spacecraft"),
                     help="output root (default data/spacecraft)")
    gen.add_argument("--points", type=int, default=100_000,
                     help="points per sample set: surface, uniform, near (default 100000)")
    gen.set_defaults(func=_generate)

    imp = sub.add_parser("import", help="import and process mesh files")
    imp.add_argument("meshes", nargs="+", type=Path, metavar="MESH",
                     help="OBJ, PLY, STL, GLB or GLTF files")
    imp.add_argument("--out", type=Path, required=True, help="output root")
    imp.add_argument("--method", choices=("auto", "boolean", "fusion"), default="auto",
                     help="watertight route (default auto: exact union when every piece is "
                          "closed, else depth-map fusion)")
    imp.add_argument("--align", choices=("axes", "obb"), default="axes",
                     help="axes: permute the file's axes; obb: minimum-volume box axes")
    imp.add_argument("--resolution", type=int, default=128,
                     help="fusion voxels along the longest side (default 128)")
    imp.add_argument("--points", type=int, default=100_000, help="points per sample set")
    imp.set_defaults(func=_import)

    pre = sub.add_parser("preview", help="contact sheet of a model library, rendered with Mitsuba")
    pre.add_argument("root", type=Path, help="library root (holds <model>/models/)")
    pre.add_argument("--out", type=Path, default=None,
                     help="PNG path (default ROOT/contact_sheet.png)")
    pre.add_argument("--size", type=int, default=160, help="tile size in pixels (default 160)")
    pre.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    pre.add_argument("--columns", type=int, default=None,
                     help="tiles per row (default: a square-ish grid)")
    pre.add_argument("--limit", type=int, default=None,
                     help="render only the first N models by name (default all)")
    pre.set_defaults(func=_preview)


def _check_points(points: int) -> None:
    if points < 1:
        raise CLIError(f"--points: expected >= 1, got {points}")


def _report(failures: list[tuple[str, str]], done: int, out: Path) -> int:
    print(f"{done} model(s) written to {out}")
    if failures:
        print(f"{len(failures)} failed:", file=sys.stderr)
        for name, message in failures:
            print(f"  {name}: {message}", file=sys.stderr)
        return EXIT_BATCH_FAILED
    return 0


def _generate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from sq_mitsuba.data.library import generate_model
    from sq_mitsuba.data.spacecraft import catalogue
    from sq_mitsuba.data.spe3r.layout import write_splits

    if args.count < 1:
        raise CLIError(f"--count: expected >= 1, got {args.count}")
    _check_points(args.points)
    entries = catalogue(args.count, args.seed)
    failures, written = [], []
    for entry in tqdm(entries, desc="models", unit="model"):
        try:
            generate_model(entry, args.out, points=args.points)
            written.append(entry)
        except Exception as error:  # one bad model must not stop the batch
            failures.append((entry.name, f"{type(error).__name__}: {error}"))
    if written:
        write_splits(args.out, [(e.name, e.split) for e in written])
    return _report(failures, len(written), args.out)


def _import(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from sq_mitsuba.data.library import import_model

    _check_points(args.points)
    if args.resolution < 16:
        raise CLIError(f"--resolution: expected >= 16, got {args.resolution}")
    failures, done = [], 0
    for path in tqdm(args.meshes, desc="import", unit="mesh"):
        try:
            import_model(path, args.out, method=args.method, align=args.align,
                         resolution=args.resolution, points=args.points)
            done += 1
        except Exception as error:
            message = str(error)
            if str(path) not in message:
                message = f"{path}: {message}"
            failures.append((path.name, message))
    return _report(failures, done, args.out)


def _preview(args: argparse.Namespace) -> int:
    from sq_mitsuba.data.contact_sheet import contact_sheet

    if args.size < 16 or args.spp < 1:
        raise CLIError("--size must be >= 16 and --spp >= 1")
    if args.columns is not None and args.columns < 1:
        raise CLIError(f"--columns: expected >= 1, got {args.columns}")
    if args.limit is not None and args.limit < 1:
        raise CLIError(f"--limit: expected >= 1, got {args.limit}")
    out = args.out or args.root / "contact_sheet.png"
    count = contact_sheet(args.root, out, tile=args.size, spp=args.spp, columns=args.columns,
                          limit=args.limit)
    print(f"contact sheet of {count} model(s) written to {out}")
    return 0
