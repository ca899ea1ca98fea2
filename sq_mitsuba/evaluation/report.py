"""Collate evaluation folders into the layout of the paper's Tables 1 and 2.

Each folder written by :func:`sq_mitsuba.evaluation.evaluate.evaluate` holds ``eval.json``
(split, label, number of primitives) and ``summary.csv`` (mean, std, median per method and
metric). A run is identified by the label its ``eval.json`` records (``sq-mitsuba eval
--label``; by default the checkpoint's folder name), or, for an ``eval.json`` without one, the
folder name of the checkpoint it records, else of the evaluation folder's parent; its ``val``
and ``test`` folders fill one row, and must be of one model (the weights' and stored
baseline's sha256 each ``eval.json`` records, where both do: else a one-line error); Table 2
(number of primitives) shows each run's M. The
paper's published rows (``eval/paper_tables.toml``) are printed beside ours, with a note on
what is not comparable. Ours and the paper's are not ranked together: in each column the best
of our methods' rows (not the baseline's nor the true mask's refinement: references) is in
bold and the best of the paper's rows in italics (each only where there are two rows or more
to choose from). Inputs are read strictly: a folder, summary or paper table that is missing,
empty, cut short, malformed or holds NaN where a number is due is a one-line error naming the
file, before anything is written.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from sq_mitsuba.config import ConfigError, read_mapping
from sq_mitsuba.inputs import finite_number, read_csv_table
from sq_mitsuba.io import atomic_write_text, check_output_folder, read_json
from sq_mitsuba.outputs import refuse_present

#: (metric key in summary.csv, key in paper_tables.toml, column title, lower is better)
COLUMNS = (("chamfer_l1_paper", "chamfer_l1", "Chamfer-L1 ↓", True),
           ("rotation_error_deg", "rotation_error_deg", "E_R [deg] ↓", True),
           ("iou_2d", "iou_2d", "IoU (2D) ↑", False))
PAPER_TABLES = Path(__file__).resolve().parents[2] / "eval" / "paper_tables.toml"
NOT_COMPARABLE = (
    "Not directly comparable: the paper's numbers come from its own dataset (64 real "
    "spacecraft models rendered in Unreal Engine, released as SPE3R) and a GPU training run; "
    "ours from the dataset named in each run's eval.json. Both use the 'paper' Chamfer "
    "convention (L1 nearest neighbours, the two directions summed, unit-size models), so "
    "that column's definition matches; E_R is the raw rotation error, as the paper's (the "
    "error over the symmetries and the folded one are in each run's summary.md, as are the "
    "occnet convention and the camera-frame Chamfer).")


def read_eval_folder(folder: str | Path) -> dict[str, Any]:
    """``eval.json`` plus {method: {metric: (mean, std)}} from ``summary.csv``, strictly.

    ``eval.json`` must name the split (``val`` or ``test``) and the number of primitives;
    ``summary.csv`` must hold a row of every metric of :data:`COLUMNS` for the network, the
    methods ``eval.json`` lists, and any other method it holds, the network's finite. Another
    method's metric that is NaN (no image gave a value, e.g. nothing segmented) is left out of
    its row.

    Raises:
        FileNotFoundError: ``<folder>: no such folder``, or ``<folder>/eval.json: missing
            ...`` (or ``summary.csv``); NotADirectoryError: ``<folder>: not a folder ...``.
        ValueError: one line naming the file (and row) for anything else amiss: not JSON,
            another split, an empty, cut-short or malformed ``summary.csv``, NaN in the
            network's metrics, a row given twice.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(f"{folder}: not a folder (give an evaluation folder, as "
                                 "`sq-mitsuba eval --out` wrote it)")
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder")
    for name in ("eval.json", "summary.csv"):
        if not (folder / name).is_file():
            from sq_mitsuba.evaluation.journal import JOURNAL

            # An evaluation still running (or stopped) keeps its journal there: said so.
            why = ("an evaluation still running, or stopped before its tables (`sq-mitsuba "
                   "eval --resume` finishes it)") if (folder / JOURNAL).is_dir() else \
                "not an evaluation folder?"
            raise FileNotFoundError(f"{folder / name}: missing ({why})")
    info = read_json(folder / "eval.json")
    where = folder / "eval.json"
    if not isinstance(info, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(info).__name__}")
    if info.get("split") not in ("val", "test"):
        raise ValueError(f"{where}: split {info.get('split')!r} is neither 'val' nor 'test'")
    primitives = info.get("num_primitives")
    if isinstance(primitives, bool) or not isinstance(primitives, int) or primitives < 1:
        raise ValueError(f"{where}: num_primitives {primitives!r} is not a positive integer")
    label = info.get("label")
    if label is not None and not (isinstance(label, str) and label.strip()):
        raise ValueError(f"{where}: label {label!r} is not a name")
    path = folder / "summary.csv"
    summary: dict[str, dict[str, tuple[float, float]]] = {}
    wanted = [metric for metric, *_ in COLUMNS]
    methods = info.get("methods", ["network"])
    if not isinstance(methods, list) or not all(isinstance(m, str) for m in methods):
        raise ValueError(f"{where}: methods {methods!r} is not a list of names")
    seen: dict[str, set[str]] = {method: set() for method in methods}
    for row in read_csv_table(path, ("method", "metric", "mean", "std")):
        method, metric = row["method"], row["metric"]
        if metric not in wanted:
            continue
        at = f"{path}: {method} {metric}"
        if metric in seen.setdefault(method, set()):
            raise ValueError(f"{at}: given twice")
        seen[method].add(metric)
        mean, std = (_cell(row[key], f"{at} {key}", method == "network")
                     for key in ("mean", "std"))
        if mean is not None and std is not None:
            summary.setdefault(method, {})[metric] = (mean, std)
    for method, metrics in seen.items():
        missing = [metric for metric in wanted if metric not in metrics]
        if missing:
            raise ValueError(f"{path}: no {method} row for {missing[0]} (cut short, or not "
                             "written by `sq-mitsuba eval`?)")
    return {"folder": folder, "split": info["split"], "info": info, "summary": summary,
            "label": label or _checkpoint_name(info) or folder.parent.name or folder.name}


