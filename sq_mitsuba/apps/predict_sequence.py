"""``sq-mitsuba predict IMAGES... --sequence``: N images of one spacecraft in, one assembly and
every pose out (``Predictor.predict_sequence``).

Files written to the output folder (each atomically, after every render; a run that fails
removes what it added, and one stopped part-way leaves no ``sequence.assembly.json``, which is
written last, beside the frames' new poses):

- ``sequence.assembly.json`` and ``sequence.glb``: the shared assembly in its body frame;
- ``<image stem>.pose.json`` per frame: the frame's pose of that assembly, in the layout
  ``sq-mitsuba predict`` writes (``q_vbs2tango``, ``r_Vo2To_vbs``, convention, camera,
  ``target``, ``target_score``, ``min_target``: the network's call, as ``predict`` records
  it; every frame is fitted all the same, one it sees no target in only with its mask given),
  with the frame's IoU after the joint fit, the half turn that carried its own reading and
  what set the frames' rotations (``poses``: ``SequencePrediction.poses``);
- ``<image stem>.overlay.png`` per frame: the image with the frame's own searched silhouette
  (red), the shared assembly's at the frame's pose (green) and the mask's outline (yellow);
- ``sequence.png``: the shared assembly from six sides (one colour per primitive);
- ``colmap/``: every frame's pose as a COLMAP sparse model (``cameras.txt``, ``images.txt``,
  ``points3D.txt``), to start structure from motion at them
  (:mod:`sq_mitsuba.apps.colmap_model`).

Lengths are for a target of unit size, or of ``target_size`` metres where given (the files'
assembly and translations scaled; the pictures are the same).

Every image (and mask, where given: one per frame, the frame's size, target bright) is read
and checked before the work: one size for all, at least two, no name twice.

A folder holds one pass: once this pass's files are written, an earlier pass's frames there
(a ``pose.json`` with a ``"sequence"`` entry and its overlay), a single image's files of a
frame's stem (``.assembly.json``, ``.obj``, ``.glb``) and, when this pass writes no
``colmap/``, the earlier one's are removed (:func:`_remove_earlier_pass`): their poses are of
an assembly ``sequence.assembly.json`` no longer holds. Single images' files of other stems
stay, as ``sq-mitsuba predict`` leaves them. Files predict did not write are neither replaced
nor removed: one of these names that no pose file of predict's vouches for is refused before
any work (:func:`check_pass_files`).
"""

from __future__ import annotations

import itertools
import math
import re
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["PASS_FILES", "SequenceRecord", "check_frame_files", "check_frame_order",
           "check_pass_files", "predict_sequence_files"]


def check_frame_files(images: Sequence[Path | str], masks: Sequence[Path | str] | None) -> None:
    """A one-line ``IsADirectoryError`` for a folder among the frames or their masks (a pass
    is often kept as a folder of frames; counted as one image it would read as "at least 2
    images, got 1"): checked before any other work."""
    from sq_mitsuba.data.masks import check_not_folder

    for path in images:
        check_not_folder(path, "image", f"give the pass's frames, e.g. {Path(path) / '*.png'}, "
                         "in their order")
    for path in masks or ():
        check_not_folder(path, "mask", f"give one mask per frame, e.g. {Path(path) / '*.png'}, "
                         "in the frames' order")


def _numbered(name: str) -> tuple[str, tuple[int, ...]]:
    """``name`` as its template (each run of ASCII digits a ``#``) and those runs' numbers."""
    return re.sub(r"[0-9]+", "#", name.lower()), tuple(map(int, re.findall(r"[0-9]+", name)))


def check_frame_order(paths: Sequence[Path]) -> None:
    """Warn (one line) when frames given in order are not in their names' numeric order: a
    shell glob sorts ``frame_10`` before ``frame_2``, and a pass taken in that order is fitted
    on a wrong motion, its silhouettes none the worse to show it. Only neighbours named alike
    but for their numbers are compared (``front``, ``side``, ``back`` say nothing of order)."""
    for before, after in itertools.pairwise(paths):
        (template, number), (template_before, number_before) = (_numbered(after.name),
                                                                _numbered(before.name))
        if number and template == template_before and number < number_before:
            warnings.warn(f"image {after}: given after {before.name}, but its name's number says "
                          "it comes before; the pass takes the frames in the order given (a "
                          "shell glob sorts frame_10 before frame_2: sort them with `ls -v`)",
                          stacklevel=3)
            return


