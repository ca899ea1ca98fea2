"""``predict``: images in, a superquadric assembly and a pose per image out, as files.

Per input image ``<stem>`` the output folder receives (each file written atomically):

- ``<stem>.assembly.json``: the assembly (named fields per primitive), loadable with
  :meth:`sq_mitsuba.geometry.assembly.Assembly.load`;
- ``<stem>.obj`` (one merged mesh) and ``<stem>.glb`` (one mesh per primitive), body frame;
- ``<stem>.pose.json``: quaternion ``q_vbs2tango`` (w, x, y, z) and translation
  ``r_Vo2To_vbs`` (metres), body to camera in the OpenCV frame (``x_cam = R(q) x_body + r``),
  the camera used, the image's size and mode, and the milliseconds taken;
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

Refinement (``refine``): the shipped path of ``Predictor.predict(images, refine=True)``
(:mod:`sq_mitsuba.inference.pipeline`: the turned copies' reading, a global pose search, then
refinement of its best few), against a mask: the given masks (one
per image, same size; bright = target, converted and thresholded as
:func:`sq_mitsuba.data.masks.read_mask` says), else the network's mask head when it has one
(``mask = "network"``), else a mask segmented from the image itself
(:func:`sq_mitsuba.data.segmentation.segment_target`). ``pose.json`` and the printed line name
the mask fitted. Silhouettes cannot tell apart poses with the same outline.

Every input is read and checked before the first prediction: a bad one is a one-line error
naming the file, and nothing is written.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from sq_mitsuba.apps.overlay import NETWORK_COLOUR, REFINED_COLOUR, overlay_image
from sq_mitsuba.apps.padding import MAX_PADDING_GROWTH, Padding, padded_camera, padding_to_aspect
from sq_mitsuba.config import in_range, validate
from sq_mitsuba.inference.refine import RefineOptions
from sq_mitsuba.inference.search import SEARCH_REFINEMENT, SearchOptions

#: Suffixes of the files written per image, in order.
OUTPUT_SUFFIXES = (".assembly.json", ".obj", ".glb", ".pose.json", ".overlay.png")


@dataclass(frozen=True)
class PredictOptions:
    """Settings of ``sq-mitsuba predict``."""

    refine: bool = False
    "Search the pose and refine it at test time against a mask (given, or read from the image)."
    mask: Literal["network", "segmentation"] = "network"
    "Without --mask: the network's mask head (segmentation for a model without one)."
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


@dataclass
class PredictRecord:
    """What :func:`predict_files` did for one image.

    Attributes:
        image: the input; files: the files written (:data:`OUTPUT_SUFFIXES` order).
        network_ms: the network's time for this image (after one untimed warm-up call on
            the first image); refine_ms: the search and refinement's (0 when not refined),
            search_ms: the search's part of it.
        iou_before, iou_after: the search's best soft IoU (search resolution) and the
            refinement's IoU (refinement resolution) against the mask; mask_source: the mask
            fitted ("file", "network" or "segmentation"); warning: the segmentation's, if any.
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

    def describe(self) -> str:
        """One line: the image, its times and (when refined) the IoUs."""
        text = f"{self.image}: network {self.network_ms:.1f} ms"
        if self.iou_before is not None:
            text += (f", searched and refined in {self.refine_ms:.0f} ms against the "
                     f"{self.mask_source} mask (IoU {self.iou_before:.3f} -> "
                     f"{self.iou_after:.3f})")
        return text + (f"; warning: {self.warning}" if self.warning else "")


def _image_mode(path: Path) -> str:
    from PIL import Image

    with Image.open(path) as image:
        return image.mode


def has_mask_head(predictor: Any) -> bool:
    """Whether the predictor's network predicts a target mask (``Prediction.mask``)."""
    model = getattr(predictor, "model", None)
    config = getattr(model, "config", None)
    return bool(getattr(model, "mask_head", None) is not None
                or getattr(config, "mask_head", False))


