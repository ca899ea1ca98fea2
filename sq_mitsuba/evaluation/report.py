"""Collate evaluation folders into the layout of the paper's Tables 1 and 2.

Each folder written by :func:`sq_mitsuba.evaluation.evaluate.evaluate` holds ``eval.json``
(split, label, number of primitives) and ``summary.csv`` (mean, std, median per method and
metric). A run is identified by its label (the training config's name unless given); its
``val`` and ``test`` folders fill one row. The paper's published rows
(``eval/paper_tables.toml``) are printed beside ours, the best value of each column in bold,
with a note on what is not comparable.
"""

from __future__ import annotations

import csv
import tomllib
from pathlib import Path
from typing import Any

from sq_mitsuba.io import atomic_write_text, read_json

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
    "that column's definition matches; the occnet convention and the camera-frame Chamfer "
    "are in each run's summary.md.")


def read_eval_folder(folder: str | Path) -> dict[str, Any]:
    """``eval.json`` plus {method: {metric: (mean, std)}} from ``summary.csv``."""
    folder = Path(folder)
    for name in ("eval.json", "summary.csv"):
        if not (folder / name).is_file():
            raise FileNotFoundError(f"{folder / name}: missing (not an evaluation folder?)")
    info = read_json(folder / "eval.json")
    summary: dict[str, dict[str, tuple[float, float]]] = {}
    with open(folder / "summary.csv", newline="", encoding="utf-8") as handle:
        for row in csv.DictReader(handle):
            try:
                summary.setdefault(row["method"], {})[row["metric"]] = (float(row["mean"]),
                                                                       float(row["std"]))
            except (KeyError, ValueError):
                raise ValueError(f"{folder / 'summary.csv'}: malformed row {row}") from None
    return {"folder": folder, "split": info.get("split"), "info": info, "summary": summary,
            "label": info.get("label") or folder.parent.name or folder.name}


def _paper_rows(path: Path | None) -> tuple[list[dict], list[dict]]:
    if path is None or not path.is_file():
        return [], []
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    tables = []
    for table in ("table1", "table2"):
        rows = []
        for entry in data.get(table, {}).values():
            rows.append({"label": f"paper {entry['label']}",
                         "val": {k: tuple(v) for k, v in entry["val"].items()},
                         "test": {k: tuple(v) for k, v in entry["test"].items()}})
        tables.append(rows)
    return tables[0], tables[1]


def _our_rows(folders: list[dict[str, Any]]) -> list[dict]:
    rows: dict[tuple[str, str], dict] = {}
    for folder in folders:
        for method, metrics in folder["summary"].items():
            label = folder["label"] if method == "network" else f"{folder['label']} ({method})"
            row = rows.setdefault((label, method), {"label": label, "val": {}, "test": {},
                                                    "M": folder["info"].get("num_primitives")})
            split = folder["split"] if folder["split"] in ("val", "test") else "val"
            for metric, paper_key, _, _ in COLUMNS:
                if metric in metrics:
                    row[split][paper_key] = metrics[metric]
    return list(rows.values())


def _table(rows: list[dict]) -> tuple[list[str], list[list[str]]]:
    header = ["run"] + [f"{split} {title}" for split in ("val", "test")
                        for _, _, title, _ in COLUMNS]
    best: dict[tuple[str, str], float] = {}
    for split in ("val", "test"):
        for _, key, _, lower in COLUMNS:
            values = [r[split][key][0] for r in rows if key in r[split]]
            if values:
                best[(split, key)] = min(values) if lower else max(values)
    body = []
    for row in rows:
        cells = [row["label"]]
        for split in ("val", "test"):
            for _, key, _, _ in COLUMNS:
                if key not in row[split]:
                    cells.append("–")
                    continue
                mean, std = row[split][key]
                text = f"{mean:.3f} ± {std:.3f}"
                cells.append(f"**{text}**" if best.get((split, key)) == mean else text)
        body.append(cells)
    return header, body


def write_report(folders: list[str | Path], out_dir: str | Path,
                 paper_tables: str | Path | None = PAPER_TABLES) -> Path:
    """Write ``report.md`` and ``report.csv`` collating evaluation ``folders`` (each one
    split of one run) with the paper's Tables 1 and 2; returns the Markdown path."""
    if not folders:
        raise ValueError("folders: give at least one evaluation folder")
    evaluations = [read_eval_folder(f) for f in folders]
    ours = _our_rows(evaluations)
    table1, table2 = _paper_rows(Path(paper_tables) if paper_tables else None)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    lines = ["# Results in the layout of the paper's tables", ""]
    csv_rows: list[list[str]] = []
    sections = [("Table 1: loss configurations", ours + table1),
                ("Table 2: number of primitives M (configuration (a))",
                 [r for r in ours if r.get("M")] + table2)]
    for title, rows in sections:
        header, body = _table(rows)
        lines += [f"## {title}", "", "| " + " | ".join(header) + " |",
                  "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(cells) + " |" for cells in body]
        lines.append("")
        csv_rows += [[title, *[c.replace("**", "") for c in cells]] for cells in body]
    if not table1:
        lines += ["The paper's numbers were not found (eval/paper_tables.toml is part of a "
                  "source checkout).", ""]
    lines += [NOT_COMPARABLE, ""]
    markdown = out_dir / "report.md"
    atomic_write_text(markdown, "\n".join(lines))
    header = ["table", *_table(ours or table1)[0]]
    text = ",".join(header) + "\n" + "".join(
        ",".join(f'"{c}"' for c in row) + "\n" for row in csv_rows)
    atomic_write_text(out_dir / "report.csv", text)
    return markdown
