"""``predict``: images in, a superquadric assembly and a pose per image out, as files.

Per input image ``<stem>`` the output folder receives (each file written atomically):

- ``<stem>.assembly.json``: the assembly (named fields per primitive), loadable with
  :meth:`sq_mitsuba.geometry.assembly.Assembly.load`;
- ``<stem>.obj`` (one merged mesh) and ``<stem>.glb`` (one mesh per primitive), body frame;
- ``<stem>.pose.json``: quaternion ``q_vbs2tango`` (w, x, y, z) and translation
  ``r_Vo2To_vbs`` (metres for a target of unit size, or of ``target_size`` metres: below),
  body to camera in the OpenCV frame (``x_cam = R(q) x_body + r``),
  the camera used, the image's size and mode, and the milliseconds taken; for a network with
  a rotation-distribution head also ``rotation_hypotheses``, its distinct candidate rotations
  best first, each ``{"q_vbs2tango": [w, x, y, z], "probability": p}`` (p: of the
  hypothesis' cell of the head's grid; with ``--refine``, those of the reading the search
  started from; the first is that reading's own rotation);
- ``<stem>.overlay.png``: the image (grey) with the network's silhouette in red and, when
  refined, the refined silhouette in green and the outline of the target mask in yellow.

Images: PNG/JPG/TIFF, any size; converted to one grey channel in [0, 1] as
:func:`sq_mitsuba.data.masks.read_gray_image` does: RGB and palette images become luminance
(ITU-R 601), an alpha channel composites them on black (transparent = space), 16-bit images
keep their 16-bit range (divided by 65535). The camera defaults to the one the model was
trained with, rescaled to each image.

Convention (images of another aspect ratio than the default camera): such an image is padded
with black, centred, to the camera's aspect ratio (space is black, so the padding looks like
more sky, and the network sees an unstretched picture as in training); the camera is taken to
span the padded picture, so the default field of view lies across the image's longer side.
The padded picture is predicted (and refined: a given mask is padded alike) and the outputs
are for the original image: the overlay is cropped back, and ``pose.json`` records the
camera of the original pixels (the padded camera with its principal point shifted by the
padding) with ``padded_to`` and a warning. A crop keeps the camera frame, so the pose needs
no change. An explicit ``camera`` of another aspect ratio is a one-line error naming the
file instead.

Target (``min_target``): every image gets the predictor's target-present score
(``Prediction.target_score``: the mask head's most confident pixel, or the segmentation for a
model without one, and 0 for an image of noise; see
:func:`sq_mitsuba.inference.images.target_scores`). Convention: an image scoring below
``min_target`` (0.92) shows no target: it is not refined, and its outputs are
``<stem>.pose.json`` alone, with ``"target": false``, its score and no pose (files of that
stem left by an earlier run are removed, so the folder does not hold a pose of nothing); the
printed line says "no target", and the command still succeeds (exit code 0).
``--set min_target=0`` takes every image for a target.

A folder a pass was predicted into (``predict --sequence``) keeps its frames: an image whose
stem names one of its poses is refused, before any work (:func:`check_not_a_pass_frame`).
Files predict did not write are never replaced or removed: a file of an output's name
(``<stem>.obj``, say) is refused before any work unless the ``<stem>.pose.json`` an earlier
run of predict wrote beside it says it is that run's (:func:`check_own_files`).

Units (``target_size``): the network reads every target at the dataset's unit size (the
longest side of its aligned box 1); a target L metres long at the same pose is the scene
scaled by L about the camera, the same image. With ``target_size`` L the assembly's files and
the translation are scaled by L (the overlay is the same); ``pose.json`` records it (null: 1).

Existence (``min_existence``): a network with existence probabilities keeps, per image, the
primitives whose probability reaches ``min_existence`` (0.5; its most probable one always),
and the files hold those alone; ``--set min_existence=0`` keeps every primitive.

Refinement (``refine``): the shipped path of ``Predictor.predict(images, refine=True)``
(:mod:`sq_mitsuba.inference.pipeline`: the turned copies' reading, a global pose search, then
refinement of its best few), against a mask: the given masks (one
per image, same size; bright = target, converted and thresholded as
:func:`sq_mitsuba.data.masks.read_mask` says), else the network's mask head when it has one
(``mask = "network"``), else a mask segmented from the image itself
(:func:`sq_mitsuba.data.segmentation.segment_target`). ``pose.json`` and the printed line name
the mask fitted. Silhouettes cannot tell apart poses with the same outline.

Every input is read and checked before the first prediction: a bad one is a one-line error
naming the file, and nothing is written. What the network's reading decides (a target whose
mask cannot be segmented or is empty) is checked after the network's pass over every image,
and every file is written only once all images are done: a failure writes nothing. The
images are not held meanwhile (each is read again where it is used, the overlays kept as
PNG bytes), so thousands of full-size frames fit: measured, 16 images of 1024 x 1024 px
peak at 0.60 GB against 0.57 GB for one (holding them cost 17 MB an image).
"""

