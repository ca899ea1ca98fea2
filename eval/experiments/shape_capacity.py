"""Why are the assemblies rounded? What the shape loss asks for when nothing else limits it.

For each model of a dataset split, the network's assembly for one of its images (the first)
is fitted *directly* to the model's surface points: Adam on every raw parameter of every
primitive, on the training's shape term alone (:func:`surface_chamfer_loss`, squared-L2
Chamfer of the counted surface samples). No image, no network: this is what M superquadrics
and that loss can reach. The script prints, per model and over all of them, the Chamfer-L1
(paper convention) to the model's surface points and the shape exponents (mean, share below
0.3: box-like; 1 is an ellipsoid) of the network's assembly and of the fit.

With ``--start-exponent 0.2`` a second fit starts from the same assembly made box-like: if
both fits end near the same Chamfer-L1 with different exponents, the loss cannot tell a box
from a rounded box.

``--from-baseline`` adds a fit from the checkpoint's trivial baseline assembly, one start for
every model: if it ends as near the surfaces as the fit from the network's reading, every
model's best assembly is reachable by gradient from one common layout, so the fits keep each
primitive's role from model to model and could serve as per-primitive training targets.

``--occupancy-weight W`` adds the training's occupancy term (paper Eq. 14) to both fits: a
loss that sees the volume, and so the corners, should bring both starts to the same shape.

Reading it: if the fit is much nearer than the network and its exponents are box-like, the
capacity and the loss allow boxes and the network falls short; if the fit stays rounded at a
similar Chamfer-L1, the Chamfer term itself is blind to edges (a rounded box's samples lie
almost as near a box's surface as the box's own).

    python eval/experiments/shape_capacity.py DATA --split test [--checkpoint PT] \\
        [--steps 300] [--models 24] [--start-exponent 0.2] [--from-baseline] \\
        [--occupancy-weight 1]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from sq_mitsuba.data.spe3r import Spe3rDataset
from sq_mitsuba.geometry.assembly import FIELDS, Assembly
from sq_mitsuba.geometry.metrics import chamfer_l1
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.inference.refine import raw_from_assembly
from sq_mitsuba.model.losses import counted_surface_samples
from sq_mitsuba.model.part_targets import fit_to_surface

BOX_LIKE = 0.3
"""Shape exponents below this count as box-like (1: ellipsoid, 0.1: nearly a box)."""


def fit_to_points(start: Assembly, target: torch.Tensor, steps: int, lr: float, level: int,
                  occupancy: tuple[torch.Tensor, torch.Tensor] | None = None,
                  occupancy_weight: float = 0.0) -> Assembly:
    """``start`` (B models) fitted to ``target`` (B, K, 3) by Adam on the raw parameters;
    with ``occupancy`` (points (B, N, 3), labels (B, N)), plus ``occupancy_weight`` times the
    training's occupancy term (paper Eq. 14): :func:`fit_to_surface`, the part targets' fit."""
    raw, _ = fit_to_surface(target, start.num_primitives, steps, lr, level,
                            start=raw_from_assembly(start).double(), occupancy=occupancy,
                            occupancy_weight=occupancy_weight)
    return Assembly.from_raw(raw)


def paper_chamfer(assembly: Assembly, target: torch.Tensor, level: int) -> torch.Tensor:
    """(B,) Chamfer-L1, paper convention, of the counted surface samples to ``target``."""
    with torch.no_grad():
        points, keep = counted_surface_samples(assembly, level)
    return chamfer_l1(points, target, "paper", pred_mask=keep)


def exponent_stats(assembly: Assembly) -> tuple[float, float]:
    """Mean shape exponent and the share below :data:`BOX_LIKE`."""
    exponents = assembly.params[..., FIELDS["shape"]].detach().double()
    return float(exponents.mean()), float((exponents < BOX_LIKE).double().mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="dataset folder in the SPE3R layout")
    parser.add_argument("--split", choices=("val", "test"), default="test")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="network checkpoint (default: the shipped model)")
    parser.add_argument("--steps", type=int, default=300, help="Adam steps of the fit")
    parser.add_argument("--lr", type=float, default=0.05, help="Adam learning rate")
    parser.add_argument("--models", type=int, default=24, help="models of the split, at most")
    parser.add_argument("--points", type=int, default=2500, help="surface points per model")
    parser.add_argument("--level", type=int, default=2, help="icosphere level of the samples")
    parser.add_argument("--start-exponent", type=float, default=None,
                        help="also fit from the network's assembly with every shape exponent "
                             "set to this (e.g. 0.2, box-like): does the loss keep the edges?")
    parser.add_argument("--from-baseline", action="store_true",
                        help="also fit from the checkpoint's trivial baseline assembly (one "
                             "start for every model)")
    parser.add_argument("--occupancy-weight", type=float, default=0.0,
                        help="add the occupancy term (labelled points near and inside the "
                             "mesh) at this weight to every fit")
    args = parser.parse_args()
    torch.manual_seed(0)

    predictor = load_model(args.checkpoint)
    dataset = Spe3rDataset(args.data, args.split, image_size=predictor.image_size,
                           num_surface=args.points, num_occupancy=4 * args.points)
    first = {}  # model index -> its first item
    for item, (model_index, _, _) in enumerate(dataset.items):
        first.setdefault(model_index, item)
    chosen = sorted(first)[:args.models]
    items = [dataset[first[m]] for m in chosen]
    images = torch.stack([i["image"] for i in items])
    target = torch.stack([i["surface_points"] for i in items]).double()
    camera = dataset.camera.rescaled(predictor.image_size, predictor.image_size)
    network = Assembly(predictor.predict(images, camera).assembly.params.detach().double())
    occupancy = (torch.stack([i["occupancy_points"] for i in items]).double(),
                 torch.stack([i["occupancy_labels"] for i in items]).double())
    fit = {"occupancy": occupancy, "occupancy_weight": args.occupancy_weight}
    fitted = fit_to_points(network, target, args.steps, args.lr, args.level, **fit)

    rows = {"network": network, f"fit ({args.steps} steps)": fitted}
    if args.start_exponent is not None:
        params = network.params.clone()
        params[..., FIELDS["shape"]] = args.start_exponent
        rows[f"fit from exponents {args.start_exponent:g}"] = fit_to_points(
            Assembly(params), target, args.steps, args.lr, args.level, **fit)
    if args.from_baseline:
        if predictor.baseline is None:
            parser.error(f"{args.checkpoint or 'the shipped model'}: holds no trivial baseline")
        raw = predictor.baseline[0].expand(len(chosen), -1, -1)
        rows["fit from the baseline"] = fit_to_points(
            Assembly.from_raw(raw), target, args.steps, args.lr, args.level, **fit)
    chamfers = {name: paper_chamfer(a, target, args.level) for name, a in rows.items()}
    print(f"{len(chosen)} {args.split} models of {args.data}, M = {network.num_primitives}, "
          f"occupancy weight {args.occupancy_weight:g}")
    print("model | " + " | ".join(f"{n} Chamfer-L1" for n in rows))
    for k, m in enumerate(chosen):
        print(f"{dataset.models[m]} | "
              + " | ".join(f"{float(c[k]):.4f}" for c in chamfers.values()))
    print()
    print("assembly | Chamfer-L1 mean | median | shape exponent mean | share < 0.3")
    for name, assembly in rows.items():
        mean_exponent, box_share = exponent_stats(assembly)
        values = chamfers[name].numpy()
        print(f"{name} | {values.mean():.4f} | {np.median(values):.4f} | {mean_exponent:.3f} | "
              f"{box_share:.2f}")


if __name__ == "__main__":
    main()
