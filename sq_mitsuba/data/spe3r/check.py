"""Check a dataset: its bookkeeping, every file, and masks against the mesh at each label's pose.

What :func:`check_dataset` reports as a problem (each one line naming the file):

- bookkeeping: a missing or unreadable ``camera.json`` / ``splits.csv``; where there is a
  manifest (``dataset.json``, our datasets), a camera that differs from it, a model count or
  ``labels.json`` that differs from what it records, rendering not finished (reported also
  when the stopped render left no ``splits.csv``), a failed model still in ``splits.csv``;
- model points, as training and evaluation read them: a ``samples.npz`` that cannot be read,
  lacks one of the arrays they need or holds NaN or infinite points; a missing one in our
  datasets (the render copies it), or, without one, a missing mesh;
- stray files anywhere in the folder: temporary files of atomic writes (``*.tmp*``, left by a
  kill), empty (0-byte) files, ``.progress`` folders of models in ``splits.csv`` (unfinished);
- labels, per entry: not an object, a missing or bad file name, a quaternion or translation
  of the wrong length, NaN or infinite, a quaternion not of norm 1, a target behind the camera;
- files: every image and mask is decoded completely (a truncated or corrupt one fails), of the
  camera's size, masks binary (ours); images or masks that no label names; EXR files where the
  manifest says there are some;
- masks against the mesh: for ``per_model`` images per model, the mesh posed by the label is
  rendered by :class:`~sq_mitsuba.render.silhouette.renderer.SilhouetteRenderer` (another
  renderer than the one that wrote the masks) and compared with the stored mask.

Convention (the IoU threshold across resolutions): a mask pixel is ``coverage >= 0.5`` of a
Monte Carlo estimate, so a pixel that an edge crosses near its middle can legitimately go
either way, and there are more such pixels, relative to the target's area, the smaller the
image. The comparison therefore leaves out the pixels whose reference coverage c is within
``tol`` of 0.5, where ``tol = 4 sigma`` of the difference of the two estimates (``sigma^2 =
0.25 / spp_check + 0.25 / spp_mask``, the largest binomial variance; the mask's spp is read
from the manifest's scene). Every other pixel has one right answer, so a correct dataset has
an IoU of 1 over them at any resolution (measured on fresh datasets of two generated spacecraft
at 64, 128 and 256 px: 1.0000 for every image, where the plain IoU over all pixels went down
to 0.986 at 64 px, below the 0.99 that a plain threshold would need), while a mask shifted by
one pixel disagrees along much of its outline (edge-tolerant IoU 0.72-0.91 at 64 px,
0.85-0.95 at 128 px, 0.93-0.98 at 256 px). ``min_iou`` (default 0.99) applies to the
edge-tolerant IoU; the plain IoU is reported beside it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sq_mitsuba.config import in_range, validate
from sq_mitsuba.data.spe3r.layout import (
    EXR,
    FAILURE_MARKS,
    FAILURES,
    IMAGES,
    MANIFEST,
    MASKS,
    MODELS,
    PROGRESS,
    SAMPLES_FILE,
    DatasetError,
    check_model_points,
    find_image,
    is_model_library,
    label_problem,
    load_model,
    read_image,
    read_labels,
    read_manifest,
    read_splits,
)
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import quaternion_to_matrix
from sq_mitsuba.io import read_json
from sq_mitsuba.render.backend import MAX_SAMPLES_PER_RENDER

#: Standard deviations of the coverage estimates' difference inside the edge tolerance.
EDGE_SIGMAS = 4.0
#: Stray files listed one by one before the rest are counted.
MAX_LISTED = 20


@dataclass(frozen=True)
class CheckOptions:
    """Options of ``sq-mitsuba dataset check`` (checked when built)."""

    per_model: int = in_range(0, 10_000_000, default=20)
    """Images per model whose mask is compared with the mesh rendered at the label pose (0:
    all); every image and mask is decoded either way."""
    min_iou: float = in_range(0, 1, default=0.99)
    """Least edge-tolerant IoU of a stored mask with the re-rendered silhouette (pixels an
    edge leaves ambiguous are left out, see the check module)."""
    spp: int = in_range(1, 65536, default=256)
    """Samples per pixel of the re-rendered silhouettes."""

    def __post_init__(self) -> None:
        validate(self)


@dataclass
class CheckReport:
    """What :func:`check_dataset` found."""

    models: int = 0
    images: int = 0
    decoded: int = 0
    #: Edge-tolerant IoU (see the module docstring) of each compared mask.
    iou: list[float] = field(default_factory=list)
    #: Plain IoU over all pixels of each compared mask.
    plain_iou: list[float] = field(default_factory=list)
    tolerance: float | None = None
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        lines = [f"{self.models} models, {self.images} labelled images, {self.decoded} images "
                 f"and masks decoded"]
        if self.iou:
            values, plain = np.asarray(self.iou), np.asarray(self.plain_iou)
            lines.append(f"label/mask IoU over {len(values)} images: min {values.min():.4f}, "
                         f"mean {values.mean():.4f} (edge pixels within {self.tolerance:.2f} "
                         f"of half coverage left out); plain IoU min {plain.min():.4f}, mean "
                         f"{plain.mean():.4f}")
        lines += [f"note: {n}" for n in self.notes]
        lines += [f"problem: {p}" for p in self.problems] or ["no problems found"]
        return "\n".join(lines)


def edge_tolerance(spp_check: int, spp_mask: int) -> float:
    """``tol`` of the module docstring: coverage within it of 0.5 is ambiguous."""
    sigma = math.sqrt(0.25 / spp_check + 0.25 / spp_mask)
    return min(0.49, EDGE_SIGMAS * sigma)


def check_spp_resolves(spp_check: int) -> None:
    """Refuse a check's ``spp_check`` too low for its own estimate to be trusted at the edge
    tolerance's widest (0.49): at 4 samples a pixel half covered reads as empty one time in
    16, and a correct mask's edges are flagged. One line naming the least spp that does."""
    room = (0.49 / EDGE_SIGMAS) ** 2  # the check's own variance, 0.25 / spp at most
    if 0.25 / spp_check > room:
        raise ValueError(f"spp {spp_check}: too few samples to tell a mask's edges from "
                         f"errors; give --spp {math.ceil(0.25 / room)} or more (default 256)")


