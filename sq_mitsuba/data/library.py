"""A model library on disk in the SPE3R layout: generate or import, process, write.

Each model lands in ``<root>/<model>/models/`` (see
:func:`sq_mitsuba.data.mesh_processing.write_model`). Two files at the root keep account:

* ``splits.csv``: ``model,train`` / ``model,test`` rows without a header (CSV: a name with a
  comma or quote is quoted), one per generated model, sorted by name.
  :func:`generate_library` merges into it: rows of models it does not generate stay, a model
  generated again keeps one row. A model's split is a function of its name and the catalogue
  seed (:func:`sq_mitsuba.data.spacecraft.generator.catalogue_split`).
* ``failures.json``: ``{model: reason}`` of the generated models whose last attempt failed;
  a later successful attempt removes the entry, and the file goes when empty. A failed
  model gets no row in ``splits.csv`` (a row from an earlier success stays, because
  that earlier model's files are still there).

Both files are rewritten atomically after every model, so an interrupted batch leaves them
consistent with the model folders written so far; with ``workers``, a few models built ahead
of the bookkeeping may be on disk without a row (``dataset render`` refuses such a library,
naming them, until the batch is run again).

One batch at a time per library: ``generate`` and ``import`` hold the library's lock
(:func:`sq_mitsuba.outputs.output_lock`) from before they read ``splits.csv`` to their end,
so a second batch started into the same library stops at once with one line, and two
batches never merge their bookkeeping over each other (the lock dies with its process,
``kill -9`` included).

Convention: a model is never replaced by another spacecraft of the same name. Catalogue
names are ``sc<index>_<archetype>``, so the catalogues of two seeds share names for other
spacecraft: ``generate`` refuses, before building anything, a batch in which a model of the
library has the name of an entry but another archetype or model seed (from its
``model_card.json``; a model without a readable card, or an imported one, counts as
another), naming the folder.

A rerun resumes: a model already complete in the library (its folder holds every file
:func:`~sq_mitsuba.data.mesh_processing.write_model` writes, and its card is this entry's:
same archetype, model seed, catalogue seed and split, and the same ``points`` per sample set)
is kept, not built again, and counted in the summary's ``written`` and ``kept``; any other
model of the batch is built (``GenerateOptions.rebuild`` builds every one again).

A run killed outright (``kill -9``, a lost machine) can leave what an atomic write had not
finished: ``<model>/.models.XXXXXXXX/`` folders (a model being written), a
``<model>/.models.old.<pid>/`` (a model being replaced, cut between its two renames) and
temporary files of ``splits.csv`` / ``failures.json``. Readers never see them (they read
``<model>/models/`` only), and the next ``generate`` or ``import`` into the library removes
them (an old model with no new one beside it is put back) before it does anything else, under
the library's lock, so no live run's files are among them.

Imported models are named after their file (:func:`model_name_for`). Convention: the name is
the file's stem, or ``<stem>_2``, ``<stem>_3``, ... when the stem is already an entry of the
output folder, was given to an earlier file of the same batch or is a root file's name
(``splits.csv``, ...); nothing is overwritten. Each imported model gets its row in
``splits.csv`` (``ImportOptions.split``: test by default, since imported spacecraft are most
often the unseen ones to evaluate on).
"""

from __future__ import annotations

import os
import re
import shutil
import unicodedata
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from sq_mitsuba.config import bounds, in_range, validate
from sq_mitsuba.data.mesh_io import SAMPLES_FILE
from sq_mitsuba.data.mesh_processing import (
    MESH_SUFFIXES,
    MODEL_FILES,
    MODEL_FOLDER,
    check_import_memory,
    file_face_count,
    load_mesh,
    model_card,
    process_mesh,
    recover_cut_write,
    sample_model,
    write_model,
)
from sq_mitsuba.data.solids import (
    FUSION_RESOLUTION,
    MIN_FUSION_RESOLUTION,
    MeshError,
    connected_pieces,
    fusion_memory_bytes,
    max_fusion_resolution,
)
from sq_mitsuba.data.spacecraft import THIN_FRACTION, CatalogueEntry, generate_spacecraft
from sq_mitsuba.data.spacecraft.generator import (
    DEFAULT_CATALOGUE_COUNT,
    DEFAULT_CATALOGUE_SEED,
    MAX_CATALOGUE_COUNT,
    MAX_CATALOGUE_SEED,
    catalogue,
)
from sq_mitsuba.io import atomic_write_json, check_output_folder, read_json
from sq_mitsuba.machine import available_memory, too_much_memory
from sq_mitsuba.outputs import holds_lock, output_lock, remove_stray_temporaries
from sq_mitsuba.processes import worker_pool

