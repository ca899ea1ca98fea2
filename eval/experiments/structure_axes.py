"""The body axes read from the visible surface's normals, against the network's rotation.

Spacecraft are built along their body axes, so the normals of the surface one image shows
cluster along those axes as the camera sees them, in every family alike. On evenly spread
test images this reads the body-to-camera rotation as the Manhattan frame of those normals
(:func:`~sq_mitsuba.geometry.manhattan_frame.manhattan_frame`), its axes ordered by the
visible surface's extent along them (:func:`frame_by_extent`: longest on x, as the body
axes are), and prints the folded rotation error (up to the four half turns, as ``sq-mitsuba
eval``) of:

* ``network``: the network's rotation;
* ``network_oracle``: the same, its best axis order (how much of its error is which axis is
  which);
* ``true_normals``: the frame of the true visible surface's normals (the nearest true
  surface point of each stride-4 cell), ordered by the true visible surface's extent (its
  depth map back-projected): what a perfect normal and depth map give;
* ``true_normals_oracle``: the same frame, its best axis order (which axis is which told);
* ``true_depth_oracle``: the frame of normals made from the true depth map itself (the cross
  product of its differences between neighbouring cells, back-projected; a depth step of
  more than 5 cm is an outline, not a face), its best axis order: what a perfect stride-4
  depth map gives without normals;
* ``edges_oracle`` (``--edges``): the rotation whose body axes, drawn through each edge pixel
  of the full-resolution image (the 2,000 strongest grey-level gradients within 3 px of the
  true mask), run along the most edges, its best axis order: straight edges as the cue
  instead of normals, needing no training (:func:`edge_frame`);
* ``head_normals`` (a checkpoint with a normal head, ``network.normal_head``): the frame of
  the head's normals in the cells its mask covers, ordered by the depth head's visible
  surface (``network.depth_head``) back-projected at the network's translation, or by the
  network's own body-frame reading turned into that frame without a depth head (where the
  head's normals all lie within 30 deg of one direction, no frame is defined and the
  network's rotation stands: ``head_fallback`` is the share of such images);
* ``head_normals_oracle``: the head's frame, its best axis order;

and, per family, the medians; with a normal head, the head's mean angle to the true normals
(``head_angle``) beside the constant's (``facing_angle``: every cell's normal read as pointing
back along its own ray, at the camera, the best a head that reads nothing can do; over the
same cells).

    .venv/bin/python eval/experiments/structure_axes.py --checkpoint MODEL --data DIR \\
        [--images 96] [--edges]
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from spread_images import (
    axes_error_deg,
    back_projected,
    folded_error_deg,
    open_spread_images,
)

from sq_mitsuba.data.spe3r.layout import model_points
from sq_mitsuba.evaluation.split import collate
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.manhattan_frame import frame_by_extent, manhattan_frame
from sq_mitsuba.geometry.rotation import axis_angle_to_matrix
from sq_mitsuba.geometry.so3_grid import so3_grid
from sq_mitsuba.model.losses import counted_surface_samples
from sq_mitsuba.model.surface_depth import visible_depth_map
from sq_mitsuba.model.surface_normals import visible_normal_map

STRIDE = 4
"""Cells of the maps, pixels at the network's input (the heads' stride)."""

def depth_normals(depth: torch.Tensor, seen: torch.Tensor, depth_origin: float,
                  camera: Camera, jump: float = 0.05) -> torch.Tensor:
    """(V, 3) unit camera-frame normals, facing the camera, of a depth map (h, w; relative to
    the body origin's depth) over its cells ``seen`` (h, w bool): at each cell whose right and
    lower neighbours are seen too and lie within ``jump`` metres in depth, the cross product of
    the two differences of the back-projected cell centres."""
    every = torch.ones(depth.shape, dtype=torch.bool)  # row by row, as reshape reads them
    points = back_projected(depth, every, depth_origin, camera, STRIDE).reshape(*depth.shape, 3)
    right = points[:-1, 1:] - points[:-1, :-1]
    down = points[1:, :-1] - points[:-1, :-1]
    keep = seen[:-1, :-1] & seen[:-1, 1:] & seen[1:, :-1]
    keep &= (right[..., 2].abs() < jump) & (down[..., 2].abs() < jump)
    normals = F.normalize(torch.cross(right, down, dim=-1), dim=-1)
    normals = torch.where(normals[..., 2:] > 0, -normals, normals)
    return normals[keep]


def facing_angle(normals: torch.Tensor, cells: torch.Tensor, camera: Camera) -> float:
    """Mean angle, degrees, between the normals (h, w, 3; camera frame) over ``cells`` (h, w
    bool) and each cell's ray reversed (from its centre's point back to the camera): the
    error of a constant reading, every face seen head on. NaN without cells."""
    if not int(cells.sum()):
        return float("nan")
    # Each cell's centre at depth 1: its ray.
    rays = back_projected(torch.zeros(cells.shape, dtype=torch.float64), cells, 1.0, camera,
                          STRIDE)
    cosine = (F.normalize(normals[cells].double(), dim=-1) * -F.normalize(rays, dim=-1)).sum(-1)
    return float(torch.rad2deg(torch.arccos(cosine.clamp(-1, 1))).mean())


def edge_pixels(image: np.ndarray, mask: np.ndarray, camera: Camera, count: int = 2000
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``count`` strongest grey-level gradients (Sobel) of ``image`` (H, W uint8) within
    3 px of ``mask`` (H, W, nonzero inside): their edge directions (P, 2) (unit, across the
    gradient), their rays' normalised coordinates (P, 2) ((u - cx) / fx, (v - cy) / fy) and
    their gradient magnitudes (P,)."""
    grey = torch.as_tensor(np.array(image), dtype=torch.float64)[None, None] / 255.0
    sobel = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]],
                         dtype=torch.float64) / 8.0
    du = F.conv2d(grey, sobel[None, None], padding=1)[0, 0]
    dv = F.conv2d(grey, sobel.T[None, None], padding=1)[0, 0]
    near = F.max_pool2d(torch.from_numpy(mask > 0).double()[None, None], 7, 1, 3)[0, 0] > 0
    near[:2], near[-2:], near[:, :2], near[:, -2:] = False, False, False, False
    magnitude = torch.hypot(du, dv) * near
    # Flat pixels' gradients are rounding noise (1e-17), not edges without a direction.
    strength, index = magnitude.flatten().topk(min(count, int((magnitude > 1e-6).sum())))
    rows, cols = index // magnitude.shape[1], index % magnitude.shape[1]
    directions = F.normalize(torch.stack([-dv.flatten()[index], du.flatten()[index]], -1),
                             dim=-1)
    rays = camera.unproject(torch.stack([cols, rows], -1).double().add(0.5), 1.0)[:, :2]
    return directions, rays, strength


