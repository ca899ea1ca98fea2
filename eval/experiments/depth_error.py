"""What the camera-frame Chamfer measures: the shape, or where the pose puts it?

The camera-frame Chamfer over distance (``sq-mitsuba eval``'s ``camera_chamfer``) places the
reading and the truth by their poses, so a wrong depth moves every point. On evenly spread
test images this prints, for the network's readings:

* the correlation of the camera-frame Chamfer with the relative translation error and with
  the body-frame Chamfer-L1 (which follows it more);
* the translation error split into depth (along the optical axis) and across, as fractions
  of the true distance, and the mean signed depth error (a bias);
* the camera-frame Chamfer with the reading placed at the true position (its own rotation
  kept): the shape as the camera sees it, what is left when the depth is right; and the same
  across the line of sight only (both clouds flattened onto the image plane's axes, x and y),
  the part of it one image shows (a nearest distance in x and y is never longer than in 3D,
  so the rest lies along the line of sight);
* the same figures with the reading held to the dataset's unit size (:func:`unit_scaled`:
  its longest body-frame side made 1, its translation scaled alike, so its image is
  unchanged): does the network's depth follow its shape's extent?

    .venv/bin/python eval/experiments/depth_error.py --checkpoint MODEL --data DIR [--images 96]
"""

from __future__ import annotations

import numpy as np
import torch
from spread_images import open_spread_images

from sq_mitsuba.evaluation.split import collate
from sq_mitsuba.geometry.assembly import FIELDS, Assembly
from sq_mitsuba.geometry.metrics import camera_frame_chamfer, chamfer_l1, translation_error
from sq_mitsuba.model.losses import counted_surface_samples


def longest_side(assembly: Assembly, level: int = 3) -> torch.Tensor:
    """(B,) the longest side of each assembly's body-frame axis-aligned box (its counted
    surface samples), the size the dataset's models are scaled to 1 by."""
    points, keep = counted_surface_samples(assembly, level)
    high = torch.where(keep[..., None], points, -torch.inf).amax(1)
    low = torch.where(keep[..., None], points, torch.inf).amin(1)
    return (high - low).amax(-1)


def unit_scaled(assembly: Assembly, translation: torch.Tensor
                ) -> tuple[Assembly, torch.Tensor]:
    """The assembly scaled to a longest body-frame side of 1 and its translation (B, 3)
    scaled alike: every camera-frame point scales about the camera centre, so the image is
    the same."""
    scale = 1.0 / longest_side(assembly)
    params = assembly.params.clone()
    params[..., FIELDS["size"]] *= scale[:, None, None]
    params[..., FIELDS["translation"]] *= scale[:, None, None]
    return Assembly(params), translation * scale[:, None]


def errors(assembly: Assembly, rotation: torch.Tensor, translation: torch.Tensor,
           batch: dict) -> dict[str, torch.Tensor]:
    """Per image: camera-frame Chamfer (as placed, and at the true position), body-frame
    Chamfer-L1, relative translation error, depth and across errors (fractions of the true
    distance), signed depth error."""
    points, keep = counted_surface_samples(assembly, 3)
    surface = batch["surface_points"].double()
    true_rotation = batch["rotation"].double()
    truth = batch["translation"].double()
    distance = truth.norm(dim=-1)
    flat = torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)  # onto the image plane's axes
    seen = (points @ rotation.transpose(-1, -2) + truth[:, None]) * flat
    true_seen = (surface @ true_rotation.transpose(-1, -2) + truth[:, None]) * flat
    return {
        "across_true_position": chamfer_l1(seen, true_seen, "occnet", pred_mask=keep) / distance,
        "body": chamfer_l1(points, surface, "paper", pred_mask=keep),
        "camera": camera_frame_chamfer(points, rotation, translation, surface, true_rotation,
                                       truth, pred_mask=keep),
        "camera_true_position": camera_frame_chamfer(points, rotation, truth, surface,
                                                     true_rotation, truth, pred_mask=keep),
        "translation": translation_error(translation, truth, relative=True),
        "depth": (translation[:, 2] - truth[:, 2]).abs() / distance,
        "across": (translation[:, :2] - truth[:, :2]).norm(dim=-1) / distance,
        "signed_depth": (translation[:, 2] - truth[:, 2]) / distance,
    }


def main() -> None:
    spread = open_spread_images(__doc__.split("\n\n")[0], min_images=2)
    read: dict[str, list[float]] = {}
    unit: dict[str, list[float]] = {}
    sides: list[float] = []
    with torch.no_grad():
        for start in range(0, len(spread.chosen), 16):
            batch = collate([spread.dataset[int(i)] for i in spread.chosen[start:start + 16]])
            prediction = spread.predictor.predict(batch["image"], spread.camera)
            assembly = Assembly(prediction.assembly.params.detach().double())
            rotation = prediction.rotation.double()
            translation = prediction.translation.double()
            for name, value in errors(assembly, rotation, translation, batch).items():
                read.setdefault(name, []).extend(value.tolist())
            scaled, moved = unit_scaled(assembly, translation)
            for name, value in errors(scaled, rotation, moved, batch).items():
                unit.setdefault(name, []).extend(value.tolist())
            sides.extend(longest_side(assembly).tolist())
    camera = np.array(read["camera"])
    print(f"{len(camera)} images of {spread.args.data} ({spread.args.split}), "
          f"{spread.args.checkpoint}")
    print(f"correlation of the camera-frame Chamfer with the translation error "
          f"{np.corrcoef(camera, read['translation'])[0, 1]:.2f}, with the body-frame "
          f"Chamfer-L1 {np.corrcoef(camera, read['body'])[0, 1]:.2f}")
    for label, values in (("as read", read), ("unit size", unit)):
        print(f"{label}: camera-frame Chamfer {np.mean(values['camera']):.4f}, translation "
              f"{np.mean(values['translation']):.4f} (depth {np.mean(values['depth']):.4f}, "
              f"across {np.mean(values['across']):.4f}, depth bias "
              f"{np.mean(values['signed_depth']):+.4f}); at the true position "
              f"{np.mean(values['camera_true_position']):.4f} (across the line of sight "
              f"{np.mean(values['across_true_position']):.4f})")
    print(f"longest body-frame side of the readings: mean {np.mean(sides):.3f}")


if __name__ == "__main__":
    main()