from __future__ import annotations

import io
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch

from sq_mitsuba.apps.overlay import (
    NETWORK_COLOUR,
    REFINED_COLOUR,
    overlay_camera,
    overlay_image,
    overlay_silhouettes,
)
from sq_mitsuba.apps.padding import MAX_PADDING_GROWTH, Padding, padded_camera, padding_to_aspect
from sq_mitsuba.config import in_range, validate
from sq_mitsuba.inference.images import DEFAULT_MIN_TARGET
from sq_mitsuba.inference.predictor import DEFAULT_MIN_EXISTENCE
from sq_mitsuba.inference.refine import RefineOptions
from sq_mitsuba.inference.search import SEARCH_REFINEMENT, SearchOptions
from sq_mitsuba.inputs import check_unique_stems, image_header
from sq_mitsuba.machine import too_much_memory

if TYPE_CHECKING:
    from sq_mitsuba.geometry.camera import Camera

#: Turned copies of each image the network's reading comes from by default, where the network
#: and the camera allow it: as many as the search reads.
DEFAULT_TURNS = SearchOptions().turns

#: Suffixes of the files written per image, in order.
OUTPUT_SUFFIXES = (".assembly.json", ".obj", ".glb", ".pose.json", ".overlay.png")
#: Why two images of one stem are refused (:func:`~sq_mitsuba.inputs.check_unique_stems`).
OUTPUTS_BY_STEM = "and the outputs are named by it (they would overwrite each other)"
#: pose.json's "convention": the pose's frames and units.
POSE_CONVENTION = ("x_cam = R(q) x_body + r; OpenCV camera frame (x right, y down, z forward); "
                   "q = (w, x, y, z); metres for a target whose longest side is target_size "
                   "metres (null: 1, the unit size the network reads every target at)")
#: Memory one image takes in `predict`, per pixel of the (padded) image, beyond the model's:
#: measured 50 bytes (a 4,000 x 4,000 px image peaks 0.8 GB above the loaded model), with a
#: margin; the image's floats, its turned copies' mask, the overlay.
PREDICT_BYTES_PER_PIXEL = 64


@dataclass(frozen=True)
class PredictOptions:
    """Settings of ``sq-mitsuba predict``."""

    refine: bool = False
    ("Search the pose and refine it at test time against a mask: --mask, else the network's "
     "mask head (the image's segmentation for a model without one)")
    turns: int | None = in_range(1, 360, default=None)
    ("Without --refine: read each image from this many in-plane turned copies (the rotation's "
     "distributions multiplied, the rest averaged; a distribution head only): on the held-out "
     "families 8 read the rotation 7 deg nearer, for 8 x the network's time. Default: 8 where "
     "the network has a distribution head and the image's camera turns exactly (square "
     "pixels, the principal point at the centre), else 1; 1 reads each image once. With "
     "--refine the search reads search.turns copies")
    mask: Literal["network", "segmentation"] = "network"
    ("Without --mask, the mask to refine against: 'network' (the network's mask head; the "
     "image's segmentation for a model without one) or 'segmentation'")
    min_target: float = in_range(0.0, 1.0, default=DEFAULT_MIN_TARGET)
    ("Target-present score from which an image shows a target; below it: 'no target', only "
     "pose.json written (0: every image)")
    min_existence: float = in_range(0.0, 1.0, default=DEFAULT_MIN_EXISTENCE)
    ("A network with existence probabilities: the probability from which a primitive is kept "
     "(its most probable one always; 0: every primitive)")
    search: SearchOptions = field(default_factory=SearchOptions)
    "Global pose search settings."
    refinement: RefineOptions = field(default_factory=lambda: SEARCH_REFINEMENT)
    "Refinement after the search."
    level: int = in_range(0, 5, default=3)
    "Icosphere level of the exported meshes and the overlay silhouettes (3: 642 vertices each)."
    overlay_spp: int = in_range(1, 1024, default=16)
    "Samples per pixel of the overlay silhouettes."
    fast: bool = True
    "Predict with the batch-norm-folded network (same output up to ~1e-5; faster on CPU)."
    target_size: float | None = in_range(0.001, 10_000.0, default=None)
    ("The target's longest side in metres (of its box along the body axes), when known, "
     "0.001 to 10,000: the assembly and the translation are scaled to it (the network reads "
     "every target at unit size; the images cannot tell a larger one farther away). None: "
     "unit size")