def _checkpoint_name(info: dict[str, Any]) -> str | None:
    """The folder name of the checkpoint an ``eval.json`` records (a training run's output
    folder: what ``sq-mitsuba eval`` labels a run by default), or None."""
    checkpoint = info.get("checkpoint")
    if not isinstance(checkpoint, str) or not checkpoint.strip():
        return None
    path = Path(checkpoint)  # '../best.pt' names no folder: its stem then, as eval does
    return next((n for n in (path.parent.name, path.stem) if n.strip(" .")), None)


def _cell(text: str, where: str, required: bool) -> float | None:
    """A summary number: finite, or None for NaN where the row may lack it."""
    if not required and text.strip().lower() in ("nan", ""):
        return None
    return finite_number(text, where)


#: The Chamfer-L1 convention of our column (``chamfer_l1_paper``), which the paper's rows must
#: state in ``[source]``: the comparison does not convert between conventions.
CHAMFER_CONVENTION = "paper"
#: The keys of a paper-tables file's ``[source]`` table; ``chamfer_convention`` is required
#: (the report's note says both columns use one convention: the file must say its own).
SOURCE_KEYS = ("title", "chamfer_convention")


def _check_source(source: Any, where: str) -> None:
    """A paper-tables file's ``[source]`` table, strictly: the Chamfer convention of its
    numbers, which must be :data:`CHAMFER_CONVENTION`, and optionally a ``title``; no other
    key.

    Convention: a file in another convention (``occnet``, say) is refused, not compared with
    another of our columns: its rows would also need our runs' numbers in that convention in
    Table 1 and 2's layout, and a refusal keeps the report's note ("both use the 'paper'
    Chamfer convention") true by construction.
    """
    if source is None:
        raise ValueError(f"{where}: no [source] table (title, chamfer_convention: the "
                         "convention of its Chamfer-L1)")
    if not isinstance(source, dict):
        raise ValueError(f"{where}: source must be a table (title, chamfer_convention)")
    unknown = sorted(set(source) - set(SOURCE_KEYS))
    if unknown:
        raise ValueError(f"{where}: source.{unknown[0]}: unknown key (expected "
                         f"{' and '.join(SOURCE_KEYS)})")
    if "chamfer_convention" not in source:
        raise ValueError(f"{where}: source.chamfer_convention: missing (the report compares "
                         f"Chamfer-L1 in the {CHAMFER_CONVENTION!r} convention: say so)")
    title = source.get("title", "untitled")
    if not isinstance(title, str) or not title.strip():
        raise ValueError(f"{where}: source.title: expected a name, got {title!r}")
    convention = source["chamfer_convention"]
    if convention != CHAMFER_CONVENTION:
        raise ValueError(f"{where}: source.chamfer_convention {convention!r}: the report "
                         f"compares our {CHAMFER_CONVENTION!r}-convention Chamfer-L1 "
                         f"(chamfer_l1_paper) with the paper's, so its numbers must be in "
                         f"that convention ({CHAMFER_CONVENTION!r})")