def compare_masks(coverage: np.ndarray, mask: np.ndarray, tolerance: float
                  ) -> tuple[float, float]:
    """(edge-tolerant IoU, plain IoU) of a stored ``mask`` (H, W) bool against a reference
    ``coverage`` (H, W) in [0, 1]; the first leaves out pixels with |coverage - 0.5| <
    ``tolerance``. An empty union counts as IoU 1."""
    rendered = coverage >= 0.5
    decisive = np.abs(coverage - 0.5) >= tolerance
    ious = []
    for keep in (decisive, np.ones_like(decisive)):
        a, b = rendered & keep, mask & keep
        union = np.logical_or(a, b).sum()
        ious.append(float(np.logical_and(a, b).sum() / union) if union else 1.0)
    return ious[0], ious[1]


def _chosen(count: int, per_model: int) -> set[int]:
    """``per_model`` evenly spaced indices of ``count`` (all where 0 or more than count)."""
    if per_model == 0 or per_model >= count:
        return set(range(count))
    return {int(i) for i in np.linspace(0, count - 1, per_model).round()}


def _stray_files(root: Path, unfinished_ok: set[str]) -> list[str]:
    """Temporary files, empty files and ``.progress`` folders (except of ``unfinished_ok``
    models) anywhere under ``root``, as relative paths with the reason."""
    strays = []
    for path in sorted(root.rglob("*")):
        relative = path.relative_to(root)
        if path.is_dir():
            if path.name == PROGRESS and relative.parts[0] not in unfinished_ok:
                strays.append(f"{relative}/: unfinished model (a render was stopped; run it "
                              f"again to finish)")
            continue
        if ".tmp" in path.name or path.name.startswith(".write-test"):
            strays.append(f"{relative}: stray temporary file (left by a killed write)")
        elif path.is_file() and path.stat().st_size == 0:
            strays.append(f"{relative}: empty file")
    return strays