@dataclass
class PredictRecord:
    """What :func:`predict_files` did for one image.

    Attributes:
        image: the input; files: the files written (:data:`OUTPUT_SUFFIXES` order).
        network_ms: the network's time for this image (after one untimed warm-up call on
            the first image); refine_ms: the search and refinement's (0 when not refined),
            search_ms: the search's part of it (the turned copies it starts from included).
        iou_before, iou_after: the search's best soft IoU (at ``search_resolution`` px) and
            the refinement's IoU (at ``refine_resolution`` px) against the mask; mask_source:
            the mask fitted ("file", "network" or "segmentation"); warning: the
            segmentation's, if any.
        target, target_score, min_target: whether the image shows a target (its score at
            least ``min_target``; see the module docstring).
    """

    image: Path
    files: list[Path]
    network_ms: float
    refine_ms: float = 0.0
    search_ms: float = 0.0
    mask_source: str | None = None
    iou_before: float | None = None
    iou_after: float | None = None
    warning: str | None = None
    target: bool = True
    target_score: float = 1.0
    min_target: float = DEFAULT_MIN_TARGET
    search_resolution: int = 0
    refine_resolution: int = 0

    def describe(self) -> str:
        """One line: the image, whether it shows a target, its times and (when refined) what
        the search and the refinement scored."""
        if not self.target:
            return (f"{self.image}: no target (target score {self.target_score:.3f} < "
                    f"min_target {self.min_target:g}); wrote its pose.json only")
        text = (f"{self.image}: target score {self.target_score:.3f}, network "
                f"{self.network_ms:.1f} ms")
        if self.iou_before is not None:
            text += (f", searched and refined in {self.refine_ms:.0f} ms against the "
                     f"{self.mask_source} mask (the search's soft IoU "
                     f"{self.iou_before:.3f} at {self.search_resolution} px, the refined "
                     f"IoU {self.iou_after:.3f} at {self.refine_resolution} px)")
        return text + (f"; warning: {self.warning}" if self.warning else "")


def _image_mode(path: Path) -> str:
    with image_header(path) as image:
        return image.mode


def has_mask_head(predictor: Any) -> bool:
    """Whether the predictor's network predicts a target mask (``Prediction.mask``)."""
    model = getattr(predictor, "model", None)
    config = getattr(model, "config", None)
    return bool(getattr(model, "mask_head", None) is not None
                or getattr(config, "mask_head", False))