SPLITS_FILE = "splits.csv"
FAILURES_FILE = "failures.json"
DEFAULT_POINTS = 100_000
MAX_POINTS = 2_000_000
"""Most points per sample set: three sets of 2,000,000 points are about 110 MB per model
(54 bytes per point across the sets, before compression)."""
#: The temporary folder of a model being written (``tempfile.mkdtemp(prefix=".models.")`` in
#: write_model: eight random characters) and a dead write's folder renamed aside to be
#: deleted (:func:`_remove_dead_folder`); the old model a write sets aside while it replaces
#: it is :func:`~sq_mitsuba.data.mesh_processing.recover_cut_write`'s.
DEAD_WRITE = re.compile(r"\.models\.[a-z0-9_]{8}")
BEING_REMOVED = re.compile(r"\.models\.removing\..+")
#: Memory of one ``generate --workers`` process (a spawned interpreter building a model):
#: measured 2026-12-02, 24 workers made a process tree of 27 processes and 3.9 GB, about
#: 160 MB each; rounded up for larger models.
GENERATE_WORKER_BYTES = 200_000_000


# --------------------------------------------------------------------------------- options

@dataclass(frozen=True)
class GenerateOptions:
    """What ``sq-mitsuba models generate`` builds: the first ``count`` models of a catalogue."""

    out: Path = Path("data/spacecraft")
    "Library root: models go to OUT/<model>/models/, splits to OUT/splits.csv."
    count: int = in_range(1, MAX_CATALOGUE_COUNT, default=DEFAULT_CATALOGUE_COUNT)
    "Number of models: the first COUNT of the catalogue (64 is the paper's 57 train / 7 test)."
    seed: int = in_range(0, MAX_CATALOGUE_SEED, default=DEFAULT_CATALOGUE_SEED)
    "Catalogue seed, 0 <= SEED < 2**32; it fixes every model's name, shape and split."
    points: int = in_range(1, MAX_POINTS, default=DEFAULT_POINTS)
    "Points per sample set: surface, uniform, near."
    generator: Literal["archetypes", "composed", "graph"] = "archetypes"
    """The 14 archetype recipes (the shipped model's catalogue), the compositional families
    (data/spacecraft/families.py; models named cs<i:05d>_<family>), or free-form part graphs
    (data/spacecraft/part_graph.py; models named pg<i:05d>_part_graph)."""
    families: Literal["all", "training", "held-out"] = "all"
    """With the composed generator: every family, the training families only, or the held-out
    families only (never trained on: the leave-family-out test)."""
    workers: int = in_range(1, 256, default=1)
    """Processes building models in parallel (each model is independent; the library's
    files are written by the main process, in catalogue order, as each model is done); at
    most what fits in this machine's memory, about 200 MB each."""
    rebuild: bool = False
    """Build every model again; by default a rerun keeps a model already complete in OUT
    (this catalogue's spacecraft, written with the same --points)."""

    def __post_init__(self) -> None:
        if isinstance(self.workers, int) and isinstance(self.count, int):  # else validate's
            check_generate_workers(self.workers, self.count)


def check_generate_workers(workers: int, count: int) -> None:
    """``ValueError`` naming ``workers`` when its processes (no more than the ``count`` models
    they share) would need more memory than this machine has (about
    :data:`GENERATE_WORKER_BYTES` each), before any is started: 256 of them were about 41 GB.
    One worker builds in this process: nothing to check."""
    processes = min(workers, count)
    memory = available_memory()
    need = processes * GENERATE_WORKER_BYTES
    if processes > 1 and memory is not None and need > memory:
        raise ValueError(too_much_memory(
            f"workers: {workers} ({processes} processes)", need, memory,
            f"expected a value in [1, {max(1, memory // GENERATE_WORKER_BYTES)}]"))


