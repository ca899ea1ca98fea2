"""Tables from evaluation rows, and the paper-style report collated from them."""

from __future__ import annotations

import csv
import zlib

import numpy as np
import pytest

from sq_mitsuba.evaluation.report import PAPER_TABLES, read_eval_folder, write_report
from sq_mitsuba.evaluation.scoring import METRICS
from sq_mitsuba.evaluation.tables import summarise, write_tables
from sq_mitsuba.geometry.rotation import mean_rotation, random_rotations
from sq_mitsuba.io import atomic_write_json


def _rows(seed: int, offset: float) -> list[dict]:
    rng = np.random.default_rng(seed)
    rows = []
    for method in ("network", "baseline", "refined_gt"):  # the last a reference: -1 better
        for model in ("sat_a", "sat_b"):
            for index in range(5):
                row = {"model": model, "index": index, "method": method, "filename": ""}
                shift = offset - (1.0 if method == "refined_gt" else 0.0)
                row.update({m: float(rng.uniform(0, 1) + shift) for m in METRICS})
                rows.append(row)
    return rows


def _eval_folder(path, split: str, label: str, offset: float):
    # A seed that is the same in every process (Python's str hash is salted per process: one
    # salt in about 70 drew two rows equal to the table's three decimals).
    rows = _rows(zlib.crc32(f"{split}|{label}".encode()) % 1000, offset)
    write_tables(rows, path)
    atomic_write_json(path / "eval.json", {"split": split, "label": label,
                                           "num_primitives": 5})
    return rows


def test_summary_matches_numpy(tmp_path):
    rows = _eval_folder(tmp_path, "val", "run", 0.0)
    stats = summarise(rows)[("network",)]["iou_2d"]
    values = np.array([r["iou_2d"] for r in rows if r["method"] == "network"])
    assert stats == pytest.approx((values.mean(), values.std(), np.median(values)))
    with open(tmp_path / "per_image.csv", newline="") as handle:
        assert len(list(csv.DictReader(handle))) == len(rows)
    folder = read_eval_folder(tmp_path)
    assert folder["summary"]["network"]["iou_2d"] == pytest.approx(stats[:2])
    for name in ("summary.md", "per_model.csv", "per_model.md"):
        assert (tmp_path / name).stat().st_size > 0


def test_report_holds_ours_and_the_papers_numbers_with_the_best_in_bold(tmp_path):
    for split in ("val", "test"):
        _eval_folder(tmp_path / "good" / split, split, "good", 0.0)
        _eval_folder(tmp_path / "bad" / split, split, "bad", 5.0)
    folders = [tmp_path / run / split for run in ("good", "bad") for split in ("val", "test")]
    report = write_report(folders, tmp_path / "report").read_text()
    assert PAPER_TABLES.is_file()
    assert "0.054 ± 0.026" in report  # paper Table 1 (a), validation Chamfer-L1
    assert "0.137 ± 0.081" in report  # paper Table 2, M = 8, test Chamfer-L1
    good = read_eval_folder(tmp_path / "good" / "val")["summary"]["network"]["chamfer_l1_paper"]
    assert f"{good[0]:.3f} ± {good[1]:.3f}" in report
    # Ours and the paper's are not ranked together: the best of our rows in bold (the "bad"
    # run is 5 worse everywhere), the best of the paper's rows in italics.
    ours, paper = _column(report, "Table 1", 1)
    assert _bold(ours) == [_best(ours, min)]
    assert "| paper (a) chamfer + reprojection | *0.054 ± 0.026* |" in report
    assert [cell for cell in paper if cell.startswith("*")] == ["*0.054 ± 0.026*"]
    assert "**0.054 ± 0.026**" not in report
    assert "**bold**: the best of our methods' rows" in report
    assert "Not directly comparable" in report
    text = (tmp_path / "report" / "report.csv").read_text()
    assert "*" not in text
    rows = list(csv.reader(text.splitlines()))
    assert any(f"{good[0]:.3f} ± {good[1]:.3f}" in row for row in rows[1:])


def _mean(cell: str) -> float:
    return float(cell.strip("*").split(" ± ")[0])


def _bold(cells: list[str]) -> list[str]:
    return [cell for cell in cells if cell.startswith("**")]


def _best(cells: list[str], pick) -> str:
    """The cell of ``pick``'s mean (min or max), as bold."""
    return f"**{pick(cells, key=_mean).strip('*')}**"


