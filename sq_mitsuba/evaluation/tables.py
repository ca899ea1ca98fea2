"""The evaluation's tables: one row per image and method (:data:`COLUMNS`), summarised per
method and per model (mean, std, median) and written as CSV and Markdown
(:func:`write_tables`)."""

from __future__ import annotations

import csv
import io as _io
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sq_mitsuba.evaluation.scoring import METRICS
from sq_mitsuba.io import atomic_write_text

__all__ = ["COLUMNS", "EXTRAS", "LIGHTING", "SHOWN", "as_number", "csv_text",
           "format_stats", "label_record", "markdown_code", "markdown_table", "markdown_text",
           "summarise", "write_tables"]

#: Search and refinement columns: the search's best soft IoU at its resolution, the refinement's
#: IoU after it (refinement resolution), and ``mask_iou``, the IoU of the mask fitted (the one
#: ``mask_source`` names: the network's, the segmentation's) against the true mask (``search``
#: and ``refined`` rows; it was ``segmentation_iou`` before 2026-12-01, whatever the source).
EXTRAS = ("search_score", "refine_iou_after", "mask_iou")
#: The label's lighting record (empty where the dataset has none, e.g. the SPE3R release).
LIGHTING = ("phase_angle_deg", "earth_in_view", "eclipse", "target_visibility")
#: Columns of ``per_image.csv``.
COLUMNS = ("model", "index", "filename", "method", *METRICS, *EXTRAS, "mask_source", *LIGHTING)
#: Metrics shown in the Markdown tables (every metric is in the CSV files).
SHOWN = ("chamfer_l1_paper", "chamfer_l1_occnet", "camera_chamfer", "iou_2d", "iou_3d",
         "rotation_error_deg", "rotation_error_sym_deg", "rotation_error_folded_deg",
         "rotation_error_axes_deg", "translation_error_rel")


def summarise(rows: Sequence[dict[str, Any]], keys: Sequence[str] = ("method",),
              metrics: Sequence[str] = METRICS
              ) -> dict[tuple, dict[str, tuple[float, float, float]]]:
    """Mean, std (population) and median of every metric per group of ``keys``; values that
    are missing or not finite are left out (NaN where none is left)."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(tuple(row[k] for k in keys), []).append(row)
    out = {}
    for group, members in groups.items():
        stats = {}
        for metric in metrics:
            values = np.array([as_number(m.get(metric)) for m in members], dtype=np.float64)
            values = values[np.isfinite(values)]
            stats[metric] = ((float(values.mean()), float(values.std()), float(np.median(values)))
                             if len(values) else (math.nan, math.nan, math.nan))
        out[group] = stats
    return out


def as_number(value: Any) -> float:
    """``float(value)``, or NaN for a value that is not a number (a blank CSV cell, None)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def csv_text(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """CSV (comma, ``\\n`` line ends) of a header and rows."""
    buffer = _io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


#: What Markdown (GitHub's: tables, strikethrough, math) reads as markup in running text: '_'
#: only where it can open or close emphasis (not between two letters or digits, so that
#: 'refined_gt' reads as it is), '&' only where it starts an entity ('&lt;').
_MARKUP = re.compile(r"[\\`*|<>\[\]$~]|(?<![^\W_])_|_(?![^\W_])|&(?=#?\w+;)")


def markdown_text(text: Any) -> str:
    """``text`` shown literally in Markdown, on one line (a user's name in a table cell or a
    label): markup characters backslash-escaped, so that a '|' adds no column and '*b*' is no
    emphasis (report.md's mark of the best); line breaks, which would end a table row, become
    spaces."""
    return _MARKUP.sub(lambda m: "\\" + m.group(), " ".join(str(text).splitlines()))


def markdown_code(text: Any) -> str:
    """``text`` as a Markdown code span, shown verbatim (a path: its '<b>' and '*' as typed):
    fenced by more backticks than it holds in a row, padded where it starts or ends with a
    backtick or a space (the renderer takes one space off each side)."""
    text = " ".join(str(text).splitlines())
    fence = "`" * (1 + max((len(run) for run in re.findall("`+", text)), default=0))
    pad = " " if text[:1] in ("`", " ") or text[-1:] in ("`", " ") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A Markdown table: ``header`` as given (the caller's column titles), every cell of
    ``rows`` as plain text (:func:`markdown_text`: a model name may hold '|' or '*')."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(markdown_text(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def format_stats(mean: float, std: float, median: float | None = None) -> str:
    """``mean ± std`` (and ``(median)``) with three decimals."""
    text = f"{mean:.3f} ± {std:.3f}"
    return text if median is None else f"{text} ({median:.3f})"


def write_tables(rows: Sequence[dict[str, Any]], out_dir: Path) -> dict[str, Any]:
    """per_image.csv, per_model.{csv,md}, summary.{csv,md}; returns the per-method summary
    {method: {metric: (mean, std, median)}}."""
    out_dir = Path(out_dir)
    atomic_write_text(out_dir / "per_image.csv",
                      csv_text(COLUMNS, [[r.get(c, "") for c in COLUMNS] for r in rows]))
    by_method = summarise(rows)
    counts = {method: sum(1 for r in rows if r["method"] == method) for (method,) in by_method}
    summary_rows = [[method, metric, *stats[metric], counts[method]]
                    for (method,), stats in by_method.items() for metric in METRICS]
    atomic_write_text(out_dir / "summary.csv", csv_text(
        ["method", "metric", "mean", "std", "median", "images"], summary_rows))
    md_rows = [[method, counts[method], *(format_stats(*stats[m]) for m in SHOWN)]
               for (method,), stats in by_method.items()]
    atomic_write_text(out_dir / "summary.md", (
        "Mean ± std (median) per method; every metric is in summary.csv.\n\n"
        + markdown_table(["method", "images", *SHOWN], md_rows)
        + "\nChamfer-L1 'paper': L1 nearest neighbours, the two directions summed (the "
        "convention of the paper's tables); 'occnet': L2 nearest neighbours, directions "
        "averaged; camera_chamfer: occnet Chamfer of the posed clouds over the true distance. "
        "Rotation errors in degrees ('sym': the least over the model's symmetries).\n"))
    by_model = summarise(rows, ("model", "method"))
    model_counts = {key: sum(1 for r in rows if (r["model"], r["method"]) == key)
                    for key in by_model}
    model_rows = [[model, method, metric, *stats[metric], model_counts[(model, method)]]
                  for (model, method), stats in sorted(by_model.items()) for metric in METRICS]
    atomic_write_text(out_dir / "per_model.csv", csv_text(
        ["model", "method", "metric", "mean", "std", "median", "images"], model_rows))
    md = [[model, method, model_counts[(model, method)],
           *(format_stats(*stats[m]) for m in SHOWN)]
          for (model, method), stats in sorted(by_model.items())]
    atomic_write_text(out_dir / "per_model.md",
                      "Mean ± std (median) per model and method.\n\n"
                      + markdown_table(["model", "method", "images", *SHOWN], md))
    return {method: stats for (method,), stats in by_method.items()}


def label_record(label: dict[str, Any]) -> dict[str, Any]:
    """The filename and lighting record (:data:`LIGHTING`) of one label ("" where absent)."""
    return {"filename": label.get("filename", ""),
            **{key: label.get(key, "") for key in LIGHTING}}