def check_fusion_resolution(resolution: int) -> None:
    """``ValueError`` naming ``resolution`` when depth fusion at it would not fit in memory.

    The bound is :func:`~sq_mitsuba.data.solids.fusion_memory_bytes` against
    :func:`~sq_mitsuba.machine.available_memory`, so an absurd value fails at once instead of
    being killed for memory after minutes.
    """
    if resolution < MIN_FUSION_RESOLUTION:
        raise ValueError(f"resolution: expected >= {MIN_FUSION_RESOLUTION}, got {resolution}")
    memory = available_memory()
    need = fusion_memory_bytes(resolution)
    if memory is not None and need > memory:
        raise ValueError(too_much_memory(
            f"resolution: {resolution} (depth fusion)", need, memory,
            f"expected a value in [{MIN_FUSION_RESOLUTION}, {max_fusion_resolution(memory)}]"))


@dataclass(frozen=True)
class ImportOptions:
    """How ``sq-mitsuba models import`` processes mesh files."""

    out: Path = Path("data/imported")
    "Library root: models go to OUT/<model>/models/."
    method: Literal["auto", "boolean", "fusion"] = "auto"
    "Watertight route: auto (exact union when every piece is closed, else depth-map fusion)."
    align: Literal["axes", "obb"] = "axes"
    "Alignment: axes (permute the file's axes) or obb (minimum-volume box axes)."
    resolution: int = field(default=FUSION_RESOLUTION, metadata=bounds(MIN_FUSION_RESOLUTION))
    """Fusion voxels along the longest side; at most what fits in this machine's memory
    (depth fusion needs up to about 2 GiB plus 128 bytes per voxel)."""
    points: int = in_range(1, MAX_POINTS, default=DEFAULT_POINTS)
    "Points per sample set: surface, uniform, near."
    split: Literal["train", "test"] = "test"
    """The imported models' row in OUT/splits.csv: test (spacecraft a model has not seen, to
    evaluate on) or train (to train on them)."""

    def __post_init__(self) -> None:
        # Checked for every method: with "auto" fusion may run, and an absurd value is an
        # error whatever the route.
        check_fusion_resolution(self.resolution)


@dataclass
class LibrarySummary:
    """What a batch did: models written, failures, and the name each input got."""

    out: Path
    """The library root."""
    written: list[str] = field(default_factory=list)
    """Names of the models written, in batch order (those kept included)."""
    kept: list[str] = field(default_factory=list)
    """Generate: the models of ``written`` already complete in the library, not built again."""
    failures: dict[str, str] = field(default_factory=dict)
    """``{model: reason}`` of this batch's failed models."""
    names: list[tuple[str, str]] = field(default_factory=list)
    """Imports: ``(input path, model name)`` of every input in order, failed ones included."""

    @property
    def ok(self) -> bool:
        return not self.failures

    def text(self) -> str:
        """The report: each written import's name, then how many models were written where
        (a failed import is listed by :meth:`failure_text` instead)."""
        lines = [f"{path} -> {name}" for path, name in self.names if name in self.written]
        if self.kept:
            lines.append(f"{len(self.written)} model(s) in {self.out}: "
                         f"{len(self.written) - len(self.kept)} built, {len(self.kept)} "
                         "already there")
        else:
            lines.append(f"{len(self.written)} model(s) written to {self.out}")
        return "\n".join(lines)

    def failure_text(self) -> str:
        """The failures, one per line under a count ("" when none)."""
        if not self.failures:
            return ""
        lines = [f"{len(self.failures)} failed:"]
        lines += [f"  {name}: {reason}" for name, reason in self.failures.items()]
        return "\n".join(lines)


# ------------------------------------------------------------------------- bookkeeping

def read_library_splits(root: Path) -> dict[str, str]:
    """``<root>/splits.csv`` as ``{model: split}`` (empty when absent)."""
    from sq_mitsuba.data.spe3r.layout import read_splits

    path = root / SPLITS_FILE
    return read_splits(path) if path.is_file() else {}