def _column(report: str, table: str, index: int) -> tuple[list[str], list[str]]:
    """Cells of column ``index`` of ``table`` in report.md: our methods' rows', the paper's
    rows'. The baseline's rows, a reference, are never bold (checked here) nor ranked."""
    section = report.split(f"## {table}")[1].split("## ")[0]
    rows = [line.strip("|").split(" | ") for line in section.splitlines()
            if line.startswith("| ") and not line.startswith("| run ")]
    reference = ("(baseline)", "(refined_gt)")
    references = [r[index].strip() for r in rows if r[0].strip().endswith(reference)]
    assert len(references) >= 2 and not _bold(references)
    ours = [r[index].strip() for r in rows if not r[0].strip().startswith("paper")
            and not r[0].strip().endswith(reference)]
    paper = [r[index].strip() for r in rows if r[0].strip().startswith("paper")]
    return ours, paper


def test_report_bolds_among_our_rows_even_where_the_paper_is_better(tmp_path):
    """Our runs far worse than the paper's: still the best of ours in bold, never a paper
    value."""
    for run, offset in (("a", 10.0), ("b", 20.0)):
        _eval_folder(tmp_path / run / "val", "val", run, offset)
    report = write_report([tmp_path / "a" / "val", tmp_path / "b" / "val"],
                          tmp_path / "report").read_text()
    for index in (1, 2):  # val Chamfer-L1 and E_R, lower is better
        ours, paper = _column(report, "Table 1", index)
        assert _bold(ours) == [_best(ours, min)]
        assert not any(c.startswith("**") for c in paper)
    ours, _ = _column(report, "Table 1", 3)  # val IoU, higher is better
    assert _bold(ours) == [_best(ours, max)]


def test_report_labels_a_run_as_its_eval_json_records(tmp_path):
    _eval_folder(tmp_path / "folder_name" / "val", "val", "config (a), 16 epochs", 0.0)
    # A label with quotes and a comma stays one cell of report.csv (written by the csv module).
    quoted = 'run "A", v2'
    _eval_folder(tmp_path / "quoted" / "val", "val", quoted, 1.0)
    report = write_report([tmp_path / "folder_name" / "val", tmp_path / "quoted" / "val"],
                          tmp_path / "report").read_text()
    assert "| config (a), 16 epochs |" in report and "folder_name" not in report
    with open(tmp_path / "report" / "report.csv", newline="") as handle:
        header, *rows = list(csv.reader(handle))
    assert all(len(row) == len(header) for row in rows)
    assert {row[1] for row in rows if row[0].startswith("Table 1")} >= \
        {"config (a), 16 epochs", quoted}
    # An eval.json without a label: the checkpoint's run folder, as `sq-mitsuba eval` names it.
    folder = tmp_path / "other" / "test"
    _eval_folder(folder, "test", "x", 0.0)
    atomic_write_json(folder / "eval.json", {"split": "test", "num_primitives": 5,
                                             "checkpoint": "/runs/stage3/best.pt"})
    assert read_eval_folder(folder)["label"] == "stage3"
    # A relative checkpoint path that names no folder ('../best.pt' was labelled '..').
    for checkpoint in ("../best.pt", "./best.pt", "best.pt"):
        atomic_write_json(folder / "eval.json", {"split": "test", "num_primitives": 5,
                                                 "checkpoint": checkpoint})
        assert read_eval_folder(folder)["label"] == "best"


def test_report_refuses_a_folder_that_is_not_an_evaluation(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"eval\.json: missing"):
        write_report([tmp_path], tmp_path / "out")
    with pytest.raises(ValueError, match="at least one"):
        write_report([], tmp_path / "out")


def test_mean_rotation_is_a_rotation_and_the_mean_of_equal_rotations():
    import torch

    rotation = random_rotations(1, torch.Generator().manual_seed(0), torch.float64)
    assert torch.allclose(mean_rotation(rotation.expand(5, 3, 3)), rotation[0], atol=1e-12)
    spread = mean_rotation(random_rotations(50, torch.Generator().manual_seed(1),
                                            torch.float64))
    assert torch.allclose(spread @ spread.T, torch.eye(3, dtype=torch.float64), atol=1e-10)
    assert float(torch.linalg.det(spread)) == pytest.approx(1.0)


