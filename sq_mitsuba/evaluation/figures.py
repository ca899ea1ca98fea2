"""Figures of the fitting and evaluation results (PNG, written atomically)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.evaluation.methods import METHODS
from sq_mitsuba.geometry.metrics import mask_iou
from sq_mitsuba.inference.fit import FitResult


def literal(text: object) -> str:
    """``text`` as matplotlib draws it, character for character: every '$' escaped. A user's
    name (a model, a label, a path) is not mathtext: 'cube $^$' would fail the figure after
    all the work, and 'twin $x_1$' would be drawn as a formula."""
    return str(text).replace("$", r"\$")


def plot_fit(result: FitResult, path: str | Path, title: str | None = None) -> Path:
    """PNG of the target masks against the fitted silhouettes at start, middle and end.

    One row per view; each snapshot overlays the silhouette (red) on the target (green):
    yellow where they agree. Written atomically.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sq_mitsuba.io import save_figure

    views = result.targets.shape[0]
    columns = 1 + len(result.snapshots)
    figure, axes = plt.subplots(views, columns, figsize=(2.1 * columns, 2.1 * views + 0.4),
                                squeeze=False)
    for view in range(views):
        target = result.targets[view].float()
        axes[view, 0].imshow(target.numpy(), cmap="gray", vmin=0, vmax=1)
        axes[view, 0].set_title(f"view {view}: mask", fontsize=8)
        for column, (step, coverage) in enumerate(result.snapshots, start=1):
            silhouette = coverage[view].float()
            overlay = torch.stack([silhouette, target, torch.zeros_like(target)], dim=-1)
            iou = float(mask_iou(silhouette, target))
            axes[view, column].imshow(overlay.clamp(0, 1).numpy())
            axes[view, column].set_title(f"step {step}: IoU {iou:.3f}", fontsize=8)
    for axis in axes.flat:
        axis.set_xticks([])
        axis.set_yticks([])
    figure.suptitle(literal(title) if title
                    else f"fit: mean IoU {result.mean_iou:.3f} (red fit, green mask)", fontsize=9)
    figure.tight_layout()
    return save_figure(figure, path)


# ------------------------------------------------------------------------------ evaluation

#: One colour per primitive (matplotlib's tab10), for assemblies and point clouds.
PRIMITIVE_COLOURS = np.array([(0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17),
                              (0.84, 0.15, 0.16), (0.58, 0.4, 0.74), (0.55, 0.34, 0.29),
                              (0.89, 0.47, 0.76), (0.5, 0.5, 0.5), (0.74, 0.74, 0.13),
                              (0.09, 0.75, 0.81)])
#: Colour per method in the charts.
METHOD_COLOURS = {"network": "tab:blue", "search": "tab:purple", "refined": "tab:orange",
                  "refined_gt": "tab:green", "baseline": "tab:gray"}
#: The fixed view of the body frame in the consistency figure: a rotation (body -> camera) that
#: shows three faces of the model's box, at a depth where a unit-size model fits the default
#: field of view.
_VIEW_AXIS_ANGLE = (0.55, -0.75, 0.25)
_VIEW_DEPTH = 2.8


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _methods_in(rows: Sequence[dict]) -> list[str]:
    present = {r["method"] for r in rows}
    return [m for m in METHODS if m in present] + sorted(present - set(METHODS))