def edge_agreement(rotations: torch.Tensor, directions: torch.Tensor, rays: torch.Tensor,
                   strength: torch.Tensor, sharpness: float = 8.0) -> torch.Tensor:
    """(G,) how well the body axes of ``rotations`` (G, 3, 3), drawn through each edge pixel,
    run along its edge: per pixel the best axis's cos^2 of the angle to the edge to the power
    ``sharpness``, times its foreshortening (an axis seen end-on explains no edge), averaged
    with the gradient magnitudes as weights. A camera-frame line of direction ``v`` through a
    pixel of normalised ray ``(x, y)`` runs along ``(v_x - x v_z, v_y - y v_z)`` in the
    image."""
    axes = rotations.transpose(1, 2)  # (G, 3 axes, 3)
    along = axes[:, :, None, :2] - rays[None, None] * axes[:, :, None, 2:]  # (G, 3, P, 2)
    length = along.norm(dim=-1).clamp_min(1e-9)
    cosine = (along * directions).sum(-1) / length
    agreement = length.clamp(max=1.0) * (cosine * cosine) ** sharpness
    return (agreement.amax(dim=1) * strength).sum(-1) / strength.sum()


def edge_frame(directions: torch.Tensor, rays: torch.Tensor, strength: torch.Tensor,
               grid: torch.Tensor, steps: int = 60) -> torch.Tensor:
    """(3, 3) the rotation of ``grid`` (G, 3, 3) whose axes run along the most edges
    (:func:`edge_agreement`), then refined by Adam on an axis-angle offset."""
    scores = torch.cat([edge_agreement(grid[i:i + 1000], directions, rays, strength)
                        for i in range(0, len(grid), 1000)])
    start = grid[scores.argmax()]
    offset = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    optimiser = torch.optim.Adam([offset], lr=0.01)
    for _ in range(steps):
        loss = -edge_agreement((start @ axis_angle_to_matrix(offset))[None], directions, rays,
                               strength)[0]
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    return (start @ axis_angle_to_matrix(offset)).detach()


