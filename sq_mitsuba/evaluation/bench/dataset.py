"""``sq-mitsuba bench dataset``: images per second of the dataset renderer, at 128 and 256 px.

One generated spacecraft, 64 samples per pixel: the per-image step of ``dataset render``
(frame, path-traced image, mask pass, 8-bit PNGs and label, each written atomically), timed
image by image after warm-up at each resolution, so the median and interquartile range are
those of the per-image time; throughput is its inverse. Building the scene (once per model
and process) is left out. Target at 256 px: >= 2 images/s on 2 CPU cores.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from sq_mitsuba.evaluation.bench import BenchOptions, Report, Timing, time_callable

RESOLUTIONS = (128, 256)
SPP = 64
#: Per-image time targets in seconds (None: recorded, no target).
TARGETS = {128: None, 256: 0.5}


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
            scene = SpaceScene(vertices, faces, tags, camera, render_options.scene, spp=SPP)
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
            rates = sorted(1.0 / s for s in samples)
            target = TARGETS[resolution]
            report.notes.append(
                f"throughput at {resolution} px: median {1.0 / timing.median:.2f} images/s "
                f"(IQR of per-image rate {rates[len(rates) // 4]:.2f} - "
                f"{rates[(3 * len(rates)) // 4]:.2f})"
                + (f"; target >= {1.0 / target:.0f} images/s" if target else ""))
    return report
