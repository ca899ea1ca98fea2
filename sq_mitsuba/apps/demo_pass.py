"""The demo's pass: N images of one spacecraft in, one assembly and every pose out.

After the single images, ``sq-mitsuba demo`` renders a pass of ``DemoSize.pass_frames`` frames
of its first spacecraft (the target tumbling about a random axis while the camera approaches,
as ``sq-mitsuba dataset render --pass-frames`` makes them), runs ``predict --sequence`` on the
frames in their order (:func:`~sq_mitsuba.apps.predict_sequence.predict_sequence_files`: the
shared assembly, one pose per frame, the overlays, the assembly from six sides) and scores
three readings of every frame against its truth with the evaluation's own
:func:`~sq_mitsuba.evaluation.scoring.score`:

- ``network``: the network's own reading of the frame;
- ``frames``: the frame alone as the pass starts from it (the network's turned copies, the
  pose search and one refinement step: the red silhouettes of the overlays), lighter than
  the single images' ``refined`` path above it on the page (50 refinement steps) and than
  ``study passes``' ``single``;
- ``sequence``: the shared assembly at the frame's pose after the joint fit (green).

Beside every metric of ``sq-mitsuba eval``, ``relative_rotation_deg``: how far the rotation
from the frame before to this one is from the true one (blank for frame 0).

Files, under the demo's ``pass/``::

    models/<name>/, splits.csv     the spacecraft (a copy of the demo's first)
    data/                          the rendered pass (SPE3R layout, ``pass`` and
                                   ``frame_in_pass`` in its labels)
    sequence/                      what ``predict --sequence`` writes
    per_frame.csv                  every metric per frame and method

Convention: as ``sq-mitsuba study passes``, the frames are read and scored at the rendered
resolution (what a user hands ``predict --sequence``), not at the network's input size as
the demo's single images are; the primitive meshes, the 2D IoU's samples and the overlays'
are the demo's (``DemoOptions.level``, ``silhouette_spp``, ``overlay_spp``). Every frame is
fitted whatever the network's target score (``min_target`` 0, as the study does): the demo
renders the target in each.
"""

from __future__ import annotations

import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["PASS_METHODS", "PASS_METRICS", "PassRecord", "pass_section", "render_pass",
           "run_pass"]

#: Methods scored per frame, in the page's order, with their labels (module docstring).
PASS_METHODS = {"network": "network, each frame alone",
                "frames": "each frame searched, one refinement step (red)",
                "sequence": "one assembly, every pose (green)"}
#: Metrics of the pass on the page (every metric is in per_frame.csv).
PASS_METRICS = {"chamfer_l1_paper": "body-frame Chamfer-L1",
                "camera_chamfer": "camera-frame Chamfer",
                "iou_2d": "2D IoU",
                "rotation_error_folded_deg": "up to half turns (deg)",
                "relative_rotation_deg": "frame to frame (deg)"}


@dataclass
class PassRecord:
    """What :func:`run_pass` did.

    Attributes:
        model: the spacecraft; frames: its frames; resolution: their side in pixels.
        rows: one dict per frame and method (the ``per_frame.csv`` rows).
        summary: {method: {metric: mean over the frames' finite values}} (NaN where none
            is finite).
        stems: the frames' file stems, in order (``sequence/<stem>.overlay.png``).
        seconds: wall time of ``predict --sequence`` (the frames' path included).
    """

    model: str
    frames: int
    resolution: int
    rows: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, dict[str, float]] = field(default_factory=dict)
    stems: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def describe(self) -> str:
        """One line: the pass's 2D IoU and relative rotation against its frames'."""
        frames, sequence = self.summary["frames"], self.summary["sequence"]
        return (f"  a pass of {self.frames} frames of {self.model}: 2D IoU "
                f"{frames['iou_2d']:.3f} (each frame searched) -> {sequence['iou_2d']:.3f} "
                f"(one assembly), frame to frame {frames['relative_rotation_deg']:.1f} -> "
                f"{sequence['relative_rotation_deg']:.1f} deg, "
                f"{self.seconds / max(self.frames, 1):.2f} s a frame")


