"""Command-line options whose defaults and help come from the library's config dataclasses.

Every default lives in one place, the config dataclass (see :mod:`sq_mitsuba.config`); a
command declares which fields it exposes, and this module builds the argparse options (type,
choices, default, help = the field's docstring plus "(default: ...)") and turns the parsed
arguments back into a validated config. A bad value is a one-line error naming the option.

    parser.add_argument(...)                       # positional / command-only arguments
    add_config_options(parser, FitOptions, {"steps": "--steps", "lr": "--lr"})
    ...
    options = config_from_args(FitOptions, args)   # ConfigError -> "--steps: expected ..."
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from sq_mitsuba.cli import CLIError
from sq_mitsuba.config import ConfigError, apply_overrides, field_docs, from_dict, to_dict

_FLAGS = "_config_flags"
# Parser default {field: config class}, beside _FLAGS: lets tests find each option's class.
_CLASSES = "_config_classes"
#: Parser default: the config class that ``--set`` overrides (see :func:`add_set_option`).
SET_CLASS = "_set_class"


def _option_kwargs(annotation: Any, default: Any) -> dict[str, Any]:
    """argparse keyword arguments (type, choices, nargs, action) for one field type."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is Literal:
        return {"choices": list(args), "type": type(args[0])}
    if annotation is bool:
        return {"action": argparse.BooleanOptionalAction}
    if origin is tuple:
        kind = args[0]
        return {"type": kind, "nargs": "+" if len(args) == 2 and args[1] is Ellipsis
                else len(args)}
    if origin in (typing.Union, types.UnionType):
        members = [a for a in args if a is not type(None)]
        return _option_kwargs(members[0], default) if len(members) == 1 else {"type": str}
    if annotation in (int, float, str, Path):
        return {"type": annotation}
    raise TypeError(f"no command-line option for a field of type {annotation!r}")


def add_config_options(parser: argparse.ArgumentParser, config_class: type,
                       flags: Mapping[str, str], metavars: Mapping[str, str] | None = None,
                       helps: Mapping[str, str] | None = None) -> None:
    """Add one option per ``field: flag`` of ``flags``; default and help come from
    ``config_class`` (its default instance and its field docstrings; ``helps`` replaces the
    docstring of a field whose wording is for readers of the code, not of ``--help``)."""
    defaults = field_defaults(config_class)
    hints = typing.get_type_hints(config_class)
    docs = field_docs(config_class)
    for name, flag in flags.items():
        default = defaults[name]
        shown = list(default) if isinstance(default, tuple) else default
        help_text = _plain_text((helps or {}).get(name, docs.get(name, ""))).rstrip(".")
        kwargs = _option_kwargs(hints[name], default)
        if metavars and name in metavars:
            kwargs["metavar"] = metavars[name]
        # A field whose text says its default itself (a None that chooses) is not given a
        # second one ("Default: 8 where ..., else 1 (default: None)").
        suffix = "" if "Default:" in help_text else f" (default: {shown})"
        parser.add_argument(flag, dest=name, default=argparse.SUPPRESS,
                            help=f"{help_text}{suffix}", **kwargs)
    known = dict(parser.get_default(_FLAGS) or {})
    known.update({name: flag for name, flag in flags.items()})
    classes = dict(parser.get_default(_CLASSES) or {})
    classes.update({name: config_class for name in flags})
    parser.set_defaults(**{_FLAGS: known, _CLASSES: classes})


def field_defaults(config_class: type) -> dict[str, Any]:
    """Each field's default (its factory's value), read without making an instance: an
    instance's own checks run at parser build time, and one that measures the machine (the
    import's fusion memory: about 2.3 GiB) crashed every ``models`` command, ``--help``
    included, on a machine with less."""
    values: dict[str, Any] = {}
    for item in dataclasses.fields(config_class):
        if item.default is not dataclasses.MISSING:
            values[item.name] = item.default
        elif item.default_factory is not dataclasses.MISSING:
            values[item.name] = item.default_factory()
    return values


def add_set_option(parser: argparse.ArgumentParser, what: str, example: str | None = None,
                   config_class: type | None = None) -> None:
    """``--set key=value`` (repeatable): dotted overrides of any field of ``what``'s config.

    ``example`` (``key=value``; default: the first numeric field at its default) is shown in
    the help; ``config_class`` is the config the overrides apply to (default: the class of the
    options added last by :func:`add_config_options`), recorded so that tests check the
    example against it.
    """
    if config_class is None:
        config_class = list((parser.get_default(_CLASSES) or {}).values())[-1]
    if example is None:
        defaults = field_defaults(config_class)
        example = next(f"{name}={value}" for name, value in defaults.items()
                       if type(value) in (int, float))
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE",
                        help=f"override a field of the {what} (dotted, e.g. {example}); "
                             f"repeatable. Fields: {settable_fields(config_class)}")
    parser.set_defaults(**{SET_CLASS: config_class})


