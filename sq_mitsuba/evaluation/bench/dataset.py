"""``sq-mitsuba bench dataset``: images per second of the dataset renderer.

One generated spacecraft, 256 x 256 pixels, 64 samples per pixel: path-traced image, mask
(with depth), 8-bit PNGs and label, each written atomically, as ``dataset render`` does.
Target: >= 2 images/s on 2 CPU cores.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from sq_mitsuba.evaluation.bench import BenchOptions, Report, Timing, time_callable

RESOLUTION, SPP = 256, 64


def run(options: BenchOptions) -> Report:
    from sq_mitsuba.data.library import generate_model
    from sq_mitsuba.data.spacecraft import catalogue
    from sq_mitsuba.data.spe3r import RenderOptions, load_model, render_image
    from sq_mitsuba.render.backend import mitsuba
    from sq_mitsuba.render.space import SpaceScene

    mi = mitsuba()
    report = Report("dataset", options=options)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        entry = catalogue(1, 0)[0]
        generate_model(entry, root / "models", points=2000)
        vertices, faces, tags = load_model(root / "models" / entry.name)
        render_options = RenderOptions(resolution=RESOLUTION, spp=SPP)
        scene = SpaceScene(vertices, faces, tags, render_options.dataset_camera(),
                           render_options.scene, spp=SPP)
        counter = iter(range(10**6))
        out = root / "out" / entry.name

        def one_image() -> None:
            # The per-image step of `dataset render`: frame, render, PNGs, label.
            render_image(scene, vertices, render_options, entry.name, next(counter), out)

        samples = time_callable(one_image, options.repeats, options.warmup)
    timing = Timing(f"image + mask + label, {RESOLUTION} px, {SPP} spp", samples,
                    target_s=0.5, note=f"model {entry.name} ({entry.archetype}), "
                                       f"{len(faces)} faces, {mi.variant()}")
    report.timings.append(timing)
    rates = sorted(1.0 / s for s in samples)
    report.notes.append(f"throughput: median {1.0 / timing.median:.2f} images/s "
                        f"(IQR of per-image rate {rates[len(rates) // 4]:.2f} - "
                        f"{rates[(3 * len(rates)) // 4]:.2f}); target >= 2 images/s")
    return report