def render_pass(library: Path, model: str, root: Path, frames: int, resolution: int,
                spp: int, seed: int, progress: bool) -> Path:
    """Copy ``model`` of ``library`` into ``root/models`` (a test model) and render one pass
    of ``frames`` frames of it into ``root/data``; returns the data folder.

    Raises:
        ValueError: the pass could not be rendered (the renderer's reason).
    """
    from sq_mitsuba.data.spe3r import RenderOptions, render_dataset
    from sq_mitsuba.data.spe3r.layout import write_splits

    models = root / "models"
    shutil.copytree(library / model, models / model)
    write_splits(models, [(model, "test")])
    data = root / "data"
    rendered = render_dataset(models, data, RenderOptions(
        images_per_model=frames, pass_frames=frames, seed=seed, resolution=resolution, spp=spp),
        progress=progress)
    if rendered.failures:
        raise ValueError(f"the pass of {model} could not be rendered: "
                         f"{next(iter(rendered.failures.values()))}")
    return data


def run_pass(predictor: Any, data: Path, root: Path, surface_points: int, volume_points: int,
             level: int, silhouette_spp: int, progress: bool, overlay_spp: int = 16
             ) -> PassRecord:
    """``predict --sequence`` on the one pass of ``data`` (files into ``root/sequence``), each
    frame scored as the module docstring says (``root/per_frame.csv``).

    Args:
        surface_points: true surface points per frame for the Chamfer distances;
        volume_points: uniform points of the model for the 3D IoU; level: icosphere level of
        the primitive meshes scored, and of the GLB and overlays written; silhouette_spp:
        samples per pixel of the 2D IoU's silhouettes; overlay_spp: of the overlays'.
    """
    from sq_mitsuba.apps.predict_sequence import predict_sequence_files
    from sq_mitsuba.evaluation.passes import pass_groups, score_frames
    from sq_mitsuba.evaluation.scoring import METRICS, ModelData
    from sq_mitsuba.evaluation.split import collate, open_split
    from sq_mitsuba.evaluation.tables import csv_text, summarise
    from sq_mitsuba.geometry.assembly import Assembly
    from sq_mitsuba.inference.loading import with_fast_path
    from sq_mitsuba.io import atomic_write_text
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    dataset = open_split(data, "test", None, surface_points)  # at the rendered resolution
    (model_index, _), items = next(iter(pass_groups(dataset).items()))
    paths = [dataset.image_file(item) for item in items]
    predictor = with_fast_path(predictor, True, min_target=0.0)  # every frame shows the target
    # pose.json names each frame from the demo's folder, as the single images' do: ``root``
    # (the demo's pass folder) is written in a staging folder first.
    names = [Path(os.path.relpath(path, root.parent)).as_posix() for path in paths]
    written = predict_sequence_files(paths, root / "sequence", predictor, camera=dataset.camera,
                                     ordered=True, progress=progress, image_names=names,
                                     level=level, overlay_spp=overlay_spp)
    result = written.result
    own = result.frames
    count = len(items)
    readings = {
        "network": (own.network.assembly, own.network.rotation, own.network.translation),
        "frames": (own.assembly, own.rotation, own.translation),
        "sequence": (Assembly(result.assembly.params.expand(count, -1, -1)), result.rotation,
                     result.translation)}
    batch = collate([dataset[item] for item in items])
    camera = dataset.camera.rescaled(dataset.image_size, dataset.image_size)
    renderer = SilhouetteRenderer(camera, spp=silhouette_spp)
    models = ModelData(dataset, volume_points)
    symmetry, volume = models.symmetry(model_index), models.volume(model_index)
    record = PassRecord(dataset.models[model_index], count, dataset.image_size,
                        stems=[path.stem for path in paths], seconds=written.seconds)
    for method, (assembly, rotation, translation) in readings.items():
        assembly = Assembly(assembly.params.detach().double())
        rotation, translation = rotation.detach().double(), translation.detach().double()
        metrics = score_frames(assembly, rotation, translation, batch, renderer, symmetry,
                               volume, level)
        for k in range(count):
            record.rows.append({"frame": k, "method": method,
                                **{name: float(value[k]) for name, value in metrics.items()}})
    header = ["model", "frame", "method", *METRICS, "relative_rotation_deg"]
    means = summarise(record.rows, ("method",), header[3:])
    record.summary = {method: {name: stats[0] for name, stats in means[(method,)].items()}
                      for method in readings}
    atomic_write_text(root / "per_frame.csv", csv_text(header, [
        [record.model, row["frame"], row["method"],
         *("" if not math.isfinite(row.get(m, math.nan)) else f"{row[m]:.6g}"
           for m in header[3:])] for row in record.rows]))
    return record