def draw(pictures: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], path: Path
         ) -> None:
    """One row per image: the image, the true normal map and the head's (x, y, z mapped to
    red, green, blue from [-1, 1]; black where no surface is seen)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = 3 if pictures[0][2] is not None else 2
    figure, axes = plt.subplots(len(pictures), columns, figsize=(2.2 * columns,
                                                                 2.2 * len(pictures)),
                                squeeze=False)
    for row, (image, true_map, head_map) in enumerate(pictures):
        panels = [(image, "image"), (0.5 + 0.5 * true_map, "true normals")]
        if head_map is not None:
            panels.append((np.clip(0.5 + 0.5 * head_map, 0, 1), "head's normals"))
        for column, (picture, title) in enumerate(panels):
            axes[row, column].imshow(picture, cmap="gray" if picture.ndim == 2 else None,
                                     interpolation="nearest")
            axes[row, column].set_axis_off()
            if row == 0:
                axes[row, column].set_title(title, fontsize=9)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp.png")
    figure.savefig(temporary, dpi=110)
    plt.close(figure)
    temporary.replace(path)


def options(parser: argparse.ArgumentParser) -> None:
    """This script's options beside the shared ones (spread_images.py)."""
    parser.add_argument("--band", type=float, default=0.0,
                        help="the true normal map's front band, metres (visible_normal_map)")
    parser.add_argument("--edges", action="store_true",
                        help="also the image's straight edges' frame (edges_oracle; about 3 s "
                             "an image)")
    parser.add_argument("--figure", type=Path,
                        help="a PNG of the first 6 images: image, true normals, head's")
    parser.add_argument("--power", type=float, default=1.0,
                        help="each cell weighs its normal's length to this power in the frame")


