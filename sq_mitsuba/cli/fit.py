"""``sq-mitsuba fit``: fit a superquadric assembly to binary masks seen from known poses."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from sq_mitsuba.io import read_json

DESCRIPTION = """\
Fit an assembly of M superquadrics to one or more binary masks with a known camera and known
poses, by gradient descent (Adam) through Mitsuba's differentiable silhouettes; the losses of
all views are summed.

Inputs:
  --masks    PNG/JPG masks (object = bright, > 127), all of the camera's size.
  --poses    SPE3R-style labels.json: a list of {"filename": ..., "q_vbs2tango_true": [w, x,
             y, z], "r_Vo2To_vbs_true": [x, y, z]}; a mask takes the entry whose filename has
             the same stem (img000001.png <- img000001.jpg). The pose maps body to camera
             (OpenCV frame: x right, y down, z forward): x_cam = R(q) x_body + r.
  --camera   SPEED-style camera.json (Nu, Nv, cameraMatrix in pixels); default: the project's
             default camera (SPEED field of view) at the masks' size.

Outputs in --out: assembly.json (the fitted parameters), assembly.glb (one mesh per
primitive), fit.png (masks against fitted silhouettes at the start, middle and end) and
fit_log.json (loss and IoU per step, final IoU per view).
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "fit", help="fit superquadrics to masks seen from known poses",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--masks", nargs="+", required=True, type=Path, metavar="PNG",
                        help="binary mask images")
    parser.add_argument("--poses", required=True, type=Path, metavar="JSON",
                        help="SPE3R-style labels.json with a pose per mask")
    parser.add_argument("--camera", type=Path, metavar="JSON",
                        help="SPEED-style camera.json (default: the default camera)")
    parser.add_argument("--primitives", type=int, default=1, metavar="M",
                        help="number of superquadrics (default 1)")
    parser.add_argument("--steps", type=int, default=150, metavar="N",
                        help="Adam steps (default 150)")
    parser.add_argument("--resolution", type=int, default=64,
                        help="width in pixels of the fitted silhouettes (default 64)")
    parser.add_argument("--lr", type=float, default=0.05, help="Adam learning rate (0.05)")
    parser.add_argument("--loss", choices=("mse", "iou"), default="mse",
                        help="per-view loss: mse (the paper's) or iou (1 - soft IoU)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR",
                        help="output folder (created)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=_run)


def _read_mask(path: Path) -> Any:
    import numpy as np
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise FileNotFoundError(f"--masks: no such file: {path}")
    try:
        with Image.open(path) as image:
            array = np.asarray(image.convert("L"))
    except UnidentifiedImageError:
        raise ValueError(f"--masks: {path} is not an image") from None
    return array > 127


def _read_poses(path: Path, masks: list[Path]) -> tuple[Any, Any]:
    """Quaternions (V, 4) and translations (V, 3) of the masks, matched by file stem."""
    import torch

    if not path.is_file():
        raise FileNotFoundError(f"--poses: no such file: {path}")
    try:
        labels = read_json(path)
    except ValueError as error:
        raise ValueError(f"--poses: {error}") from None
    if not isinstance(labels, list):
        raise ValueError(f"--poses: {path} must hold a list of labels")
    by_stem = {}
    for index, entry in enumerate(labels):
        if not isinstance(entry, dict) or "filename" not in entry:
            raise ValueError(f"--poses: entry {index} has no 'filename'")
        by_stem[Path(str(entry["filename"])).stem] = entry
    quaternions, translations = [], []
    for mask in masks:
        entry = by_stem.get(mask.stem)
        if entry is None:
            raise ValueError(f"--poses: no label with the stem of mask {mask.name!r}")
        try:
            q = [float(v) for v in entry["q_vbs2tango_true"]]
            r = [float(v) for v in entry["r_Vo2To_vbs_true"]]
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"--poses: label {entry['filename']!r} needs q_vbs2tango_true "
                             "(4 numbers) and r_Vo2To_vbs_true (3 numbers)") from None
        if len(q) != 4 or len(r) != 3:
            raise ValueError(f"--poses: label {entry['filename']!r} needs 4 quaternion and "
                             "3 translation components")
        quaternions.append(q)
        translations.append(r)
    return (torch.tensor(quaternions, dtype=torch.float64),
            torch.tensor(translations, dtype=torch.float64))


def _run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from sq_mitsuba.evaluation.figures import plot_fit
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.geometry.rotation import quaternion_to_matrix
    from sq_mitsuba.io import atomic_write_json
    from sq_mitsuba.learning.fit import fit_assembly

    masks = torch.from_numpy(np.stack([_read_mask(p) for p in args.masks]))
    height, width = masks.shape[1:]
    if args.camera is not None:
        if not args.camera.is_file():
            raise FileNotFoundError(f"--camera: no such file: {args.camera}")
        camera = Camera.load(args.camera)
    else:
        camera = Camera.default(width).rescaled(width, height)
    quaternions, translations = _read_poses(args.poses, list(args.masks))
    norms = quaternions.norm(dim=-1, keepdim=True)
    if bool((norms < 1e-8).any()):
        raise ValueError("--poses: a quaternion has zero norm")
    rotations = quaternion_to_matrix(quaternions / norms)

    result = fit_assembly(masks, camera, rotations, translations, args.primitives, args.steps,
                          resolution=args.resolution, lr=args.lr, loss=args.loss,
                          seed=args.seed, progress=not args.quiet)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    result.assembly.save(out / "assembly.json")
    result.assembly.export(out / "assembly.glb")
    plot_fit(result, out / "fit.png")
    atomic_write_json(out / "fit_log.json", {
        "masks": [str(p) for p in args.masks],
        "steps": args.steps, "primitives": args.primitives, "resolution": args.resolution,
        "loss": args.loss, "lr": args.lr, "seed": args.seed,
        "final_iou": [float(v) for v in result.final_iou],
        "mean_iou": result.mean_iou,
        "loss_per_step": result.losses,
        "iou_per_step": result.ious,
    })
    ious = ", ".join(f"{float(v):.3f}" for v in result.final_iou)
    print(f"fitted {args.primitives} primitive(s) to {len(args.masks)} mask(s): "
          f"mean IoU {result.mean_iou:.3f} ({ious}); wrote {out}/assembly.json, "
          f"assembly.glb, fit.png, fit_log.json")
    return 0
