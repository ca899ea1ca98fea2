"""The demo's files: per image its pictures (the input, the silhouettes before and after the
fit, the predicted assembly beside the true mesh) and its assembly and pose files, and the
page's content (:mod:`sq_mitsuba.apps.demo_page` writes the page)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["DEMO_FORMAT", "DEMO_OUTPUTS", "MANIFEST", "METHOD_LABELS", "PAGE_METRICS",
           "foreign_entry", "is_demo_record", "save_png", "shown_model", "stem_of",
           "write_demo_page", "write_outputs"]

#: The file that marks a folder as a demo's output (and holds its record).
MANIFEST = "demo.json"
#: The record's "format": the mark of a demo.json the demo wrote.
DEMO_FORMAT = "sq-mitsuba-demo/1"
#: Keys every demo.json holds (a demo's record): one of a demo written before the format mark
#: is recognised by them all.
RECORD_KEYS = frozenset({"options", "checkpoint", "baseline", "images", "models"})
#: Everything a demo writes at the top of its folder (the module docstring of
#: :mod:`sq_mitsuba.apps.demo`): a folder holding anything else is not (only) a demo's.
DEMO_OUTPUTS = frozenset({"index.html", "index.md", MANIFEST, "per_image.csv", "summary.csv",
                          "summary.md", "per_model.csv", "per_model.md", "images", "assemblies",
                          "models", "data", "pass", "train"})
#: Methods scored per image, in the page's order, with their labels.
METHOD_LABELS = {"network": "network", "refined": "search + refined (image's mask)",
                 "baseline": "trivial baseline"}
#: Metrics on the page (every metric of ``sq-mitsuba eval`` is in per_image.csv).
PAGE_METRICS = {"chamfer_l1_paper": "Chamfer-L1 (paper)",
                "camera_chamfer": "camera-frame Chamfer",
                "iou_2d": "2D IoU", "iou_3d": "3D IoU",
                "rotation_error_deg": "rotation error (deg)",
                "rotation_error_folded_deg": "up to half turns (deg)",
                "rotation_error_axes_deg": "up to the axes' names (deg)",
                "translation_error_m": "translation error (m)"}


def is_demo_record(path: Path) -> bool:
    """Whether ``path`` is a demo.json a demo wrote: a JSON object with :data:`DEMO_FORMAT`
    as its "format", or (a demo before that mark) every key of :data:`RECORD_KEYS`. A file
    merely named demo.json (``{}``, someone's notes) is not one."""
    from sq_mitsuba.outputs import json_record

    record = json_record(path)
    return record.get("format") == DEMO_FORMAT or RECORD_KEYS <= record.keys()


def foreign_entry(folder: Path) -> Path | None:
    """An entry at the top of ``folder`` that a demo does not write (:data:`DEMO_OUTPUTS`),
    or None: the demo replaces its folder as a whole, so one there would be deleted."""
    return next((path for path in sorted(folder.iterdir()) if path.name not in DEMO_OUTPUTS),
                None)


def stem_of(record: dict[str, Any]) -> str:
    """File stem of one image's outputs: ``<model>_<index>``."""
    return f"{record['model']}_{record['index']:04d}"


def save_png(path: Path, rgb: np.ndarray) -> None:
    """RGB (H, W, 3) uint8 or float in [0, 1] as PNG, atomically."""
    from PIL import Image

    from sq_mitsuba.io import atomic_path

    if rgb.dtype != np.uint8:
        rgb = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    with atomic_path(path) as tmp:
        Image.fromarray(rgb, "RGB").save(tmp, format="PNG")


def write_outputs(records: Sequence[dict[str, Any]], data: Path, out: Path,
                   options: Any, progress: bool) -> None:
    """Per image: the pictures (images/) and the assembly and pose files (assemblies/)."""
    from sq_mitsuba.apps.overlay import NETWORK_COLOUR, REFINED_COLOUR, overlay_image
    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.data.spe3r.layout import load_model
    from sq_mitsuba.evaluation.figures import assembly_picture, mesh_picture
    from sq_mitsuba.geometry.rotation import matrix_to_quaternion
    from sq_mitsuba.io import atomic_write_json
    from sq_mitsuba.progress import progress_bar
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

    # The pictures are drawn at the rendered resolution, from the stored full-size files.
    dataset = Spe3rDataset(data, "test", num_surface=1, num_occupancy=2)
    camera = dataset.camera
    renderer = SilhouetteRenderer(camera, spp=options.overlay_spp)
    meshes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    (out / "images").mkdir(exist_ok=True)
    (out / "assemblies").mkdir(exist_ok=True)
    for record in progress_bar(records, desc="pictures and files", unit="img",
                               disable=not progress):
        stem = stem_of(record)
        image, mask = dataset.read_pair(record["item"])
        picture = image.astype(np.float64) / 255.0
        outline = mask >= 128
        for method, colour in (("network", NETWORK_COLOUR), ("refined", REFINED_COLOUR)):
            assembly, rotation, translation = record[method]
            with torch.no_grad():
                silhouette = render_assembly(assembly, rotation[None], translation[None],
                                             renderer, options.level)[0].numpy()
            name = "network" if method == "network" else "refined"
            save_png(out / "images" / f"{stem}.{name}.png",
                      overlay_image(picture, [(silhouette, colour)], outline))
            assembly.save(out / "assemblies" / f"{stem}.{name}.assembly.json")
            assembly.export(out / "assemblies" / f"{stem}.{name}.glb", level=options.level)
        assembly, rotation, translation = record["refined"]
        save_png(out / "images" / f"{stem}.assembly.png",
                  assembly_picture(assembly, rotation, translation, camera, options.level))
        if record["model"] not in meshes:
            vertices, faces, _ = load_model(data / record["model"])
            meshes[record["model"]] = (vertices, faces)
        truth = mesh_picture(*meshes[record["model"]], record["gt_rotation"],
                             record["gt_translation"], camera)
        save_png(out / "images" / f"{stem}.truth.png", np.repeat(truth[..., None], 3, -1))
        poses = {}
        for method in ("network", "refined"):
            _, rotation, translation = record[method]
            poses[method] = {"q_vbs2tango": [float(v) for v in
                                             matrix_to_quaternion(rotation[None])[0]],
                             "r_Vo2To_vbs": [float(v) for v in translation]}
        poses["truth"] = {
            "q_vbs2tango": [float(v) for v in matrix_to_quaternion(
                record["gt_rotation"][None])[0]],
            "r_Vo2To_vbs": [float(v) for v in record["gt_translation"]]}
        atomic_write_json(out / "assemblies" / f"{stem}.pose.json", {
            "image": f"data/{record['model']}/images/{record['filename']}",
            "convention": "x_cam = R(q) x_body + r; OpenCV camera frame (x right, y down, "
                          "z forward); q = (w, x, y, z); metres",
            "camera": camera.to_speed_dict(), **poses})


def shown_model(checkpoint: str) -> str:
    """How the page names the model: the shipped one by its place in the package, not by
    this machine's path to it; another checkpoint by the path it was given as."""
    from sq_mitsuba.model.checkpoint import SHIPPED_MODEL

    if not checkpoint or Path(checkpoint) == SHIPPED_MODEL:
        return "the model shipped with sq_mitsuba (sq_mitsuba/model/weights/model.pt)"
    return checkpoint


def write_demo_page(out: Path, options: Any, records: Sequence[dict[str, Any]],
                table: dict[str, dict[str, tuple[float, float, float]]], checkpoint: str,
                baseline_source: str, curves: bool, stages: dict[str, float],
                wall: float, passed: Any = None,
                pass_skipped: str | None = None) -> tuple[Path, Path]:
    """The page (index.html, index.md) of the demo's images and, where one was run, its pass
    (:class:`~sq_mitsuba.apps.demo_pass.PassRecord`; ``pass_skipped``: why a pass that was
    rendered could not be fitted, said on the page)."""
    from sq_mitsuba.apps.demo_page import DemoPage, PageImage, write_page
    from sq_mitsuba.apps.demo_pass import pass_section
    from sq_mitsuba.evaluation.tables import as_number, markdown_code
    from sq_mitsuba.inference.search import SearchOptions

    preset = options.preset
    # A user's path in a code span: index.md shows its '<b>', '*' or '|' as typed (index.html
    # escapes the same text; the backticks read as quotes there).
    model = shown_model(checkpoint)
    model = markdown_code(model) if model == checkpoint else model
    models = sorted({r["model"] for r in records})
    sources = sorted({r["metrics"]["refined"].get("mask_source") or "none" for r in records})
    mask_sources = " / ".join({"network": "the network's mask head",
                               "segmentation": "threshold segmentation"}.get(m, m)
                              for m in sources)
    intro = [
        f"{len(records)} image(s) of {len(models)} procedural spacecraft the model never saw "
        f"(catalogue seed {options.seed}; the shipped model trains on catalogue seed 0), "
        f"path-traced at {preset.resolution} x {preset.resolution} px in the default space "
        "scene. For each image the network predicts a superquadric assembly and its pose; "
        "a global search then scores candidate rotations (for a model with a rotation "
        f"distribution head its own, read again from {SearchOptions().turns} in-plane turns of "
        "the image, whose means also give the assembly, position and mask the search fits; a "
        "uniform grid of SO(3) for one without; each with the four half turns of the body "
        f"frame) by Mitsuba silhouettes against the mask read from the image ({mask_sources}), and "
        f"test-time refinement ({preset.refine_steps} steps at most) adjusts the pose of the "
        "best through the differentiable silhouette, its rotation held near the search's. "
        "Silhouettes cannot tell apart poses with the same outline.",
        f"Model: {model}. Trivial baseline: "
        f"{baseline_source}.",
        "Silhouettes: red, the network's prediction; green, after refinement; yellow, the "
        "outline of the true mask. 2D IoU is measured at the network's input size; Chamfer-L1 "
        "(paper convention: L1 nearest neighbours, both directions summed) in the unit-size "
        "body frame; the camera-frame Chamfer compares the posed clouds, over the true "
        "distance. Rotation error up to half turns: the least over the four half turns of the "
        "body frame (which end of an axis is '+' cannot be seen on an unknown model; chance "
        "79 deg median).",
        *([pass_skipped[0].upper() + pass_skipped[1:]] if pass_skipped else []),
        "Times: " + ", ".join(f"{k} {v:.0f} s" for k, v in stages.items())
        + f"; {wall:.0f} s in all before this page.",
    ]
    summary = [(METHOD_LABELS[m], {k: table[m][k][0] for k in PAGE_METRICS})
               for m in METHOD_LABELS if m in table]
    images = []
    for record in records:
        stem = stem_of(record)
        refined = record["metrics"]["refined"]
        images.append(PageImage(
            title=f"{record['model']}, image {record['index']}",
            pictures=[
                (f"data/{record['model']}/images/{record['filename']}", "input image"),
                (f"images/{stem}.network.png",
                 f"network: 2D IoU {as_number(record['metrics']['network']['iou_2d']):.3f}"),
                (f"images/{stem}.refined.png",
                 f"refined: 2D IoU {as_number(refined['iou_2d']):.3f}"),
                (f"images/{stem}.assembly.png", "refined assembly, one colour per primitive"),
                (f"images/{stem}.truth.png", "ground-truth mesh at the true pose"),
            ],
            metrics=[(METHOD_LABELS[m], {k: as_number(record["metrics"][m][k])
                                         for k in PAGE_METRICS})
                     for m in METHOD_LABELS],
            links=[
                ("network assembly (JSON)", f"assemblies/{stem}.network.assembly.json"),
                ("network assembly (GLB)", f"assemblies/{stem}.network.glb"),
                ("refined assembly (JSON)", f"assemblies/{stem}.refined.assembly.json"),
                ("refined assembly (GLB)", f"assemblies/{stem}.refined.glb"),
                ("poses (JSON)", f"assemblies/{stem}.pose.json"),
            ]))
    figures = [("images/training_curves.png",
                "training curves of the model trained by --train")] if curves else []
    page = DemoPage(
        title="sq-mitsuba demo: spacecraft as superquadric assemblies from one image",
        intro=intro, metric_labels=dict(PAGE_METRICS), summary=summary, figures=figures,
        images=images,
        sections=[] if passed is None else [pass_section(passed)],
        files=[("every metric, per image (CSV)", "per_image.csv"),
               ("summary: mean, std, median (CSV)", "summary.csv"),
               ("per model (Markdown)", "per_model.md"),
               ("run record (JSON)", MANIFEST),
               ("the rendered dataset (SPE3R layout)", "data/dataset.json")])
    return write_page(out, page)