def _check_bookkeeping(root: Path, camera: Camera, splits: dict[str, str],
                       manifest: dict[str, Any] | None, report: CheckReport) -> set[str]:
    """Manifest, failures.json and splits.csv agree; returns the failed models."""
    failed: set[str] = set()
    if (root / FAILURES).is_file():
        try:
            failures = read_json(root / FAILURES)
            failed = set(failures) if isinstance(failures, dict) else set()
        except ValueError as error:
            report.problems.append(str(error))
        for model in sorted(failed):
            reason = failures[model]
            report.notes.append(f"{model}: failed, left out of splits.csv ({reason})")
            if model in splits:
                report.problems.append(f"splits.csv: {model} is listed but failed "
                                       f"({FAILURES})")
    if (root / FAILURE_MARKS).is_dir():
        failed |= {p.name for p in (root / FAILURE_MARKS).iterdir() if p.is_dir()}
    if manifest is None:
        report.notes.append("no dataset.json: settings and image counts unknown (the SPE3R "
                            "release, or another tool); files and labels checked only")
        return failed
    if manifest["settings"].get("camera") != camera.to_speed_dict() and \
            Camera.from_speed_dict(manifest["settings"]["camera"]) != camera:
        report.problems.append("camera.json: differs from the camera in dataset.json")
    for model, entry in sorted(manifest["models"].items()):
        if model in failed:
            continue
        if model not in splits:
            report.problems.append(f"splits.csv: {model} of dataset.json is missing (and not "
                                   f"in {FAILURES})")
        elif isinstance(entry, dict) and entry.get("split") not in (None, splits[model]):
            report.problems.append(f"splits.csv: {model} is {splits[model]}, dataset.json "
                                   f"says {entry.get('split')}")
    for model in sorted(set(splits) - set(manifest["models"])):
        report.problems.append(f"splits.csv: {model} is not in dataset.json")
    return failed


def _check_files(root: Path, model: str, labels: list[Any], camera: Camera,
                 ours: bool, exr: bool, chosen: set[int], report: CheckReport
                 ) -> dict[int, np.ndarray]:
    """Decode every image and mask of a model's labels; returns the chosen masks that passed."""
    masks: dict[int, np.ndarray] = {}
    named: dict[str, set[str]] = {IMAGES: set(), MASKS: set()}
    for index, label in enumerate(labels):
        problem = label_problem(label)
        filename = label.get("filename") if isinstance(label, dict) else None
        where = f"{model}/labels.json: entry {index}" + (
            f" ({filename})" if isinstance(filename, str) else "")
        if problem is not None:
            report.problems.append(f"{where}: {problem}")
            if isinstance(filename, str):  # named by an entry, if a bad one: not "no label"
                for folder in (IMAGES, MASKS):
                    named[folder].add(find_image(root, model, folder, filename).name)
            continue
        arrays = {}
        for folder in (IMAGES, MASKS):
            path = find_image(root, model, folder, filename)
            named[folder].add(path.name)
            try:
                image = read_image(path, verify=path.suffix.lower() == ".png")
            except DatasetError as error:
                report.problems.append(f"{model}/{folder}/{path.name}: "
                                       f"{str(error).split(': ', 1)[-1]}")
                continue
            array = np.asarray(image if image.mode == "L" else image.convert("L"))
            if array.shape != (camera.height, camera.width):
                report.problems.append(f"{model}/{folder}/{path.name}: {array.shape[1]} x "
                                       f"{array.shape[0]} px, camera.json says {camera.width} "
                                       f"x {camera.height}")
                continue
            report.decoded += 1
            arrays[folder] = array
        if MASKS in arrays and ours and not np.isin(arrays[MASKS], (0, 255)).all():
            report.problems.append(f"{model}/{MASKS}/{filename}: not binary (values other "
                                   f"than 0 and 255)")
        elif MASKS in arrays and index in chosen:
            masks[index] = arrays[MASKS] >= 128
        if exr:
            path = root / model / EXR / f"{Path(filename).stem}.exr"
            try:
                import OpenEXR

                # The size from the header first: a small file of zeros can decode to
                # gigabytes, and an image of another size than the camera's is wrong anyway.
                size = _exr_size_problem(path, camera)
                if size is not None:
                    report.problems.append(f"{model}/{EXR}/{path.name}: {size}")
                    continue
                with OpenEXR.File(str(path)) as exr_file:
                    channels = exr_file.channels()
                    bad = sum(int((~np.isfinite(np.asarray(channel.pixels, np.float64))).sum())
                              for channel in channels.values())
            except Exception as error:  # OpenEXR raises several kinds on a bad file
                report.problems.append(f"{model}/{EXR}/{path.name}: cannot read ({error})")
            else:
                if bad:  # a radiance image is finite everywhere (the renderer's are)
                    report.problems.append(f"{model}/{EXR}/{path.name}: {bad} value(s) NaN "
                                           "or infinite")
    for folder, names in named.items():
        directory = root / model / folder
        present = {p.name for p in directory.iterdir() if not p.name.startswith(".")} \
            if directory.is_dir() else set()
        for extra in sorted(present - names)[:MAX_LISTED]:
            report.problems.append(f"{model}/{folder}/{extra}: no label names it")
    return masks