def _check_inputs(paths: list[Path], camera: Any, masks: list[Path] | None,
                  options: PredictOptions, pad: bool, segmented: bool
                  ) -> tuple[list[Padding | None], list[str | None], list[str | None]]:
    """Read every image (and mask) and check them, keeping none of their pixels (thousands of
    full-size frames would not fit in memory: :class:`_Inputs` reads each again when it is
    used); returns a :class:`Padding` (or None) per image, the reason its target cannot be
    segmented where refinement will need the segmentation (an error only for an image that
    shows a target, known after the network's pass), and a warning per image."""
    from sq_mitsuba.data.masks import read_gray_image, read_mask
    from sq_mitsuba.data.segmentation import segment_target
    from sq_mitsuba.machine import available_memory

    memory = available_memory()
    if not paths:
        raise ValueError("images: give at least one image")
    if masks is not None and not options.refine:
        raise ValueError("masks: only used with refinement (--refine)")
    if masks is not None and len(masks) != len(paths):
        raise ValueError(f"masks: {len(masks)} given for {len(paths)} images (one per image)")
    check_unique_stems(paths, "images", OUTPUTS_BY_STEM)
    paddings: list[Padding | None] = []
    problems: list[str | None] = [None] * len(paths)
    warnings: list[str | None] = [None] * len(paths)
    for k, path in enumerate(paths):
        check_image_memory(path, camera, memory)  # from the header, before the pixels are decoded
        picture = read_gray_image(path)
        padding = padding_to_aspect(picture.shape[1], picture.shape[0], camera)
        if padding is not None and not pad:
            raise ValueError(f"image {path}: {picture.shape[1]} x {picture.shape[0]} px has "
                             f"another aspect ratio than the camera given ({camera.width} x "
                             f"{camera.height}): give the images' own camera")
        if padding is not None and (padding.padded_width * padding.padded_height
                                    > MAX_PADDING_GROWTH * picture.size):
            raise ValueError(f"image {path}: {picture.shape[1]} x {picture.shape[0]} px is too "
                             f"far from the camera's aspect ratio ({camera.width} x "
                             f"{camera.height}) to pad (more than {MAX_PADDING_GROWTH} x its "
                             "pixels); crop it to the target, or pass its camera (--camera)")
        paddings.append(padding)
        if masks is not None:
            target = read_mask(masks[k])
            if target.shape != picture.shape:
                raise ValueError(f"mask {masks[k]}: {target.shape[1]} x {target.shape[0]} px, "
                                 f"its image {path} is {picture.shape[1]} x "
                                 f"{picture.shape[0]} px")
        elif segmented:
            try:
                warnings[k] = segment_target(picture).warning
            except ValueError as error:
                problems[k] = (f"image {path}: cannot segment the target for refinement "
                               f"({error}); pass a mask (--mask)")
        if padding is not None:
            warnings[k] = "; ".join(w for w in (padding.describe(), warnings[k]) if w)
    return paddings, problems, warnings


def check_image_memory(path: Path, camera: Any, memory: int | None) -> None:
    """One line when the image at ``path``, padded as it would be, needs more memory than
    ``memory`` bytes (:data:`PREDICT_BYTES_PER_PIXEL`); nothing where its header cannot be
    read (decoding it says why), the memory is unknown, or the image is too far from the
    camera's aspect ratio to be padded (the checks after decoding name that)."""
    if memory is None:
        return
    try:
        with image_header(path) as header:
            width, height = header.size
    except Exception:  # not an image, a folder, ...: read_gray_image's one line says what
        return
    padding = padding_to_aspect(width, height, camera)
    pixels = width * height if padding is None else padding.padded_width * padding.padded_height
    if pixels > MAX_PADDING_GROWTH * width * height:
        return  # never padded: refused for its size or aspect ratio once read, not for memory
    if pixels * PREDICT_BYTES_PER_PIXEL > memory:
        raise ValueError(too_much_memory(
            f"image {path}: {width} x {height} px ({PREDICT_BYTES_PER_PIXEL} bytes a pixel)",
            pixels * PREDICT_BYTES_PER_PIXEL, memory, "scale it down"))


@dataclass
class _Inputs:
    """The checked inputs, read again where they are used: the picture (padded where it
    needs it) and, with refinement, the mask to fit (the file's, or the segmentation's)."""

    paths: list[Path]
    paddings: list[Padding | None]
    masks: list[Path] | None
    segmented: bool

    def raw(self, k: int) -> np.ndarray:
        """Image k as given (unpadded)."""
        from sq_mitsuba.data.masks import read_gray_image

        return read_gray_image(self.paths[k], warn=False)  # warned when checked

    def padded(self, k: int, array: np.ndarray) -> np.ndarray:
        """An array of image k's size padded as image k is."""
        return array if self.paddings[k] is None else self.paddings[k].pad(array)

    def picture(self, k: int) -> np.ndarray:
        """Image k, padded where it needs it."""
        return self.padded(k, self.raw(k))

    def target(self, k: int, raw: np.ndarray) -> np.ndarray | None:
        """The mask to fit for image k (its unpadded picture ``raw``, decoded once by the
        caller, for the segmentation), padded alike; None: the network's own."""
        from sq_mitsuba.data.masks import read_mask
        from sq_mitsuba.data.segmentation import segment_target

        if self.masks is not None:
            return self.padded(k, read_mask(self.masks[k], warn=False))
        if self.segmented:
            return self.padded(k, segment_target(raw).mask)
        return None


def predicted_pose(pose: Path) -> dict[str, Any] | None:
    """The contents of ``pose`` where it is a pose file ``predict`` (or ``predict --sequence``)
    wrote, else None (no file, one that cannot be read, someone else's). The mark: its
    ``"convention"`` starts with :data:`POSE_CONVENTION` (a pass's adds its body frame) and it
    records the ``"checkpoint"`` and the ``"target"`` call, as every pose of predict does."""
    from sq_mitsuba.outputs import json_record

    earlier = json_record(pose)
    convention = earlier.get("convention")
    if (isinstance(convention, str) and convention.startswith(POSE_CONVENTION)
            and "checkpoint" in earlier and "target" in earlier):
        return earlier
    return None


