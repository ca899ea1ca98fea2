"""The demo's page: ``index.html`` and its Markdown twin ``index.md``, with the same content.

Both link every picture and file by a path relative to the page (no inline images), so the
folder can be moved, served or opened from disk as it is. The HTML page carries one small
inline script: once the window has loaded, it sets ``data-broken-images`` on ``<body>`` to the
number of ``<img>`` elements that failed to load (``naturalWidth == 0``), so a headless browser
(``--dump-dom``) can tell whether every picture reached the screen.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from sq_mitsuba.io import atomic_write_text

PAGE_FILE, MARKDOWN_FILE = "index.html", "index.md"

#: Counts the pictures that did not load, once everything has (see the module docstring).
BROKEN_IMAGES_SCRIPT = """\
window.addEventListener("load", function () {
  var broken = 0;
  document.querySelectorAll("img").forEach(function (img) {
    if (!img.complete || img.naturalWidth === 0) { broken += 1; }
  });
  document.body.dataset.brokenImages = String(broken);
});"""

_STYLE = """\
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1400px;
       padding: 0 1em; color: #222; background: #fafafa; }
table { border-collapse: collapse; margin: 0.6em 0 1.2em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
figure { display: inline-block; margin: 0 0.4em 0.4em 0; vertical-align: top; }
figure img { width: 220px; height: auto; display: block; background: #000; }
figcaption { font-size: 0.8em; max-width: 220px; }
section { border-top: 1px solid #ddd; padding-top: 0.6em; }
.wide img { width: 720px; }
.wide figcaption { max-width: 720px; }"""


@dataclass
class PageImage:
    """One image's block: its pictures, its metrics per method and its files.

    Attributes:
        title: heading; pictures: (relative path, caption) in display order;
        metrics: (method label, {metric key: value}) rows; links: (label, relative path).
    """

    title: str
    pictures: list[tuple[str, str]]
    metrics: list[tuple[str, dict[str, float]]]
    links: list[tuple[str, str]]


@dataclass
class PageSection:
    """A section of its own after the images (the pass of several images of one spacecraft).

    Attributes:
        title: heading; text: paragraphs of plain text; metric_labels: {metric key: column
        heading}; rows: (method label, {metric key: value}); figures: (relative path,
        caption) shown wide; pictures: (relative path, caption) in display order; links:
        (label, relative path).
    """

    title: str
    text: list[str]
    metric_labels: dict[str, str]
    rows: list[tuple[str, dict[str, float]]]
    figures: list[tuple[str, str]] = field(default_factory=list)
    pictures: list[tuple[str, str]] = field(default_factory=list)
    links: list[tuple[str, str]] = field(default_factory=list)


@dataclass
class DemoPage:
    """Everything the page shows.

    Attributes:
        title: the page's title; intro: paragraphs of plain text.
        metric_labels: {metric key: column heading}, in column order.
        summary: (method label, {metric key: mean over the images}) rows.
        figures: extra (relative path, caption) pictures shown wide (training curves).
        images: one :class:`PageImage` per image; sections: :class:`PageSection` s shown
        after the images; files: (label, relative path) links.
    """

    title: str
    intro: list[str]
    metric_labels: dict[str, str]
    summary: list[tuple[str, dict[str, float]]]
    figures: list[tuple[str, str]] = field(default_factory=list)
    images: list[PageImage] = field(default_factory=list)
    sections: list[PageSection] = field(default_factory=list)
    files: list[tuple[str, str]] = field(default_factory=list)


def _value(value: float) -> str:
    return f"{value:.3f}" if math.isfinite(value) else "n/a"


def _html_table(labels: dict[str, str], rows: Sequence[tuple[str, dict[str, float]]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in ("method", *labels.values()))
    body = "".join(
        "<tr><td>" + html.escape(name) + "</td>"
        + "".join(f"<td>{_value(values.get(k, math.nan))}</td>" for k in labels) + "</tr>"
        for name, values in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _markdown_table(labels: dict[str, str], rows: Sequence[tuple[str, dict[str, float]]]
                    ) -> str:
    from sq_mitsuba.evaluation.tables import markdown_table

    table = markdown_table(
        ["method", *labels.values()],
        [[name, *(_value(values.get(k, math.nan)) for k in labels)] for name, values in rows])
    return table.rstrip("\n")


def _figure(path: str, caption: str, wide: bool = False) -> str:
    attribute = ' class="wide"' if wide else ""
    return (f'<figure{attribute}><a href="{html.escape(path)}"><img src="{html.escape(path)}" '
            f'alt="{html.escape(caption)}"></a><figcaption>{html.escape(caption)}'
            "</figcaption></figure>")


def _links_html(links: Sequence[tuple[str, str]]) -> str:
    return "<ul>" + "".join(f'<li><a href="{html.escape(path)}">{html.escape(label)}</a></li>'
                            for label, path in links) + "</ul>"


def page_html(page: DemoPage) -> str:
    """The HTML text of ``page``."""
    parts = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
             f"<title>{html.escape(page.title)}</title>", f"<style>\n{_STYLE}\n</style>",
             f"<script>\n{BROKEN_IMAGES_SCRIPT}\n</script>", "</head>", "<body>",
             f"<h1>{html.escape(page.title)}</h1>"]
    parts += [f"<p>{html.escape(text)}</p>" for text in page.intro]
    parts.append("<h2>Summary: mean over the images</h2>")
    parts.append(_html_table(page.metric_labels, page.summary))
    for path, caption in page.figures:
        parts.append(_figure(path, caption, wide=True))
    parts.append("<h2>Images</h2>")
    for image in page.images:
        parts.append(f"<section><h3>{html.escape(image.title)}</h3>")
        parts.append("<div>" + "".join(_figure(p, c) for p, c in image.pictures) + "</div>")
        parts.append(_html_table(page.metric_labels, image.metrics))
        parts.append(_links_html(image.links))
        parts.append("</section>")
    for section in page.sections:
        parts.append(f"<h2>{html.escape(section.title)}</h2>")
        parts += [f"<p>{html.escape(text)}</p>" for text in section.text]
        parts.append(_html_table(section.metric_labels, section.rows))
        parts += [_figure(path, caption, wide=True) for path, caption in section.figures]
        parts.append("<div>" + "".join(_figure(p, c) for p, c in section.pictures) + "</div>")
        parts.append(_links_html(section.links))
    if page.files:
        parts.append("<h2>Files</h2>")
        parts.append(_links_html(page.files))
    parts += ["</body>", "</html>"]
    return "\n".join(parts) + "\n"


def page_markdown(page: DemoPage) -> str:
    """The Markdown twin of ``page``: the same text, tables, pictures and links (a name or
    caption shown as typed: :func:`~sq_mitsuba.evaluation.tables.markdown_text`)."""
    from sq_mitsuba.evaluation.tables import markdown_text

    lines = [f"# {page.title}", ""]
    for text in page.intro:
        lines += [text, ""]
    lines += ["## Summary: mean over the images", "",
              _markdown_table(page.metric_labels, page.summary), ""]
    for path, caption in page.figures:
        lines += [f"![{markdown_text(caption)}]({path})", "", f"*{caption}*", ""]
    lines += ["## Images", ""]
    for image in page.images:
        lines += [f"### {markdown_text(image.title)}", ""]
        lines.append(" ".join(f"![{markdown_text(c)}]({p})" for p, c in image.pictures))
        lines += ["", "Pictures, left to right: " + "; ".join(c for _, c in image.pictures)
                  + ".", ""]
        lines += [_markdown_table(page.metric_labels, image.metrics), ""]
        lines += [f"- [{markdown_text(label)}]({path})" for label, path in image.links]
        lines.append("")
    for section in page.sections:
        lines += [f"## {section.title}", ""]
        for text in section.text:
            lines += [text, ""]
        lines += [_markdown_table(section.metric_labels, section.rows), ""]
        for path, caption in section.figures:
            lines += [f"![{markdown_text(caption)}]({path})", "", f"*{caption}*", ""]
        if section.pictures:
            lines.append(" ".join(f"![{markdown_text(c)}]({p})" for p, c in section.pictures))
            lines += ["", "Pictures, left to right: "
                      + "; ".join(c for _, c in section.pictures) + ".", ""]
        lines += [f"- [{markdown_text(label)}]({path})" for label, path in section.links]
        lines.append("")
    if page.files:
        lines += ["## Files", ""]
        lines += [f"- [{markdown_text(label)}]({path})" for label, path in page.files]
        lines.append("")
    return "\n".join(lines)


def write_page(out_dir: str | Path, page: DemoPage) -> tuple[Path, Path]:
    """Write ``index.html`` and ``index.md`` into ``out_dir`` (atomically); returns both."""
    out_dir = Path(out_dir)
    atomic_write_text(out_dir / PAGE_FILE, page_html(page))
    atomic_write_text(out_dir / MARKDOWN_FILE, page_markdown(page))
    return out_dir / PAGE_FILE, out_dir / MARKDOWN_FILE