#: The range of each paper metric's mean (Chamfer-L1 >= 0, an angle in degrees, an IoU).
PAPER_RANGES = {"chamfer_l1": (0.0, math.inf), "rotation_error_deg": (0.0, 180.0),
                "iou_2d": (0.0, 1.0)}


def _pair(value: Any, where: str, metric: str) -> tuple[float, float]:
    """A paper entry's ``[mean, std]``: two finite numbers (not text), the mean within
    ``metric``'s range (:data:`PAPER_RANGES`), std >= 0."""
    if not isinstance(value, list) or len(value) != 2:
        raise ValueError(f"{where}: expected [mean, std], got {value!r}")
    mean, std = (finite_number(v, where, text=False) for v in value)
    low, high = PAPER_RANGES[metric]
    if not low <= mean <= high:
        raise ValueError(f"{where}: mean {mean:g} outside [{low:g}, {high:g}]")
    if std < 0:
        raise ValueError(f"{where}: std {std:g} is negative")
    return mean, std


def read_paper_tables(path: str | Path) -> tuple[list[dict], list[dict]]:
    """The rows of Tables 1 and 2 of a paper-tables TOML (see ``eval/paper_tables.toml``),
    strictly: only the tables ``table1``, ``table2`` and ``source``, at least one row, every
    row a ``label``, ``val`` and ``test`` with ``[mean, std]`` of each metric, Table 2's rows
    their number of ``primitives``, and ``source`` the ``chamfer_convention``
    :data:`CHAMFER_CONVENTION` (and optionally a ``title``): a file in another convention is
    refused rather than compared with another column (:func:`_check_source`).

    Raises:
        ValueError: ``paper tables <path>: ...`` (missing, not TOML, or a bad entry, named).
    """
    path = Path(path)
    try:
        data = read_mapping(path)
    except ConfigError as error:
        raise ValueError(f"paper tables {error}") from None
    where = f"paper tables {path}"
    unknown = sorted(set(data) - {"source", "table1", "table2"})
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r} (expected table1, table2 and "
                         "source: is it the paper's tables?)")
    tables: list[list[dict]] = []
    for table in ("table1", "table2"):
        entries = data.get(table, {})
        if not isinstance(entries, dict):
            raise ValueError(f"{where}: {table} must be a table of rows")
        rows = []
        for key, entry in entries.items():
            at = f"{where}: {table}.{key}"
            keys = {"label", "val", "test"} | ({"primitives"} if table == "table2" else set())
            if not isinstance(entry, dict) or set(entry) != keys:
                got = sorted(entry) if isinstance(entry, dict) else type(entry).__name__
                raise ValueError(f"{at}: expected the keys {sorted(keys)}, got {got}")
            if not isinstance(entry["label"], str) or not entry["label"].strip():
                raise ValueError(f"{at}.label: expected a name, got {entry['label']!r}")
            row: dict[str, Any] = {"label": f"paper {entry['label']}", "M": None,
                                   "paper": True}
            if table == "table2":
                m = entry["primitives"]
                if isinstance(m, bool) or not isinstance(m, int) or m < 1:
                    raise ValueError(f"{at}.primitives: expected a positive integer, got {m!r}")
                row["M"] = m
            for split in ("val", "test"):
                metrics = entry[split]
                names = {paper_key for _, paper_key, _, _ in COLUMNS}
                if not isinstance(metrics, dict) or set(metrics) != names:
                    got = sorted(metrics) if isinstance(metrics, dict) else metrics
                    raise ValueError(f"{at}.{split}: expected the metrics {sorted(names)}, "
                                     f"got {got}")
                row[split] = {k: _pair(v, f"{at}.{split}.{k}", k) for k, v in metrics.items()}
            rows.append(row)
        tables.append(rows)
    if not tables[0] and not tables[1]:
        raise ValueError(f"{where}: no rows in table1 or table2 (is it the paper's tables?)")
    _check_source(data.get("source"), where)
    return tables[0], tables[1]


