"""Benchmark suites behind ``sq-mitsuba bench SUITE``.

Each module ``sq_mitsuba/bench/<suite>.py`` defines ``run(options) -> Report``. A report is a
table of timings (median and spread over repeats) plus free-form notes; ``--write`` stores it
in ``eval/BENCHMARKS.md`` between markers for its suite, with the machine and date, replacing
the previous figures of that suite only.
"""

from __future__ import annotations

import datetime as _dt
import importlib
import os
import pkgutil
import platform
import re
import statistics
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from sq_mitsuba.config import in_range, validate
from sq_mitsuba.io import atomic_write_text

BENCHMARKS_MD = Path(__file__).resolve().parents[2] / "eval" / "BENCHMARKS.md"


@dataclass(frozen=True)
class BenchOptions:
    """Options common to all suites."""

    repeats: int = in_range(1, 100_000, default=20)
    "Timed runs of each operation."
    warmup: int = in_range(0, 10_000, default=3)
    "Untimed runs before the timed ones."
    threads: int = in_range(1, 1024, default=2)
    "Torch CPU threads (2: the reference machine)."
    device: str = "cpu"
    "Torch device of the suites that use one (cpu, cuda or cuda:N)."
    batch: int | None = in_range(1, 4096, default=None)
    """bench train: also measure the network alone against the full step at this batch
    size (besides 32)."""
    step_only: bool = False
    """bench train: only the network-alone against full-step figures (always so on a GPU);
    recorded as the section train-step."""

    def __post_init__(self) -> None:
        if not _DEVICE.fullmatch(self.device):
            raise ValueError(f"device: {self.device!r} is not a device; expected cpu, cuda or "
                             "cuda:N")


#: The device names of :class:`BenchOptions`: the CPU, or a CUDA GPU (by index).
_DEVICE = re.compile(r"cpu|cuda(:[0-9]+)?")


def check_device(name: str) -> None:
    """Raise ``ValueError`` (``device: ...``, one line) unless ``name`` is a device this torch
    can use: ``cpu``, or ``cuda`` / ``cuda:N`` with CUDA available and GPU ``N`` present.
    Checked before any suite runs, so that a bad ``--device`` is bad input, not a failure
    halfway through."""
    if not _DEVICE.fullmatch(name):
        raise ValueError(f"device: {name!r} is not a device; expected cpu, cuda or cuda:N")
    if name == "cpu":
        return
    import torch

    if torch.version.cuda is None:
        raise ValueError(f"device: {name!r}: CUDA is not available in this torch build "
                         f"(torch {torch.__version__}); use cpu")
    if not torch.cuda.is_available():
        raise ValueError(f"device: {name!r}: CUDA is not available (torch "
                         f"{torch.__version__} sees no CUDA GPU); use cpu")
    index = int(name.partition(":")[2] or 0)
    if index >= torch.cuda.device_count():
        raise ValueError(f"device: {name!r}: no such GPU; torch sees "
                         f"{torch.cuda.device_count()} (cuda:0 to "
                         f"cuda:{torch.cuda.device_count() - 1})")


@dataclass
class Timing:
    """Wall times of one measured operation, in seconds."""

    name: str
    samples: list[float]
    target_s: float | None = None
    note: str = ""

    @property
    def median(self) -> float:
        return statistics.median(self.samples)

    @property
    def spread(self) -> tuple[float, float]:
        """Interquartile range (25th, 75th percentile)."""
        if len(self.samples) < 2:
            return (self.samples[0], self.samples[0])
        q = statistics.quantiles(self.samples, n=4, method="inclusive")
        return (q[0], q[2])

    def row(self) -> str:
        lo, hi = self.spread
        target = "" if self.target_s is None else f"<= {self.target_s * 1e3:.0f} ms"
        met = "" if self.target_s is None else ("yes" if self.median <= self.target_s else "NO")
        return (f"| {self.name} | {self.median * 1e3:.2f} | {lo * 1e3:.2f} - {hi * 1e3:.2f} "
                f"| {len(self.samples)} | {target} | {met} | {self.note} |")


#: The command of a section whose name is no suite (the heading reads as a command to run).
_COMMANDS = {"train-step": "train --step-only"}


@dataclass
class Report:
    """What a suite measured."""

    suite: str
    timings: list[Timing] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    options: BenchOptions = field(default_factory=BenchOptions)

    def to_markdown(self) -> str:
        lines = [
            f"### `sq-mitsuba bench {_COMMANDS.get(self.suite, self.suite)}`",
            "",
            f"Measured {_dt.date.today().isoformat()} on {machine_description(self.options)}.",
            "",
            "| operation | median ms | IQR ms | runs | target | met | note |",
            "|---|---:|---:|---:|---|---|---|",
            *(t.row() for t in self.timings),
        ]
        if self.notes:
            lines += ["", *(f"- {n}" for n in self.notes)]
        return "\n".join(lines) + "\n"


def time_callable(fn: Callable[[], object], repeats: int, warmup: int,
                  sync: Callable[[], None] | None = None) -> list[float]:
    """Wall-clock seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls.

    The calls are counted on a transient progress bar (stderr; a line every 30 s into a log):
    a suite runs for minutes, and its table comes at the end."""
    from sq_mitsuba.progress import progress_bar

    samples: list[float] = []
    with progress_bar(total=warmup + repeats, desc=f"bench {_suite_running or ''}".rstrip(),
                      unit="run", leave=False) as bar:
        for _ in range(warmup):
            fn()
            bar.update()
        if sync:
            sync()
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            if sync:
                sync()
            samples.append(time.perf_counter() - start)
            bar.update()
    return samples


