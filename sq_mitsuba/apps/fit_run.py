"""The ``sq-mitsuba fit`` job: masks and pose labels in, fitted assembly, mesh, figure and log out.

:func:`run_fit` checks every input (the output folder, each mask, each label, the camera, the
memory the resolution needs) before the fit starts, so a bad input costs no rendering and
leaves nothing behind; then it fits (:func:`sq_mitsuba.inference.fit.fit_assembly`) and writes,
each file atomically, into the output folder:

- ``assembly.json``: the fitted parameters (:meth:`Assembly.save`);
- ``assembly.glb``: one mesh per primitive;
- ``fit.png``: masks against fitted silhouettes at the start, middle and end
  (:func:`sq_mitsuba.evaluation.figures.plot_fit`);
- ``fit_log.json``: the inputs and options (``"options"``, with their ``"options_hash"``),
  loss and IoU per step, final IoU per view (see :func:`fit_log`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sq_mitsuba.config import config_hash, to_dict, validate
from sq_mitsuba.data.masks import check_not_folder, read_label_poses, read_masks
from sq_mitsuba.data.spe3r.layout import check_outside_datasets
from sq_mitsuba.evaluation.figures import plot_fit
from sq_mitsuba.geometry.assembly import JSON_FORMAT
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import quaternion_to_matrix
from sq_mitsuba.inference.fit import FitOptions, FitResult, fit_assembly
from sq_mitsuba.inputs import check_unique_stems
from sq_mitsuba.io import atomic_write_json, check_output_folder
from sq_mitsuba.outputs import json_record, refuse_present

OUTPUT_FILES = ("assembly.json", "assembly.glb", "fit.png", "fit_log.json")
"""What :func:`run_fit` writes into its output folder."""

#: Radius (m) of a ball about the body origin that holds any fitted assembly: each primitive
#: has semi-axes up to 0.5, widened across by the taper up to 1.9 times (so within
#: sqrt(2 x 0.95^2 + 0.5^2) = 1.44 of its centre), and its centre lies up to 0.5 from the
#: origin along each axis (0.87 away; :class:`~sq_mitsuba.geometry.assembly.ParameterRanges`):
#: 2.31, rounded up.
ASSEMBLY_REACH_M = 2.5


@dataclass
class FitRun:
    """What :func:`run_fit` did.

    Attributes:
        result: the fit (:class:`FitResult`).
        out: the output folder.
        masks: the mask files, in view order.
    """

    result: FitResult
    out: Path
    masks: list[Path]

    @property
    def files(self) -> list[Path]:
        """The files written, in :data:`OUTPUT_FILES` order."""
        return [self.out / name for name in OUTPUT_FILES]

    def summary(self) -> str:
        """One line: primitives, masks, mean and per-view IoU, files written."""
        result = self.result
        ious = ", ".join(f"{float(v):.3f}" for v in result.final_iou)
        return (f"fitted {result.options.num_primitives} primitive(s) to {len(self.masks)} "
                f"mask(s): mean IoU {result.mean_iou:.3f} ({ious}) at the fit's "
                f"{result.options.resolution} px (--resolution); wrote "
                f"{self.out}/{', '.join(OUTPUT_FILES)}")


def fit_log(run_masks: Sequence[Path], poses: Path, camera: Camera, camera_path: Path | None,
            result: FitResult) -> dict[str, Any]:
    """The ``fit_log.json`` record of a fit.

    Keys: ``masks`` (paths), ``poses``, ``camera`` (SPEED-style dict) and ``camera_file``
    (None: the default camera), ``options`` (:class:`FitOptions` as a dict) and
    ``options_hash``, ``final_iou`` (per view), ``mean_iou``, ``loss_per_step`` (steps,),
    ``iou_per_step`` (steps, views).
    """
    return {
        "masks": [str(p) for p in run_masks],
        "poses": str(poses),
        "camera": camera.to_speed_dict(),
        "camera_file": None if camera_path is None else str(camera_path),
        "options": to_dict(result.options),
        "options_hash": config_hash(result.options),
        "final_iou": [float(v) for v in result.final_iou],
        "mean_iou": result.mean_iou,
        "loss_per_step": result.losses,
        "iou_per_step": result.ious,
    }


def run_fit(masks: Sequence[str | Path], poses: str | Path, out: str | Path,
            options: FitOptions | None = None, camera: str | Path | None = None,
            progress: bool = False) -> FitRun:
    """Fit superquadrics to mask files seen from labelled poses; write the results to ``out``.

    Args:
        masks: mask image files, one per view (see :func:`sq_mitsuba.data.masks.read_mask`:
            object bright, converted to gray and thresholded at half range).
        poses: SPE3R-style ``labels.json`` with an entry per mask, matched by file stem.
        out: output folder (created; the files of :data:`OUTPUT_FILES` an earlier fit wrote
            there are replaced, another's of those names refused).
        options: fit settings (default :class:`FitOptions`).
        camera: SPEED-style ``camera.json`` of the masks; default: the project's default
            camera (SPEED field of view) at the masks' size.
        progress: show a progress bar.

    Returns:
        A :class:`FitRun`.

    Raises:
        ValueError, OSError: a bad input, one line naming the file (and entry) at fault, raised
            before the fit starts and before anything is written.
    """
    options = options if options is not None else FitOptions()
    validate(options)
    mask_paths = [Path(p) for p in masks]
    poses = Path(poses)
    check_outside_datasets(Path(out), None, "fit")  # its masks may be a dataset's
    out = check_output_folder(out, OUTPUT_FILES,
                              keep=[*mask_paths, poses, *([camera] if camera else [])])
    # A fit's folder (its log, or an interrupted one's assembly.json) is replaced; elsewhere a
    # file of an output's name is someone else's (a user's assembly.json, say).
    if not ({"masks", "poses", "options", "options_hash"} <= json_record(out / "fit_log.json")
            .keys() or json_record(out / "assembly.json").get("format") == JSON_FORMAT):
        refuse_present(out, OUTPUT_FILES, "an output of fit, but no earlier fit there wrote it")
    # Cheap checks first: files present, a label per mask; then the images are decoded.
    for path in mask_paths:
        check_not_folder(path, "mask")
        if not path.is_file():
            raise FileNotFoundError(f"mask {path}: no such file")
    # Poses are matched to masks by stem: two masks of one stem would get one pose.
    check_unique_stems(mask_paths, "masks",
                       "and poses are matched by stem; give each mask its own name")
    quaternions, translations = read_label_poses(poses, mask_paths)
    images = read_masks(mask_paths)
    height, width = images.shape[1:]
    behind = [mask_paths[i].name for i in range(len(mask_paths)) if translations[i, 2] <= 0]
    if behind:
        raise ValueError(f"labels {poses}: the pose of {behind[0]!r} puts the object behind "
                         "the camera (r_Vo2To_vbs_true z <= 0)")
    camera_path = None if camera is None else Path(camera)
    if camera_path is None:
        # Square pixels and the SPEED horizontal field of view at any aspect ratio, as the
        # SPEED camera itself (1920 x 1200, fx = fy): rescaling a square camera would stretch them.
        fit_camera = Camera.from_fov(Camera.default().fov_x_deg, width, height)
    else:
        check_not_folder(camera_path, "camera")
        if not camera_path.is_file():
            raise FileNotFoundError(f"camera {camera_path}: no such file")
        try:
            fit_camera = Camera.load(camera_path)
        except (ValueError, KeyError, TypeError) as error:
            message = str(error).strip("'\"")
            raise ValueError(message if str(camera_path) in message
                             else f"camera {camera_path}: {message}") from None
        if (fit_camera.width, fit_camera.height) != (width, height):
            raise ValueError(f"camera {camera_path}: {fit_camera.width} x {fit_camera.height} "
                             f"px, but the masks ({mask_paths[0]}, ...) are {width} x "
                             f"{height}")
    _check_depths(mask_paths, images, translations, fit_camera, poses)
    rotations = quaternion_to_matrix(quaternions / quaternions.norm(dim=-1, keepdim=True))

    # fit_assembly checks the tensors and the memory the resolution needs before rendering.
    result = fit_assembly(images, fit_camera, rotations, translations, options,
                          progress=progress)

    out.mkdir(parents=True, exist_ok=True)
    # An earlier run's log goes first: the log, written last, says the other files are this
    # run's and complete (an interrupt between them leaves no log beside mixed files).
    (out / "fit_log.json").unlink(missing_ok=True)
    result.assembly.save(out / "assembly.json")
    result.assembly.export(out / "assembly.glb")
    plot_fit(result, out / "fit.png")
    # The log goes last: its presence says the other files are complete.
    atomic_write_json(out / "fit_log.json",
                      fit_log(mask_paths, poses, fit_camera, camera_path, result))
    return FitRun(result=result, out=out, masks=mask_paths)


def _check_depths(mask_paths: list[Path], masks: Any, translations: Any, camera: Camera,
                  poses: Path) -> None:
    """Refuse a pose whose depth puts the object so far that no assembly (within
    :data:`ASSEMBLY_REACH_M` of its origin) can span its mask: one line naming the labels
    file and the mask (a depth in millimetres, or a typo, would fit noise)."""
    focal = max(camera.fx, camera.fy)
    for k, path in enumerate(mask_paths):
        rows = masks[k].any(dim=1).nonzero()
        columns = masks[k].any(dim=0).nonzero()
        extent = max(int(rows[-1] - rows[0]), int(columns[-1] - columns[0])) + 1
        depth = float(translations[k, 2])
        if depth <= ASSEMBLY_REACH_M:
            continue
        widest = 2 * ASSEMBLY_REACH_M * focal / (depth - ASSEMBLY_REACH_M)
        if widest < extent:
            raise ValueError(f"labels {poses}: the pose of {path.name!r} puts the object at "
                             f"z = {depth:g} m, where an assembly (at most "
                             f"{2 * ASSEMBLY_REACH_M:.2f} m across) spans at most "
                             f"{widest:.3g} px, but its mask spans {extent} px (a depth in "
                             "other units than metres?)")
        # Sideways: an origin whose assembly cannot reach the mask fits nothing (no gradient).
        u, v = (float(x) for x in camera.project(translations[k:k + 1].double())[0])
        gap_u = max(float(columns[0]) - u, u - float(columns[-1]) - 1, 0.0)
        gap_v = max(float(rows[0]) - v, v - float(rows[-1]) - 1, 0.0)
        gap = (gap_u ** 2 + gap_v ** 2) ** 0.5
        if gap > widest / 2:
            raise ValueError(f"labels {poses}: the pose of {path.name!r} puts the object's "
                             f"origin at pixel ({u:.0f}, {v:.0f}), {gap:.0f} px "
                             f"beside its mask, where an assembly reaches at most "
                             f"{widest / 2:.3g} px from it (another frame's translation?)")


__all__ = ["ASSEMBLY_REACH_M", "OUTPUT_FILES", "FitRun", "fit_log", "run_fit"]