def settable_fields(config_class: type) -> str:
    """The fields ``--set`` can change, for its help: ``a, b, c.{d, e}, f.KEY`` (a nested
    config's fields in braces, a ``dict`` field's entries as ``.KEY``)."""
    hints = typing.get_type_hints(config_class)
    parts = []
    for item in dataclasses.fields(config_class):
        if not item.init:
            continue
        annotation = hints[item.name]
        if typing.get_origin(annotation) in (typing.Union, types.UnionType):
            members = [a for a in typing.get_args(annotation) if a is not type(None)]
            annotation = members[0] if len(members) == 1 else annotation
        if dataclasses.is_dataclass(annotation):
            parts.append(f"{item.name}.{{{settable_fields(annotation)}}}")
        elif typing.get_origin(annotation) is dict:
            parts.append(f"{item.name}.KEY")
        else:
            parts.append(item.name)
    return ", ".join(parts)


def config_from_args(config_class: type, args: argparse.Namespace, base: Any = None,
                     **extra: Any) -> Any:
    """The validated ``config_class`` instance: ``base`` (default: the class defaults), then
    the options given on the command line, then ``extra`` fields, then ``--set`` overrides.

    A ``ConfigError`` becomes a :class:`CLIError` naming the option (``--steps: ...``).
    """
    flags: dict[str, str] = getattr(args, _FLAGS, None) or {}
    base = base if base is not None else config_class()
    values = to_dict(base)
    given = {name: getattr(args, name) for name in flags if hasattr(args, name)}
    given.update(extra)
    overrides = getattr(args, "overrides", None) or []
    _check_given_once(config_class, flags, list(given), overrides)
    for name, value in given.items():
        values[name] = list(value) if isinstance(value, tuple) else (
            str(value) if isinstance(value, Path) else value)
    try:
        config = from_dict(config_class, values)
    except ConfigError as error:
        message = str(error)
        for name, flag in flags.items():
            if message.startswith(f"{name}:") or message.startswith(f"{name}["):
                message = flag + message[len(name):]
                break
        raise CLIError(message) from None
    if overrides:
        try:
            config = apply_overrides(config, overrides)
        except ConfigError as error:
            raise CLIError(f"--set {error}") from None
    return config


def _check_given_once(config_class: type, flags: Mapping[str, str], given: list[str],
                      overrides: list[str]) -> None:
    """Refuse a field set twice, by its option and by ``--set`` (``--no-refine --set
    refine=true``) or by two ``--set`` of one key (or of a key and a field within it): the
    later would silently win. One line naming both."""
    defaults = config_class()
    seen: dict[str, str] = {}
    for name in given:
        flag = flags.get(name, f"--{name.replace('_', '-')}")
        boolean = isinstance(getattr(defaults, name, None), bool)
        seen[name] = f"{flag} / --no-{flag[2:]}" if boolean else flag
    for override in overrides:
        key = override.split("=", 1)[0].strip()
        for earlier_key, earlier in seen.items():
            if key == earlier_key or key.startswith(f"{earlier_key}.") \
                    or earlier_key.startswith(f"{key}."):
                raise CLIError(f"--set {override}: {earlier_key} is also given by {earlier}; "
                               "give it once")
        seen[key] = f"--set {override}"


def refuse_unused_settings(args: argparse.Namespace, fields: tuple[str, ...], flag: str) -> None:
    """A ``--set`` of one of ``fields`` (a field, or a table's: ``search.grid``) is refused
    in one line where ``flag`` is not given: it would act on nothing, silently."""
    for override in getattr(args, "overrides", None) or []:
        if override.split("=", 1)[0].strip().split(".")[0] in fields:
            raise CLIError(f"--set {override}: only used with {flag}")


def output_path(text: str) -> Path:
    """The argparse type of an output path: an empty one is refused, not taken for the working
    folder (``Path("")`` is ``.``)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; give the output's path")
    return Path(text)


def _refuse_folder_form(text: str, advice: str) -> None:
    """Refuse a file's path that ends in a separator (a folder, as the user wrote it; ``Path``
    would silently strip it)."""
    import os

    if text.endswith(("/", os.sep)) or (os.altsep and text.endswith(os.altsep)):
        raise argparse.ArgumentTypeError(f"{text!r} ends in a separator, a folder; {advice}")


def output_file_path(text: str) -> Path:
    """The argparse type of an output file: :func:`output_path`, and a path that ends in a
    separator refused, not written as a file of the folder's name (``export --out newdir/``
    wrote a file ``newdir``)."""
    _refuse_folder_form(text, "give the file to write in it")
    return output_path(text)


def input_file_path(text: str) -> Path:
    """The argparse type of an input file: an empty path refused, and one that ends in a
    separator (``img.png/``), which the system would not open as a file."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; give the file to read")
    _refuse_folder_form(text, "give the file to read")
    return Path(text)


def _plain_text(doc: str) -> str:
    """A field docstring as ``--help`` shows it: reST's ``code`` as `code` and a role's
    :func:`name` (or :class:, :meth:, ...) as its name, the leading ~ of a path dropped."""
    import re

    doc = re.sub(r":[a-z]+:`~?([^`]+)`", lambda m: m.group(1).rsplit(".", 1)[-1], doc)
    return doc.replace("``", "`")