def is_pass_pose(pose: Path) -> bool:
    """Whether ``pose`` is a frame's pose file that ``predict --sequence`` wrote (a pose of
    predict's with a ``"sequence"`` entry); False for no file, one that cannot be read, a
    single image's, or someone else's."""
    earlier = predicted_pose(pose)
    return earlier is not None and "sequence" in earlier


def _exists(path: Path) -> bool:
    return path.exists() or path.is_symlink()


def check_own_files(out: Path, stems: Sequence[str]) -> None:
    """A one-line ``ValueError`` naming the first file of :data:`OUTPUT_SUFFIXES` of a stem in
    ``stems`` that is in ``out`` but not predict's own, which this run would replace or
    remove. Predict's own are the files its ``<stem>.pose.json`` (written last,
    :func:`predicted_pose`) vouches for: itself, and the stem's other files unless that pose is
    a single image's without a target (predict wrote its pose alone). Where there is no pose
    file, an assembly file of this package (``<stem>.assembly.json``) vouches for the stem's
    files: a run of predict stopped among them (the pose goes first and comes back last).
    Checked before any work: a file predict did not write is never replaced or removed."""
    from sq_mitsuba.geometry.assembly import JSON_FORMAT
    from sq_mitsuba.outputs import json_record

    # The pose first: where it is someone else's, it is the file to name.
    suffixes = (".pose.json", *(s for s in OUTPUT_SUFFIXES if s != ".pose.json"))
    for stem in stems:
        present = [out / f"{stem}{suffix}" for suffix in suffixes
                   if _exists(out / f"{stem}{suffix}")]
        if not present:
            continue
        pose = predicted_pose(out / f"{stem}.pose.json")
        if present[0].name != f"{stem}.pose.json" and json_record(
                out / f"{stem}.assembly.json").get("format") == JSON_FORMAT:
            continue  # no pose: a run stopped among the stem's files left them
        alone = pose is not None and pose.get("target") is False and "sequence" not in pose
        for path in present:
            if pose is None and path.name.endswith(".pose.json"):
                why = "not a pose file sq-mitsuba predict wrote"
            elif pose is None:
                why = (f"no pose file of sq-mitsuba predict beside it ({stem}.pose.json) says "
                       "predict wrote it")
            elif alone and not path.name.endswith(".pose.json"):
                why = (f"{stem}.pose.json is of an image without a target, for which predict "
                       "writes no other file")
            else:
                continue
            raise ValueError(f"{path}: {why}, and this run would replace or remove it; move "
                             "it or choose another --out")


def check_not_a_pass_frame(out: Path, paths: Sequence[Path]) -> None:
    """A one-line ``ValueError`` when an image's pose file in ``out`` is a frame of a pass
    (:func:`is_pass_pose`): a single image's pose there would be of another assembly than the
    pass's ``sequence.assembly.json`` and COLMAP model beside it, which would then disagree
    with the folder's own files."""
    for path in paths:
        pose = out / f"{path.stem}.pose.json"
        if path.stem == "sequence" and (out / "sequence.assembly.json").is_file():
            raise ValueError(f"out {out}: holds a pass (sequence.assembly.json), which an "
                             f"image named {path.name} would replace: choose another --out")
        if is_pass_pose(pose):
            raise ValueError(f"out {out}: {pose.name} is a frame of the pass in this folder "
                             f"(sequence.assembly.json); a single image's prediction would "
                             f"replace its pose with one of another assembly: choose another "
                             f"--out")