#: The pass's own files in its folder (besides the frames'): replaced (or, colmap/'s, removed)
#: only where the folder holds a pass predict wrote (:func:`check_pass_files`).
PASS_FILES = ("sequence.assembly.json", "sequence.glb", "sequence.png")


def check_pass_files(out: Path, stems: Sequence[str]) -> None:
    """A one-line ``ValueError``, before any work, naming a file in ``out`` that this pass
    would replace or remove but that predict did not write: a frame's file that its
    ``<stem>.pose.json`` does not vouch for (:func:`~sq_mitsuba.apps.predict.check_own_files`),
    or one of :data:`PASS_FILES` or ``colmap/``'s files in a folder that holds no pass of
    predict's (no frame pose of one, :func:`~sq_mitsuba.apps.predict.is_pass_pose`)."""
    from sq_mitsuba.apps.colmap_model import COLMAP_FILES
    from sq_mitsuba.apps.predict import check_own_files, is_pass_pose

    check_own_files(out, stems)
    present = [path for path in (*(out / name for name in PASS_FILES),
                                 *(out / "colmap" / name for name in COLMAP_FILES))
               if path.exists() or path.is_symlink()]
    if present and not any(is_pass_pose(pose) for pose in out.glob("*.pose.json")):
        raise ValueError(f"{present[0]}: this folder holds no pass sq-mitsuba predict wrote (no "
                         "frame's pose.json of one), and this run would replace or remove it; "
                         "move it or choose another --out")


def _remove_earlier_pass(out: Path, stems: set[str], colmap_written: bool) -> int:
    """Delete what an earlier run left in ``out`` that contradicts this pass (see the module
    docstring); files it cannot read as an earlier pass's are left alone. Returns how many
    files went."""
    from sq_mitsuba.apps.colmap_model import COLMAP_FILES
    from sq_mitsuba.apps.predict import OUTPUT_SUFFIXES, is_pass_pose

    gone = []
    for pose in out.glob("*.pose.json"):
        stem = pose.name.removesuffix(".pose.json")
        if stem not in stems and is_pass_pose(pose):
            gone += [pose, out / f"{stem}.overlay.png"]
    for stem in stems:  # a single image's assembly beside this pass's pose of that stem
        gone += [out / f"{stem}{suffix}" for suffix in OUTPUT_SUFFIXES
                 if suffix not in (".pose.json", ".overlay.png")]
    stale_colmap = not colmap_written and (out / "colmap").is_dir()
    if stale_colmap:
        gone += [out / "colmap" / name for name in COLMAP_FILES]
    removed = 0
    for path in gone:
        if path.is_file():
            path.unlink()
            removed += 1
    if stale_colmap:
        try:
            (out / "colmap").rmdir()
        except OSError:  # holds the user's own files: they stay
            pass
    return removed


#: The views of ``sequence.png``: (label, (pitch, yaw) in degrees of the body -> camera
#: rotation), the assembly at the centre; "seen from +x" puts the camera on the body's +x axis.
_SIDES = (("+x", (0.0, 90.0)), ("-x", (0.0, -90.0)), ("+y", (-90.0, 0.0)), ("-y", (90.0, 0.0)),
          ("+z", (0.0, 180.0)), ("-z", (0.0, 0.0)))


@dataclass
class SequenceRecord:
    """What :func:`predict_sequence_files` did: the files, the frames' IoUs, the time and the
    prediction itself (``result``: the :class:`~sq_mitsuba.inference.prediction.
    SequencePrediction` as fitted, at the network's unit size)."""

    files: list[Path] = field(default_factory=list)
    iou: list[float] = field(default_factory=list)
    frame_iou: list[float] = field(default_factory=list)
    seconds: float = 0.0
    result: Any = None
    ordered: bool = False
    free: bool = False  # motion="free": the frames in order were not put on a turn
    removed: int = 0  # files of an earlier pass in the folder, removed

    def describe(self) -> str:
        count = len(self.iou)
        poses = getattr(self.result, "poses", None)
        why = "motion='free'" if self.free else "no turn found that enough frames agree on"
        how = {"motion": "; the frames kept on one constant-rate turn",
               "motion start": "; the frames that disagreed with one constant-rate turn "
                               "started from it",
               "given": "; the frames related by the rotations given",
               "readings": f"; each frame's rotation from its own reading ({why})"
                           if self.ordered else "; each frame's rotation from its own reading, "
                           "its half turn chosen by the shape (frames whose outlines look "
                           "alike may be half a turn apart: --ordered or "
                           "--relative-rotations relate them)"}.get(poses, "")
        return (f"{count} frames: one assembly, {count} poses in {self.seconds:.1f} s "
                f"({self.seconds / max(count, 1):.2f} s per frame); silhouette IoU against the "
                f"masks {np.mean(self.frame_iou):.3f} (each frame's own search) -> "
                f"{np.mean(self.iou):.3f} (one shape, all frames){how}")


