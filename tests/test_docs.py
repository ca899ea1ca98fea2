"""The documentation runs as written: the Python snippets of the README and of the guides
under docs/ execute, their command lines and the ``--set`` examples of every ``--help`` parse,
and every relative link of every page reaches its file and heading."""

from __future__ import annotations

import argparse
import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from sq_mitsuba.cli import build_parser
from sq_mitsuba.cli._options import SET_CLASS
from sq_mitsuba.config import apply_overrides

ROOT = Path(__file__).resolve().parents[1]
# The README and the guides under docs/, read as one text.
README = "\n".join(path.read_text(encoding="utf-8")
                   for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))])

# Each snippet runs in a fresh namespace of one interpreter (one torch import for all), in a
# folder that holds the run the training section loads (runs/cpu/best.pt).
_RUNNER = """
import sys, traceback
failed = 0
for index, code in enumerate(sys.argv[1:]):
    try:
        exec(compile(code, f"README snippet {index}", "exec"), {"__name__": "__main__"})
    except Exception:
        failed += 1
        print(f"README snippet {index} failed:", file=sys.stderr)
        traceback.print_exc()
sys.exit(failed)
"""


def _python_snippets() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README, re.S)


@pytest.mark.slow
def test_readme_python_snippets_run_as_written(eval_checkpoint, tmp_path):
    snippets = _python_snippets()
    assert len(snippets) >= 4
    (tmp_path / "runs" / "cpu").mkdir(parents=True)
    shutil.copyfile(eval_checkpoint, tmp_path / "runs" / "cpu" / "best.pt")
    done = subprocess.run([sys.executable, "-W", "error::UserWarning", "-c", _RUNNER,
                           *snippets], cwd=tmp_path, capture_output=True, text=True,
                          timeout=300, env={**_environment(), "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr[-3000:]
    assert not done.stderr.strip(), done.stderr[-3000:]  # no warnings either
    assert (tmp_path / "a.glb").stat().st_size > 0 and (tmp_path / "primitive.glb").is_file()


def _environment() -> dict[str, str]:
    import os

    return dict(os.environ)


def _without_optional(text: str) -> str:
    """``text`` without its ``[...]`` groups (optional parts; nested ones included)."""
    while True:
        shorter = re.sub(r"\s*\[[^\[\]]*\]", "", text)
        if shorter == text:
            return text
        text = shorter


def _readme_commands() -> list[list[str]]:
    """Every ``sq-mitsuba`` command line of the README's shell blocks, as arguments (optional
    ``[...]`` parts dropped; lines that elide with ``...`` skipped)."""
    commands = []
    for block in re.findall(r"```(?:bash|sh)\n(.*?)```", README, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = _without_optional(line.split(" #")[0].strip())
            match = re.search(r"(?:^|\s|/)sq-mitsuba\s+(.*)", line)
            if not match or "..." in line or "$(" in line:
                continue
            commands.append(shlex.split(match.group(1)))
    return commands


def _set_values(argv: list[str]) -> list[str]:
    return [argv[i + 1] for i, word in enumerate(argv[:-1]) if word == "--set"]


def _leaf_parser(argv: list[str]) -> argparse.ArgumentParser:
    """The parser of the (sub)command that ``argv`` names."""
    parser = build_parser(argv[0])
    for word in argv:
        children = next((a.choices for a in parser._actions
                         if isinstance(a, argparse._SubParsersAction)), None)
        if not children or word not in children:
            break
        parser = children[word]
    return parser


@pytest.mark.parametrize("argv", _readme_commands(), ids=lambda a: " ".join(a[:2]))
def test_readme_command_lines_parse(argv):
    namespace = build_parser(argv[0]).parse_args(argv)  # SystemExit on an unknown option
    assert namespace.command == argv[0]
    config_class = _leaf_parser(argv).get_default(SET_CLASS)
    if config_class is not None:
        apply_overrides(config_class(), _set_values(argv))


def test_the_readme_commands_were_found():
    found = {tuple(argv[:2]) for argv in _readme_commands()}
    assert {("predict", "photo.png"), ("fit", "--masks"), ("train", "--config"),
            ("dataset", "render"), ("report", "runs/cpu/val")} <= found


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
             ) -> list[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    found = [(path, parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                found += _parsers(child, (*path, name))
    return found


def _override_class(path: tuple[str, ...], parser: argparse.ArgumentParser) -> type | None:
    """The config class a command's ``--set`` changes (``train``'s is its TrainConfig, the
    ``study`` group's help is its subcommand's)."""
    if path == ("train",):
        from sq_mitsuba.training.config import TrainConfig

        return TrainConfig
    if path == ("study",):
        from sq_mitsuba.evaluation.study import StudyOptions

        return StudyOptions
    return parser.get_default(SET_CLASS)


HELP_EXAMPLES = [
    (path, example, _override_class(path, parser))
    for path, parser in _parsers(build_parser())
    for example in sorted(set(
        re.findall(r"--set\s+([a-z_][\w.]*=[^\s,;)]*[^\s,;).])", parser.format_help())
        + re.findall(r"e\.g\.\s+([a-z_][\w.]*=[^\s,;)]*[^\s,;).])", parser.format_help())))
    if not example.startswith("key=")  # the placeholder of "--set key=value"
]


def test_every_set_option_shows_an_example():
    with_set = {path for path, parser in _parsers(build_parser())
                if any("--set" in a.option_strings for a in parser._actions)}
    assert with_set <= {path for path, _, _ in HELP_EXAMPLES}
    assert len(with_set) >= 7


@pytest.mark.parametrize(("path", "example", "config_class"), HELP_EXAMPLES,
                         ids=[f"{' '.join(p)}: {e}" for p, e, _ in HELP_EXAMPLES])
def test_help_examples_parse(path, example, config_class):
    assert config_class is not None, f"{' '.join(path)}: --set of which config?"
    apply_overrides(config_class(), [example])


def test_every_optional_value_shows_its_default():
    """An option that takes a value and may be left out says what leaving it out means."""
    missing = []
    for path, parser in _parsers(build_parser()):
        grouped = {a for g in parser._mutually_exclusive_groups if g.required
                   for a in g._group_actions}
        for action in parser._actions:
            if (not action.option_strings or action.required or action in grouped
                    or action.nargs == 0 or isinstance(action, argparse._AppendAction)
                    or isinstance(action, argparse.BooleanOptionalAction)):
                continue
            if "default" not in (action.help or "").lower():
                missing.append(f"{' '.join(path)} {action.option_strings[0]}")
    assert not missing, missing


# Every markdown page of the repository (the virtual environment and build outputs aside).
_SKIPPED = {".venv", "demo_output", ".pytest_cache"}
_PAGES = sorted(path for path in ROOT.rglob("*.md")
                if not _SKIPPED & set(path.relative_to(ROOT).parts))
_FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)
_CODE_SPAN = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"\]\(([^)\s]+)\)")


def _slugs(page: Path) -> Iterator[str]:
    """The anchors GitHub gives a page's headings: lower case, punctuation dropped, spaces as
    hyphens, a repeated heading numbered -1, -2, ..."""
    seen: dict[str, int] = {}
    for line in _FENCE.sub("", page.read_text(encoding="utf-8")).splitlines():
        heading = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not heading:
            continue
        text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.group(1))
        slug = re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        yield slug if count == 0 else f"{slug}-{count}"


def test_the_pages_were_found():
    names = {path.relative_to(ROOT).as_posix() for path in _PAGES}
    assert {"README.md", "eval/MODEL_CARD.md", "eval/experiments/README.md"} <= names


@pytest.mark.parametrize("page", _PAGES, ids=lambda path: path.relative_to(ROOT).as_posix())
def test_relative_links_reach_a_file_and_heading(page: Path):
    """A link to a file of the repository names one that exists, and a link to a heading
    (``page.md#anchor`` or ``#anchor``) names one that page has: moving a section or a file
    cannot leave a dead link behind."""
    text = _CODE_SPAN.sub("", _FENCE.sub("", page.read_text(encoding="utf-8")))
    dead = []
    for target in _LINK.findall(text):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        linked = (page.parent / path).resolve() if path else page
        if not linked.exists():
            dead.append(f"{target} (no such file)")
        elif anchor and linked.suffix == ".md" and anchor not in set(_slugs(linked)):
            dead.append(f"{target} (no such heading)")
    assert not dead, f"{page.relative_to(ROOT)}: dead links: {dead}"