def test_report_command(tmp_path, capsys):
    from sq_mitsuba.cli import main

    _eval_folder(tmp_path / "run" / "val", "val", "run", 0.0)
    assert main(["report", str(tmp_path / "run" / "val"), "--out", str(tmp_path / "r")]) == 0
    assert "0.594 ± 0.183" in (tmp_path / "r" / "report.md").read_text()
    assert main(["report", str(tmp_path / "nothing"), "--out", str(tmp_path / "r2")]) == 2
    assert capsys.readouterr().err.strip().endswith(f"{tmp_path / 'nothing'}: no such folder")
    (tmp_path / "empty").mkdir()
    assert main(["report", str(tmp_path / "empty"), "--out", str(tmp_path / "r2")]) == 2
    assert "empty/eval.json: missing (not an evaluation folder?)" in capsys.readouterr().err
    # An evaluation still writing (or stopped): its journal is there, and said so.
    (tmp_path / "empty" / ".eval_partial").mkdir()
    assert main(["report", str(tmp_path / "empty"), "--out", str(tmp_path / "r2")]) == 2
    assert ("empty/eval.json: missing (an evaluation still running, or stopped before its "
            "tables (`sq-mitsuba eval --resume` finishes it))") in capsys.readouterr().err


def test_a_val_and_a_test_of_two_networks_under_one_label_are_refused(tmp_path):
    """Two exports in one folder get one default label: their val and test must not share a
    row. The eval.json files record the weights' sha256; the same weights pass."""
    for split, sha in (("val", "a" * 64), ("test", "b" * 64), ("again", "a" * 64)):
        _eval_folder(tmp_path / split, "test" if split == "again" else split, "exp", 0.0)
        atomic_write_json(tmp_path / split / "eval.json", {
            "split": "test" if split == "again" else split, "label": "exp",
            "num_primitives": 5, "identity": {"checkpoint": {"sha256": sha}}})
    with pytest.raises(ValueError, match=rf"^{tmp_path / 'test'}: run 'exp' evaluates another "
                                         rf"model \(weights and stored baseline bbbbbbbbbbbb\) "
                                         rf"than {tmp_path / 'val'} \(aaaaaaaaaaaa; a "
                                         r"checkpoint and its export differ too\); name the "
                                         "runs apart with eval --label"):
        write_report([tmp_path / "val", tmp_path / "test"], tmp_path / "report")
    assert not (tmp_path / "report").exists()
    assert "| exp |" in write_report([tmp_path / "val", tmp_path / "again"],
                                     tmp_path / "report").read_text()


@pytest.mark.parametrize(("old", "new", "named"), [
    ('chamfer_convention = "paper"', 'chamfer_convention = "occnet"',
     "source.chamfer_convention 'occnet': the report compares our 'paper'-convention "
     "Chamfer-L1 (chamfer_l1_paper) with the paper's, so its numbers must be in that "
     "convention ('paper')"),
    ("[source]\n", "[source]\nbogus = 1\n",
     "source.bogus: unknown key (expected title and chamfer_convention)"),
    ('chamfer_convention = "paper"\n', "",
     "source.chamfer_convention: missing (the report compares Chamfer-L1 in the 'paper' "
     "convention: say so)"),
    ("title = ", "title = 3 # ", "source.title: expected a name, got 3"),
], ids=["another convention", "unknown key", "no convention", "title not text"])
def test_report_reads_the_papers_source_strictly(old, new, named, tmp_path, capsys):
    """The [source] table says which Chamfer convention the paper's numbers use; the report
    compares them with our 'paper' column and says both use it: another convention, an
    unknown key or none stated is refused (one line naming it), nothing written."""
    from sq_mitsuba.cli import main

    _eval_folder(tmp_path / "run" / "val", "val", "run", 0.0)
    text = PAPER_TABLES.read_text()
    assert old in text
    paper = tmp_path / "paper.toml"
    paper.write_text(text.replace(old, new, 1))
    out = tmp_path / "report"
    assert main(["report", str(tmp_path / "run" / "val"), "--out", str(out), "--paper",
                 str(paper)]) == 2
    assert capsys.readouterr().err.strip() == \
        f"sq-mitsuba report: error: paper tables {paper}: {named}"
    assert not out.exists()
    # The file as shipped passes, and the note says what it checked.
    assert main(["report", str(tmp_path / "run" / "val"), "--out", str(out), "--paper",
                 str(PAPER_TABLES)]) == 0
    assert "Both use the 'paper' Chamfer convention" in (out / "report.md").read_text()