def _check_inputs(paths: list[Path], camera: Any, masks: list[Path] | None,
                  options: PredictOptions, pad: bool, predictor: Any = None
                  ) -> tuple[list[np.ndarray], list[np.ndarray] | None, list[str | None],
                             list[Padding | None]]:
    """Read every image (and mask) and check them; returns the pictures and targets (padded
    to the camera's aspect ratio where ``pad`` allows and an image needs it), a warning and a
    :class:`Padding` (or None) per image."""
    from sq_mitsuba.data.masks import read_gray_image, read_mask
    from sq_mitsuba.data.segmentation import segment_target

    if not paths:
        raise ValueError("images: give at least one image")
    if masks is not None and not options.refine:
        raise ValueError("masks: only used with refinement (--refine)")
    if masks is not None and len(masks) != len(paths):
        raise ValueError(f"masks: {len(masks)} given for {len(paths)} images (one per image)")
    stems = [p.stem for p in paths]
    if len(set(stems)) != len(stems):
        twice = sorted({s for s in stems if stems.count(s) > 1})
        raise ValueError(f"images: several inputs are named {twice[0]!r} (without suffix); "
                         "their outputs would overwrite each other")
    pictures, paddings = [], []
    for path in paths:
        picture = read_gray_image(path)
        padding = padding_to_aspect(picture.shape[1], picture.shape[0], camera)
        if padding is not None and not pad:
            raise ValueError(f"image {path}: {picture.shape[1]} x {picture.shape[0]} px has "
                             f"another aspect ratio than the camera's {camera.width} x "
                             f"{camera.height}; pass the images' own camera (--camera)")
        if padding is not None and (padding.padded_width * padding.padded_height
                                    > MAX_PADDING_GROWTH * picture.size):
            raise ValueError(f"image {path}: {picture.shape[1]} x {picture.shape[0]} px is too "
                             f"far from the camera's aspect ratio ({camera.width} x "
                             f"{camera.height}) to pad (more than {MAX_PADDING_GROWTH} x its "
                             "pixels); crop it to the target, or pass its camera (--camera)")
        pictures.append(picture)
        paddings.append(padding)
    targets = None
    warnings: list[str | None] = [None] * len(paths)
    if masks is not None:
        targets = []
        for path, picture, mask_path in zip(paths, pictures, masks, strict=True):
            target = read_mask(mask_path)
            if target.shape != picture.shape:
                raise ValueError(f"mask {mask_path}: {target.shape[1]} x {target.shape[0]} px, "
                                 f"its image {path} is {picture.shape[1]} x "
                                 f"{picture.shape[0]} px")
            targets.append(target)
    elif options.refine and not (options.mask == "network" and has_mask_head(predictor)):
        targets = []
        for k, (path, picture) in enumerate(zip(paths, pictures, strict=True)):
            try:
                segmentation = segment_target(picture)
            except ValueError as error:
                raise ValueError(f"image {path}: cannot segment the target for refinement "
                                 f"({error}); pass a mask (--mask)") from None
            targets.append(segmentation.mask)
            warnings[k] = segmentation.warning
    for k, padding in enumerate(paddings):
        if padding is None:
            continue
        pictures[k] = padding.pad(pictures[k])
        if targets is not None:
            targets[k] = padding.pad(targets[k])
        warnings[k] = "; ".join(w for w in (padding.describe(), warnings[k]) if w)
    return pictures, targets, warnings, paddings