def pass_section(record: PassRecord, prefix: str = "pass") -> Any:
    """The page's section of the pass (:class:`~sq_mitsuba.apps.demo_page.PageSection`);
    ``prefix``: the pass's folder, relative to the page."""
    from sq_mitsuba.apps.demo_page import PageSection

    by_frame = {(row["method"], row["frame"]): row for row in record.rows}
    pictures = [(f"{prefix}/sequence/{stem}.overlay.png",
                 f"frame {k}: 2D IoU {by_frame[('frames', k)]['iou_2d']:.3f} searched -> "
                 f"{by_frame[('sequence', k)]['iou_2d']:.3f} one assembly")
                for k, stem in enumerate(record.stems)]
    text = [
        f"{record.frames} frames of {record.model} in their order, path-traced at "
        f"{record.resolution} x {record.resolution} px while the target tumbles about a "
        "random axis and the camera approaches. 'sq-mitsuba predict FRAMES... --sequence' "
        "reads every frame (the network's turned copies, the pose search and one refinement "
        "step), brings the readings into one body frame with the pass kept on one "
        "constant-rate turn, and fits one shared assembly and every frame's pose to all the "
        f"frames' masks at once through Mitsuba's silhouettes ({record.seconds:.1f} s, "
        f"{record.seconds / max(record.frames, 1):.2f} s a frame).",
        "Mean over the frames, scored at the rendered resolution (the single images above "
        "at the network's input size); 'frame to frame': the "
        "error of the rotation from the frame before to this one, which several views pin "
        "even where the absolute rotation (which axis is which) stays wrong. Overlays (as "
        "'predict --sequence' writes them): red, each frame searched alone; green, the shared "
        "assembly at the frame's pose; yellow, the outline of the mask the fit reads from the "
        "image (the network's, not the true mask the single images above outline: where it "
        "misses dark faces or arrays, green can fill yellow while the 2D IoU against the "
        "truth stays low).",
    ]
    return PageSection(
        title=f"A pass of {record.frames} images: one assembly and every pose",
        text=text, metric_labels=dict(PASS_METRICS),
        rows=[(label, record.summary[method]) for method, label in PASS_METHODS.items()],
        figures=[(f"{prefix}/sequence/sequence.png",
                  "the shared assembly from six sides (one colour per primitive)")],
        pictures=pictures,
        links=[("shared assembly (JSON)", f"{prefix}/sequence/sequence.assembly.json"),
               ("shared assembly (GLB)", f"{prefix}/sequence/sequence.glb"),
               ("first frame's pose (JSON)", f"{prefix}/sequence/{record.stems[0]}.pose.json"),
               ("every pose as a COLMAP model (images.txt)",
                f"{prefix}/sequence/colmap/images.txt"),
               ("every metric, per frame (CSV)", f"{prefix}/per_frame.csv"),
               ("the rendered pass (SPE3R layout)", f"{prefix}/data/dataset.json")])
