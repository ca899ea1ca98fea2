"""Quality against the number of frames: one assembly and every pose from passes of N frames.

Renders one pass of ``--frames`` frames of each of ``--models`` spacecraft of a catalogue seed
the shipped model never trained on (default 4242; it trained on seed 0; with ``--held-out``
the held-out families of the compositional catalogue of that seed), in the default space
scene (:func:`sq_mitsuba.data.frames.sample_pass_frame`: the target tumbling about a random
axis, the camera approaching), then scores, for N in ``--counts``, the first N frames of each
pass: the single-image shipped path (``Predictor.predict(refine=True)``, each frame alone)
(run once per pass on all its frames, the first N taken) and, within it, the network's own
reading of each frame (method "network": one pass, no turned copies), against
``Predictor.predict_sequence`` (one assembly, N poses; ``--set`` its options), with the metrics of
``sq-mitsuba eval`` (:func:`sq_mitsuba.evaluation.scoring.score`) per frame, and the error of
the relative rotations between consecutive frames. Writes ``sequence_passes.csv`` (one row per
model, N, method and frame), prints the table of medians and means, and draws
``sequence_passes.png`` (quality against N).

    .venv/bin/python eval/experiments/sequence_passes.py --out /tmp/passes
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

import sq_mitsuba
from sq_mitsuba.data.frames import sample_pass_frame
from sq_mitsuba.data.library import generate_model
from sq_mitsuba.data.spacecraft import HELD_OUT_FAMILIES, catalogue, composed_catalogue
from sq_mitsuba.data.spe3r.layout import MODELS, SAMPLES_FILE, load_model
from sq_mitsuba.data.symmetry import model_symmetries
from sq_mitsuba.evaluation.passes import relative_rotation_errors
from sq_mitsuba.evaluation.scoring import score, volume_points
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import matrix_to_quaternion
from sq_mitsuba.inference.body_frame import reframed
from sq_mitsuba.inference.prediction import Prediction
from sq_mitsuba.inference.refine import refine_pose_and_shape
from sq_mitsuba.inference.sequence import SequenceOptions, stage_refine_options
from sq_mitsuba.render.scene_config import SceneConfig
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer
from sq_mitsuba.render.space import SpaceScene

SHOWN = ("chamfer_l1_paper", "camera_chamfer", "iou_2d", "rotation_error_folded_deg",
         "rotation_error_axes_deg", "relative_rotation_deg")


def render_pass(model_dir: Path, camera: Camera, frames: int, seed: int, spp: int) -> dict:
    """Images (N, H, W) float, masks (N, H, W), rotations (N, 3, 3), translations (N, 3)."""
    vertices, faces, tags = load_model(model_dir)
    config = SceneConfig()
    scene = SpaceScene(vertices, faces, tags, camera, config, spp=spp, dataset_seed=seed)
    images, masks, rotations, translations = [], [], [], []
    for index in range(frames):
        frame = sample_pass_frame(vertices, camera, config, seed, model_dir.name, index, frames)
        result = scene.render(frame)
        images.append(result.image_8bit())
        masks.append(result.mask > 127)
        rotations.append(frame.rotation)
        translations.append(np.asarray(frame.translation))
    return {"image": torch.from_numpy(np.stack(images)),
            "mask": torch.from_numpy(np.stack(masks)),
            "rotation": torch.from_numpy(np.stack(rotations)),
            "translation": torch.from_numpy(np.stack(translations))}


def oracle_methods(alone: Prediction, shot: dict, count: int, camera: Camera,
                   options: SequenceOptions) -> dict:
    """The diagnostic methods of ``--oracle``: frame 0's reading in the true body frame at the
    true poses, as read and with its shape fitted to the true masks, the poses held."""
    truth = shot["rotation"][:count].double()
    translation = shot["translation"][:count].double()
    carried = reframed(alone.assembly[:1], truth[0].T @ alone.rotation[0].double(),
                       torch.zeros(3, dtype=torch.float64))
    tick = time.perf_counter()
    fitted = refine_pose_and_shape(carried, truth, translation, shot["mask"][:count], camera,
                                   stage_refine_options(options, options.steps, poses=False),
                                   shared=True)
    seconds = time.perf_counter() - tick
    expand = (count, -1, -1)
    return {"oracle_pose": (Assembly(carried.params.expand(*expand)), truth, translation, 0.0),
            "oracle_fit": (Assembly(fitted.assembly.params.expand(*expand)), truth,
                           fitted.translation, seconds)}


def sequence_options(settings: list[str]) -> SequenceOptions:
    """SequenceOptions with ``FIELD=VALUE`` settings applied (values typed as the defaults)."""
    options = SequenceOptions()
    changes = {}
    for setting in settings:
        name, _, text = setting.partition("=")
        default = getattr(options, name)
        changes[name] = (text.lower() in ("1", "true", "yes")) if isinstance(default, bool) \
            else type(default)(text)
    return dataclasses.replace(options, **changes)


def _mean_and_median(values: list[float]) -> tuple[float, float]:
    """Mean and median of the finite values (NaN for a metric a method has no value of, such as
    the network's seconds or frame 0's relative rotation)."""
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return float("nan"), float("nan")
    return float(finite.mean()), float(np.median(finite))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--models", type=int, default=6)
    parser.add_argument("--catalogue-seed", type=int, default=4242)
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="the model to run (default: the shipped one)")
    parser.add_argument("--held-out", action="store_true",
                        help="spacecraft of the held-out families (never trained on) from the "
                             "compositional catalogue of --catalogue-seed, not the archetypes")
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--counts", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="SequenceOptions fields for the joint fit (e.g. steps=30)")
    parser.add_argument("--variant", action="append", default=[],
                        metavar="NAME:FIELD=VALUE[,FIELD=VALUE]",
                        help="another joint fit scored on the same frames, as method NAME "
                             "(the --set options with these changes); repeatable")
    parser.add_argument("--oracle", action="store_true",
                        help="also score, from the true poses (a diagnostic, not a method): "
                             "frame 0's reading carried into the true body frame as it is "
                             "(oracle_pose) and fitted to the N true masks with the poses held "
                             "(oracle_fit): can the frames' silhouettes correct the shape?")
    args = parser.parse_args()
    options = sequence_options(args.set)
    variants = {"sequence": options}
    for text in args.variant:
        name, _, settings = text.partition(":")
        variants[name] = sequence_options(args.set + [s for s in settings.split(",") if s])
    args.out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    predictor = sq_mitsuba.load_model(args.checkpoint, fast=True)
    camera = Camera.default(args.resolution)
    renderer = SilhouetteRenderer(camera, spp=4)
    library = args.out / "models"
    rows = []
    entries = (composed_catalogue(args.models, args.catalogue_seed, HELD_OUT_FAMILIES)
               if args.held_out else catalogue(args.models, args.catalogue_seed))
    for entry in entries:
        model_dir = library / entry.name
        if not (model_dir / MODELS / SAMPLES_FILE).is_file():
            generate_model(entry, library, points=20_000)
        shot = render_pass(model_dir, camera, args.frames, args.seed, args.spp)
        with np.load(model_dir / MODELS / SAMPLES_FILE) as samples:
            surface = torch.from_numpy(samples["surface_points"][:2500]).double()
        symmetry = torch.as_tensor(np.asarray(model_symmetries(model_dir)), dtype=torch.float64)
        volume = volume_points(model_dir, 20_000)
        # The single-image path (each frame alone, predict(refine=True)) runs once per pass:
        # its frames are independent, so the first N of them are the N-frame result.
        tick = time.perf_counter()
        alone = predictor.predict(shot["image"][:max(args.counts)], camera, refine=True)
        alone_seconds = (time.perf_counter() - tick) / max(args.counts)
        for count in args.counts:
            images = shot["image"][:count]
            batch = {"mask": shot["mask"][:count, None].double(),
                     "rotation": shot["rotation"][:count].double(),
                     "translation": shot["translation"][:count].double(),
                     "surface_points": surface.expand(count, -1, -1)}
            batch["quaternion"] = matrix_to_quaternion(batch["rotation"])
            network = alone.network  # the network's own reading (one pass, no turned copies)
            methods = {"single": (alone.assembly[:count], alone.rotation[:count].double(),
                                  alone.translation[:count].double(), alone_seconds * count),
                       "network": (network.assembly[:count], network.rotation[:count].double(),
                                   network.translation[:count].double(), float("nan"))}
            for name, variant in variants.items() if count >= 2 else ():
                tick = time.perf_counter()
                sequence = predictor.predict_sequence(images, camera, ordered=True,
                                                      options=variant)
                methods[name] = (Assembly(sequence.assembly.params.expand(count, -1, -1)),
                                 sequence.rotation, sequence.translation,
                                 time.perf_counter() - tick)
            if args.oracle and count >= 2:
                methods.update(oracle_methods(alone, shot, count, camera, options))
            for method, (assembly, rotation, translation, seconds) in methods.items():
                metrics = score(assembly, rotation, translation, batch, renderer,
                                [symmetry] * count, [volume] * count, level=2)
                metrics["relative_rotation_deg"] = relative_rotation_errors(
                    rotation, batch["rotation"])
                for k in range(count):
                    rows.append({"model": entry.name, "frames": count, "method": method,
                                 "frame": k, "seconds_per_frame": seconds / count,
                                 **{name: float(value[k]) for name, value in metrics.items()}})
            print(entry.name, count, {m: f"{v[3] / count:.2f} s/frame" for m, v in
                                      methods.items()}, flush=True)
    with open(args.out / "sequence_passes.csv", "w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    summary = {}
    for count in args.counts:
        for method in ("single", "network", *variants, "oracle_pose", "oracle_fit"):
            chosen = [r for r in rows if r["frames"] == count and r["method"] == method]
            if not chosen:
                continue
            stats = {name: _mean_and_median([r[name] for r in chosen])
                     for name in (*SHOWN, "seconds_per_frame")}
            summary[(count, method)] = stats
            print(f"N={count:2d} {method:8s} " + "  ".join(
                f"{name} {mean:.3f}/{median:.3f}" for name, (mean, median) in stats.items()))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 4, figsize=(15, 3.4))
    panels = [("chamfer_l1_paper", "body-frame Chamfer-L1 (mean)"),
              ("iou_2d", "2D IoU (mean)"),
              ("rotation_error_folded_deg", "folded rotation (median, deg)"),
              ("relative_rotation_deg", "relative rotation (median, deg)")]
    for axis, (name, label) in zip(axes, panels, strict=True):
        which = 1 if "median" in label else 0
        colours = ("tab:red", "tab:gray", "tab:green", "tab:blue", "tab:orange", "tab:purple")
        for method, colour in zip(("single", "network", *variants), colours, strict=False):
            counts = [c for c in args.counts if (c, method) in summary]
            axis.plot(counts, [summary[(c, method)][name][which] for c in counts], "o-",
                      color=colour, label=method)
        axis.set_xscale("log", base=2)
        axis.set_xticks(args.counts, [str(c) for c in args.counts])
        axis.set_xlabel("frames N")
        axis.set_title(label, fontsize=9)
        axis.grid(alpha=0.3)
    axes[0].legend()
    figure.suptitle(f"{args.models} unseen spacecraft (catalogue seed {args.catalogue_seed}), "
                    f"one pass each, {args.resolution} px", fontsize=10)
    figure.tight_layout()
    figure.savefig(args.out / "sequence_passes.png", dpi=110)


if __name__ == "__main__":
    main()
