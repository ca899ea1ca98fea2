"""``sq-mitsuba dataset render | check | preview``: SPE3R-layout datasets rendered by Mitsuba."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "dataset", help="render, check and preview datasets in the SPE3R layout",
        description="Physically based datasets (images, masks, pose labels) in the SPE3R layout.")
    commands = parser.add_subparsers(dest="dataset_command", metavar="ACTION", required=True)

    render = commands.add_parser(
        "render", help="path-trace images, masks and labels of every model",
        description="Render every model of --models (a `sq-mitsuba models generate` folder) in "
                    "the space scene. Re-running the same command resumes an interrupted run.")
    render.add_argument("--models", type=Path, required=True, help="model library folder")
    render.add_argument("--out", type=Path, required=True, help="dataset folder to write")
    render.add_argument("--images-per-model", type=int, default=1000)
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("--resolution", type=int, default=256, help="square image side (px)")
    render.add_argument("--spp", type=int, default=64, help="path-tracing samples per pixel")
    render.add_argument("--exr", action="store_true",
                        help="also write linear radiance, depth and coverage (OpenEXR)")
    render.add_argument("--camera", type=Path, default=None,
                        help="SPEED-style camera.json to render with, rescaled to --resolution "
                             "pixels wide (default: 35.45 deg field of view, square)")
    render.add_argument("--scene", type=Path, default=None,
                        help="scene configuration JSON (default scenes/space.json)")
    render.add_argument("--workers", type=int, default=1,
                        help="processes rendering models in parallel (default 1)")
    render.add_argument("--quiet", action="store_true", help="no progress bar")
    render.set_defaults(func=_render)

    check = commands.add_parser(
        "check", help="validate a dataset: files, labels, label/mask agreement",
        description="Re-render each model's mesh at its label poses and compare with the "
                    "stored masks (exit 1 when a problem is found).")
    check.add_argument("root", type=Path)
    check.add_argument("--per-model", type=int, default=20,
                       help="images checked per model (0: all)")
    check.add_argument("--min-iou", type=float, default=0.99)
    check.add_argument("--quiet", action="store_true")
    check.set_defaults(func=_check)

    preview = commands.add_parser(
        "preview", help="contact sheet of images with mask outlines and pose axes")
    preview.add_argument("root", type=Path)
    preview.add_argument("--out", type=Path, default=None,
                         help="PNG to write (default ROOT/preview.png)")
    preview.add_argument("--count", type=int, default=16, help="images on the sheet")
    preview.set_defaults(func=_preview)


def _render(args: argparse.Namespace) -> int:
    from sq_mitsuba.data.spe3r import RenderOptions, render_dataset
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.render.scene_config import SceneConfig

    camera = Camera.load(args.camera) if args.camera is not None else None
    options = RenderOptions(images_per_model=args.images_per_model, seed=args.seed,
                            resolution=args.resolution, spp=args.spp, exr=args.exr,
                            scene=SceneConfig.load(args.scene), camera=camera)
    summary = render_dataset(args.models, args.out, options, progress=not args.quiet,
                             workers=args.workers)
    print(f"{len(summary.models_done)} models done ({summary.rendered} images rendered, "
          f"{summary.skipped} already there) in {args.out}")
    for model, reason in summary.failures.items():
        print(f"FAILED {model}: {reason}")
    return 1 if summary.failures else 0


def _check(args: argparse.Namespace) -> int:
    from sq_mitsuba.data.spe3r import check_dataset

    report = check_dataset(args.root, per_model=args.per_model or None, min_iou=args.min_iou,
                           progress=not args.quiet)
    print(report.summary())
    return 0 if report.ok else 1


def _preview(args: argparse.Namespace) -> int:
    from sq_mitsuba.data.spe3r import preview_dataset

    out = preview_dataset(args.root, args.out or args.root / "preview.png", count=args.count)
    print(f"wrote {out}")
    return 0