def plot_per_model(rows: Sequence[dict], path: str | Path,
                   metrics: tuple[str, ...] = ("chamfer_l1_paper", "iou_3d",
                                               "rotation_error_folded_deg", "iou_2d")) -> Path:
    """Bar charts of the mean of each metric per model, std error bars, one bar per method
    (as the paper's Fig. 10). ``rows`` as in ``per_image.csv``."""
    from sq_mitsuba.io import save_figure

    plt = _pyplot()
    models = sorted({r["model"] for r in rows})
    methods = _methods_in(rows)
    figure, axes = plt.subplots(len(metrics), 1, squeeze=False, figsize=(
        max(6.0, 0.35 * len(models) * len(methods) + 2.0), 2.4 * len(metrics) + 0.6))
    width = 0.8 / max(len(methods), 1)
    x = np.arange(len(models))
    for axis, metric in zip(axes[:, 0], metrics, strict=True):
        for k, method in enumerate(methods):
            means, stds = [], []
            for model in models:
                values = np.array([float(r[metric]) for r in rows
                                   if r["model"] == model and r["method"] == method], float)
                values = values[np.isfinite(values)]
                means.append(values.mean() if len(values) else np.nan)
                stds.append(values.std() if len(values) else 0.0)
            axis.bar(x + (k - (len(methods) - 1) / 2) * width, means, width, yerr=stds,
                     capsize=2, label=literal(method), color=METHOD_COLOURS.get(method),
                     error_kw={"elinewidth": 0.8})
        axis.set_ylabel(metric, fontsize=8)
        axis.set_xticks(x)
        axis.set_xticklabels([literal(m) for m in models] if axis is axes[-1, 0]
                             else [""] * len(models),
                             rotation=40, ha="right", fontsize=7)
        axis.tick_params(axis="y", labelsize=7)
        axis.grid(axis="y", alpha=0.3)
    axes[0, 0].legend(fontsize=7, ncol=len(methods), loc="upper left",
                      bbox_to_anchor=(0.0, 1.28), frameon=False)
    figure.suptitle("mean ± std per model", fontsize=9, x=0.99, ha="right")
    figure.tight_layout()
    return save_figure(figure, path)