def _exr_size_problem(path: Path, camera: Camera) -> str | None:
    """What is wrong with the size of the EXR ``path`` (None: every part is the camera's
    size), read from its header alone (``dataWindow``): no pixel is decoded."""
    import OpenEXR

    with OpenEXR.File(str(path), header_only=True) as exr_file:
        windows = [part.header["dataWindow"] for part in exr_file.parts]
    for low, high in windows:
        width, height = int(high[0]) - int(low[0]) + 1, int(high[1]) - int(low[1]) + 1
        if (width, height) != (camera.width, camera.height):
            return (f"{width} x {height} px, camera.json says {camera.width} x "
                    f"{camera.height} (not decoded)")
    return None


def _check_points(model_dir: Path, ours: bool, report: CheckReport) -> None:
    """The model's points, as training and evaluation read them: ``samples.npz`` with every
    array they need, finite (ours always have one: the render copies it), else the mesh."""
    samples = model_dir / MODELS / SAMPLES_FILE
    if ours and not samples.is_file():
        report.problems.append(f"{model_dir.name}/{MODELS}/{SAMPLES_FILE}: missing (the "
                               f"render copies it from the model library)")
        return
    try:
        check_model_points(model_dir)
    except DatasetError as error:
        report.problems.append(str(error).replace(f"{model_dir.parent}/", "", 1))


def check_dataset_root(root: Path) -> None:
    """Refuse, before any work, a ``root`` that is no dataset at all (bad input, not a dataset
    with problems): one line. ``dataset check`` and ``dataset preview`` both start here.

    Raises:
        FileNotFoundError: ``root`` does not exist.
        DatasetError: ``root`` is a file, a model library, or a folder with neither
            ``camera.json`` nor ``dataset.json`` (every dataset has one: SPE3R's release
            the camera, a render the manifest from before its first image).
    """
    if not root.exists():
        raise FileNotFoundError(f"{root}: no such folder")
    if not root.is_dir():
        raise DatasetError(f"{root}: not a folder (expected a dataset folder)")
    if is_model_library(root):
        raise DatasetError(f"{root}: a model library, not a dataset: render one with "
                           f"sq-mitsuba dataset render --models {root} --out DATA (or check a "
                           "library's models with sq-mitsuba models preview)")
    if not (root / "camera.json").exists() and not (root / MANIFEST).exists():
        raise DatasetError(f"{root}: not a dataset (no camera.json and no {MANIFEST}); render "
                           "one with sq-mitsuba dataset render --models LIBRARY --out DATA")


