"""How high can the 2D IoU go? The silhouette of superquadric assemblies at the *true* pose.

Render and compare fits a pose (and optionally the shape) to one mask. Its 2D IoU is bounded by
how well the assembly's outline can match the true one at all. This script measures that bound
for a dataset split, one image per row of a ladder, against the true mask at the true pose:

- ``network, own pose``: the network's assembly at the network's pose (the eval's figure);
- ``network, true pose``: the same assembly at the true pose (a perfect pose search);
- ``3D fit, M``: the assembly fitted to the model's surface points in 3D by the training's shape
  term (``shape_capacity.py``'s fit; no image), with ``M`` primitives (the network's M, or
  more: the network's primitives repeated with noise, then fitted);
- ``3D + silhouette fit``: the 3D fit fitted again with the silhouette term (soft IoU against
  the true mask at the true pose, through Mitsuba) beside the shape term: an assembly that
  knows both the surface and the outline.

Each row prints the mean and median 2D IoU and the Chamfer-L1 (paper convention). Reading it:
the ``3D fit`` rows say what 2D IoU a shape as accurate in 3D as M superquadrics allow reaches
with a perfect pose; if that is below a target, no pose search and no shape-preserving
refinement reaches the target from that network, and what is missing is the shape reading.

    python eval/experiments/iou_ceiling.py DATA --split test [--images 64] [--checkpoint PT] \\
        [--primitives 8 12] [--joint-weight 0.02]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from shape_capacity import fit_to_points, paper_chamfer

from sq_mitsuba.data.spe3r import Spe3rDataset
from sq_mitsuba.evaluation.split import collate, evenly
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.metrics import mask_iou
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.inference.refine import raw_from_assembly
from sq_mitsuba.model.losses import soft_iou_loss, surface_chamfer_loss
from sq_mitsuba.render.silhouette.renderer import (
    SilhouetteRenderer,
    render_assembly,
    render_assembly_loss,
)

EXTRA_NOISE = 0.3
"""Standard deviation of the noise added to the raw parameters of repeated primitives."""


def with_more_primitives(assembly: Assembly, count: int) -> Assembly:
    """``assembly`` (B, M) grown to ``count`` primitives: its own first, then its primitives
    repeated in order with Gaussian noise on their raw parameters (a start for a fit)."""
    raw = raw_from_assembly(assembly).double()
    extra = raw[:, torch.arange(count - raw.shape[1]) % raw.shape[1]]
    return Assembly.from_raw(torch.cat([raw, extra + EXTRA_NOISE * torch.randn_like(extra)], 1))


def fit_outline_and_surface(start: Assembly, surface: torch.Tensor, rotation: torch.Tensor,
                            translation: torch.Tensor, masks: torch.Tensor,
                            renderer: SilhouetteRenderer, weight: float, steps: int,
                            level: int) -> Assembly:
    """``start`` (B assemblies) fitted by Adam to the surface points ``surface`` (B, K, 3) and,
    at ``weight``, to the masks (B, S, S) at the poses (B, 3, 3), (B, 3) by the soft IoU of
    their Mitsuba silhouettes."""
    raw = raw_from_assembly(start).double().requires_grad_(True)
    optimizer = torch.optim.Adam([raw], lr=0.02)
    for _ in range(steps):
        optimizer.zero_grad(set_to_none=True)
        assembly = Assembly.from_raw(raw)
        outline, _ = render_assembly_loss(
            assembly, rotation, translation, renderer,
            lambda coverage, item: soft_iou_loss(coverage, masks[item]), level)
        (surface_chamfer_loss(assembly, surface, level) + weight * outline).backward()
        optimizer.step()
    return Assembly.from_raw(raw.detach())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="dataset folder in the SPE3R layout")
    parser.add_argument("--split", choices=("train", "val", "test"), default="test")
    parser.add_argument("--images", type=int, default=64, help="images spread evenly")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="network checkpoint (default: the shipped model)")
    parser.add_argument("--primitives", type=int, nargs="*", default=[8, 12],
                        help="also fit with these many primitives (more than the network's)")
    parser.add_argument("--steps", type=int, default=300, help="Adam steps of the 3D fits")
    parser.add_argument("--joint-steps", type=int, default=100,
                        help="Adam steps of the 3D + silhouette fit (0: skip it)")
    parser.add_argument("--joint-weight", type=float, default=0.02,
                        help="weight of the silhouette term in the 3D + silhouette fit")
    parser.add_argument("--level", type=int, default=2, help="icosphere level of the meshes")
    args = parser.parse_args()
    torch.manual_seed(0)

    predictor = load_model(args.checkpoint)
    dataset = Spe3rDataset(args.data, args.split, image_size=predictor.image_size,
                           num_surface=2500)
    camera = dataset.camera.rescaled(predictor.image_size, predictor.image_size)
    renderer = SilhouetteRenderer(camera, spp=32)
    batch = collate([dataset[i] for i in evenly(len(dataset), args.images)])
    prediction = predictor.predict(batch["image"], camera)
    network = Assembly(prediction.assembly.params.detach().double())
    rotation, translation = batch["rotation"].double(), batch["translation"].double()
    masks, surface = batch["mask"][:, 0].double(), batch["surface_points"].double()

    fitted = fit_to_points(network, surface, args.steps, 0.05, args.level)
    rows = [("network, own pose", network, prediction.rotation.double(),
             prediction.translation.double()),
            ("network, true pose", network, rotation, translation),
            (f"3D fit, M = {network.num_primitives}", fitted, rotation, translation)]
    for count in (c for c in args.primitives if c > network.num_primitives):
        more = fit_to_points(with_more_primitives(network, count), surface, args.steps, 0.05,
                             args.level)
        rows.append((f"3D fit, M = {count}", more, rotation, translation))
    if args.joint_steps > 0:
        joint = fit_outline_and_surface(fitted, surface, rotation, translation, masks,
                                        renderer, args.joint_weight, args.joint_steps,
                                        args.level)
        rows.append((f"3D + silhouette fit, M = {network.num_primitives}", joint, rotation,
                     translation))

    print(f"{len(masks)} {args.split} images of {args.data}, every one against its true mask")
    print("assembly, pose | 2D IoU mean | median | Chamfer-L1 mean")
    for name, assembly, pose_rotation, pose_translation in rows:
        with torch.no_grad():
            silhouettes = render_assembly(assembly, pose_rotation, pose_translation, renderer,
                                          args.level)
        iou = mask_iou(silhouettes, masks)
        chamfer = paper_chamfer(assembly, surface, args.level)
        print(f"{name} | {float(iou.mean()):.3f} | {float(iou.median()):.3f} | "
              f"{float(chamfer.mean()):.4f}", flush=True)


if __name__ == "__main__":
    main()
