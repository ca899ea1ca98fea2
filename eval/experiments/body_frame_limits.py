"""What limits the body-frame Chamfer-L1: the frame the network reads, or the shape?

On evenly spread test images of a dataset, the network's body-frame reading is scored against
the true surface (Chamfer-L1, the paper's) five ways:

* ``read``: as read (the figure ``sq-mitsuba eval`` reports);
* ``axes_sorted``: its axes relabelled by the dataset's rule (extents sorted x >= y >= z);
* ``oriented_box``: in its own oriented box's frame (the processed models' "obb" rule);
* ``best_of_24``: after the best of the 24 axis-aligned rotations (oracle labels and ends);
* ``true_pose``: the camera-frame reading carried into the body frame by the true rotation.

    .venv/bin/python eval/experiments/body_frame_limits.py --checkpoint MODEL --data DIR
"""

from __future__ import annotations

import numpy as np
import torch
from spread_images import open_spread_images

from sq_mitsuba.data.mesh_processing import alignment_rotation
from sq_mitsuba.evaluation.split import collate
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.metrics import chamfer_l1
from sq_mitsuba.geometry.so3_grid import axis_turns
from sq_mitsuba.inference.body_frame import canonical_frame, reframed
from sq_mitsuba.model.losses import counted_surface_samples


def points(assembly: Assembly) -> torch.Tensor:
    """The kept surface samples (1, P, 3) of one assembly."""
    samples, keep = counted_surface_samples(assembly, 3)
    return samples[0][keep[0]][None]


def main() -> None:
    spread = open_spread_images(__doc__.split("\n\n")[0], min_images=1)
    args, predictor, dataset = spread.args, spread.predictor, spread.dataset
    camera, chosen = spread.camera, spread.chosen
    turns = axis_turns()
    scores: dict[str, list[float]] = {name: [] for name in (
        "read", "axes_sorted", "oriented_box", "best_of_24", "true_pose")}
    for start in range(0, len(chosen), 16):
        batch = collate([dataset[int(i)] for i in chosen[start:start + 16]])
        prediction = predictor.predict(batch["image"], camera)
        for k in range(len(batch["model"])):
            assembly = Assembly(prediction.assembly.params[k:k + 1].detach().double())
            read = points(assembly)
            truth = batch["surface_points"][k:k + 1].double()

            def chamfer(p: torch.Tensor, truth: torch.Tensor = truth) -> float:
                return float(chamfer_l1(p, truth, "paper")[0])
            sorted_axes = torch.from_numpy(alignment_rotation(read[0].numpy(), None, "axes"))
            box, centre = canonical_frame(assembly)
            carried = batch["rotation"][k].double().T @ prediction.rotation[k].double()
            scores["read"].append(chamfer(read))
            scores["axes_sorted"].append(chamfer(read @ sorted_axes.T))
            scores["oriented_box"].append(chamfer(points(reframed(assembly, box, centre))))
            scores["best_of_24"].append(min(chamfer(read @ turn.T) for turn in turns))
            scores["true_pose"].append(chamfer(read @ carried.T))
    print(f"{len(scores['read'])} images of {args.data} ({args.split}), {args.checkpoint}")
    for name, values in scores.items():
        print(f"{name:13s} Chamfer-L1 mean {np.mean(values):.4f}  median {np.median(values):.4f}")


if __name__ == "__main__":
    main()