def check_dataset(root: str | Path, options: CheckOptions | None = None, *,
                  progress: bool = True, **fields: Any) -> CheckReport:
    """Validate a dataset (see the module docstring); problems are collected, not raised.

    ``options`` (default :class:`CheckOptions`) or its fields as keywords (``per_model=None``
    means all, as 0 does). Raises, before any work, ``ValueError`` for bad options,
    ``FileNotFoundError`` for a ``root`` that does not exist and :class:`DatasetError` for one
    that is no dataset (:func:`check_dataset_root`: bad input, not a dataset with
    problems). Reads only: the dataset is left as it was.
    """
    from sq_mitsuba.progress import progress_bar
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    if fields.get("per_model", 0) is None:
        fields["per_model"] = 0
    options = CheckOptions(**{**_fields_of(options), **fields})
    check_spp_resolves(options.spp)
    root = Path(root)
    report = CheckReport()
    check_dataset_root(root)
    try:
        manifest = read_manifest(root)
    except (OSError, ValueError) as error:
        report.problems.append(str(error))
        return report
    unfinished = manifest is not None and manifest.get("state") != "complete"
    if unfinished:
        # A stopped render leaves no splits.csv (the last model to finish writes it): say why.
        report.problems.append(f"dataset.json: state {manifest.get('state')!r}: rendering has "
                               f"not finished (run the render command again)")
    partial = False
    try:
        camera = Camera.load(root / "camera.json")
        splits = read_splits(root / "splits.csv")
    except FileNotFoundError as error:
        partial = unfinished and Path(str(error.filename)).name == "splits.csv"
        why = " (written when rendering finishes)" if partial else ""
        report.problems.append(f"{error.filename}: missing{why}")
        if not partial:
            return report
        # The models finished so far are checked all the same (camera.json was read).
        splits = {model: str(entry.get("split")) for model, entry in manifest["models"].items()
                  if (root / model / "labels.json").is_file()}
    except (OSError, ValueError) as error:
        report.problems.append(str(error))
        return report
    if not partial:  # an unfinished dataset's bookkeeping is not yet whole
        failed = _check_bookkeeping(root, camera, splits, manifest, report)
        strays = _stray_files(root, failed)
        report.problems += strays[:MAX_LISTED]
        if len(strays) > MAX_LISTED:
            report.problems.append(f"... and {len(strays) - MAX_LISTED} more stray files")
    ours = manifest is not None
    exr = bool(ours and manifest["settings"].get("exr"))
    spp_mask = options.spp
    if ours:
        from sq_mitsuba.render.space import mask_samples

        try:
            spp_mask = mask_samples(int(manifest["scene"]["mask"]["spp"]), camera)
        except (KeyError, TypeError, ValueError):
            pass
    report.tolerance = edge_tolerance(options.spp, spp_mask)
    most = MAX_SAMPLES_PER_RENDER // (camera.width * camera.height)
    if options.spp > most:  # before any model is read: a default that fails says what fits
        raise ValueError(f"--spp {options.spp}: a render of {camera.width} x {camera.height} "
                         f"px takes at most {most} samples a pixel (Mitsuba's 2^32 samples "
                         f"a render); give --spp {most} or less")
    renderer = None
    for model in progress_bar(sorted(splits), disable=not progress, desc="check"):
        report.models += 1
        try:
            labels = read_labels(root / model / "labels.json")
        except DatasetError as error:
            report.problems.append(str(error))
            continue
        report.images += len(labels)
        if ours:
            entry = manifest["models"].get(model)
            expected = manifest["images_per_model"]
            if len(labels) != expected:
                report.problems.append(f"{model}/labels.json: {len(labels)} labels, "
                                       f"dataset.json says {expected} per model")
            elif isinstance(entry, dict) and entry.get("labels_sha256") is not None:
                import hashlib

                digest = hashlib.sha256((root / model / "labels.json").read_bytes())
                if digest.hexdigest() != entry["labels_sha256"]:
                    report.problems.append(f"{model}/labels.json: changed since dataset.json "
                                           f"was written (sha256 differs)")
        _check_points(root / model, ours, report)
        chosen = _chosen(len(labels), options.per_model)
        masks = _check_files(root, model, labels, camera, ours, exr, chosen, report)
        if not masks:
            continue
        try:
            vertices, faces, _ = load_model(root / model)
        except DatasetError as error:  # named as the points' check names it, and once
            problem = str(error).replace(f"{root}/", "", 1)
            if problem not in report.problems:
                report.problems.append(problem)
            continue
        if renderer is None:
            renderer = SilhouetteRenderer(camera, spp=options.spp)
        vertices_t = torch.tensor(vertices, dtype=torch.float32)
        faces_t = torch.tensor(faces, dtype=torch.int64)
        for index, mask in sorted(masks.items()):
            label = labels[index]
            rotation = quaternion_to_matrix(torch.tensor(label["q_vbs2tango_true"],
                                                         dtype=torch.float32))
            translation = torch.tensor(label["r_Vo2To_vbs_true"], dtype=torch.float32)
            with torch.no_grad():
                posed = vertices_t @ rotation.T + translation
                coverage = renderer.render(posed[None], faces_t)[0].numpy()
            iou, plain = compare_masks(coverage, mask, report.tolerance)
            report.iou.append(iou)
            report.plain_iou.append(plain)
            if iou < options.min_iou:
                report.problems.append(f"{model}/{label['filename']}: label/mask IoU "
                                       f"{iou:.4f} < {options.min_iou} (plain IoU "
                                       f"{plain:.4f})")
    return report


def _fields_of(options: CheckOptions | None) -> dict[str, Any]:
    if options is None:
        return {}
    return {name: getattr(options, name) for name in ("per_model", "min_iou", "spp")}