def bench_dataset(root: Path, count: int, seed: int, images: int, resolution: int,
                 render_seed: int, suite: str, pass_frames: int = 1) -> Path:
    """A small SPE3R-layout dataset of the first ``count`` models of the archetype catalogue of
    ``seed``, every model in the test split, rendered into ``root/data`` (models in
    ``root/models``); ``suite`` names the bench in the error when a render fails."""
    from sq_mitsuba.data.library import generate_model
    from sq_mitsuba.data.spacecraft import catalogue
    from sq_mitsuba.data.spe3r import RenderOptions, render_dataset

    models = root / "models"
    entries = catalogue(count, seed)
    for entry in entries:
        generate_model(entry, models, points=20_000)
    (models / "splits.csv").write_text("".join(f"{e.name},test\n" for e in entries))
    data = root / "data"
    summary = render_dataset(models, data, RenderOptions(
        images_per_model=images, resolution=resolution, spp=16, seed=render_seed,
        pass_frames=pass_frames), progress=False)
    if summary.failures:
        raise RuntimeError(f"bench {suite}: rendering failed: {summary.failures}")
    return data


def load_average() -> float:
    """The 1-minute load average (NaN where the platform has none): benchmark records carry it
    because other processes on the cores inflate the timings."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def cpu_model() -> str:
    """The CPU's model name and its widest vector instructions (``AMD EPYC, AVX2``): machines
    of one model name differ in them, and so do Dr.Jit's LLVM kernels (16 lanes with AVX-512,
    8 with AVX2) and oneDNN's convolutions."""
    model, flags = "", set()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                if line.startswith("model name") and not model:
                    model = line.split(":", 1)[1].strip()
                elif line.startswith("flags") and not flags:
                    flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    model = model or platform.processor() or "unknown CPU"
    vector = next((name for flag, name in (("avx512f", "AVX-512"), ("avx2", "AVX2"),
                                            ("avx", "AVX")) if flag in flags), None)
    return f"{model}, {vector}" if vector else model


def machine_description(options: BenchOptions) -> str:
    import torch

    if options.device.startswith("cuda") and torch.cuda.is_available():
        where = f"GPU {torch.cuda.get_device_name()}"
    else:
        cores = os.cpu_count() or options.threads
        where = f"{cpu_model()}, " + (f"{options.threads} of {cores} cores used"
                                      if options.threads <= cores else
                                      f"{options.threads} threads on {cores} cores")
    return (f"{platform.node() or 'host'} ({where}; {platform.system()} {platform.machine()}, "
            f"Python {platform.python_version()}, torch {torch.__version__})")


#: The suite :func:`run_suites` is running (named on :func:`time_callable`'s progress bar).
_suite_running: str | None = None


#: Modules of this package that are not timing suites: ``curves`` trains configs for equal
#: wall time (``sq-mitsuba bench curves``, :func:`sq_mitsuba.bench.curves.run_curves`), so
#: ``bench all`` leaves it out.
NOT_TIMING_SUITES = frozenset({"curves"})


def available_suites() -> list[str]:
    """The timing suites, each a module of this package with a ``run(options)``."""
    return sorted(m.name for m in pkgutil.iter_modules(__path__)
                  if not m.name.startswith("_") and m.name not in NOT_TIMING_SUITES)


def run_suite(name: str, options: BenchOptions) -> Report:
    if name not in available_suites():
        raise ValueError(f"unknown benchmark suite {name!r}; choose from {available_suites()}")
    check_device(options.device)
    module = importlib.import_module(f"{__name__}.{name}")
    return module.run(options)


def run_suites(names: Sequence[str], options: BenchOptions, write: bool = False,
               path: Path = BENCHMARKS_MD) -> Iterator[Report]:
    """Run the suites ``names`` (``["all"]``: every suite) with ``options.threads`` torch
    threads, yielding each report when done; ``write`` records each in ``path`` first."""
    import torch

    validate(options)
    names = available_suites() if list(names) == ["all"] else list(names)
    for name in names:
        if name not in available_suites():
            raise ValueError(f"unknown benchmark suite {name!r}; choose from "
                             f"{available_suites()}")
    check_device(options.device)
    torch.set_num_threads(options.threads)
    global _suite_running
    for name in names:
        _suite_running = name
        try:
            report = run_suite(name, options)
        finally:
            _suite_running = None
        if write:
            write_report(report, path)
        yield report


def write_report(report: Report, path: Path = BENCHMARKS_MD) -> None:
    """Replace this suite's section of ``path`` (or append it), atomically."""
    write_section(report.suite, report.to_markdown(), path)


def write_section(name: str, markdown: str, path: Path = BENCHMARKS_MD) -> None:
    """Replace the section ``name`` of ``path`` (between ``<!-- bench:NAME:start/end -->``)
    by ``markdown``, or append it, atomically."""
    start, end = f"<!-- bench:{name}:start -->", f"<!-- bench:{name}:end -->"
    block = f"{start}\n{markdown}{end}"
    text = path.read_text(encoding="utf-8") if path.exists() else (
        "# Benchmarks\n\nLatest figures of `sq-mitsuba bench SUITE --write`, one section per "
        "suite, each with the machine and date it was measured on. Median and interquartile "
        "range over repeated runs after warm-up.\n")
    pattern = re.compile(re.escape(start) + r".*?" + re.escape(end), re.DOTALL)
    if pattern.search(text):
        text = pattern.sub(lambda _: block, text)
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    atomic_write_text(path, text)