def predict_files(images: list[str | Path], out_dir: str | Path, predictor: Any,
                  options: PredictOptions | None = None, camera: Any = None,
                  masks: list[str | Path] | None = None,
                  progress: bool = True) -> list[PredictRecord]:
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

    Returns:
        One :class:`PredictRecord` per image, in order.
    """
    from PIL import Image
    from tqdm import tqdm

    from sq_mitsuba.inference.loading import with_fast_path
    from sq_mitsuba.io import atomic_path, atomic_write_json, check_output_folder
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

    options = options or PredictOptions()
    validate(options)
    explicit_camera = camera is not None
    camera = camera or predictor.camera
    paths = [Path(p) for p in images]
    mask_paths = [Path(m) for m in masks] if masks is not None else None
    pictures, targets, warnings, paddings = _check_inputs(paths, camera, mask_paths, options,
                                                          pad=not explicit_camera,
                                                          predictor=predictor)
    out = check_output_folder(out_dir)
    predictor = with_fast_path(predictor, options.fast)
    out.mkdir(parents=True, exist_ok=True)
    # One untimed call first: the first run of a network sets up its kernels (~1 s), which
    # would otherwise count against the first image.
    predictor.predict(torch.from_numpy(pictures[0]).float()[None],
                      padded_camera(camera, pictures[0].shape[1], pictures[0].shape[0]))
    renderers: dict[Any, Any] = {}
    records = []
    for k, (path, picture) in enumerate(tqdm(list(zip(paths, pictures, strict=True)),
                                             desc="predict", unit="img",
                                             disable=not progress)):
        image_camera = padded_camera(camera, picture.shape[1], picture.shape[0])
        padding = paddings[k]
        if image_camera not in renderers:
            renderers[image_camera] = SilhouetteRenderer(image_camera, spp=options.overlay_spp)
        renderer = renderers[image_camera]
        tick = time.perf_counter()
        prediction = predictor.predict(torch.from_numpy(picture).float()[None], image_camera)
        record = PredictRecord(path, [], 1000 * (time.perf_counter() - tick),
                               warning=warnings[k])
        assembly, rotation, translation = (prediction.assembly, prediction.rotation,
                                           prediction.translation)
        quaternion = prediction.quaternion
        with torch.no_grad():
            before = render_assembly(assembly, rotation, translation, renderer,
                                     options.level)[0].numpy()
        layers = [(before, NETWORK_COLOUR)]
        outline = None
        if options.refine:
            tick = time.perf_counter()
            # The shipped path (Predictor.refine): the turned copies' reading, the mask, the
            # search and the refinement; the mask given or segmented was read before the work.
            given = targets is not None
            fitted = predictor.refine(
                torch.from_numpy(picture).float()[None], prediction, image_camera,
                mask=torch.from_numpy(targets[k])[None] if given else options.mask,
                search=options.search, refinement=options.refinement)
            fit = fitted.fit
            if not bool(fit.fitted[0]):
                raise ValueError(f"image {path}: the network's mask is empty (nothing to fit); "
                                 "pass a mask (--mask) or --set mask=segmentation")
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
            with torch.no_grad():
                after = render_assembly(assembly, rotation, translation, renderer,
                                        options.level)[0].numpy()
            layers.append((after, REFINED_COLOUR))
        stem = out / path.stem
        record.files.append(assembly.save(Path(f"{stem}.assembly.json")))
        record.files.append(assembly.export(Path(f"{stem}.obj"), level=options.level))
        record.files.append(assembly.export(Path(f"{stem}.glb"), level=options.level))
        own_camera = image_camera if padding is None else padding.crop_camera(image_camera)
        pose = {
            "image": str(path), "width": own_camera.width, "height": own_camera.height,
            "image_mode": _image_mode(path),
            "q_vbs2tango": [float(v) for v in quaternion[0]],
            "r_Vo2To_vbs": [float(v) for v in translation[0]],
            "convention": "x_cam = R(q) x_body + r; OpenCV camera frame (x right, y down, "
                          "z forward); q = (w, x, y, z); metres",
            "camera": own_camera.to_speed_dict(),
            "checkpoint": str(getattr(predictor, "source", None) or ""),
            "refined": options.refine, "network_ms": round(record.network_ms, 3),
        }
        if options.refine:
            pose.update(refine_ms=round(record.refine_ms, 3),
                        search_ms=round(record.search_ms, 3), search_score=record.iou_before,
                        iou_after=record.iou_after, mask_source=record.mask_source,
                        mask=str(mask_paths[k]) if mask_paths is not None
                        else record.mask_source)
        if padding is not None:
            pose["padded_to"] = [padding.padded_width, padding.padded_height]
        if record.warning:
            pose["warning"] = record.warning
        atomic_write_json(Path(f"{stem}.pose.json"), pose)
        record.files.append(Path(f"{stem}.pose.json"))
        overlay_path = Path(f"{stem}.overlay.png")
        with atomic_path(overlay_path) as tmp:
            overlay = overlay_image(picture, layers, outline)
            if padding is not None:
                overlay = padding.crop(overlay)
            Image.fromarray(overlay, "RGB").save(tmp, format="PNG")
        record.files.append(overlay_path)
        records.append(record)
    return records


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
    image_camera = None
    if camera is not None:
        try:
            image_camera = Camera.load(camera)
        except FileNotFoundError:
            raise FileNotFoundError(f"camera {camera}: no such file") from None
        except ValueError as error:
            message = str(error)
            raise ValueError(message if str(camera) in message else f"camera {camera}: "
                             f"{message}") from None
    predictor = load_model(checkpoint)  # predict_files folds it once the inputs are checked
    return predict_files(images, out_dir, predictor, options, image_camera, masks, progress)