def _weights_sha256(info: dict[str, Any]) -> str | None:
    """The sha256 of the evaluated network's weights an ``eval.json`` records, if any."""
    identity = info.get("identity")
    checkpoint = identity.get("checkpoint") if isinstance(identity, dict) else None
    sha = checkpoint.get("sha256") if isinstance(checkpoint, dict) else None
    return sha if isinstance(sha, str) else None


def _our_rows(folders: list[dict[str, Any]]) -> list[dict]:
    rows: dict[tuple[str, str], dict] = {}
    # One label, one network: a val and a test evaluation of two checkpoints saved in one
    # folder (whose name is the default label) would otherwise share a row.
    first_of: dict[str, dict[str, Any]] = {}
    for folder in folders:
        other = first_of.setdefault(folder["label"], folder)
        ours, theirs = _weights_sha256(folder["info"]), _weights_sha256(other["info"])
        if ours is not None and theirs is not None and ours != theirs:
            raise ValueError(f"{folder['folder']}: run {folder['label']!r} evaluates another "
                             f"model (weights and stored baseline {ours[:12]}) than "
                             f"{other['folder']} ({theirs[:12]}; a checkpoint and its export "
                             "differ too); name the runs apart with eval --label")
        for method, metrics in folder["summary"].items():
            label = folder["label"] if method == "network" else f"{folder['label']} ({method})"
            row = rows.setdefault((label, method), {"label": label, "val": {}, "test": {},
                                                    "M": folder["info"].get("num_primitives"),
                                                    "paper": False, "method": method})
            split = folder["split"]
            if metrics and any(key in row[split] for _, key, _, _ in COLUMNS):
                raise ValueError(f"{folder['folder']}: a second {split} evaluation of the run "
                                 f"{folder['label']!r} (give each run's val and test once; "
                                 "name the runs apart with eval --label)")
            for metric, paper_key, _, _ in COLUMNS:
                if metric in metrics:
                    row[split][paper_key] = metrics[metric]
    return list(rows.values())


#: How the best value of a column is marked in report.md, among our rows and the paper's.
EMPHASIS = {False: "**", True: "*"}
BEST_NOTE = ("In each column, **bold**: the best of our methods' rows; *italics*: the best "
             "of the paper's rows (the two groups are not ranked together; the baseline and "
             "the refinement against the true mask, references, are not ranked).")
#: Our rows that are references, not methods: never marked best.
REFERENCES = ("baseline", "refined_gt")


def _table(rows: list[dict], with_m: bool
           ) -> tuple[list[str], list[list[str]], list[list[str]]]:
    """Header, plain cells and Markdown cells of a table of ``rows``; ``with_m``: a column of
    each run's M. The Markdown marks the best value of each column among our rows and, apart,
    among the paper's (:data:`EMPHASIS`), where a group has two values or more."""
    from sq_mitsuba.evaluation.tables import markdown_text  # torch: see write_report

    header = ["run", *(["M"] if with_m else [])] + [
        f"{split} {title}" for split in ("val", "test") for _, _, title, _ in COLUMNS]
    best: dict[tuple[bool, str, str], float] = {}
    for paper in (False, True):
        group = [r for r in rows if r.get("paper", False) == paper
                 and r.get("method") not in REFERENCES]
        for split in ("val", "test"):
            for _, key, _, lower in COLUMNS:
                values = [r[split][key][0] for r in group if key in r[split]]
                if len(values) > 1:
                    best[(paper, split, key)] = min(values) if lower else max(values)
    plain, marked = [], []
    for row in rows:
        paper = row.get("paper", False)
        cells = [row["label"], *([str(row["M"])] if with_m else [])]
        # The label as text, not Markdown: a '|' would add a column, '*b*' read as a best mark.
        marks = [markdown_text(row["label"]), *cells[1:]]
        for split in ("val", "test"):
            for _, key, _, _ in COLUMNS:
                if key not in row[split]:
                    cells.append("–")
                    marks.append("–")
                    continue
                mean, std = row[split][key]
                text = f"{mean:.3f} ± {std:.3f}"
                cells.append(text)
                emphasis = EMPHASIS[paper] if best.get((paper, split, key)) == mean \
                    and row.get("method") not in REFERENCES else ""
                marks.append(f"{emphasis}{text}{emphasis}")
        plain.append(cells)
        marked.append(marks)
    return header, plain, marked


