"""How much of its input's detail does the network's reading use?

On evenly spread test images this reads each image as given (the network's input size S) and
with its detail cut to a coarser side s (area-averaged to s x s, then bilinearly back to S x S,
so the network sees the same size and framing with less in it), and prints for each s the
body-frame Chamfer-L1, the camera-frame Chamfer over distance, the same at the true position
(the shape as the camera sees it, depth taken out) and the relative translation error. A
reading that does not change until s is small does not use the detail above s: a larger input
would not help it.

    .venv/bin/python eval/experiments/input_detail.py --checkpoint MODEL --data DIR [--images 96]
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from depth_error import errors
from spread_images import open_spread_images

from sq_mitsuba.evaluation.split import collate
from sq_mitsuba.geometry.assembly import Assembly

#: Coarser sides tried, as fractions of the input's.
FRACTIONS = (1.0, 2 / 3, 1 / 2, 1 / 3)


def degraded(images: torch.Tensor, side: int) -> torch.Tensor:
    """(B, C, S, S) images with their detail cut to ``side`` pixels: area-averaged to
    ``side`` x ``side``, then bilinearly resized back to S x S (unchanged at ``side == S``)."""
    size = images.shape[-1]
    if side == size:
        return images
    coarse = F.interpolate(images, size=(side, side), mode="area")
    return F.interpolate(coarse, size=(size, size), mode="bilinear", align_corners=False)


def main() -> None:
    spread = open_spread_images(__doc__.split("\n\n")[0], min_images=1)
    size = spread.predictor.image_size
    sides = [max(8, round(size * fraction)) for fraction in FRACTIONS]
    read: dict[int, dict[str, list[float]]] = {side: {} for side in sides}
    with torch.no_grad():
        for start in range(0, len(spread.chosen), 16):
            batch = collate([spread.dataset[int(i)] for i in spread.chosen[start:start + 16]])
            images = batch["image"]  # (B, H, W) grey, or (B, C, H, W)
            grey = images.dim() == 3
            for side in sides:
                cut = degraded(images[:, None] if grey else images, side)
                prediction = spread.predictor.predict(cut[:, 0] if grey else cut, spread.camera)
                found = errors(Assembly(prediction.assembly.params.detach().double()),
                               prediction.rotation.double(), prediction.translation.double(),
                               batch)
                for name, value in found.items():
                    read[side].setdefault(name, []).extend(value.tolist())
    print(f"{len(spread.chosen)} images of {spread.args.data} ({spread.args.split}), "
          f"{spread.args.checkpoint}, input {size} px")
    for side in sides:
        values = read[side]
        print(f"detail {side} px: body-frame Chamfer-L1 {np.mean(values['body']):.4f}, "
              f"camera-frame {np.mean(values['camera']):.4f}, at the true position "
              f"{np.mean(values['camera_true_position']):.4f}, translation "
              f"{np.mean(values['translation']):.4f}")


if __name__ == "__main__":
    main()
