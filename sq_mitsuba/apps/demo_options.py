"""The settings and the result of ``sq-mitsuba demo`` (:func:`sq_mitsuba.apps.demo.run_demo`):
its sizes (``--size``), the small training run of ``--train``, and what a run did.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from sq_mitsuba.apps.demo_files import METHOD_LABELS, PAGE_METRICS
from sq_mitsuba.config import in_range
from sq_mitsuba.inference.search import SEARCH_REFINEMENT

__all__ = ["DEMO_CATALOGUE_SEED", "SIZES", "DemoOptions", "DemoResult", "DemoSize",
           "DemoTraining", "describe_sizes"]

#: Catalogue seed of the demo's spacecraft: any seed but the training catalogue's (0).
DEMO_CATALOGUE_SEED = 20261122

@dataclass(frozen=True)
class DemoSize:
    """How much a demo renders and refines."""

    models: int = in_range(1, 64, default=5)
    "Spacecraft generated."
    images: int = in_range(1, 64, default=3)
    "Images rendered per spacecraft."
    resolution: int = in_range(32, 1024, default=256)
    "Side in pixels of the rendered images (and of the page's pictures)."
    spp: int = in_range(1, 1024, default=64)
    "Path-tracing samples per pixel of the images."
    refine_steps: int = in_range(1, 1000, default=SEARCH_REFINEMENT.steps)
    """Test-time refinement steps at most (about 40 ms per image and step on 2 cores); the
    default is the shipped path's (``predict --refine``), so the page shows what it gives."""
    pass_frames: int = in_range(0, 64, default=8)
    """Frames of the pass of the first spacecraft (one assembly and every pose from them;
    :mod:`sq_mitsuba.apps.demo_pass`); 0 or 1: no pass."""


#: The sizes of ``--size``: tiny for CI (seconds), small, default (minutes on 2 cores).
SIZES: dict[str, DemoSize] = {
    "tiny": DemoSize(models=2, images=1, resolution=128, spp=16, refine_steps=8,
                     pass_frames=3),
    "small": DemoSize(models=3, images=2, resolution=256, spp=32, refine_steps=30,
                      pass_frames=4),
    "default": DemoSize(),
}


@dataclass(frozen=True)
class DemoTraining:
    """The small training run of ``sq-mitsuba demo --train`` (from scratch, on the CPU)."""

    models: int = in_range(2, 10_000, default=24)
    "Spacecraft of the training library (the first of the training catalogue)."
    catalogue_seed: int = in_range(0, 2**32 - 1, default=0)
    "Catalogue seed of the training library (0: the shipped model's catalogue)."
    images_per_model: int = in_range(1, 10_000, default=24)
    "Images rendered per training spacecraft."
    resolution: int = in_range(32, 1024, default=64)
    "Side in pixels of the training images."
    spp: int = in_range(1, 1024, default=16)
    "Path-tracing samples per pixel of the training images."
    config: str = "tiny.toml"
    "Training config, a file of the repository's train/configs/ (not installed with the package)."
    overrides: tuple[str, ...] = ("network.image_size=64", "optim.epochs=6",
                                  "optim.batch_size=8", "checkpoint_every=0",
                                  "validation.images=16", "validation.batch_size=16")
    "Changes to that config (dotted key=value, as `sq-mitsuba train --set`)."


@dataclass(frozen=True)
class DemoOptions:
    """Settings of ``sq-mitsuba demo``."""

    size: Literal["tiny", "small", "default"] = "default"
    """Preset: tiny (2 spacecraft x 1 image at 128 px, 8 refinement steps, a pass of 3
    frames; for CI), small (3 x 2 at 256 px, 30 steps, a pass of 4) or default (5 x 3 at 256
    px, the shipped path's 25 steps, a pass of 8)."""
    seed: int = in_range(0, 2**32 - 1, default=DEMO_CATALOGUE_SEED)
    """Catalogue seed of the demo's spacecraft (and seed of their images); the shipped model
    trained on catalogue seed 0, so these are spacecraft it never saw."""
    points: int = in_range(1000, 2_000_000, default=20_000)
    "Points per sample set of each spacecraft (surface, uniform, near): Chamfer and 3D IoU."
    surface_points: int = in_range(1, 1_000_000, default=2500)
    "Ground-truth surface points per image for the Chamfer distances."
    batch_size: int = in_range(1, 1024, default=8)
    "Images per network and refinement batch."
    level: int = in_range(0, 5, default=3)
    "Icosphere level of the primitive meshes for points, silhouettes, pictures and GLB files."
    silhouette_spp: int = in_range(1, 1024, default=32)
    "Samples per pixel of the silhouettes scored by the 2D IoU."
    overlay_spp: int = in_range(1, 1024, default=16)
    "Samples per pixel of the silhouettes drawn on the page."
    baseline_images: int = in_range(1, 1_000_000, default=256)
    "Images whose mean prediction and mean pose make the baseline, when it is computed here."
    train: bool = False
    """First train a small model from scratch (library, dataset, training; measured 2.6-5.8
    minutes in all on 2 cores) and demonstrate it instead of the shipped one."""
    training: DemoTraining = field(default_factory=DemoTraining)
    "The training run of --train."

    @property
    def preset(self) -> DemoSize:
        """The :class:`DemoSize` of :attr:`size`."""
        return SIZES[self.size]


@dataclass
class DemoResult:
    """What :func:`~sq_mitsuba.apps.demo.run_demo` did.

    Attributes:
        out_dir: the output folder; page: its index.html; markdown: index.md.
        images, models: images and spacecraft shown.
        summary: {method: {metric: (mean, std, median)}} over the images.
        checkpoint: the model demonstrated; baseline: where the baseline came from.
        wall_seconds: the whole run, checks to the last rename.
        passed: the pass of the first spacecraft (:class:`~sq_mitsuba.apps.demo_pass.
        PassRecord`), None without one.
    """

    out_dir: Path
    page: Path
    markdown: Path
    images: int
    models: int
    summary: dict[str, dict[str, tuple[float, float, float]]]
    checkpoint: str
    baseline: str
    wall_seconds: float
    stages: dict[str, float] = field(default_factory=dict)
    passed: Any = None

    def describe(self) -> str:
        """A few lines: the main numbers, then where to look and the wall time."""
        lines = []
        for method, label in METHOD_LABELS.items():
            stats = self.summary.get(method)
            if stats is not None:
                lines.append(f"  {label}: " + ", ".join(
                    f"{PAGE_METRICS[m]} {stats[m][0]:.3f}" for m in
                    ("chamfer_l1_paper", "iou_2d", "rotation_error_folded_deg")))
        if self.passed is not None:
            lines.append(self.passed.describe())
        lines.append(f"demo of {self.images} image(s) of {self.models} unseen spacecraft done "
                     f"in {self.wall_seconds:.0f} s (wall); open {self.page}")
        return "\n".join(lines)


def describe_sizes() -> str:
    """One line per preset, for the command's help."""
    return "\n".join(f"  {name}: {s.models} spacecraft x {s.images} image(s) at {s.resolution} "
                     f"px, {s.refine_steps} refinement steps, "
                     + (f"a pass of {s.pass_frames} frames" if s.pass_frames >= 2 else "no pass")
                     for name, s in SIZES.items())
