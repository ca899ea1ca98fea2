"""``sq-mitsuba bench dataset``: images per second of the dataset renderer, at 128 and 256 px.

One generated spacecraft, 64 samples per pixel: the per-image step of ``dataset render``
(frame, path-traced image, mask pass, 8-bit PNGs and label, each written atomically), timed
image by image after warm-up at each resolution, so the median and interquartile range are
those of the per-image time; throughput is its inverse. Building the scene (once per model
and process) is left out of it and timed on its own. Target at 256 px: >= 2 images/s on 2
CPU cores. At each resolution the mask pass alone is also timed with the renderer's lean
``target_coverage`` integrator and with Mitsuba's ``path`` integrator that it replaced, in
the same run.

Then the visibility statistics of the default scene: :data:`VISIBILITY_MODELS` models x
:data:`VISIBILITY_IMAGES` images at 128 px (the training resolution), the share of images whose
target mean grey level is below 10/255 (target <= 3 %) and the phase-angle histogram.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

from sq_mitsuba.bench import BenchOptions, Report, Timing, time_callable

RESOLUTIONS = (128, 256)
SPP = 64
#: Per-image time targets in seconds (None: recorded, no target).
TARGETS = {128: None, 256: 0.5}
VISIBILITY_MODELS, VISIBILITY_IMAGES, VISIBILITY_SPP = 8, 25, 16
DARK = 10 / 255


def visibility_notes(root: Path) -> list[str]:
    """Dark-image share and phase histogram of the default scene (see the module docstring)."""
    import numpy as np

    from sq_mitsuba.data.frames import sample_frame
    from sq_mitsuba.data.library import generate_model
    from sq_mitsuba.data.spacecraft import catalogue
    from sq_mitsuba.data.spe3r import RenderOptions, load_model
    from sq_mitsuba.render.space import SpaceScene

    options = RenderOptions(resolution=128, spp=VISIBILITY_SPP)
    camera = options.dataset_camera()
    means, phases = [], []
    for entry in catalogue(VISIBILITY_MODELS, 0):
        generate_model(entry, root / "visibility", points=2000)
        vertices, faces, tags = load_model(root / "visibility" / entry.name)
        scene = SpaceScene(vertices, faces, tags, camera, options.scene, spp=VISIBILITY_SPP)
        for index in range(VISIBILITY_IMAGES):
            frame = sample_frame(vertices, camera, options.scene, 0, entry.name, index)
            means.append(scene.render(frame).visibility()[0])
            phases.append(frame.phase_angle_deg)
    means = np.asarray(means)
    histogram, _ = np.histogram(phases, bins=np.arange(0, 181, 15))
    return [f"visibility, default scene, {len(means)} images ({VISIBILITY_MODELS} models x "
            f"{VISIBILITY_IMAGES}, 128 px, {VISIBILITY_SPP} spp): "
            f"{100 * float((means < DARK).mean()):.1f} % with a target mean below 10/255 "
            f"(target <= 3 %); median target mean {255 * float(np.median(means)):.1f}/255",
            "phase angles (15 deg bins from 0 to 180): " +
            ", ".join(str(int(c)) for c in histogram)]


def run(options: BenchOptions) -> Report:
    from sq_mitsuba.data.library import generate_model
    from sq_mitsuba.data.spacecraft import catalogue
    from sq_mitsuba.data.spe3r import RenderOptions, load_model, render_image
    from sq_mitsuba.render.backend import mitsuba
    from sq_mitsuba.render.space import SpaceScene, mask_samples

    mi = mitsuba()
    report = Report("dataset", options=options)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        entry = catalogue(1, 0)[0]
        generate_model(entry, root / "models", points=2000)
        vertices, faces, tags = load_model(root / "models" / entry.name)
        for resolution in RESOLUTIONS:
            render_options = RenderOptions(resolution=resolution, spp=SPP)
            camera = render_options.dataset_camera()

            def build_scene(camera=camera, render_options=render_options) -> Any:
                return SpaceScene(vertices, faces, tags, camera, render_options.scene, spp=SPP)

            report.timings.append(Timing(
                f"scene setup (once a model), {resolution} px", time_callable(
                    build_scene, options.repeats, options.warmup),
                note="both scenes loaded and one frame's parameters set, no render"))
            scene = build_scene()
            counter = iter(range(10**6))
            out = root / f"out{resolution}" / entry.name

            def one_image(scene=scene, render_options=render_options, out=out,
                          counter=counter) -> None:
                # The per-image step of `dataset render`: frame, render, PNGs, label.
                render_image(scene, vertices, render_options, entry.name, next(counter), out)

            samples = time_callable(one_image, options.repeats, options.warmup)
            timing = Timing(
                f"image + mask + label, {resolution} px, {SPP} spp", samples,
                target_s=TARGETS[resolution],
                note=f"model {entry.name} ({entry.archetype}), {len(faces)} faces, mask "
                     f"{mask_samples(render_options.scene.mask.spp, camera)} spp, "
                     f"{mi.variant()}")
            report.timings.append(timing)
            low, high = Timing("rate", [1.0 / s for s in samples]).spread
            target = TARGETS[resolution]
            report.notes.append(
                f"throughput at {resolution} px: median {1.0 / timing.median:.2f} images/s "
                f"(IQR of per-image rate {low:.2f} - {high:.2f})"
                + (f"; target >= {1.0 / target:.0f} images/s" if target else ""))
            report.notes.append(mask_pass_ratio(report, scene, vertices, resolution, options))
        report.notes += visibility_notes(root)
    return report


def mask_pass_ratio(report: Report, scene: Any, vertices: Any, resolution: int,
                    options: BenchOptions) -> str:
    """Time the mask pass alone with the lean ``target_coverage`` integrator (the renderer's)
    and with Mitsuba's ``path`` at ``max_depth = 1`` (what it replaces, same images), adding
    both timings to ``report``; returns the note with their ratio."""
    from sq_mitsuba.data.frames import sample_frame

    frame = sample_frame(vertices, scene.camera, scene.config, 0, "bench", 0)
    path = scene.mi.load_dict({"type": "path", "max_depth": 1})
    medians = {}
    for name, integrator in (("target_coverage", None), ("path, max_depth 1", path)):
        def mask_pass(integrator: Any = integrator) -> None:
            scene.mask_pass(frame, integrator)

        timing = Timing(f"mask pass alone, {resolution} px, {name}",
                        time_callable(mask_pass, options.repeats, options.warmup))
        report.timings.append(timing)
        medians[name] = timing.median
    return (f"mask pass at {resolution} px: target_coverage / path = "
            f"{medians['target_coverage'] / medians['path, max_depth 1']:.2f} (same run; "
            "< 1: the lean integrator is faster)")
