"""Every ``--help`` works, and options built from config fields show the config's defaults.

The parsers are walked generically from :func:`sq_mitsuba.cli.build_parser`: every subcommand
and sub-subcommand. ``add_config_options`` records, as parser defaults, which field each option
sets (``_config_flags``) and of which config class (``_config_classes``); the default shown in
the help must be the one of a fresh instance of that class.
"""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from sq_mitsuba.cli import build_parser, command_names, main


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
          ) -> list[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """(command path, parser) of ``parser`` and of every parser below it."""
    found = [(path, parser)]
    for name, child in _subparsers(parser).items():
        found += _walk(child, (*path, name))
    return found


PARSERS = _walk(build_parser())
COMMANDS = [path for path, _ in PARSERS]


def test_every_module_registers_the_command_named_after_it():
    # main() relies on it to build only the parser of the command it runs.
    assert sorted(_subparsers(build_parser())) == command_names()


@pytest.mark.parametrize("path", COMMANDS, ids=lambda p: " ".join(p) or "sq-mitsuba")
def test_help_exits_zero(path, capsys):
    with pytest.raises(SystemExit) as stop:
        main([*path, "--help"])
    assert stop.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: sq-mitsuba")
    assert " ".join(("sq-mitsuba", *path)) in out.splitlines()[0]


def _help_of_option(parser: argparse.ArgumentParser, flag: str) -> str:
    for action in parser._actions:
        if flag in action.option_strings:
            return action.help or ""
    raise AssertionError(f"{flag} is recorded in _config_flags but not an option")


CONFIG_OPTIONS = [
    (path, parser, name, flag)
    for path, parser in PARSERS
    for name, flag in (parser.get_default("_config_flags") or {}).items()
]


def test_some_options_come_from_config_classes():
    commands = {path[0] for path, *_ in CONFIG_OPTIONS}
    assert {"fit", "bench"} <= commands


@pytest.mark.parametrize(("path", "parser", "name", "flag"), CONFIG_OPTIONS,
                         ids=[f"{' '.join(p)} {f}" for p, _, _, f in CONFIG_OPTIONS])
def test_config_option_help_shows_the_config_default(path, parser, name, flag):
    classes = parser.get_default("_config_classes") or {}
    assert name in classes, f"{flag}: no config class recorded for field {name!r}"
    default = getattr(classes[name](), name)
    shown = list(default) if isinstance(default, tuple) else default
    text = _help_of_option(parser, flag)
    if "Default:" in text:  # a None that chooses, said in the field's own text: said once
        assert "(default:" not in text, text
    else:
        assert text.endswith(f"(default: {shown})")
    # And the parsed value, when the option is left out, is that default.
    from sq_mitsuba.cli._options import config_from_args

    namespace = argparse.Namespace(_config_flags={name: flag})
    assert getattr(config_from_args(classes[name], namespace), name) == default


def test_top_level_help_lists_commands_without_importing_the_fit_library():
    """`sq-mitsuba --help` lists fit from its HELP line without importing learning.fit."""
    code = ("import sys; from sq_mitsuba.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit as e:\n    assert e.code == 0\n"
            "assert 'sq_mitsuba.inference.fit' not in sys.modules\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert "fit superquadrics to masks" in out


def test_top_level_help_imports_neither_torch_nor_mitsuba():
    """`sq-mitsuba --help` stays fast (~0.3 s instead of ~2 s with torch): no command module
    imports torch, Mitsuba or Dr.Jit to be listed."""
    code = ("import sys; from sq_mitsuba.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit as e:\n    assert e.code == 0\n"
            "heavy = sorted(m for m in ('torch', 'mitsuba', 'drjit', 'numpy') "
            "if m in sys.modules)\n"
            "print('HEAVY', heavy)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.splitlines()[-1] == "HEAVY []"


def test_version_prints_the_package_version(capsys):
    from sq_mitsuba import __version__

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out == f"sq-mitsuba {__version__}\n"


def _leaf_fields(config_class: type, prefix: str = "") -> list[str]:
    """Dotted names of every field ``--set`` can change (nested configs walked into)."""
    import dataclasses
    import typing

    names = []
    hints = typing.get_type_hints(config_class)
    for item in dataclasses.fields(config_class):
        annotation = hints[item.name]
        members = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(members) == 1 and typing.get_origin(annotation) is not None:
            annotation = members[0]
        if dataclasses.is_dataclass(annotation):
            names += _leaf_fields(annotation, f"{prefix}{item.name}.")
        else:
            names.append(f"{prefix}{item.name}")
    return names


SET_PARSERS = [(path, parser) for path, parser in PARSERS
               if parser.get_default("_set_class") is not None]


def test_some_commands_have_set():
    assert {path for path, _ in SET_PARSERS} >= {("eval",), ("predict",), ("fit",)}


@pytest.mark.parametrize(("path", "parser"), SET_PARSERS,
                         ids=[" ".join(path) for path, _ in SET_PARSERS])
def test_set_help_lists_every_settable_field(path, parser):
    """`--set` help names every field (a nested config's as `name.{a, b}`)."""
    config_class = parser.get_default("_set_class")
    text = " ".join(_help_of_option(parser, "--set").split())
    listed = text.split("Fields: ", 1)[1]
    words = set(listed.replace("{", " ").replace("}", " ").replace(",", " ").split())
    for name in _leaf_fields(config_class):
        *outer, leaf = name.split(".")
        assert all(f"{part}.{{" in listed for part in outer), (name, listed)
        assert leaf in words or f"{leaf}.KEY" in words, (name, listed)


def _parser_of(*path: str) -> argparse.ArgumentParser:
    return dict(PARSERS)[path]


def test_help_texts_say_what_a_user_needs():
    top = _subparsers(build_parser())
    assert "issues" not in (top["bench"].description or "")
    bench_help = next(a for a in build_parser()._actions
                      if isinstance(a, argparse._SubParsersAction))._choices_actions
    bench_line = next(a.help for a in bench_help if a.dest == "bench")
    assert "issues" not in bench_line and "time" in bench_line
    half = " ".join(_help_of_option(_parser_of("export"), "--half").split())
    assert "module note" not in half and "half the file size" in half
    preview = _parser_of("models", "preview").description or ""
    assert "contact_sheet.png" in preview and "suffix" in preview
