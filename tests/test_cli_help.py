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
    assert _help_of_option(parser, flag).endswith(f"(default: {shown})")
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