def predict_files(images: list[str | Path], out_dir: str | Path, predictor: Any,
                  options: PredictOptions | None = None, camera: Any = None,
                  masks: list[str | Path] | None = None,
                  progress: bool = True,
                  other_inputs: Sequence[str | Path] = ()) -> list[PredictRecord]:
    """Predict every image and write its files (see the module docstring).

    Args:
        images: image paths; all are read and checked before any prediction.
        out_dir: output folder (created; must be writable).
        predictor: a :class:`sq_mitsuba.inference.predictor.Predictor`.
        options: :class:`PredictOptions` (default settings when None).
        camera: a :class:`~sq_mitsuba.geometry.camera.Camera` of the images, or of images
            of the same aspect ratio (default: the predictor's).
        masks: with refinement, one mask per image (default: segmented from the image).
        progress: show a progress bar.
        other_inputs: the run's other input files (a camera file, say), refused if an
            output would overwrite one.

    Returns:
        One :class:`PredictRecord` per image, in order.
    """
    from sq_mitsuba.inference.loading import with_fast_path
    from sq_mitsuba.io import check_output_folder
    from sq_mitsuba.progress import progress_bar
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    options = options or PredictOptions()
    validate(options)
    explicit_camera = camera is not None
    camera = camera or predictor.camera
    paths = [Path(p) for p in images]
    mask_paths = [Path(m) for m in masks] if masks is not None else None
    # With refinement and no masks given, the mask to fit is segmented from the image unless
    # the network reads one itself.
    segmented = mask_paths is None and options.refine and not (
        options.mask == "network" and has_mask_head(predictor))
    # What needs no pixels first: a wrong option or output is said before every image is
    # decoded (and perhaps segmented).
    if options.turns is not None and options.turns > 1 and options.refine:
        raise ValueError(f"turns: {options.turns} is for the network's reading alone; with "
                         "--refine the search reads its own turned copies (--set "
                         "search.turns=T)")
    if options.turns is not None:
        predictor.check_turns(options.turns, camera)
    out = check_output_folder(out_dir, [f"{path.stem}{suffix}" for path in paths
                                        for suffix in OUTPUT_SUFFIXES],
                              keep=[*paths, *(mask_paths or []), *other_inputs])
    check_not_a_pass_frame(out, paths)
    check_own_files(out, [path.stem for path in paths])  # a user's <stem>.obj is not ours
    paddings, problems, warnings = _check_inputs(paths, camera, mask_paths, options,
                                                 pad=not explicit_camera, segmented=segmented)
    inputs = _Inputs(paths, paddings, mask_paths, segmented)
    predictor = with_fast_path(predictor, options.fast, min_target=options.min_target,
                               min_existence=options.min_existence)

    def reading_turns(image_camera: Camera) -> int:
        """The turned copies the network's reading of an image comes from (with --refine the
        search reads its own: the reading it is given is the unturned one)."""
        if options.turns is not None:
            return options.turns
        return DEFAULT_TURNS if not options.refine and predictor.can_turn(image_camera) else 1

    def read(k: int, picture: np.ndarray) -> tuple[Any, Any, PredictRecord]:
        """The network's reading of image k: its camera, prediction and record."""
        image_camera = padded_camera(camera, picture.shape[1], picture.shape[0])
        tick = time.perf_counter()
        prediction = predictor.predict(torch.from_numpy(picture).float()[None], image_camera,
                                       turns=reading_turns(image_camera))
        record = PredictRecord(paths[k], [], 1000 * (time.perf_counter() - tick),
                               warning=warnings[k], target=bool(prediction.target[0]),
                               target_score=float(prediction.target_score[0]),
                               min_target=predictor.min_target)
        return image_camera, prediction, record

    # One untimed call first: the first run of a network sets up its kernels (~1 s), which
    # would otherwise count against the first image.
    read(0, inputs.picture(0))
    # With refinement, the network's pass over every image first (milliseconds each): what it
    # decides (which images show a target, and so which need their mask) is checked before
    # the search. Only the records are kept; the images are read again below.
    records: dict[int, PredictRecord] = {}
    if options.refine:
        for k in range(len(paths)):
            record = read(k, inputs.picture(k))[2]
            if record.target and problems[k] is not None:
                raise ValueError(problems[k])  # a target to refine, but no mask to fit
            records[k] = record
    # Each image's files, the overlay as PNG bytes: kept until every image is done.
    outputs: list[tuple[PredictRecord, dict[str, Any], Any, bytes | None]] = []
    renderers: dict[Any, Any] = {}
    for k, path in enumerate(progress_bar(paths, desc="predict", unit="img", disable=not progress)):
        raw = inputs.raw(k)
        picture = inputs.padded(k, raw)
        image_camera, prediction, record = read(k, picture)
        record = records.get(k, record)  # the first pass's timing, where there was one
        padding = paddings[k]
        own_camera = image_camera if padding is None else padding.crop_camera(image_camera)
        pitch = None if padding is None else padding.pixel_pitch_m()  # the lens in metres kept
        pose: dict[str, Any] = {
            "image": str(path), "width": own_camera.width, "height": own_camera.height,
            "image_mode": _image_mode(path), "target": record.target,
            "target_score": record.target_score, "min_target": record.min_target,
        }
        if not record.target:
            pose.update(convention=POSE_CONVENTION, target_size=options.target_size,
                        camera=own_camera.to_speed_dict(pitch),
                        checkpoint=str(getattr(predictor, "source", None) or ""),
                        refined=False, network_ms=round(record.network_ms, 3))
            if padding is not None:
                pose["padded_to"] = [padding.padded_width, padding.padded_height]
            outputs.append((record, pose, None, None))
            continue
        if image_camera not in renderers:
            renderers[image_camera] = SilhouetteRenderer(overlay_camera(image_camera),
                                                         spp=options.overlay_spp)
        renderer = renderers[image_camera]
        renderer.reseed(0)  # an image's overlay the same whatever images came before it
        assembly, rotation, translation = (prediction.assembly, prediction.rotation,
                                           prediction.translation)
        quaternion = prediction.quaternion
        before = overlay_silhouettes(assembly, rotation, translation, renderer, options.level,
                                     picture.shape)[0]
        layers = [(before, NETWORK_COLOUR)]
        outline = None
        reading = prediction  # whose rotation hypotheses pose.json lists
        if options.refine:
            tick = time.perf_counter()
            # The shipped path (Predictor.refine): the turned copies' reading, the mask, the
            # search and the refinement; the mask given or segmented was read before the work.
            target = inputs.target(k, raw)
            given = target is not None
            fitted = predictor.refine(
                torch.from_numpy(picture).float()[None], prediction, image_camera,
                mask=torch.from_numpy(target)[None] if given else options.mask,
                search=options.search, refinement=options.refinement)
            fit = fitted.fit
            reading = fit.start
            if not bool(fit.fitted[0]):
                raise ValueError(f"image {path}: the network's mask of it is empty (no pixel "
                                 "above 0.5 after the turned copies' mean), nothing to refine "
                                 "against; pass a mask (--mask) or --set mask=segmentation")
            record.mask_source = ("file" if mask_paths is not None else "segmentation") \
                if given else fit.mask_source
            outline = fit.mask[0].numpy()
            record.refine_ms = 1000 * (time.perf_counter() - tick)
            record.search_ms = 1000 * fit.search_seconds
            assembly, rotation, translation = (fitted.assembly, fitted.rotation,
                                               fitted.translation)
            quaternion = fitted.quaternion
            record.iou_before = float(fit.search_score[0])
            record.iou_after = float(fit.iou[0])
            record.search_resolution = options.search.resolution
            record.refine_resolution = options.refinement.resolution
            layers.append((overlay_silhouettes(assembly, rotation, translation, renderer,
                                               options.level, picture.shape)[0], REFINED_COLOUR))
        if options.target_size is not None:  # the scene scaled about the camera: same image
            assembly = assembly.scaled(options.target_size)
            translation = translation * options.target_size
        pose.update({
            "q_vbs2tango": [float(v) for v in quaternion[0]],
            "r_Vo2To_vbs": [float(v) for v in translation[0]],
            "convention": POSE_CONVENTION,
            "target_size": options.target_size,
            "camera": own_camera.to_speed_dict(pitch),
            "checkpoint": str(getattr(predictor, "source", None) or ""),
            "refined": options.refine, "network_ms": round(record.network_ms, 3),
        })
        # The turned copies the reading whose hypotheses are listed comes from (1: the image
        # alone; with --refine the search's own reading, its start).
        pose["turns"] = int(fit.turns) if options.refine else reading_turns(image_camera)
        hypotheses = _rotation_hypotheses(reading)
        if hypotheses is not None:
            pose["rotation_hypotheses"] = hypotheses
        if options.refine:
            pose.update(refine_ms=round(record.refine_ms, 3),
                        search_ms=round(record.search_ms, 3), search_score=record.iou_before,
                        search_resolution=record.search_resolution,
                        iou_after=record.iou_after,
                        refine_resolution=record.refine_resolution,
                        mask_source=record.mask_source,
                        mask=str(mask_paths[k]) if mask_paths is not None
                        else record.mask_source)
        if padding is not None:
            pose["padded_to"] = [padding.padded_width, padding.padded_height]
        if record.warning:
            pose["warning"] = record.warning
        overlay = overlay_image(picture, layers, outline)
        if padding is not None:
            overlay = padding.crop(overlay)
        outputs.append((record, pose, assembly, _png_bytes(overlay)))
    out.mkdir(parents=True, exist_ok=True)
    return [_write_outputs(out / record.image.stem, record, pose, assembly, overlay,
                           options.level) for record, pose, assembly, overlay in outputs]


