"""``sq-mitsuba bench models``: seconds per model for generation and processing."""

from __future__ import annotations

import shutil
import statistics
import tempfile
import time
from pathlib import Path

from sq_mitsuba.bench import BenchOptions, Report, Timing, time_callable

TARGET_END_TO_END_S = 10.0


def _union_seconds(entries: list) -> list[float]:
    """Seconds of the recipe and exact union of each catalogue entry, one call each."""
    from sq_mitsuba.data.spacecraft import generate_spacecraft

    queue = iter(entries)

    def build() -> None:
        entry = next(queue)
        generate_spacecraft(entry.seed, entry.archetype).union()
    return time_callable(build, repeats=len(entries), warmup=0)


def run(options: BenchOptions) -> Report:
    """Time generation (recipe + exact union), processing (normalise + 3 x 100k labelled
    points) and the whole write per model, over the archetypes of the default catalogue; and
    generation alone for the compositional families and the free-form part graphs."""
    from sq_mitsuba.data.library import generate_model
    from sq_mitsuba.data.mesh_processing import process_mesh, sample_model
    from sq_mitsuba.data.spacecraft import (
        catalogue,
        composed_catalogue,
        generate_spacecraft,
        graph_catalogue,
    )

    entries = catalogue(max(14, min(options.repeats, 64)), seed=0)
    generate_s, process_s, sample_s, total_s = [], [], [], []
    warm = catalogue(1, seed=1)[0]
    root = Path(tempfile.mkdtemp(prefix="sq-bench-models-"))
    try:
        for _ in range(max(1, options.warmup)):  # Mitsuba start-up and kernel compilation
            generate_model(warm, root)
        for entry in entries:
            start = time.perf_counter()
            raw = generate_spacecraft(entry.seed, entry.archetype).union()
            t1 = time.perf_counter()
            model = process_mesh(raw, method="solid")
            t2 = time.perf_counter()
            sample_model(model.mesh, seed=entry.seed)
            t3 = time.perf_counter()
            generate_s.append(t1 - start)
            process_s.append(t2 - t1)
            sample_s.append(t3 - t2)
        queue = iter(entries)
        total_s = time_callable(lambda: generate_model(next(queue), root),
                                repeats=len(entries), warmup=0)
        composed_s = _union_seconds(composed_catalogue(len(entries), 0))
        graph_s = _union_seconds(graph_catalogue(len(entries), 0))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    n = len(entries)
    return Report("models", [
        Timing("generate (recipe + exact union)", generate_s),
        Timing("generate, compositional families", composed_s),
        Timing("generate, free-form part graphs", graph_s),
        Timing("process (checks, normalise)", process_s),
        Timing("sample 3 x 100k points + occupancy labels", sample_s),
        Timing("end to end per model (incl. writing files)", total_s,
               target_s=TARGET_END_TO_END_S),
    ], notes=[f"{n} models of the default catalogue (seed 0), every archetype at least once; "
              "procedural models take the exact boolean route.",
              f"64 models at the median end-to-end time: about "
              f"{64 * statistics.median(total_s):.0f} s."], options=options)