def read_failures(root: Path) -> dict[str, str]:
    """``<root>/failures.json`` as ``{model: reason}`` (empty when absent)."""
    path = root / FAILURES_FILE
    if not path.is_file():
        return {}
    data = read_json(path)
    if not isinstance(data, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
        raise ValueError(f"{path}: expected a JSON object of model name -> reason")
    return data


def _write_failures(root: Path, failures: dict[str, str]) -> None:
    path = root / FAILURES_FILE
    if failures:
        atomic_write_json(path, dict(sorted(failures.items())))
    elif path.exists():
        path.unlink()


def _write_splits(root: Path, splits: dict[str, str]) -> None:
    from sq_mitsuba.data.spe3r.layout import write_splits

    write_splits(root, sorted(splits.items()))


def _check_root(root: Path) -> None:
    """A folder that is, or can be created as, a writable folder, and not a rendered dataset
    (whose model copies and splits.csv a batch would silently rewrite, as ``dataset render``
    refuses the library as its output): checked before any work."""
    from sq_mitsuba.data.spe3r.layout import MANIFEST

    check_output_folder(root)
    held = [name for name in (MANIFEST, "camera.json") if (root / name).exists()]
    if held:
        raise ValueError(f"{root}: the output folder is a dataset (it holds {held[0]}), not a "
                         "model library; write the models into another folder")


def _remove_dead_folder(path: Path) -> None:
    """Delete a dead write's folder: renamed aside first, so that a worker a killed run left
    behind, still writing into it, fails its own rename instead of publishing a model whose
    files are half deleted; then deleted."""
    aside = path if BEING_REMOVED.fullmatch(path.name) else \
        path.with_name(f".models.removing.{os.getpid()}.{path.name}")
    try:
        os.rename(path, aside)
    except FileNotFoundError:  # gone meanwhile (that worker published or removed it)
        return
    shutil.rmtree(aside, ignore_errors=True)


def _remove_dead_writes_of(folder: Path) -> list[Path]:
    """:func:`remove_dead_writes` in one model folder."""
    dead = [p for p in sorted(folder.iterdir()) if p.is_dir() and not p.is_symlink() and (
        DEAD_WRITE.fullmatch(p.name) or BEING_REMOVED.fullmatch(p.name))]
    for path in dead:
        _remove_dead_folder(path)
    # Cut between write_model's two renames: the old model comes back (or goes, beside one).
    found = dead + recover_cut_write(folder)
    if found:
        try:
            folder.rmdir()  # a first write of this model, killed: nothing else was there
        except OSError:  # not empty: a model, or anything else, stays
            pass
    return found


def remove_dead_writes(root: Path) -> list[Path]:
    """Remove what killed writes left in the library ``root`` (see the module docstring):
    ``<model>/.models.XXXXXXXX/`` folders, a ``<model>/.models.old.<pid>/`` beside its model
    (one with no model beside it is put back as ``models/``), model folders left empty by
    them, and temporary files of ``splits.csv`` and ``failures.json``. Returns what was
    removed or put back.

    Only while this run holds the library's lock (:func:`output_lock`): then no live run
    writes there (nothing is removed when that lock ran unlocked).
    """
    if not root.is_dir() or not holds_lock(root):
        return []
    done = remove_stray_temporaries(root, of=SPLITS_FILE)
    done += remove_stray_temporaries(root, of=FAILURES_FILE)
    for folder in sorted(root.iterdir()):
        if folder.is_symlink() or not folder.is_dir():
            continue
        try:  # best effort: what cannot be cleared here is a rebuilt model's own business
            done += _remove_dead_writes_of(folder)
        except OSError:
            continue
    return done


def _reason(error: Exception) -> str:
    return f"{type(error).__name__}: {error}"


def _progress(items: Iterable, desc: str, unit: str, show: bool, total: int | None = None):
    from sq_mitsuba.progress import progress_bar

    return progress_bar(items, desc=desc, unit=unit, disable=not show, total=total)


# --------------------------------------------------------------------------- generate

def generate_model(entry: CatalogueEntry, out_root: str | Path,
                   points: int = DEFAULT_POINTS) -> Path:
    """Generate, process, sample and write one catalogue entry; return its models folder.

    Raises :class:`MeshError` (nothing written) when the spacecraft is not one connected body.
    """
    spacecraft = generate_spacecraft(entry.seed, entry.archetype, entry.name)
    raw = spacecraft.union()
    model = process_mesh(raw, method="solid")
    pieces = connected_pieces(model.mesh)
    if pieces != 1:
        raise MeshError(f"{entry.name}: the union of its parts has {pieces} disconnected "
                        "pieces; every appendage must overlap the part it is mounted on")
    model.checks["one_piece"] = True
    samples = sample_model(model.mesh, points, points, points, seed=entry.seed)
    card = model_card(entry.name, model, samples, source="procedural",
                      archetype=entry.archetype, seed=entry.seed, split=entry.split,
                      catalogue_seed=entry.catalogue_seed,
                      generator_mesh_sha256=raw.digest(),
                      thin_part_thickness=round(spacecraft.thin * model.normalisation.scale, 6),
                      thin_fraction=THIN_FRACTION, parts=spacecraft.part_summary(),
                      part_materials=spacecraft.materials())
    return write_model(out_root, entry.name, model, samples, card)


def generate_library(options: GenerateOptions | None = None,
                     progress: bool = True) -> LibrarySummary:
    """Generate the first ``options.count`` catalogue models into ``options.out``.

    One failing model does not stop the batch: it is recorded in the summary and in
    ``failures.json`` and left out of ``splits.csv`` (see the module docstring for how both
    files merge with an existing library). Options, ``splits.csv`` and ``failures.json`` are
    checked before any model is built.
    """
    options = options or GenerateOptions()
    validate(options)
    root = Path(options.out)
    _check_root(root)
    with output_lock(root, command="sq-mitsuba models generate"):
        return _generate_locked(root, options, progress)


def same_spacecraft_problem(root: Path, entry: CatalogueEntry) -> str | None:
    """Why generating ``entry`` into the library ``root`` would replace another spacecraft
    of the same name (None: there is no model of that name, or it is this entry's own
    spacecraft: same archetype and model seed, so generating it again gives it again)."""
    folder = root / entry.name
    if not (folder / "models").exists():  # no model there (a file in the way fails the model)
        return None
    card_path = folder / "models" / "model_card.json"
    wanted = (f"model {entry.name} of catalogue seed {entry.catalogue_seed} is "
              f"{entry.archetype} seed {entry.seed}")
    try:
        card = read_json(card_path)
    except (OSError, ValueError):
        return (f"{folder}: holds a model of this name without a readable model_card.json, "
                f"so it cannot be told apart from another spacecraft ({wanted})")
    if not isinstance(card, dict):
        card = {}
    if card.get("source") != "procedural":
        return (f"{folder}: holds a model of this name from {card.get('source')!r}, not a "
                f"generated one ({wanted})")
    if (card.get("archetype"), card.get("seed")) != (entry.archetype, entry.seed):
        return (f"{folder}: holds another spacecraft of this name ({card.get('archetype')} "
                f"seed {card.get('seed')}, catalogue seed {card.get('catalogue_seed')}); "
                f"{wanted}")
    return None


def model_complete(root: Path, entry: CatalogueEntry, points: int) -> bool:
    """Whether ``root`` holds ``entry``'s model complete, as :func:`generate_model` would write
    it: every file of :data:`~sq_mitsuba.data.mesh_processing.MODEL_FILES`, and a readable card
    of this entry (procedural, the same archetype, model seed, catalogue seed and split) with
    ``points`` points in each sample set. Such a model is kept by a rerun (see the module
    docstring)."""
    folder = root / entry.name / MODEL_FOLDER
    if not all((folder / name).is_file() for name in MODEL_FILES):
        return False
    try:
        card = read_json(folder / "model_card.json")
    except (OSError, ValueError):
        return False
    if not isinstance(card, dict) or not isinstance(card.get("samples"), dict):
        return False
    ours = (card.get("source"), card.get("archetype"), card.get("seed"),
            card.get("catalogue_seed"), card.get("split"))
    # The card records the catalogue seed and split too: a model of the same spacecraft
    # from another catalogue is built again (cheap, rare) so its card says this one.
    if ours != ("procedural", entry.archetype, entry.seed, entry.catalogue_seed, entry.split):
        return False
    if not all(card["samples"].get(k) == points for k in ("surface", "uniform", "near")):
        return False
    return files_intact(folder, card)


def files_intact(folder: Path, card: dict) -> bool:
    """Whether a model's files are as written, as far as a quick look tells (about a
    millisecond a model): the OBJ holds the card's vertex and face counts and ends its last
    line, the GLB is as long as its header says, the samples archive's index (at its end)
    reads. A file cut short or emptied since (by hand, a full disk) makes the model be built
    again by a rerun rather than kept as "already there"; a NaN written into the samples is
    the renderer's to refuse (``check_model_points``)."""
    import struct
    import zipfile

    try:
        text = (folder / "model_normalized.obj").read_bytes()
        counts = (text.count(b"\nv "), text.count(b"\nf "))
        if counts != (card.get("vertices"), card.get("faces")) or not text.endswith(b"\n"):
            return False  # (the writer ends every line: a cut inside the last face shows)
        glb = folder / "model_normalized.glb"
        with open(glb, "rb") as file:
            header = file.read(12)
        if len(header) < 12 or header[:4] != b"glTF" or \
                struct.unpack("<I", header[8:12])[0] != glb.stat().st_size:
            return False
        with zipfile.ZipFile(folder / SAMPLES_FILE) as archive:  # its index is at its end
            return bool(archive.namelist())
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):
        return False