def assembly_picture(assembly, rotation, translation, camera, level: int = 3) -> np.ndarray:
    """RGB (H, W, 3) in [0, 1] of batch item 0 of an assembly at a pose (``x_cam = R x + t``),
    ray cast by Mitsuba, one colour per primitive (:data:`PRIMITIVE_COLOURS`), Lambert-shaded;
    black background."""
    from sq_mitsuba.render.preview import render_face_ids

    vertices, faces = assembly.merged_mesh(level)
    posed = vertices[0].detach().double() @ rotation.detach().double().T + \
        translation.detach().double()
    face, shade = render_face_ids(posed.numpy(), faces.numpy(), camera)
    per_primitive = len(faces) // assembly.num_primitives
    colours = PRIMITIVE_COLOURS[(np.maximum(face, 0) // per_primitive) % len(PRIMITIVE_COLOURS)]
    return np.where((face >= 0)[..., None], colours * shade[..., None], 0.0)


def mesh_picture(vertices, faces, rotation, translation, camera) -> np.ndarray:
    """Grey (H, W) in [0, 1]: a body-frame mesh at a pose, ray cast and Lambert-shaded."""
    from sq_mitsuba.render.preview import render_face_ids

    posed = np.asarray(vertices, float) @ rotation.detach().double().numpy().T + \
        translation.detach().double().numpy()
    _, shade = render_face_ids(posed, np.asarray(faces), camera)
    return shade


def _overlay(silhouette: Tensor, mask: Tensor) -> np.ndarray:
    """Red prediction, green mask, yellow where both (H, W, 3)."""
    silhouette, mask = silhouette.float(), mask.float()
    return torch.stack([silhouette, mask, torch.zeros_like(mask)], -1).clamp(0, 1).numpy()


def _bare(axis) -> None:
    axis.set_xticks([])
    axis.set_yticks([])


def plot_qualitative(examples: Sequence[dict], dataset, camera, figure_camera, renderer,
                     path: str | Path, level: int = 3) -> Path:
    """One row per example (as the paper's Fig. 12): the input image; the network's
    silhouette at its predicted pose over the ground-truth mask (red prediction, green mask,
    yellow both; its 2D IoU below); where refined, the same for the search and refinement
    fitted to the mask read from the image ("search + refined") and for those fitted to the
    ground-truth mask ("refined (GT mask)"); where scored, the same for the trivial baseline
    (the mean training assembly at the mean training pose); then the network's assembly at its
    predicted pose, one colour per primitive (Mitsuba ray casting); its surface points without
    those inside another primitive (body frame); the ground-truth mesh at the true pose.

    Args:
        examples: dicts with ``image``, ``mask`` (S, S), ``model``, ``index``,
            ``gt_rotation``, ``gt_translation`` and per method a tuple (assembly of batch size
            1, rotation (3, 3), translation (3,)).
        camera: intrinsics of the S x S images; renderer: a SilhouetteRenderer for them.
        figure_camera: the same camera at the resolution of the ray-cast pictures.
    """
    from sq_mitsuba.data.spe3r import load_model
    from sq_mitsuba.io import save_figure
    from sq_mitsuba.render.silhouette.renderer import render_assembly

    plt = _pyplot()
    first = examples[0] if examples else {}
    compared = [m for m in ("network", "refined", "refined_gt", "baseline") if m in first]
    titles = {"network": "network vs mask", "refined": "search + refined",
              "refined_gt": "refined (GT mask)", "baseline": "baseline vs mask"}
    columns = ["input", *(titles[m] for m in compared), "assembly", "surface points",
               "ground truth"]
    rows = max(len(examples), 1)
    figure = plt.figure(figsize=(2.0 * len(columns), 2.1 * rows + 0.3))
    meshes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for row, example in enumerate(examples):
        assembly, rotation, translation = example["network"]
        pictures: list[Any] = [example["image"].numpy()]
        ious = []
        for method in compared:
            shape, r, t = example[method]
            with torch.no_grad():
                silhouette = render_assembly(shape, r[None], t[None], renderer, level)[0]
            ious.append(float(mask_iou(silhouette.float(), example["mask"].float())))
            pictures.append(_overlay(silhouette, example["mask"]))
        pictures.append(assembly_picture(assembly, rotation, translation, figure_camera, level))
        pictures.append(None)  # the 3D point cloud
        if example["model"] not in meshes:
            vertices, faces, _ = load_model(dataset.root / example["model"])
            meshes[example["model"]] = (vertices, faces)
        pictures.append(mesh_picture(*meshes[example["model"]], example["gt_rotation"],
                                     example["gt_translation"], figure_camera))
        for column, picture in enumerate(pictures):
            index = row * len(columns) + column + 1
            if picture is None:
                axis = figure.add_subplot(rows, len(columns), index, projection="3d")
                _point_cloud(axis, assembly, level)
            else:
                axis = figure.add_subplot(rows, len(columns), index)
                axis.imshow(picture, cmap="gray", vmin=0, vmax=1)
                _bare(axis)
            if row == 0:
                axis.set_title(columns[column], fontsize=8)
            if 1 <= column <= len(ious):
                axis.set_xlabel(f"IoU {ious[column - 1]:.2f}", fontsize=7)
        figure.axes[row * len(columns)].set_ylabel(f"{literal(example['model'])}\nimage "
                                                   f"{example['index']}", fontsize=7)
    figure.tight_layout()
    return save_figure(figure, path)


def _point_cloud(axis, assembly, level: int) -> None:
    """Surface points of batch item 0 without those inside another primitive, one colour per
    primitive, in the body frame (unit size)."""
    with torch.no_grad():
        points, inside = assembly.surface_points_with_mask(level)  # (1, M, V, 3), (1, M, V)
    count, per = points.shape[1], points.shape[2]
    keep = (~inside[0]).reshape(-1).numpy()
    primitive = np.repeat(np.arange(count), per)[keep]
    cloud = points[0].reshape(-1, 3).detach().double().numpy()[keep]
    axis.scatter(cloud[:, 0], cloud[:, 1], cloud[:, 2], s=0.4, depthshade=False,
                 c=PRIMITIVE_COLOURS[primitive % len(PRIMITIVE_COLOURS)])
    axis.set_box_aspect((1, 1, 1))
    for limits in (axis.set_xlim, axis.set_ylim, axis.set_zlim):
        limits(-0.55, 0.55)
    axis.view_init(elev=20, azim=-60)
    axis.set_axis_off()


def fixed_view() -> tuple[Tensor, Tensor]:
    """The rotation (3, 3) and translation (3,) of the consistency figure's fixed view."""
    axis_angle = torch.tensor(_VIEW_AXIS_ANGLE, dtype=torch.float64)
    skew = torch.zeros(3, 3, dtype=torch.float64)
    skew[0, 1], skew[0, 2], skew[1, 2] = -axis_angle[2], axis_angle[1], -axis_angle[0]
    skew = skew - skew.T
    return torch.linalg.matrix_exp(skew), torch.tensor([0.0, 0.0, _VIEW_DEPTH],
                                                       dtype=torch.float64)


def plot_consistency(dataset, views: Sequence[Sequence[int]], predictor, camera,
                     figure_camera, path: str | Path, level: int = 3) -> Path:
    """For each model, several of its images and the assembly predicted from each, all shown
    from one fixed view of the body frame (as the paper's Fig. 11): predictions that agree
    whatever the image look alike, primitive colours included. Each is the network's single
    reading of the image (``eval --turns T`` scores readings of T turned copies; the figure
    shows how far single readings agree).

    Args:
        views: per model shown, dataset item indices of its images.
        predictor: the :class:`~sq_mitsuba.inference.predictor.Predictor`; camera: intrinsics
            of the dataset's S x S images; figure_camera: of the ray-cast pictures.
    """
    from sq_mitsuba.io import save_figure

    plt = _pyplot()
    rotation, translation = fixed_view()
    columns = max((len(v) for v in views), default=1)
    figure, axes = plt.subplots(2 * max(len(views), 1), columns, squeeze=False,
                                figsize=(1.9 * columns, 3.9 * max(len(views), 1)))
    for axis in axes.flat:
        _bare(axis)
        axis.set_frame_on(False)
    for group, items in enumerate(views):
        batch = [dataset[i] for i in items]
        images = torch.stack([item["image"] for item in batch])
        prediction = predictor.predict(images, camera)
        for k, item in enumerate(batch):
            top, bottom = axes[2 * group, k], axes[2 * group + 1, k]
            top.imshow(item["image"][0].numpy(), cmap="gray", vmin=0, vmax=1)
            bottom.imshow(assembly_picture(prediction.assembly[k], rotation, translation,
                                           figure_camera, level))
            top.set_title(f"image {item['index']}", fontsize=7)
            for axis in (top, bottom):
                axis.set_frame_on(True)
        axes[2 * group, 0].set_ylabel(literal(batch[0]["model"]), fontsize=7)
        axes[2 * group + 1, 0].set_ylabel("assembly,\nfixed view", fontsize=7)
    figure.suptitle("images of a model, and below each the assembly predicted from it,\n"
                    "all in one fixed view of the body frame", fontsize=8)
    figure.tight_layout()
    return save_figure(figure, path)


def plot_illumination(table: Sequence[dict], path: str | Path,
                      metrics: Sequence[str], title: str = "") -> Path:
    """Each metric against the phase angle: one line per background and method (mean), a
    shaded band of ± one std, and separate markers (with std bars) for eclipse groups.

    Args:
        table: rows with ``method``, ``background`` ("space", "earth", "eclipse"; another
            name is drawn after those),
            ``phase_deg`` (x), and per metric ``<metric>_mean`` and ``<metric>_std``.
        metrics: the metrics to plot, one panel each.
    """
    from sq_mitsuba.io import save_figure

    plt = _pyplot()
    columns = min(3, len(metrics))
    panels = math.ceil(len(metrics) / columns)
    figure, axes = plt.subplots(panels, columns, squeeze=False,
                                figsize=(4.2 * columns, 2.9 * panels + 0.5))
    known = ("space", "earth", "eclipse")
    backgrounds = sorted({r["background"] for r in table},
                         key=lambda b: (known.index(b) if b in known else len(known), b))
    methods = _methods_in(table)
    styles = ("-", "--", ":", "-.")
    line_colours = ("tab:blue", "tab:red", "tab:green", "tab:purple")
    for axis, metric in zip(axes.flat, metrics, strict=False):
        for b, background in enumerate(backgrounds):
            for m, method in enumerate(methods):
                group = sorted((r for r in table if r["background"] == background
                                and r["method"] == method), key=lambda r: r["phase_deg"])
                if not group:
                    continue
                x = np.array([r["phase_deg"] for r in group], float)
                mean = np.array([r[f"{metric}_mean"] for r in group], float)
                std = np.array([r[f"{metric}_std"] for r in group], float)
                label = literal(f"{background}, {method}")
                if background == "eclipse":  # one marker a method, side by side
                    axis.errorbar(x + 4.0 * m, mean, yerr=std, fmt="sD^v"[m % 4],
                                  color="black", ms=4, mfc="white" if m else "black",
                                  capsize=2, label=label)
                    continue
                colour = line_colours[b % len(line_colours)]
                axis.plot(x, mean, styles[m % len(styles)], color=colour, marker=".",
                          label=label)
                axis.fill_between(x, mean - std, mean + std, color=colour, alpha=0.12,
                                  linewidth=0)
        axis.set_title(metric, fontsize=8)
        axis.set_xlabel("sun phase angle [deg]", fontsize=7)
        axis.set_xlim(-5, 185)
        axis.set_xticks(range(0, 181, 30))
        axis.tick_params(labelsize=7)
        axis.grid(alpha=0.3)
    for axis in list(axes.flat)[len(metrics):]:
        axis.set_visible(False)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", fontsize=7,
                  ncol=min(4, max(len(labels), 1)), frameon=False)
    figure.suptitle((literal(title) + "\n" if title else "") + "metrics against the sun phase "
                    "angle (lines: mean; shaded: ± std; black markers: eclipse frames, one shape "
                    "a method, each 4 deg to the right of the one before)", fontsize=9)
    figure.tight_layout(rect=(0, 0.04 + 0.02 * math.ceil(len(labels) / 4), 1, 1))
    return save_figure(figure, path)


def plot_quality_vs_frames(summary: dict[tuple[int, str], dict[str, tuple[float, ...]]],
                           counts: Sequence[int], path: str | Path, passes: int,
                           panels: Sequence[tuple[str, str, str]],
                           methods: Sequence[str]) -> Path:
    """Quality against the number of frames N of a pass study: one panel per metric, one line
    per method.

    Args:
        summary: {(N, method): {metric: (mean, std, median)}}.
        counts: the N scored (the x axis, log 2).
        passes: how many passes the figures come from (the title's).
        panels: (metric, title, statistic) per panel; statistic "mean" or "median".
        methods: the methods drawn, in the legend's order ("network", "single", "sequence"
            have their colours; another is drawn in the cycle's).
    """
    from sq_mitsuba.io import save_figure

    plt = _pyplot()
    colours = {"network": "tab:gray", "single": "tab:red", "sequence": "tab:blue"}
    figure, axes = plt.subplots(1, len(panels), figsize=(3.3 * len(panels), 3.2),
                                squeeze=False)
    for axis, (name, title, statistic) in zip(axes[0], panels, strict=True):
        which = 2 if statistic == "median" else 0
        for method in methods:
            shown = [c for c in counts if (c, method) in summary
                     and math.isfinite(summary[(c, method)][name][which])]
            if shown:
                axis.plot(shown, [summary[(c, method)][name][which] for c in shown], "o-",
                          color=colours.get(method), label=literal(method))
        axis.set_xscale("log", base=2)
        axis.set_xticks(list(counts), [str(c) for c in counts])
        axis.set_xlabel("frames N")
        axis.set_title(f"{title}, {statistic}", fontsize=9)
        axis.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    figure.suptitle(f"One assembly from the first N frames of each of {passes} pass(es) "
                    "against those frames alone (every line scores the same N frames)",
                    fontsize=10)
    figure.tight_layout()
    return save_figure(figure, path)
