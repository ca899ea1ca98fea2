"""What the visible surface gives: a single reading fitted to the surface one image shows.

Readers that go through a 2.5D map (the depth of the surface seen in each pixel) and then
complete the shape were found to carry to unseen classes where readers of the whole shape
retrieve their training shapes instead (GenRe, Zhang et al. 2018; Tatarchenko et al. 2019).
This asks how far that route could take this project's assemblies, before any network is
trained for it. On evenly spread test images, each network reading (its kept primitives) is
fitted in the body frame, at the true pose, by Adam on its raw parameters, and scored against
the true surface (body-frame Chamfer-L1, the paper's):

* ``read``: as read (the figure ``sq-mitsuba eval`` reports);
* ``visible``: fitted to the true visible surface, the nearest true surface point in each
  stride-``--stride`` cell of the network's input (what a perfect depth map shows), by a
  2.5D Chamfer: every visible point near the assembly's surface, and the assembly's own
  visible samples (the nearest in each cell) near the visible points. Nothing pulls the far
  side: the reading and the primitives' own symmetry complete it;
* ``visible_head`` (a checkpoint with a depth head): the same fit to the network's own depth
  map, the head's depth in each cell its mask head covers, back-projected at the true pose;
* ``surface``: fitted to the whole true surface (the representation's ceiling, as
  ``shape_capacity.py``).

With a depth head, its map itself is scored too (``depth_*`` rows, metres, mean absolute error
over the cells the true surface covers): the head's, a flat map at the body origin's depth
(nothing learned), and on the cells that both cover, the reading's own visible depth at the
true pose beside the head's (does the head know more of the depth than the shape reader?).

    .venv/bin/python eval/experiments/visible_surface_fit.py --checkpoint MODEL --data DIR \\
        [--images 96] [--steps 150] [--stride 4]
"""

from __future__ import annotations

import argparse
from functools import partial

import numpy as np
import torch
from spread_images import (
    back_projected,
    distance,
    folded_error_deg,
    open_spread_images,
    thinned,
)

from sq_mitsuba.evaluation.split import collate
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import axis_angle_to_matrix
from sq_mitsuba.geometry.so3_grid import with_half_turns
from sq_mitsuba.inference.refine import raw_from_assembly
from sq_mitsuba.model.losses import counted_surface_samples, surface_chamfer_loss
from sq_mitsuba.model.surface_depth import cells_at_pose, visible_depth_map

TRUTH_POINTS = 16000
"""True surface points per model for its visible surface (about 10 per covered cell)."""


def to_camera(points: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor
              ) -> torch.Tensor:
    """(K, 3) body-frame points placed by one pose (rotation (3, 3), translation (3,))."""
    return points @ rotation.T + translation


def nearest_per_cell(camera_points: torch.Tensor, cells: torch.Tensor, side: int
                     ) -> torch.Tensor:
    """(K,) bool: the points nearest the camera in their cell (one per covered cell, ties
    aside), points outside the grid never."""
    z = camera_points[:, 2].detach()
    nearest = torch.full((side * side + 1,), torch.inf, dtype=z.dtype)
    nearest = nearest.scatter_reduce(0, cells, z, reduce="amin")
    return (z <= nearest[cells]) & (cells < side * side)


def seen_from(points: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor,
              k: torch.Tensor, size: int, stride: int) -> torch.Tensor:
    """(K,) bool: the body-frame points (K, 3) nearest the camera in their stride-``stride``
    cell of the S = ``size`` image at one pose (rotation (3, 3), translation (3,))."""
    camera, flat, side = cells_at_pose(points[None], rotation[None], translation[None], k,
                                       size, stride)
    return nearest_per_cell(camera[0], flat[0], side)


def visible_chamfer(assembly: Assembly, visible: torch.Tensor, rotation: torch.Tensor,
                    translation: torch.Tensor, k: torch.Tensor, stride: int, size: int,
                    level: int) -> torch.Tensor:
    """The 2.5D Chamfer of one assembly (batch 1, body frame) against visible points (V, 3,
    body frame): the visible points' mean squared distance to the assembly's counted samples
    plus the assembly's visible samples' (at the pose) to the visible points."""
    points, keep = counted_surface_samples(assembly, level)
    points = points[0][keep[0]]
    seen = seen_from(points, rotation, translation, k, size, stride)
    squared = torch.cdist(visible, points).square()
    forward = squared.amin(1).mean()
    backward = squared[:, seen].amin(0).mean() if bool(seen.any()) else squared.sum() * 0
    return forward + backward


