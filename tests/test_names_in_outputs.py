"""Users' names (models, labels, checkpoint paths) shown in figures and Markdown as written.

A '$' in a name is not mathtext (an unbalanced one failed the figure after the evaluation had
scored every image; a balanced one was drawn as a formula); a '|' or '*' in a name is not
Markdown (a '|' added a column, '*b*' read as report.md's mark of the best); the default eval
label is the checkpoint's real folder name; report replaces only a report it wrote.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
from output_checks import error_line, one_torch_thread  # noqa: F401 (autouse fixture)

from sq_mitsuba.cli import main
from sq_mitsuba.evaluation.evaluate import default_label
from sq_mitsuba.evaluation.report import write_report
from sq_mitsuba.evaluation.scoring import METRICS
from sq_mitsuba.evaluation.tables import write_tables
from sq_mitsuba.io import atomic_write_json

#: An unbalanced name (mathtext fails on it) and a balanced one (drawn as a formula).
MATH_NAMES = ("cube $^$", "twin $x_1$")


def _drawn(text) -> tuple[str, bool]:
    """What matplotlib draws for a Text artist: (the string, whether as mathtext)."""
    return text._preprocess_math(text.get_text())


def _capture(monkeypatch, module) -> list:
    """The figures ``module.save_figure`` saves (it still saves them: drawing is the test)."""
    saved, original = [], module.save_figure

    def keep(figure, path):
        saved.append(figure)
        return original(figure, path)

    monkeypatch.setattr(module, "save_figure", keep)
    return saved


def _cells(line: str) -> list[str]:
    """The cells of a Markdown table row: split at the '|' not escaped."""
    return re.split(r"(?<!\\)\|", line.strip())[1:-1]


# ------------------------------------------------------------------------- D7: mathtext


def test_per_model_figure_draws_names_with_dollars_as_written(tmp_path, monkeypatch):
    import sq_mitsuba.io
    from sq_mitsuba.evaluation.figures import plot_per_model

    saved = _capture(monkeypatch, sq_mitsuba.io)
    rows = [{"model": model, "method": method, **{m: 0.5 + k for m in METRICS}}
            for k, model in enumerate(MATH_NAMES) for method in ("network", "my $m$")]
    assert plot_per_model(rows, tmp_path / "per_model.png").stat().st_size > 0
    figure = saved[0]
    ticks = {_drawn(t) for t in figure.axes[-1].get_xticklabels()}
    assert ticks == {(name, False) for name in MATH_NAMES}
    legend = {_drawn(t) for t in figure.axes[0].get_legend().get_texts()}
    assert legend == {("network", False), ("my $m$", False)}


def test_illumination_figure_draws_its_title_and_names_as_written(tmp_path, monkeypatch):
    from matplotlib.text import Text

    import sq_mitsuba.io
    from sq_mitsuba.evaluation.figures import plot_illumination

    saved = _capture(monkeypatch, sq_mitsuba.io)
    table = [{"method": "network", "background": "my $x$", "phase_deg": phase,
              "iou_2d_mean": 0.5, "iou_2d_std": 0.1} for phase in (15.0, 45.0)]
    plot_illumination(table, tmp_path / "lighting.png", ["iou_2d"], "data $^$/per_image.csv")
    texts = [_drawn(t) for t in saved[0].findobj(Text) if "$" in t.get_text()]
    assert texts and not any(math for _, math in texts)
    assert any(text.startswith("data $^$/per_image.csv\n") for text, _ in texts)
    assert ("my $x$, network", False) in texts


@pytest.fixture(scope="module")
def math_dataset(train_dataset, tmp_path_factory) -> Path:
    """:func:`train_dataset` with its two train models named :data:`MATH_NAMES`."""
    root = tmp_path_factory.mktemp("names") / "data $x$"
    root.mkdir()
    shutil.copy(train_dataset / "camera.json", root)
    lines, names = [], iter(MATH_NAMES)
    for line in (train_dataset / "splits.csv").read_text().splitlines():
        model, split = line.rsplit(",", 1)
        name = next(names) if split == "train" else model
        shutil.copytree(train_dataset / model, root / name)
        lines.append(f"{name},{split}\n")
    (root / "splits.csv").write_text("".join(lines))
    return root


def test_dataset_preview_draws_model_names_as_written(math_dataset, tmp_path, monkeypatch):
    import sq_mitsuba.data.spe3r.preview as preview

    saved = _capture(monkeypatch, preview)
    out = preview.preview_dataset(math_dataset, tmp_path / "sheet.png", count=3)
    assert out.stat().st_size > 0
    titles = [_drawn(axis.title) for axis in saved[0].axes if axis.get_title()]
    assert set(MATH_NAMES) <= {text.split(" 0")[0] for text, _ in titles}
    assert not any(math for _, math in titles)


def test_eval_of_models_named_with_dollars_writes_its_figures(math_dataset, eval_checkpoint,
                                                              tmp_path):
    """It failed drawing per_model.png, after scoring every image, and removed --out."""
    out = tmp_path / "ev"
    assert main(["eval", "--checkpoint", str(eval_checkpoint), "--data", str(math_dataset),
                 "--split", "val", "--out", str(out), "--set", "surface_points=500",
                 "--set", "volume_points=3000", "--set", "qualitative=2",
                 "--set", "consistency_views=2", "--quiet"]) == 0
    for name in ("per_model.png", "qualitative.png", "consistency.png"):
        assert (out / name).stat().st_size > 0
    markdown = (out / "per_model.md").read_text()
    assert "| cube \\$^\\$ | network |" in markdown


# ------------------------------------------------------------------------- D8: Markdown


def test_markdown_text_and_code_show_names_as_written():
    from sq_mitsuba.evaluation.tables import markdown_code, markdown_text

    assert markdown_text("a|b *c* _d_ <b> [l](u) `x` $y$ ~z~ \\ &lt;") == (
        "a\\|b \\*c\\* \\_d\\_ \\<b\\> \\[l\\](u) \\`x\\` \\$y\\$ \\~z\\~ \\\\ \\&lt;")
    # What is no markup stays as it is: numbers, words joined by '_', a lone '&'.
    for text in ("0.123 ± 0.045 (0.100)", "-1e-05", "n/a", "refined_gt", "run (refined_gt)",
                 "R&D"):
        assert markdown_text(text) == text
    assert markdown_text("two\nlines") == "two lines"
    assert markdown_code("ck <b>/m.pt") == "`ck <b>/m.pt`"
    assert markdown_code("a`b") == "``a`b``"
    assert markdown_code("`x ") == "`` `x  ``"


def test_per_model_markdown_keeps_a_name_with_a_bar_in_one_cell(tmp_path):
    rows = [{"model": model, "index": 0, "method": "network", "filename": "",
             **{m: 0.5 for m in METRICS}} for model in ("a|b", "*c*")]
    write_tables(rows, tmp_path)
    table = [line for line in (tmp_path / "per_model.md").read_text().splitlines()
             if line.startswith("|")]
    assert len({len(_cells(line)) for line in table}) == 1
    assert [_cells(line)[0].strip() for line in table[2:]] == ["\\*c\\*", "a\\|b"]


def _eval_folder(path: Path, split: str, label: str, offset: float) -> None:
    rows = [{"model": "sat", "index": k, "method": "network", "filename": "",
             **{m: 0.1 * k + offset for m in METRICS}} for k in range(3)]
    write_tables(rows, path)
    atomic_write_json(path / "eval.json", {"split": split, "label": label, "num_primitives": 5})


def test_report_shows_labels_as_text_not_markdown(tmp_path):
    """'*b*' read as italics, report.md's mark of the paper's best; a '|' (in a label an
    earlier default wrote) added a column."""
    _eval_folder(tmp_path / "b", "val", "*b*", 0.0)
    _eval_folder(tmp_path / "x", "val", "ck|x", 1.0)
    markdown = write_report([tmp_path / "b", tmp_path / "x"], tmp_path / "r").read_text()
    table = markdown.split("## Table 1")[1].split("## ")[0]
    rows = [line for line in table.splitlines() if line.startswith("|")]
    assert len({len(_cells(line)) for line in rows}) == 1
    labels = [_cells(line)[0].strip() for line in rows]
    assert "\\*b\\*" in labels and "ck\\|x" in labels
    assert "**" in table  # the best of our rows is still bold


def test_demo_page_shows_the_checkpoint_path_in_a_code_span(tmp_path):
    from sq_mitsuba.apps.demo_files import write_demo_page

    options = SimpleNamespace(preset=SimpleNamespace(resolution=64, refine_steps=3), seed=1)
    checkpoint = 'ck <b>&"x" #1/my *model* é.pt'
    _, markdown = write_demo_page(tmp_path, options, [], {}, checkpoint, "computed here",
                                  False, {"render": 1.0}, 2.0)
    assert f"Model: `{checkpoint}`." in markdown.read_text()


# ---------------------------------------------------------------------- D9: default label


def test_default_label_is_the_real_folder_and_a_valid_label(tmp_path, monkeypatch):
    (tmp_path / "run" / "sub").mkdir(parents=True)
    monkeypatch.chdir(tmp_path / "run" / "sub")
    assert default_label(SimpleNamespace(source=Path("../best.pt"))) == "run"
    assert default_label(SimpleNamespace(source=Path("./best.pt"))) == "sub"
    # What --label refuses ('|', line breaks: a row of report.md) is never the default.
    assert default_label(SimpleNamespace(source=Path("ck|x/best.pt"))) == "ck_x"
    assert default_label(SimpleNamespace(source=Path("/best.pt"))) == "best"
    assert default_label(SimpleNamespace(source=None)) == "model"


# --------------------------------------------------- D2: report replaces only its own files


@pytest.mark.parametrize("name", ["report.md", "report.csv"])
def test_report_refuses_a_users_file_of_its_names(name, tmp_path, capsys):
    _eval_folder(tmp_path / "ev", "val", "run", 0.0)
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / name).write_text("MY NOTES\n")
    with pytest.raises(ValueError, match=re.escape(f"{notes / name}: an output of report")):
        write_report([tmp_path / "ev"], notes)
    assert main(["report", str(tmp_path / "ev"), "--out", str(notes)]) == 2
    assert f"{notes / name}: an output of report, but no earlier report wrote it" in \
        error_line(capsys)
    assert [p.name for p in notes.iterdir()] == [name]
    assert (notes / name).read_text() == "MY NOTES\n"


def test_report_replaces_its_own_earlier_report(tmp_path):
    _eval_folder(tmp_path / "a", "val", "first", 0.0)
    _eval_folder(tmp_path / "b", "val", "second", 0.0)
    assert "first" in write_report([tmp_path / "a"], tmp_path / "r").read_text()
    markdown = write_report([tmp_path / "b"], tmp_path / "r").read_text()
    assert "second" in markdown and "first" not in markdown
    assert "second" in (tmp_path / "r" / "report.csv").read_text()