def _side_rotation(pitch_deg: float, yaw_deg: float) -> torch.Tensor:
    pitch, yaw = math.radians(pitch_deg), math.radians(yaw_deg)
    about_x = torch.tensor([[1, 0, 0], [0, math.cos(pitch), -math.sin(pitch)],
                            [0, math.sin(pitch), math.cos(pitch)]], dtype=torch.float64)
    about_y = torch.tensor([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0],
                            [-math.sin(yaw), 0, math.cos(yaw)]], dtype=torch.float64)
    return about_x @ about_y


def _sides_picture(assembly: Any, path: Path) -> Path:
    """The assembly from six sides, side by side, as a PNG."""
    from PIL import Image, ImageDraw

    from sq_mitsuba.evaluation.figures import assembly_picture
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.io import atomic_path

    camera = Camera.default(192)
    translation = torch.tensor([0.0, 0.0, 2.2], dtype=torch.float64)
    tiles = []
    for label, (pitch, yaw) in _SIDES:
        picture = assembly_picture(assembly, _side_rotation(pitch, yaw), translation, camera)
        tile = Image.fromarray((np.clip(picture, 0, 1) * 255 + 0.5).astype(np.uint8), "RGB")
        ImageDraw.Draw(tile).text((6, 4), f"seen from {label}", fill=(230, 230, 230))
        tiles.append(tile)
    sheet = Image.new("RGB", (camera.width * len(tiles), camera.height))
    for k, tile in enumerate(tiles):
        sheet.paste(tile, (k * camera.width, 0))
    with atomic_path(path) as tmp:
        sheet.save(tmp, format="PNG")
    return path