def fit(start: Assembly, loss, steps: int, lr: float) -> Assembly:
    """``start`` (batch 1) fitted by Adam on its raw parameters to ``loss(assembly)``."""
    raw = raw_from_assembly(start).float().clone().requires_grad_(True)
    optimizer = torch.optim.Adam([raw], lr=lr)
    for _ in range(steps):
        optimizer.zero_grad(set_to_none=True)
        loss(Assembly.from_raw(raw)).backward()
        optimizer.step()
    return Assembly.from_raw(raw.detach())


def registered(read: Assembly, cloud: torch.Tensor, hypotheses: torch.Tensor,
               translation: torch.Tensor, k: torch.Tensor, stride: int, size: int, level: int,
               pose_steps: int, steps: int, lr: float) -> tuple[Assembly, torch.Tensor]:
    """The reading registered to a camera-frame visible cloud (V, 3), then fitted to it.

    Every start, each rotation hypothesis (K, 3, 3) turned by each half turn, is moved by
    Adam on a rotation vector and a translation step, the reading's shape held, for
    ``pose_steps``; the start whose 2.5D Chamfer ends lowest keeps its pose, and the shape
    is then fitted at it as :func:`fit`. Returns the fitted assembly (body frame) and its
    rotation (3, 3)."""
    starts = with_half_turns(hypotheses).reshape(-1, 3, 3)
    best = (torch.inf, starts[0], translation)
    for start in starts:
        omega = torch.zeros(3, requires_grad=True)
        shift = torch.zeros(3, requires_grad=True)
        optimizer = torch.optim.Adam([{"params": [omega], "lr": lr * 2},
                                      {"params": [shift], "lr": lr}])
        for step in range(pose_steps + 1):
            rotation = axis_angle_to_matrix(omega) @ start
            place = translation + shift
            loss = visible_chamfer(read, (cloud - place) @ rotation, rotation, place, k,
                                   stride, size, level)
            if step == pose_steps:
                break
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        if float(loss.detach()) < best[0]:
            best = (float(loss.detach()), rotation.detach(), place.detach())
    _, rotation, place = best
    body_cloud = (cloud - place) @ rotation
    fitted = fit(read, lambda a: visible_chamfer(a, body_cloud, rotation, place, k, stride,
                                                 size, level), steps, lr)
    return fitted, rotation


def head_visible_points(surface_depth: torch.Tensor, mask: torch.Tensor,
                        rotation: torch.Tensor, translation: torch.Tensor, camera: Camera,
                        stride: int) -> torch.Tensor:
    """(V, 3) body-frame points of a depth head's map (1, h, w; depth relative to the body
    origin's) in the cells a mask (H, W probability) covers by half or more, each cell's
    centre back-projected at the pose."""
    covered = torch.nn.functional.avg_pool2d(mask[None, None].float(), stride)[0, 0] >= 0.5
    side = surface_depth.shape[-1]
    points = back_projected(surface_depth[0], covered[:side, :side], float(translation[2]),
                            camera, stride)
    return (points.to(rotation) - translation) @ rotation