def _generate_one(entry: CatalogueEntry, root: Path, points: int) -> str | None:
    """Build one model; the reason it failed, or None (a worker's job: errors come back as
    text, so that one bad model does not stop the batch)."""
    try:
        generate_model(entry, root, points=points)
    except Exception as error:  # any failure of one model is that model's alone
        return _reason(error)
    return None


def _generate_outcomes(entries: Sequence[CatalogueEntry], root: Path, points: int,
                       workers: int) -> Iterator[str | None]:
    """Each entry's outcome (:func:`_generate_one`), in catalogue order, as it is known:
    built here, or by ``workers`` processes a few models ahead of the bookkeeping."""
    if workers == 1 or len(entries) <= 1:
        for entry in entries:
            yield _generate_one(entry, root, points)
        return
    with worker_pool(min(workers, len(entries))) as pool:
        yield from pool.map(_generate_one, entries, [root] * len(entries),
                            [points] * len(entries))


def _generate_locked(root: Path, options: GenerateOptions, progress: bool) -> LibrarySummary:
    """:func:`generate_library` under the library's lock."""
    splits = read_library_splits(root)
    failures = read_failures(root)
    if options.generator == "composed":
        from sq_mitsuba.data.spacecraft import (
            HELD_OUT_FAMILIES,
            TRAINING_FAMILIES,
            composed_catalogue,
        )

        families = {"all": None, "training": TRAINING_FAMILIES,
                    "held-out": HELD_OUT_FAMILIES}[options.families]
        entries = composed_catalogue(options.count, options.seed, families)
    elif options.families != "all":
        raise ValueError(f"families: only with --generator composed (the "
                         f"{options.generator} generator has no families to choose from)")
    elif options.generator == "graph":
        from sq_mitsuba.data.spacecraft import graph_catalogue

        entries = graph_catalogue(options.count, options.seed)
    else:
        entries = catalogue(options.count, options.seed)
    # Before the clash check: an old model put back by it is a model of the library too.
    remove_dead_writes(root)
    clashes = [problem for entry in entries
               if (problem := same_spacecraft_problem(root, entry)) is not None]
    if clashes:
        more = f" (and {len(clashes) - 1} more model(s) of this library)" \
            if len(clashes) > 1 else ""
        raise ValueError(f"{clashes[0]}{more}; nothing generated: a model is never replaced "
                         "by another spacecraft of the same name (generate into another "
                         "--out, or remove those folders)")
    kept = set() if options.rebuild else {
        entry.name for entry in entries if model_complete(root, entry, options.points)}
    todo = [entry for entry in entries if entry.name not in kept]
    summary = LibrarySummary(root)
    outcomes = _generate_outcomes(todo, root, options.points, options.workers)
    try:
        for entry in _progress(entries, "models", "model", progress, total=len(entries)):
            # Outcomes come in the order of todo, which keeps the catalogue's order.
            reason = None if entry.name in kept else next(outcomes)
            if entry.name in kept:
                summary.kept.append(entry.name)
            if reason is not None:
                if entry.name in splits:
                    reason += " (the earlier model in this folder is kept)"
                summary.failures[entry.name] = failures[entry.name] = reason
            else:
                summary.written.append(entry.name)
                # A kept model whose row is there already changes nothing: no rewrite.
                if entry.name not in kept or splits.get(entry.name) != entry.split:
                    splits[entry.name] = entry.split
                    _write_splits(root, splits)
                failures.pop(entry.name, None)
            _write_failures(root, failures)
    finally:  # Ctrl-C here, between two models: the workers end now, not at exit
        outcomes.close()
    return summary