def predict_sequence_files(images: list[str | Path], out_dir: str | Path, predictor: Any,
                           camera: Any = None, relative_rotations: Any = None,
                           options: Any = None, ordered: bool = False,
                           other_inputs: Sequence[str | Path] = (),
                           masks: Sequence[str | Path] | None = None,
                           progress: bool = False,
                           target_size: float | None = None,
                           image_names: Sequence[str] | None = None, level: int = 3,
                           overlay_spp: int = 4) -> SequenceRecord:
    """Predict one assembly and every pose from ``images`` (frames of one spacecraft) and write
    the files of the module docstring into ``out_dir``. ``other_inputs``: the run's other
    input files (the checkpoint, a camera or rotations file), refused if an output would
    overwrite one. ``masks``: one mask file per frame, in their order, fitted instead of the
    network's masks (default: the network's mask head, or the segmentation). ``progress``:
    show the stage in progress. ``target_size``: the target's longest side in metres, when
    known: the assembly and the translations written are scaled to it (``PredictOptions``'
    field of that name; default: unit size). ``image_names``: what each frame's
    ``pose.json`` records as its ``"image"``, in their order (default: the path given; the
    demo gives paths relative to its output folder, which it writes elsewhere first).
    ``level``: icosphere level of the GLB's meshes and the overlays' silhouettes (0-5);
    ``overlay_spp``: samples per pixel of the overlays' silhouettes (1-1024).

    Raises:
        ValueError: one line naming the image or argument: fewer than two images, sizes that
            differ, frames of another aspect ratio than the camera, a name twice, an
            unreadable image, a frame without a target, an output that would overwrite an
            input or that a folder stands in the way of.
    """
    from PIL import Image

    from sq_mitsuba.apps.colmap_model import COLMAP_FILES, write_colmap_model
    from sq_mitsuba.apps.overlay import (
        NETWORK_COLOUR,
        REFINED_COLOUR,
        overlay_camera,
        overlay_image,
        overlay_silhouettes,
    )
    from sq_mitsuba.apps.padding import padding_to_aspect
    from sq_mitsuba.apps.predict import (
        OUTPUTS_BY_STEM,
        POSE_CONVENTION,
        check_image_memory,
        check_target_size,
    )
    from sq_mitsuba.checks import check_int
    from sq_mitsuba.data.masks import read_gray_image, read_mask
    from sq_mitsuba.geometry.assembly import Assembly
    from sq_mitsuba.inference.loading import with_fast_path
    from sq_mitsuba.inputs import check_unique_stems
    from sq_mitsuba.io import (
        atomic_path,
        atomic_write_json,
        check_output_folder,
    )
    from sq_mitsuba.machine import available_memory
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    level = check_int("level", level, 0, 5)
    overlay_spp = check_int("overlay_spp", overlay_spp, 1, 1024)
    check_target_size(target_size)
    check_frame_files(images, masks)
    paths = [Path(p) for p in images]
    if len(paths) < 2:
        raise ValueError(f"images: a sequence needs at least 2 images, got {len(paths)}")
    check_unique_stems(paths, "images", OUTPUTS_BY_STEM)
    if image_names is not None and len(image_names) != len(paths):
        raise ValueError(f"image_names: {len(image_names)} names for {len(paths)} images")
    if ordered:
        check_frame_order(paths)
    named = next((path for path in paths if path.stem == "sequence"), None)
    if named is not None:  # its single-image files would be the pass's own (and go with them)
        raise ValueError(f"image {named}: a frame named 'sequence' would share its files' "
                         "names with the pass's sequence.assembly.json and sequence.glb; "
                         "rename it")
    given = predictor.camera if camera is None else camera
    memory = available_memory()
    for path in paths:  # every frame is held at once: each gets its share of the memory
        check_image_memory(path, given, None if memory is None else memory // len(paths))
    pictures = [read_gray_image(p) for p in paths]
    for path, picture in zip(paths[1:], pictures[1:], strict=True):
        if picture.shape != pictures[0].shape:
            raise ValueError(f"image {path}: {picture.shape[1]} x {picture.shape[0]} px, the "
                             f"first frame {paths[0]} is {pictures[0].shape[1]} x "
                             f"{pictures[0].shape[0]} px (a sequence has one size)")
    height, width = pictures[0].shape[:2]
    mask_paths = None if masks is None else [Path(m) for m in masks]
    given_masks = None
    if mask_paths is not None:
        if len(mask_paths) != len(paths):
            raise ValueError(f"mask: {len(mask_paths)} mask{'' if len(mask_paths) == 1 else 's'}"
                             f" for {len(paths)} images (one per "
                             "frame, in their order)")
        given_masks = [read_mask(m) for m in mask_paths]
        for mask_path, mask in zip(mask_paths, given_masks, strict=True):
            if mask.shape != (height, width):
                raise ValueError(f"mask {mask_path}: {mask.shape[1]} x {mask.shape[0]} px, the "
                                 f"frames are {width} x {height} px")
    if padding_to_aspect(width, height, given) is not None:  # the single image's test
        where, fix = (("the checkpoint's camera", "give the frames' own camera (--camera)")
                      if camera is None else ("the camera given", "give the frames' own camera"))
        raise ValueError(f"image {paths[0]}: {width} x {height} px, another aspect ratio than "
                         f"{where} ({given.width} x {given.height}); a pass is not padded to "
                         f"it: {fix}")
    # COLMAP's text lines are split at white space: such names get no model (said now).
    spaced = [path.name for path in paths if any(c.isspace() for c in path.name)]
    if spaced:
        warnings.warn(f"image {spaced[0]}: a name with white space, which a COLMAP text model "
                      "cannot hold; colmap/ is not written", stacklevel=2)
    out = check_output_folder(out_dir, ["sequence.assembly.json", "sequence.glb", "sequence.png"]
                              + ([] if spaced else [f"colmap/{name}" for name in COLMAP_FILES])
                              + [f"{path.stem}{suffix}" for path in paths
                                 for suffix in (".pose.json", ".overlay.png")],
                              keep=[*paths, *(mask_paths or []), *other_inputs])
    check_pass_files(out, [path.stem for path in paths])  # replaces only what predict wrote
    predictor = with_fast_path(predictor, True)
    record = SequenceRecord(ordered=ordered,
                            free=getattr(options, "motion", None) == "free")
    started = time.perf_counter()
    frames = torch.from_numpy(np.stack(pictures)).float()
    kwargs: dict[str, Any] = {} if options is None else {"options": options}
    if given_masks is not None:
        kwargs["mask"] = torch.from_numpy(np.stack(given_masks))
    try:
        result = predictor.predict_sequence(frames, camera, relative_rotations=relative_rotations,
                                            ordered=ordered, progress=progress, **kwargs)
    except ValueError as error:  # "images: frame k ..." named by its file
        found = re.match(r"images: frame (\d+) (.*)", str(error), re.S)
        if found is None:
            raise
        raise ValueError(f"image {paths[int(found[1])]}: {found[2]}") from None
    record.seconds = time.perf_counter() - started
    record.result = result
    record.iou = [float(v) for v in result.iou]
    record.frame_iou = [float(v) for v in result.frame_iou]
    out.mkdir(parents=True, exist_ok=True)
    # The files at the target's size; the pictures from the result as fitted (the same
    # images: the scene scaled about the camera).
    metric = result if target_size is None else result.scaled(target_size)
    own = result.frames
    image_camera = own.camera
    renderer = SilhouetteRenderer(overlay_camera(image_camera), spp=overlay_spp)
    count = len(paths)
    shape = pictures[0].shape
    # The renders before any file: a failure there leaves the folder as it was.
    shared = overlay_silhouettes(Assembly(result.assembly.params.expand(count, -1, -1)),
                                 result.rotation, result.translation, renderer, level, shape)
    alone = overlay_silhouettes(Assembly(own.assembly.params.double()), own.rotation.double(),
                                own.translation.double(), renderer, level, shape)
    # The shared assembly written last, an earlier pass's removed first: a run stopped in
    # between leaves frames without their assembly, never beside an earlier pass's.
    (out / "sequence.assembly.json").unlink(missing_ok=True)
    record.files.append(_sides_picture(result.assembly, out / "sequence.png"))
    scores, threshold = own.target_score, float(predictor.min_target)
    for k, (path, picture) in enumerate(zip(paths, pictures, strict=True)):
        # The target fields as `predict` records them (the network's call); every frame is
        # fitted all the same: one it sees no target in is refused unless its mask is given.
        pose = {
            "image": str(path) if image_names is None else image_names[k],
            "width": image_camera.width, "height": image_camera.height,
            "target": True if scores is None else bool(float(scores[k]) >= threshold),
            "target_score": None if scores is None else float(scores[k]),
            "min_target": threshold,
            "q_vbs2tango": [float(v) for v in result.quaternion[k]],
            "r_Vo2To_vbs": [float(v) for v in metric.translation[k]],
            "convention": f"{POSE_CONVENTION}; the body frame of sequence.assembly.json",
            "target_size": target_size,
            "camera": image_camera.to_speed_dict(),
            "checkpoint": str(getattr(predictor, "source", None) or ""),
            "turns": int(own.fit.turns),  # the frame's reading: the search's copies
            "sequence": {"frame": k, "frames": count, "reference": result.reference,
                         "iou": record.iou[k], "frame_iou": record.frame_iou[k],
                         "half_turn": [[float(v) for v in row] for row in result.half_turns[k]],
                         "mask_source": "file" if mask_paths is not None
                         else own.fit.mask_source, "steps": result.steps,
                         "poses": result.poses},
        }
        atomic_write_json(out / f"{path.stem}.pose.json", pose)
        record.files.append(out / f"{path.stem}.pose.json")
        overlay = overlay_image(picture, [(alone[k], NETWORK_COLOUR), (shared[k], REFINED_COLOUR)],
                                own.fit.mask[k].numpy())
        with atomic_path(out / f"{path.stem}.overlay.png") as tmp:
            Image.fromarray(overlay, "RGB").save(tmp, format="PNG")
        record.files.append(out / f"{path.stem}.overlay.png")
    if not spaced:
        record.files += write_colmap_model(out / "colmap", image_camera,
                                           [p.name for p in paths], result.quaternion.double(),
                                           metric.translation.double())
    record.files.append(metric.assembly.export(out / "sequence.glb", level=level))
    record.files.append(metric.assembly.save(out / "sequence.assembly.json"))
    record.removed = _remove_earlier_pass(out, {path.stem for path in paths},
                                          colmap_written=not spaced)
    return record