def depth_errors(head_depth: torch.Tensor, read: Assembly, truth: torch.Tensor,
                 rotation: torch.Tensor, translation: torch.Tensor, k: torch.Tensor, size: int,
                 stride: int) -> dict[str, float]:
    """Mean absolute errors (metres) of depth maps relative to the body origin's against the
    true visible surface's (cells of ``stride`` px at the true pose): the head's map (1, h, w),
    a flat map (0), and on the cells both cover, the reading's visible surface and the head."""
    def depth_map(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        depth, valid = visible_depth_map(points[None].float(), rotation[None], translation[None],
                                         k, size, stride)
        return depth[0, 0], valid[0, 0]

    true_depth, true_valid = depth_map(truth)
    samples, keep = counted_surface_samples(read, 3)
    read_depth, read_valid = depth_map(samples[0][keep[0]].detach())
    head = head_depth[0].float()
    both = true_valid & read_valid
    return {"depth_head": float((head - true_depth).abs()[true_valid].mean()),
            "depth_flat": float(true_depth.abs()[true_valid].mean()),
            "depth_head_both": float((head - true_depth).abs()[both].mean()),
            "depth_reading_both": float((read_depth - true_depth).abs()[both].mean())}


def positive(text: str) -> int:
    """An integer of at least 1 (argparse's one-line error otherwise)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"need at least 1, got {value}")
    return value


def options(parser: argparse.ArgumentParser) -> None:
    """This script's options beside the shared ones (spread_images.py)."""
    parser.add_argument("--steps", type=positive, default=200)
    parser.add_argument("--lr", type=float, default=0.02)
    parser.add_argument("--stride", type=positive, default=4)
    parser.add_argument("--level", type=int, default=2, help="icosphere level of the fit")
    parser.add_argument("--pose-steps", type=positive, default=40,
                        help="steps of each start's registration")
    parser.add_argument("--surface", action="store_true",
                        help="also fit the whole true surface (the ceiling; slow)")


def main() -> None:
    spread = open_spread_images(__doc__.split("\n\n")[0], add_arguments=options,
                                surface_points=TRUTH_POINTS)
    args, predictor, dataset, camera = spread.args, spread.predictor, spread.dataset, \
        spread.camera
    size, chosen = predictor.image_size, spread.chosen
    rng = np.random.default_rng(0)
    network = predictor.model.eval()
    has_head = network.depth_head is not None
    rows: list[dict[str, float]] = []
    for start in range(0, len(chosen), 16):
        batch = collate([dataset[int(i)] for i in chosen[start:start + 16]])
        prediction = predictor.predict(batch["image"], camera)
        head_depth = None
        if has_head:
            with torch.no_grad():
                head_depth = network(batch["image"], camera.matrix()).surface_depth
        for item, model in enumerate(batch["model"]):
            rotation = batch["rotation"][item].float()
            translation = batch["translation"][item].float()
            k = batch["camera"][item].float()
            truth = batch["surface_points"][item].float()
            visible = truth[seen_from(truth, rotation, translation, k, size, args.stride)]
            read = Assembly(prediction.item_assembly(item).params.detach().float())
            scored = thinned(truth.float(), rng)
            row = {"model": model}

            def score(assembly: Assembly, scored: torch.Tensor = scored) -> float:
                samples, keep = counted_surface_samples(assembly, 3)
                return distance(thinned(samples[0][keep[0]].detach(), rng), scored)

            def to_cloud(cloud: torch.Tensor, pose_r: torch.Tensor, pose_t: torch.Tensor,
                         k: torch.Tensor = k):
                return partial(visible_chamfer, visible=cloud, rotation=pose_r,
                               translation=pose_t, k=k, stride=args.stride, size=size,
                               level=args.level)

            row["read"] = score(read)
            # The network's own placement: the visible points carried into its body frame.
            net_rotation = prediction.rotation[item].float()
            net_translation = prediction.translation[item].float()
            seen_camera = to_camera(visible, rotation, translation)
            in_network_frame = (seen_camera - net_translation) @ net_rotation
            clouds = {"visible": (visible, rotation, translation),
                      "visible_at_reading": (in_network_frame, net_rotation, net_translation)}
            if head_depth is not None:
                clouds["head"] = (head_visible_points(
                    head_depth[item], prediction.mask[item], rotation, translation, camera,
                    args.stride), rotation, translation)
                clouds["head_at_reading"] = (head_visible_points(
                    head_depth[item], prediction.mask[item], net_rotation, net_translation,
                    camera, args.stride), net_rotation, net_translation)
                row.update(depth_errors(head_depth[item], read, truth, rotation, translation,
                                        k, size, args.stride))
            for name, (cloud, pose_r, pose_t) in clouds.items():
                row[name] = score(fit(read, to_cloud(cloud, pose_r, pose_t), args.steps,
                                      args.lr))
            hypotheses = prediction.rotation_hypotheses[item].float()
            folded = {"read": net_rotation}
            registered_clouds = {"registered": seen_camera}
            if head_depth is not None:
                head_camera = to_camera(clouds["head_at_reading"][0], net_rotation,
                                        net_translation)
                registered_clouds["registered_head"] = head_camera
            for name, cloud in registered_clouds.items():
                fitted, folded[name] = registered(
                    read, cloud, hypotheses, net_translation, k, args.stride, size, 1,
                    args.pose_steps, args.steps, args.lr)
                row[name] = score(fitted)
            for name, found in folded.items():
                row[f"folded_{name}"] = folded_error_deg(found, rotation)
            if args.surface:
                target = thinned(truth.float(), rng)
                row["surface"] = score(fit(read, partial(surface_chamfer_loss, target=target,
                                                         level=args.level),
                                           args.steps, args.lr))
            rows.append(row)
        print(f"{len(rows)} / {len(chosen)} images", flush=True)
    columns = [c for c in rows[0] if c != "model"]
    print("\nbody-frame Chamfer-L1 (paper; depth_* rows: depth error in metres), mean "
          "(median) over", len(rows), "images")
    for column in columns:
        values = np.array([r[column] for r in rows])
        print(f"  {column:24s} {values.mean():.4f} ({np.median(values):.4f})")


if __name__ == "__main__":
    main()