# ----------------------------------------------------------------------------- import

def model_name_for(path: Path) -> str:
    """A folder-safe model name from a file name: its stem's letters and digits (any
    script's, in Unicode's composed form, as a file of macOS's decomposed name would not
    be), ``.``, ``-`` and ``_`` kept, every other run of characters one ``_``."""
    stem = unicodedata.normalize("NFC", path.stem)
    return re.sub(r"[^\w.-]+", "_", stem).strip("._") or "model"


#: Names a model folder cannot take: the files a library or a dataset keeps at its root
#: (``dataset render`` refuses a model folder named as one of the dataset's, its writer's
#: ``OVERWRITE_DELETES``: written out here, since that module imports torch; a test keeps
#: the two lists together).
RESERVED_NAMES = frozenset({SPLITS_FILE, FAILURES_FILE, "camera.json", "dataset.json",
                            "preview.png", "contact_sheet.png"})


def _model_folders(root: Path) -> list[str]:
    """The model folders of a library (those holding a processed mesh), sorted."""
    return sorted(p.parent.parent.name for p in root.glob(f"*/{MODEL_FOLDER}/{MODEL_FILES[0]}"))


def import_names(paths: Sequence[str | Path], out_root: str | Path,
                 taken: Iterable[str] = ()) -> list[str]:
    """The model name each file gets (see the module docstring): its stem, or the first free
    ``<stem>_<k>`` (k = 2, 3, ...) when the stem is taken in ``out_root``, by an earlier file
    of ``paths``, by a root file of a library or dataset (:data:`RESERVED_NAMES`) or by a
    name of ``taken`` (the rows of ``splits.csv``, whose folders may be gone)."""
    root = Path(out_root)
    taken = set(taken) | ({p.name for p in root.iterdir()} if root.is_dir() else set())
    taken |= RESERVED_NAMES
    names = []
    for path in paths:
        base = model_name_for(Path(path))
        name, k = base, 1
        while name in taken:
            k += 1
            name = f"{base}_{k}"
        taken.add(name)
        names.append(name)
    return names