#: The first line of report.md (and the header of report.csv, :func:`_csv_header`): how a
#: rerun tells the files an earlier report wrote, which it replaces, from a user's of the same
#: names (``--out notes`` holding the user's notes/report.md), which it refuses.
TITLE = "# Results in the layout of the paper's tables"


def _csv_header() -> str:
    from sq_mitsuba.evaluation.tables import csv_text  # torch: see write_report

    return csv_text(["table", *_table([], True)[0]], []).rstrip("\n")


def _first_line(path: Path) -> str | None:
    """The first line of the plain file ``path`` (a few kB read at most), or None: not a
    file, a link, unreadable."""
    try:
        if path.is_symlink() or not path.is_file():
            return None
        with open(path, "rb") as handle:
            head = handle.read(4096)
    except OSError:
        return None
    return head.split(b"\n", 1)[0].rstrip(b"\r").decode("utf-8", errors="replace")


def refuse_foreign_outputs(out_dir: Path) -> None:
    """A one-line ``ValueError`` for a ``report.md`` or ``report.csv`` in ``out_dir`` that no
    earlier report wrote (by its first line): someone else's file, never replaced."""
    for name, first in (("report.md", TITLE), ("report.csv", _csv_header())):
        path = out_dir / name
        if (path.exists() or path.is_symlink()) and _first_line(path) != first:
            refuse_present(out_dir, (name,), "an output of report, but no earlier report "
                           "wrote it")


def write_report(folders: list[str | Path], out_dir: str | Path,
                 paper_tables: str | Path | None = None) -> Path:
    """Write ``report.md`` and ``report.csv`` collating evaluation ``folders`` (each one
    split of one run) with the paper's Tables 1 and 2; returns the Markdown path.

    Every input is read strictly (:func:`read_eval_folder`, :func:`read_paper_tables`) and
    ``out_dir`` checked before anything is written: a ``report.md`` or ``report.csv`` there
    that an earlier report did not write is refused (:func:`refuse_foreign_outputs`).
    ``paper_tables`` None: the tables of a source checkout (``eval/paper_tables.toml``), or
    none, with a note, where it is absent. Table 2 (number of primitives) shows each run's M.
    """
    if not folders:
        raise ValueError("folders: give at least one evaluation folder")
    evaluations = [read_eval_folder(f) for f in folders]
    ours = _our_rows(evaluations)
    if paper_tables is None:
        table1, table2 = read_paper_tables(PAPER_TABLES) if PAPER_TABLES.is_file() else ([], [])
    else:
        table1, table2 = read_paper_tables(paper_tables)
    out_dir = check_output_folder(out_dir, ("report.md", "report.csv"))
    refuse_foreign_outputs(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    lines = [TITLE, ""]
    csv_rows: list[list[str]] = []
    sections = [("Table 1: loss configurations", ours + table1, False),
                ("Table 2: number of primitives M (configuration (a))", ours + table2, True)]
    for title, rows, with_m in sections:
        header, body, marked = _table(rows, with_m)
        lines += [f"## {title}", "", "| " + " | ".join(header) + " |",
                  "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(cells) + " |" for cells in marked]
        lines.append("")
        for row, plain in zip(rows, body, strict=True):
            m = "" if row["M"] is None else str(row["M"])
            csv_rows.append([title, plain[0], m, *plain[2 if with_m else 1:]])
    if not table1 and not table2:
        lines += ["The paper's numbers were not found (eval/paper_tables.toml is part of a "
                  "source checkout; --paper names another copy).", ""]
    lines += [BEST_NOTE, "", NOT_COMPARABLE, ""]
    markdown = out_dir / "report.md"
    atomic_write_text(markdown, "\n".join(lines))
    # The csv module quotes and escapes: a label may hold commas and quotes (cli/eval.py
    # refuses only '|' and line breaks). Imported here: tables imports torch, which the CLI's
    # parser, importing this module, does without.
    from sq_mitsuba.evaluation.tables import csv_text

    atomic_write_text(out_dir / "report.csv",
                      csv_text(["table", *_table([], True)[0]], csv_rows))
    return markdown