def main() -> None:
    spread = open_spread_images(__doc__.split("\n\n")[0], add_arguments=options,
                                surface_points=100)
    args, predictor, dataset, camera = spread.args, spread.predictor, spread.dataset, \
        spread.camera
    size, chosen = predictor.image_size, spread.chosen
    network = predictor.model.eval()
    grid = so3_grid(5000) if args.edges else None
    full_camera = dataset.camera
    rows: list[dict[str, float | str]] = []
    pictures: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
    for start in range(0, len(chosen), 16):
        batch = collate([dataset[int(i)] for i in chosen[start:start + 16]])
        prediction = predictor.predict(batch["image"], camera)
        with torch.no_grad():
            output = network(batch["image"], camera.matrix())
        for item, model in enumerate(batch["model"]):
            truth = batch["rotation"][item].double()
            translation = batch["translation"][item].double()
            k = batch["camera"][item].double()
            points = model_points(args.data / model)
            surface = torch.from_numpy(points["surface"]).double()[None]
            normals = torch.from_numpy(points["normals"]).double()[None]
            true_normal, valid = visible_normal_map(surface, normals, truth[None],
                                                    translation[None], k, size, STRIDE,
                                                    band=args.band)
            true_depth, _ = visible_depth_map(surface, truth[None], translation[None], k,
                                              size, STRIDE)
            seen = valid[0, 0]
            row: dict[str, float | str] = {"family": model.split("_", 1)[-1]}
            if output.surface_normals is not None:
                row["head_fallback"] = 0.0
            row["network"] = folded_error_deg(prediction.rotation[item], truth)
            row["network_oracle"] = axes_error_deg(prediction.rotation[item].double(), truth)
            vectors = true_normal[0].permute(1, 2, 0)[seen]
            frame, _ = manhattan_frame(vectors, vectors.norm(dim=1) ** args.power)
            cloud = back_projected(true_depth[0, 0], seen, float(translation[2]), camera,
                                   STRIDE)
            row["true_normals"] = folded_error_deg(frame_by_extent(frame, cloud), truth)
            row["true_normals_oracle"] = axes_error_deg(frame, truth)
            try:
                frame, _ = manhattan_frame(depth_normals(true_depth[0, 0], seen,
                                                         float(translation[2]), camera))
                row["true_depth_oracle"] = axes_error_deg(frame, truth)
            except ValueError:  # too few faces seen whole
                row["true_depth_oracle"] = float("nan")
            if grid is not None:
                image, true_mask = dataset.read_pair(int(chosen[start + item]))
                frame = edge_frame(*edge_pixels(image, true_mask, full_camera), grid)
                row["edges_oracle"] = axes_error_deg(frame, truth)
            if output.surface_normals is not None:
                mask = prediction.mask[item][None, None].float()
                covered = F.avg_pool2d(mask, STRIDE)[0, 0] >= 0.5
                head = output.surface_normals[item].double().permute(1, 2, 0)  # (h, w, 3)
                if int(covered.sum()) < 2:
                    covered = torch.ones_like(covered)
                try:
                    frame, _ = manhattan_frame(head[covered],
                                               head[covered].norm(dim=1) ** args.power)
                except ValueError:  # one face seen: no frame; the network's rotation stands
                    frame = prediction.rotation[item].double()
                    row["head_fallback"] = 1.0
                if output.surface_depth is not None:
                    cloud = back_projected(output.surface_depth[item, 0], covered,
                                           float(prediction.translation[item, 2]), camera,
                                           STRIDE)
                else:  # the network's own reading, turned into the camera frame
                    reading = prediction.item_assembly(item)
                    samples, keep = counted_surface_samples(reading, 2)
                    cloud = samples[0][keep[0]].double() @ prediction.rotation[item].double().T
                row["head_normals"] = folded_error_deg(frame_by_extent(frame, cloud), truth)
                row["head_normals_oracle"] = axes_error_deg(frame, truth)
                both = covered & seen
                cosine = (F.normalize(head[both], dim=-1) * F.normalize(
                    true_normal[0].permute(1, 2, 0)[both], dim=-1)).sum(-1)
                row["head_angle"] = float(torch.rad2deg(torch.arccos(cosine.clamp(-1, 1)))
                                          .mean()) if int(both.sum()) else float("nan")
                row["facing_angle"] = facing_angle(true_normal[0].permute(1, 2, 0), both,
                                                   camera)
            if args.figure is not None and len(pictures) < 6:
                head_map = None if output.surface_normals is None else \
                    output.surface_normals[item].double().permute(1, 2, 0).numpy()
                pictures.append((batch["image"][item, 0].numpy(),
                                 true_normal[0].permute(1, 2, 0).numpy(), head_map))
            rows.append(row)
        print(f"{len(rows)} / {len(chosen)} images", flush=True)
    if args.figure is not None:
        draw(pictures, args.figure)
    columns = [c for c in rows[0] if c != "family"]
    print(f"\nfolded rotation error, degrees, over {len(rows)} images: median (mean)")
    for column in columns:
        values = np.array([r[column] for r in rows], dtype=float)
        print(f"  {column:22s} {np.nanmedian(values):6.1f} ({np.nanmean(values):5.1f})")
    by_family: dict[str, list[dict[str, float | str]]] = defaultdict(list)
    for row in rows:
        by_family[str(row["family"])].append(row)
    print("\nmedians by family: " + ", ".join(columns))
    for family, members in sorted(by_family.items()):
        medians = [np.nanmedian(np.array([m[c] for m in members], dtype=float))
                   for c in columns]
        print(f"  {family:22s} {len(members):3d} images: " +
              " ".join(f"{value:6.1f}" for value in medians))


if __name__ == "__main__":
    main()