def check_distinct_files(paths: Sequence[str | Path]) -> None:
    """One-line ``ValueError`` naming both arguments when two of ``paths`` (existing files)
    are one file: typed twice, as ``./box.obj``, through a link or a hard link. Each would
    become its own model (``box``, ``box_2``), one spacecraft possibly in both splits."""
    first: dict[tuple[int, int], str | Path] = {}
    for path in paths:
        status = os.stat(path)  # the file a link leads to: its device and inode
        key = (status.st_dev, status.st_ino)
        if key in first:
            named = f"{path} given twice" if str(first[key]) == str(path) else \
                f"{first[key]} and {path} are the same file, given twice"
            raise ValueError(f"meshes: {named}; give each mesh once (each file becomes its "
                             "own model)")
        first[key] = path


def import_model(path: str | Path, out_root: str | Path, method: str = "auto",
                 align: str = "axes", resolution: int = FUSION_RESOLUTION,
                 points: int = DEFAULT_POINTS, name: str | None = None) -> Path:
    """Load, process, sample and write one mesh file; errors name the file.

    ``name`` defaults to :func:`model_name_for` the file; an existing model of that name is
    replaced (:func:`import_models` picks names that never replace anything).
    """
    path = Path(path)
    check_fusion_resolution(resolution)
    mesh = load_mesh(path)
    try:
        model = process_mesh(mesh, method=method, align=align, resolution=resolution,
                             recentre=True)
    except MeshError as error:
        raise MeshError(f"{path}: {error}") from None
    pieces = connected_pieces(model.mesh)
    if pieces > 1:  # kept (a real model may be so), but said: often a strut or transform lost
        import warnings

        warnings.warn(f"{path}: {pieces} separate pieces: parts that do not touch in the file "
                      "stay apart in the model (a strut, or a node's transform, missing?)",
                      stacklevel=2)
    name = name or model_name_for(path)
    seed = int(np.frombuffer(model.mesh.digest().encode()[:8], dtype=np.uint64)[0] % 2**32)
    samples = sample_model(model.mesh, points, points, points, seed=seed)
    card = model_card(name, model, samples, source=str(path), archetype="imported",
                      seed=None, parts={"imported_mesh": 1})
    return write_model(out_root, name, model, samples, card)