def check_target_size(target_size: float | None) -> None:
    """A one-line ``ValueError`` naming ``target_size`` unless it is None or a number within
    ``PredictOptions.target_size``'s bounds (metres)."""
    if target_size is not None:
        validate(PredictOptions(target_size=target_size))


def _rotation_hypotheses(reading: Any) -> list[dict[str, Any]] | None:
    """The first item's rotation hypotheses of ``reading`` (a Prediction) for pose.json, best
    first: ``q_vbs2tango`` (w, x, y, z; w >= 0) and the probability the network gives the
    hypothesis' cell of its grid; None for a network without a rotation-distribution head
    (its one rotation is the pose). Where the distribution has fewer separate modes than the
    predictor lists, the list pads with the best at probability 0: those are left out."""
    from sq_mitsuba.geometry.rotation import matrix_to_quaternion

    if reading.rotation_log_probabilities is None:
        return None
    quaternions = matrix_to_quaternion(reading.rotation_hypotheses[0].double())
    return [{"q_vbs2tango": [float(v) for v in q], "probability": float(p)}
            for k, (q, p) in enumerate(zip(quaternions, reading.rotation_scores[0],
                                           strict=True)) if k == 0 or float(p) > 0]


def _png_bytes(picture: np.ndarray) -> bytes:
    """An RGB picture (H, W, 3) uint8 encoded as PNG (a fraction of its pixels' memory)."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(picture, "RGB").save(buffer, format="PNG")
    return buffer.getvalue()


def _write_outputs(stem: Path, record: PredictRecord, pose: dict[str, Any], assembly: Any,
                   overlay: bytes | None, level: int) -> PredictRecord:
    """Write one image's files (:data:`OUTPUT_SUFFIXES`; its pose.json alone, and the stem's
    other files of an earlier run removed, for an image without a target). The pose.json goes
    first and comes back last: a run stopped in between leaves no earlier pose beside the new
    shape, and a pose.json means its image's files are complete."""
    from sq_mitsuba.io import atomic_write_bytes, atomic_write_json

    files = record.files
    pose_path = Path(f"{stem}.pose.json")
    pose_path.unlink(missing_ok=True)
    if assembly is None:
        for suffix in OUTPUT_SUFFIXES:
            if suffix != ".pose.json":
                Path(f"{stem}{suffix}").unlink(missing_ok=True)
    else:
        files.append(assembly.save(Path(f"{stem}.assembly.json")))
        files.append(assembly.export(Path(f"{stem}.obj"), level=level))
        files.append(assembly.export(Path(f"{stem}.glb"), level=level))
    if overlay is not None:
        overlay_path = Path(f"{stem}.overlay.png")
        atomic_write_bytes(overlay_path, overlay)
        files.append(overlay_path)
    atomic_write_json(pose_path, pose)
    files.append(pose_path)
    return record


def predict_images(images: list[str | Path], out_dir: str | Path,
                   checkpoint: str | Path | None = None, camera: str | Path | None = None,
                   masks: list[str | Path] | None = None,
                   options: PredictOptions | None = None,
                   progress: bool = True) -> list[PredictRecord]:
    """:func:`predict_files` with the model of a checkpoint file (None: the model shipped
    with the package; a clear error when there is none) and a SPEED-style ``camera.json``
    (None: the checkpoint's camera)."""
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.inference.loading import load_model

    options = options or PredictOptions()
    validate(options)
    from sq_mitsuba.data.masks import check_not_folder

    image_camera = None
    if camera is not None:
        check_not_folder(camera, "camera")
        try:
            image_camera = Camera.load(camera)
        except FileNotFoundError:
            raise FileNotFoundError(f"camera {camera}: no such file") from None
        except ValueError as error:
            message = str(error)
            raise ValueError(message if str(camera) in message else f"camera {camera}: "
                             f"{message}") from None
    predictor = load_model(checkpoint)  # predict_files folds it once the inputs are checked
    inputs = [path for path in (checkpoint, camera) if path is not None]
    return predict_files(images, out_dir, predictor, options, image_camera, masks, progress,
                         other_inputs=inputs)
