"""The settings of ``sq-mitsuba dataset render`` (:class:`RenderOptions`), what one run did
(:class:`RenderSummary`), and the checks that refuse, before any work, a render this machine
cannot do (:func:`check_render_resources`). :mod:`.writer` renders with them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from sq_mitsuba.config import in_range, validate
from sq_mitsuba.data.spe3r.layout import DatasetError
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.io import nearest_existing
from sq_mitsuba.machine import available_memory, memory_text, too_much_memory
from sq_mitsuba.render.backend import MAX_SAMPLES_PER_RENDER
from sq_mitsuba.render.scene_config import SceneConfig

__all__ = ["MAX_RESOLUTION", "MAX_SHARDS", "SEED_LIMIT", "RenderOptions", "RenderSummary",
           "check_disk_room", "check_render_resources", "estimate_render_memory",
           "parse_shard", "texture_memory"]

SEED_LIMIT = 2**32
"""Dataset seeds are 0 <= seed < SEED_LIMIT."""
MAX_RESOLUTION = 65536
"""Largest ``resolution`` accepted at all; :func:`check_render_resources` bounds it further by
the memory of the machine."""
MAX_SHARDS = 100_000
_SHARD = re.compile(r"(\d+)/(\d+)")

#: Memory of one rendering process: measured peaks (Mitsuba LLVM on 2 threads) 0.50 GiB at
#: 256 px, 0.54 at 512, 0.58 at 1024 and 0.78 GiB at 2048 px, independent of spp (Mitsuba
#: renders in one recorded kernel); the estimate leaves about 1.5 times that.
BASE_MEMORY_BYTES = 3 * 2**28  # 0.75 GiB
BYTES_PER_PIXEL = 160
EXR_BYTES_PER_PIXEL = 48
#: Memory of the scene's textures beyond the default scene's (which the base figure holds), a
#: texel: measured 2026-12-02, the star map 16384 texels wide peaked at 9.4 GB for 64 px
#: images (66 bytes a texel: Mitsuba keeps the map and its sampling warp), the Earth's albedo
#: map of 8192 x 4096 took 1.85 GB to make (55 bytes a texel, then Mitsuba's copy).
TEXTURE_BYTES_PER_TEXEL = 70
#: Fewest bytes a rendered image and its mask take on disk, a pixel: a 256 px image of a
#: target against black space and its mask took 0.12 B/px as PNG (8 held-out frames,
#: 2026-12-02); a fifth of that is a bound no dataset comes under.
MIN_DISK_BYTES_PER_PIXEL = 0.025


def parse_shard(text: str) -> tuple[int, int]:
    """``"I/N"`` as (I, N), with 0 <= I < N <= :data:`MAX_SHARDS`."""
    match = _SHARD.fullmatch(text.strip()) if isinstance(text, str) else None
    if match is None or not int(match[1]) < int(match[2]) <= MAX_SHARDS:
        raise ValueError(f"shard: expected I/N with 0 <= I < N <= {MAX_SHARDS} (e.g. 0/4 for "
                         f"the first of 4), got {text!r}")
    return int(match[1]), int(match[2])


@dataclass(frozen=True)
class RenderOptions:
    """How ``sq-mitsuba dataset render`` renders a dataset (checked when built)."""

    images_per_model: int = in_range(1, 10_000_000, default=1000)
    """Images per model. Raising it on an existing dataset adds exactly the images an
    uninterrupted larger run writes; lowering it is an error."""
    seed: int = in_range(0, SEED_LIMIT - 1, default=0)
    """Dataset seed, 0 <= seed < 2^32; with the model name and image index it seeds each
    image."""
    resolution: int = in_range(8, MAX_RESOLUTION, default=256)
    """Image width in pixels (square, or the camera's aspect ratio). Checked before any work
    against this machine's memory (estimate: 0.75 GiB + 160 bytes per pixel per worker)."""
    spp: int = in_range(1, 1 << 20, default=64)
    """Path-tracing samples per pixel."""
    exr: bool = False
    """Also write linear radiance, depth and coverage (OpenEXR)."""
    camera: Path | None = None
    """SPEED-style camera.json to render with, rescaled to resolution pixels wide (none: the
    SPEED camera's 35.45 deg field of view, square)."""
    pass_frames: int = in_range(1, 100_000, default=1)
    """1: every image of a model is drawn on its own (pose, sun, Earth). N > 1: a model's images
    are passes of N frames, in order: the target tumbling about a random axis at 3-15 deg per
    frame while the camera approaches, the sun and the Earth fixed in the camera frame
    (sample_pass_frame); the labels record "pass" and "frame_in_pass"."""
    workers: int = in_range(1, 256, default=1)
    """Processes rendering models in parallel on this machine (they share its cores)."""
    shard: str = "0/1"
    """This run's share of the work, I/N with 0 <= I < N: block I of N of all (model, image)
    pairs. N shards into one folder, in any order, equal one unsharded run."""
    overwrite: bool = False
    """Start clean: first delete the output folder's dataset (dataset.json, camera.json,
    splits.csv, failures.json, preview.png, .failures/, the model folders its dataset.json
    lists and the tool's temporary files; nothing else). Only a folder whose dataset.json is
    this tool's manifest is cleared; a non-empty folder without one is refused."""
    scene: SceneConfig = field(default_factory=SceneConfig.load)
    """The space scene (default: scenes/space.json)."""

    def __post_init__(self) -> None:
        validate(self)
        _, count = parse_shard(self.shard)
        if self.overwrite and count > 1:
            raise ValueError("overwrite: not with shard N > 1 (each shard would delete the "
                             "others' images); delete the old dataset first, or render into "
                             "a new folder")

    @property
    def shard_count(self) -> int:
        return parse_shard(self.shard)[1]

    def dataset_camera(self) -> Camera:
        """The camera images are rendered with: ``camera`` (loaded, rescaled to ``resolution``
        pixels wide) or the default one. Errors name the file."""
        if self.camera is None:
            return Camera.default(self.resolution)
        path = Path(self.camera)
        try:
            camera = Camera.load(path)
        except FileNotFoundError:
            raise DatasetError(f"camera: {path}: no such file") from None
        except (OSError, ValueError) as error:
            message = str(error)
            raise DatasetError(message if str(path) in message else f"{path}: {message}") \
                from None
        if camera.width != self.resolution:
            camera = camera.rescaled(self.resolution)
        if abs(camera.fx - camera.fy) > 1e-6 * camera.fx:
            raise DatasetError(f"{path}: the dataset renderer needs square pixels (fx == fy), "
                               f"got fx {camera.fx:g}, fy {camera.fy:g}")
        return camera


@dataclass
class RenderSummary:
    """What one :func:`render_dataset` call did."""

    rendered: int = 0
    skipped: int = 0
    models_done: list[str] = field(default_factory=list)
    failures: dict[str, str] = field(default_factory=dict)
    #: Every model of the dataset is settled and splits.csv, failures.json and the manifest
    #: are final (False: other shards, or a rerun after a kill, still have work to do).
    complete: bool = False
    shard: str = "0/1"


def estimate_render_memory(width: int, height: int, exr: bool = False,
                           scene: SceneConfig | None = None) -> int:
    """Bytes one rendering process needs for ``width`` x ``height`` images (an estimate with
    about 1.5x margin over measured peaks, see :data:`BASE_MEMORY_BYTES`), with ``scene``'s
    textures where larger than the default scene's (:func:`texture_memory`)."""
    per_pixel = BYTES_PER_PIXEL + (EXR_BYTES_PER_PIXEL if exr else 0)
    textures = 0 if scene is None else texture_memory(scene)
    return BASE_MEMORY_BYTES + per_pixel * width * height + textures


def _texels(scene: SceneConfig) -> int:
    """Texels of the star map (width x width / 2) and of the Earth's albedo map."""
    texture = scene.earth.texture
    return scene.stars.envmap_width ** 2 // 2 + texture.width * texture.height


def texture_memory(scene: SceneConfig) -> int:
    """Bytes a rendering process needs for ``scene``'s textures beyond the default scene's
    (:data:`TEXTURE_BYTES_PER_TEXEL`); 0 for textures no larger."""
    return TEXTURE_BYTES_PER_TEXEL * max(0, _texels(scene) - _texels(SceneConfig()))


def check_disk_room(out_dir: Path, camera: Camera, images: int) -> None:
    """Refuse a render of ``images`` images whose files could not fit on ``out_dir``'s disk
    even at the fewest bytes an image takes (:data:`MIN_DISK_BYTES_PER_PIXEL`): a run of ten
    million 2048 px images started on a disk of 53 GB without a word."""
    import shutil

    folder = nearest_existing(Path(out_dir).absolute())  # the disk it will be made on
    try:
        free = shutil.disk_usage(folder).free
    except OSError:  # no figure: nothing to refuse on
        return
    need = int(images * camera.width * camera.height * MIN_DISK_BYTES_PER_PIXEL)
    if need > free:
        raise DatasetError(f"images_per_model: {images:,} images of {camera.width} x "
                           f"{camera.height} px need at least {memory_text(need)} on disk, "
                           f"more than the {memory_text(free)} free under {folder}; lower "
                           "--images-per-model or --resolution, or render into another disk")


def check_render_resources(camera: Camera, options: RenderOptions,
                           memory: int | None = None) -> None:
    """Refuse a render this machine cannot do, before any work: more samples per image than
    Mitsuba takes in one render, or more memory (estimated, times ``workers``) than
    ``memory`` (default :func:`available_memory`). ``DatasetError`` naming the resolution."""
    from sq_mitsuba.render.space import mask_samples

    width, height = camera.width, camera.height
    memory = available_memory() if memory is None else memory
    textures = texture_memory(options.scene)
    need = estimate_render_memory(width, height, options.exr) + textures
    if memory is not None and need * options.workers > memory:
        if textures > need / 2:  # the scene's maps, not the images, are what is too large
            raise DatasetError(too_much_memory(
                f"the scene's textures (stars.envmap_width {options.scene.stars.envmap_width}, "
                f"earth.texture {options.scene.earth.texture.width} x "
                f"{options.scene.earth.texture.height}: {memory_text(textures)} a process, "
                f"{options.workers} rendering process(es))", need * options.workers, memory,
                "lower --set stars.envmap_width, earth.texture.width and .height, or "
                "--workers"))
        raise DatasetError(too_much_memory(
            f"resolution: {width} x {height} px ({options.workers} rendering process(es), "
            f"each {memory_text(BASE_MEMORY_BYTES)} + "
            f"{BYTES_PER_PIXEL + (EXR_BYTES_PER_PIXEL if options.exr else 0)} bytes a pixel"
            f"{f' + {memory_text(textures)} of scene textures' if textures else ''})",
            need * options.workers, memory, "lower --resolution or --workers"))
    mask_spp = mask_samples(options.scene.mask.spp, camera)
    samples = width * height * max(options.spp, mask_spp)
    if samples > MAX_SAMPLES_PER_RENDER:
        raise DatasetError(f"resolution: {width} x {height} px at {options.spp} spp (masks: "
                           f"{mask_spp}) is {samples:,} samples per render, more than "
                           f"Mitsuba's 2^32; lower --resolution or --spp")