def import_models(paths: Sequence[str | Path], options: ImportOptions | None = None,
                  progress: bool = True) -> LibrarySummary:
    """Import mesh files into ``options.out``, each into its own new model folder.

    Every path must exist, have a supported suffix, name another file than the other
    paths (:func:`check_distinct_files`) and, where its header or lines tell its faces
    (:func:`~sq_mitsuba.data.mesh_processing.file_face_count`), fit in memory
    (:func:`~sq_mitsuba.data.mesh_processing.check_import_memory`), all checked before any
    work; a file that
    cannot be read or processed is a failure of the batch, reported in the summary (imports
    keep no ``failures.json``: the files named on the command line are the record), not an
    error. ``summary.names`` tells which model name each file got.
    """
    options = options or ImportOptions()
    validate(options)
    if not paths:
        raise ValueError("meshes: no files given")
    for path in map(Path, paths):
        if path.is_dir():
            raise ValueError(f"{path}: is a folder, not a mesh file")
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file")
        if path.suffix.lower() not in MESH_SUFFIXES:
            raise ValueError(f"{path}: unsupported format {path.suffix!r}; "
                             f"expected one of {', '.join(MESH_SUFFIXES)}")
        # A mesh too large for memory: refused here, where the file says its size, before
        # the batch starts (other formats: when loaded, a failure of that file alone).
        if (faces := file_face_count(path)) is not None:
            check_import_memory(path, faces)
    check_distinct_files(paths)
    root = Path(options.out)
    _check_root(root)
    with output_lock(root, command="sq-mitsuba models import"):  # names picked under it
        return _import_locked(paths, root, options, progress)


def _import_locked(paths: Sequence[str | Path], root: Path, options: ImportOptions,
                   progress: bool) -> LibrarySummary:
    """:func:`import_models` under the library's lock."""
    remove_dead_writes(root)  # first: a folder a killed import left empty frees its name
    # Read (and so checked) once, before any model. A library imported before imports kept
    # rows has none: `dataset render` took its models for training ones; they keep that
    # split, so that this batch's rows do not leave them without one.
    splits = read_library_splits(root) if (root / SPLITS_FILE).is_file() else \
        {name: "train" for name in _model_folders(root)}
    names = import_names(paths, root, taken=set(splits))
    summary = LibrarySummary(root, names=[(str(p), n) for p, n in zip(paths, names, strict=True)])
    for path, name in _progress(list(zip(map(Path, paths), names, strict=True)), "import",
                                "mesh", progress):
        try:
            import_model(path, root, method=options.method, align=options.align,
                         resolution=options.resolution, points=options.points, name=name)
        except Exception as error:  # one bad file must not stop the batch
            message = str(error)
            if str(path) not in message:
                message = f"{path}: {message}"
            summary.failures[name] = message
        else:
            summary.written.append(name)
            # Its row at once (atomically), as generate does: a library with a model folder
            # and no row is one `dataset render` refuses.
            splits[name] = options.split
            _write_splits(root, splits)
    return summary
