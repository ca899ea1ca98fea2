"""The project's one configuration style: frozen dataclasses, documented where they are declared.

A config is a tree of ``@dataclass(frozen=True)`` classes. Every field has a type hint, a
default, and a string literal on the line after it that documents it (read by
:func:`field_docs` and shown by :func:`describe` in ``--help``)::

    @dataclass(frozen=True)
    class SunConfig:
        enabled: bool = True
        "Whether the scene is lit by the sun."
        irradiance: float = positive(1361.0)
        "Solar irradiance in W/m^2."

Mappings and files (TOML or JSON) become configs through :func:`from_dict` and :func:`load`,
which are strict: unknown keys, wrong types, NaN and numbers out of a field's :func:`bounds` are
:class:`ConfigError` s with one-line messages that name the dotted field, e.g.
``scenes/space.json: sun.irradiance: expected a number, got 'x'``. Configs built in code are
checked by :func:`validate`. Rules that tie several fields together go in ``__post_init__``
(raise ``ValueError``; :func:`from_dict` prefixes the message with the field path).
Command lines change fields with :func:`apply_overrides` (``sun.enabled=false``); :func:`to_dict`,
:func:`save` and :func:`config_hash` record what a run used.

Supported field types: ``int`` (never ``bool``), ``float`` (accepts integers), ``bool``, ``str``,
``pathlib.Path``, ``Literal[...]``, ``tuple[X, Y]`` and ``tuple[X, ...]`` (lists in files),
``dict[str, X]``, ``X | None`` and other unions, and nested config dataclasses.

This module uses the standard library only and imports nothing from the rest of the project.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import hashlib
import inspect
import json
import math
import re
import textwrap
import tomllib
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from functools import cache
from os import PathLike
from pathlib import Path, PurePath
from typing import Any, Literal, TypeVar, Union, get_args, get_origin

__all__ = [
    "Bounds",
    "ConfigError",
    "apply_overrides",
    "bounds",
    "config_hash",
    "describe",
    "field_docs",
    "from_dict",
    "in_range",
    "load",
    "non_negative",
    "positive",
    "save",
    "to_dict",
    "to_toml",
    "validate",
]

T = TypeVar("T")

_BOUNDS_KEY = "bounds"
"""Field-metadata key of a :class:`Bounds`."""
_NONFINITE_KEY = "allow_nonfinite"
"""Field-metadata key that lets a float field hold NaN and infinities."""
_NULL_WORDS = frozenset({"null", "none"})
"""Bare override values that mean ``None`` for fields that accept it (TOML has no null)."""
_BARE_TOML_KEY = re.compile(r"[A-Za-z0-9_-]+")
_MAX_SHOWN = 80
"""Longest rendering of a bad value in an error message."""
_NoneType = type(None)


class ConfigError(ValueError):
    """An invalid configuration value, file or override. The message is one line."""


# --- bounds ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Bounds:
    """An interval of allowed numbers, stored in a field's metadata by :func:`bounds`."""

    low: float | None = None
    """Lower limit, or ``None`` for no lower limit."""
    high: float | None = None
    """Upper limit, or ``None`` for no upper limit."""
    low_inclusive: bool = True
    """Whether ``low`` itself is allowed."""
    high_inclusive: bool = True
    """Whether ``high`` itself is allowed."""

    def __contains__(self, x: float) -> bool:
        if self.low is not None and not (x >= self.low if self.low_inclusive else x > self.low):
            return False
        return self.high is None or (x <= self.high if self.high_inclusive else x < self.high)

    def describe(self) -> str:
        """The interval as text: ``in [1, 10]``, ``in (0, 1]``, ``> 0`` or ``<= 5``."""
        if self.low is not None and self.high is not None:
            left = "[" if self.low_inclusive else "("
            right = "]" if self.high_inclusive else ")"
            return f"in {left}{_num(self.low)}, {_num(self.high)}{right}"
        if self.low is not None:
            return f"{'>=' if self.low_inclusive else '>'} {_num(self.low)}"
        if self.high is not None:
            return f"{'<=' if self.high_inclusive else '<'} {_num(self.high)}"
        return "any value"


def bounds(
    low: float | None = None,
    high: float | None = None,
    *,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
    allow_nonfinite: bool = False,
) -> dict[str, Any]:
    """Field metadata that limits a number (or every number of a tuple or dict) to an interval.

    Use as ``field(default=..., metadata=bounds(1, 10))``. ``None`` leaves a side open.
    ``allow_nonfinite=True`` lets a float field hold NaN and infinities (refused by default).
    """
    for limit in (low, high):
        if limit is not None and (isinstance(limit, bool) or not math.isfinite(limit)):
            raise ValueError(f"bounds: limits must be finite numbers or None, got {limit!r}")
    if low is not None and high is not None and low > high:
        raise ValueError(f"bounds: low {low!r} is above high {high!r}")
    meta: dict[str, Any] = {}
    if low is not None or high is not None:
        meta[_BOUNDS_KEY] = Bounds(low, high, low_inclusive, high_inclusive)
    if allow_nonfinite:
        meta[_NONFINITE_KEY] = True
    return meta


def _bounded_field(default: Any, default_factory: Any, meta: dict[str, Any]) -> Any:
    kwargs: dict[str, Any] = {"metadata": meta}
    if default is not dataclasses.MISSING:
        kwargs["default"] = default
    if default_factory is not dataclasses.MISSING:
        kwargs["default_factory"] = default_factory
    return dataclasses.field(**kwargs)


def in_range(
    low: float | None,
    high: float | None,
    *,
    default: Any = dataclasses.MISSING,
    default_factory: Callable[[], Any] | Any = dataclasses.MISSING,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
) -> Any:
    """A dataclass field limited to ``[low, high]``: ``x: float = in_range(0, 1, default=0.5)``."""
    meta = bounds(low, high, low_inclusive=low_inclusive, high_inclusive=high_inclusive)
    return _bounded_field(default, default_factory, meta)


def positive(
    default: Any = dataclasses.MISSING,
    *,
    default_factory: Callable[[], Any] | Any = dataclasses.MISSING,
) -> Any:
    """A dataclass field that must be > 0: ``lr: float = positive(1e-3)``."""
    return _bounded_field(default, default_factory, bounds(0, None, low_inclusive=False))


def non_negative(
    default: Any = dataclasses.MISSING,
    *,
    default_factory: Callable[[], Any] | Any = dataclasses.MISSING,
) -> Any:
    """A dataclass field that must be >= 0: ``steps: int = non_negative(100)``."""
    return _bounded_field(default, default_factory, bounds(0, None))


# --- small helpers --------------------------------------------------------------------------


def _num(x: float) -> str:
    """A number for messages: ``20`` rather than ``20.0``, full precision otherwise."""
    if isinstance(x, float) and x.is_integer() and abs(x) < 1e15:
        return str(int(x))
    return repr(x)


def _show(value: Any) -> str:
    """A value as it would appear in a config file, shortened for one-line messages."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    text = repr(value)
    return text if len(text) <= _MAX_SHOWN else text[: _MAX_SHOWN - 3] + "..."


def _at(where: str, message: str) -> str:
    return f"{where}: {message}" if where else message


def _join(where: str, name: str) -> str:
    return f"{where}.{name}" if where else name


def _join_key(where: str, key: str) -> str:
    """Path of a dict entry: ``weights.silhouette``, or ``weights["solar panel"]``."""
    return _join(where, key) if key.isidentifier() else f"{where}[{json.dumps(key)}]"


def _is_config_class(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _require_instance(obj: Any, func: str) -> None:
    if not dataclasses.is_dataclass(obj) or isinstance(obj, type):
        raise TypeError(f"{func}: expected a config dataclass instance, got {type(obj).__name__}")


def _union_members(tp: Any) -> tuple[Any, ...] | None:
    if get_origin(tp) in (Union, types.UnionType):
        return get_args(tp)
    return None


def _single_member(tp: Any) -> Any:
    """``X`` for ``X | None``; ``tp`` itself otherwise."""
    members = _union_members(tp)
    if members is None:
        return tp
    rest = [m for m in members if m is not _NoneType]
    return rest[0] if len(rest) == 1 else tp


def _is_mapping_type(tp: Any) -> bool:
    return get_origin(tp) in (dict, Mapping)


@cache
def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except NameError as exc:
        raise TypeError(f"cannot resolve the annotations of {cls.__qualname__}: {exc}") from exc


def _init_fields(cls: type) -> dict[str, dataclasses.Field[Any]]:
    """The fields a config is built from (``init=False`` fields are derived, not configured)."""
    return {f.name: f for f in dataclasses.fields(cls) if f.init}


def _default_of(f: dataclasses.Field[Any]) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


_SINGULAR = {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}
_PLURAL = {bool: "booleans", int: "integers", float: "numbers", str: "strings"}


def _expected(tp: Any) -> str:
    """What a value of type ``tp`` looks like, in words: ``a list of 2 numbers``."""
    if tp is Any:
        return "any value"
    if tp is _NoneType:
        return "null"
    if tp in _SINGULAR:
        return _SINGULAR[tp]
    if isinstance(tp, type) and issubclass(tp, PurePath):
        return "a path (string)"
    if _is_config_class(tp):
        return f"a table of {tp.__name__} fields"
    members = _union_members(tp)
    if members is not None:
        return " or ".join(_expected(m) for m in members)
    origin, args = get_origin(tp), get_args(tp)
    if origin is Literal:
        return "one of " + ", ".join(_show(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_plural(args[0])}"
        if args and all(a == args[0] for a in args):
            return f"a list of {len(args)} {_plural(args[0])}"
        return f"a list of {len(args)} items" if args else "a list"
    if _is_mapping_type(tp):
        return f"a table of {_plural(args[1])}" if len(args) == 2 else "a table"
    return f"a value of type {tp!r}"


def _plural(tp: Any) -> str:
    if tp in _PLURAL:
        return _PLURAL[tp]
    if isinstance(tp, type) and issubclass(tp, PurePath):
        return "paths"
    if _is_config_class(tp):
        return f"{tp.__name__} tables"
    return "items"


def _type_error(where: str, tp: Any, value: Any, suffix: str = "") -> ConfigError:
    if not suffix and type(value).__module__ == "numpy" and hasattr(value, "item"):
        # A config is written out as TOML and JSON, which hold Python's numbers, not numpy's.
        suffix = f" (numpy's: give {type(value.item()).__name__}(...))"
    error = ConfigError(_at(where, f"expected {_expected(tp)}, got {_show(value)}{suffix}"))
    error._type_mismatch = (where, suffix)  # type: ignore[attr-defined]  # see _convert
    return error


def _unknown_key(path: str, key: str, names: Iterable[str]) -> ConfigError:
    names = list(names)
    message = f"{path}: unknown key; expected one of: {', '.join(names) or '(none)'}"
    close = difflib.get_close_matches(key, names, n=1)
    if close:
        message += f" (did you mean {close[0]!r}?)"
    return ConfigError(message)


# --- checking and converting values ---------------------------------------------------------


def _check_number(x: float, where: str, meta: Mapping[str, Any]) -> None:
    if isinstance(x, float) and not math.isfinite(x) and not meta.get(_NONFINITE_KEY, False):
        raise ConfigError(_at(where, f"expected a finite number, got {_show(x)}"))
    limits = meta.get(_BOUNDS_KEY)
    if limits is not None and x not in limits:
        raise ConfigError(_at(where, f"expected a value {limits.describe()}, got {_num(x)}"))


def _convert(tp: Any, value: Any, where: str, meta: Mapping[str, Any], coerce: bool) -> Any:
    """Check ``value`` against the annotation ``tp`` and the field's bounds; return it converted.

    ``coerce=True`` (data from files and overrides) turns lists into tuples, strings into paths
    and tables into config dataclasses. ``coerce=False`` (:func:`validate`) wants the Python
    types themselves. Integers are accepted for floats either way.
    """
    if tp is Any:
        return value
    members = _union_members(tp)
    if members is not None:
        if value is None:
            if _NoneType in members:
                return None
            raise _type_error(where, tp, value)
        options = [m for m in members if m is not _NoneType]
        if len(options) == 1:  # X | None: X's message, unless the value is of another type
            try:
                return _convert(options[0], value, where, meta, coerce)
            except ConfigError as exc:
                mismatch = getattr(exc, "_type_mismatch", None)
                if mismatch is None or mismatch[0] != where:
                    raise  # a bad element or number: X's own message is the useful one
                raise _type_error(where, tp, value, mismatch[1]) from None
        for option in options:
            try:
                return _convert(option, value, where, meta, coerce)
            except ConfigError:
                continue
        raise _type_error(where, tp, value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise _type_error(where, tp, value)
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            _check_number(value, where, meta)
            return value
        raise _type_error(where, tp, value)
    if tp is float:
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise _type_error(where, tp, value)
        try:
            number = float(value)
        except OverflowError:
            raise _type_error(where, tp, value, " (too large)") from None
        _check_number(number, where, meta)
        return number
    if tp is str:
        if isinstance(value, str):
            return value
        raise _type_error(where, tp, value)
    if isinstance(tp, type) and issubclass(tp, PurePath):
        if isinstance(value, PurePath):
            return value if isinstance(value, tp) else tp(value)
        if coerce and isinstance(value, str) and value:
            return tp(value)
        raise _type_error(where, tp, value)
    if _is_config_class(tp):
        if isinstance(value, tp):
            _validate_instance(value, where)
            return value
        if coerce and isinstance(value, Mapping):
            return _from_mapping(tp, value, where)
        raise _type_error(where, tp, value)
    origin, args = get_origin(tp), get_args(tp)
    if origin is Literal:
        for option in args:
            if value == option and type(value) is type(option):
                return option
        raise _type_error(where, tp, value)
    if origin is tuple or tp is tuple:
        if not isinstance(value, tuple | list):
            raise _type_error(where, tp, value)
        if not coerce and isinstance(value, list):  # a config built in code, not parsed
            raise _type_error(where, tp, value, f" (a tuple in code: {tuple(value)!r})")
        if len(args) == 2 and args[1] is Ellipsis:
            element_types = [args[0]] * len(value)
        elif not args:
            element_types = [Any] * len(value)
        elif len(value) != len(args):
            raise _type_error(where, tp, value, f" (length {len(value)})")
        else:
            element_types = list(args)
        return tuple(
            _convert(t, v, f"{where}[{i}]", meta, coerce)
            for i, (t, v) in enumerate(zip(element_types, value, strict=True))
        )
    if _is_mapping_type(tp) or tp is dict:
        key_type, value_type = args if len(args) == 2 else (str, Any)
        if key_type is not str:
            raise TypeError(f"{where}: config tables must have str keys, not {key_type!r}")
        if not isinstance(value, Mapping):
            raise _type_error(where, tp, value)
        result = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise ConfigError(_at(where, f"keys must be strings, got {_show(key)}"))
            result[key] = _convert(value_type, item, _join_key(where, key), meta, coerce)
        return result
    raise TypeError(f"{where or 'config'}: unsupported config annotation {tp!r}")


def _construct(cls: type[T], kwargs: dict[str, Any], where: str) -> T:
    """``cls(**kwargs)``, with ``__post_init__`` errors prefixed by the config's path."""
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ConfigError(_at(where, str(exc))) from exc


def _from_mapping(cls: type[T], data: Mapping[str, Any], where: str) -> T:
    if not isinstance(data, Mapping):
        raise _type_error(where, cls, data)
    hints = _hints(cls)
    fields = _init_fields(cls)
    for key in data:
        if not isinstance(key, str):
            raise ConfigError(_at(where, f"keys must be strings, got {_show(key)}"))
        if key not in fields:
            raise _unknown_key(_join(where, key), key, fields)
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        path = _join(where, name)
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], path, f.metadata, coerce=True)
            continue
        default = _default_of(f)
        if default is dataclasses.MISSING:
            raise ConfigError(f"{path}: missing required key")
        kwargs[name] = _convert(hints[name], default, path, f.metadata, coerce=False)
    return _construct(cls, kwargs, where)


def _validate_instance(obj: Any, where: str) -> None:
    cls = type(obj)
    hints = _hints(cls)
    for name, f in _init_fields(cls).items():
        _convert(hints[name], getattr(obj, name), _join(where, name), f.metadata, coerce=False)


def validate(obj: Any, where: str = "") -> None:
    """Check a config built in code: types, NaN and bounds of every field, nested ones included.

    Raises :class:`ConfigError` naming the first bad field. Tuples must be tuples, paths
    ``pathlib.Path`` and nested configs dataclass instances (what :func:`from_dict` produces).
    """
    _require_instance(obj, "validate")
    _validate_instance(obj, where)


def from_dict(cls: type[T], data: Mapping[str, Any], where: str = "") -> T:
    """Build a config from a mapping (parsed TOML or JSON), strictly.

    Unknown keys, wrong types, NaN / infinities and out-of-bounds numbers raise
    :class:`ConfigError`; missing keys take the field defaults (which are checked too).
    ``where`` is a dotted prefix for the field paths in messages.
    """
    if not _is_config_class(cls):
        raise TypeError(f"from_dict: expected a config dataclass, got {cls!r}")
    return _from_mapping(cls, data, where)


# --- files ----------------------------------------------------------------------------------


class _DuplicateKeyError(ValueError):
    pass


def _no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    result: dict[str, Any] = {}
    for key, value in pairs:
        if key in result:
            raise _DuplicateKeyError(key)
        result[key] = value
    return result


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".json"):
        shown = repr(path.suffix) if path.suffix else "no suffix"
        raise ConfigError(f"{path}: unsupported config file type ({shown}); use .toml or .json")
    return suffix


def read_mapping(path: str | PathLike[str]) -> Mapping[str, Any]:
    """The top-level table of a ``.toml`` or ``.json`` file; one-line :class:`ConfigError`
    naming the file when it is missing, unreadable, malformed or not a table."""
    path = Path(path)
    suffix = _suffix(path)
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, not a config file") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if suffix == ".toml":
        try:
            return tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: malformed TOML: {exc}") from None
        except RecursionError:  # arrays nested deeper than the parser's stack
            raise ConfigError(f"{path}: malformed TOML: nested too deeply") from None
    try:
        data = json.loads(text, object_pairs_hook=_no_duplicate_keys)
    except RecursionError:
        raise ConfigError(f"{path}: malformed JSON: nested too deeply") from None
    except json.JSONDecodeError as exc:
        where = f"line {exc.lineno}, column {exc.colno}"
        raise ConfigError(f"{path}: malformed JSON at {where}: {exc.msg}") from None
    except _DuplicateKeyError as exc:
        raise ConfigError(f"{path}: duplicate key {exc.args[0]!r}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a JSON object at the top, got {type(data).__name__}")
    return data


def load(cls: type[T], path: str | PathLike[str]) -> T:
    """Read a config from a ``.toml`` or ``.json`` file (by suffix) with :func:`from_dict`.

    Every error message starts with the file: ``scenes/space.json: sun.irradiance: ...``.
    """
    path = Path(path)
    data = read_mapping(path)
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def save(obj: Any, path: str | PathLike[str]) -> None:
    """Write a config to a ``.toml`` or ``.json`` file (by suffix) that :func:`load` reads back
    (whole or not at all: a temporary file beside it, renamed; this module imports nothing of
    the project, so not ``sq_mitsuba.io``'s helper)."""
    import os

    path = Path(path)
    if _suffix(path) == ".toml":
        text = to_toml(obj)
    else:
        text = json.dumps(to_dict(obj), indent=2, ensure_ascii=False) + "\n"
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # the usual permissions
    try:
        temporary.write_text(text, encoding="utf-8")
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


# --- exporting ------------------------------------------------------------------------------


def _to_plain(tp: Any, value: Any) -> Any:
    if value is None:
        return None
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        hints = _hints(type(value))
        return {
            name: _to_plain(hints[name], getattr(value, name)) for name in _init_fields(type(value))
        }
    tp = _single_member(tp)
    if isinstance(value, bool | str):
        return value
    if isinstance(value, int) and tp is float:
        return float(value)  # so that 1 and 1.0 in a float field export (and hash) alike
    if isinstance(value, PurePath):
        return value.as_posix()
    if isinstance(value, tuple | list):
        args = get_args(tp) if get_origin(tp) is tuple else ()
        if len(args) == 2 and args[1] is Ellipsis:
            element_types = [args[0]] * len(value)
        elif len(args) == len(value):
            element_types = list(args)
        else:
            element_types = [Any] * len(value)
        return [_to_plain(t, v) for t, v in zip(element_types, value, strict=True)]
    if isinstance(value, Mapping):
        args = get_args(tp)
        value_type = args[1] if len(args) == 2 else Any
        return {str(k): _to_plain(value_type, v) for k, v in value.items()}
    return value


def flatten_dict(data: Any, prefix: str = "") -> dict[str, Any]:
    """A nested dict (a config's :func:`to_dict`) as one level of dotted keys:
    ``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (what differences between two configs name)."""
    if isinstance(data, dict):
        out: dict[str, Any] = {}
        for key, value in data.items():
            out.update(flatten_dict(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: data}


def to_dict(obj: Any) -> dict[str, Any]:
    """A config as JSON-able data: tuples become lists, paths strings, float fields floats.

    ``from_dict(type(obj), to_dict(obj)) == obj``. Fields with ``init=False`` are left out.
    """
    _require_instance(obj, "to_dict")
    return _to_plain(type(obj), obj)


def _canonical_json(obj: Any) -> str:
    return json.dumps(to_dict(obj), sort_keys=True, separators=(",", ":"), ensure_ascii=False)


def config_hash(obj: Any) -> str:
    """First 16 hex digits of the sha256 of the config's canonical JSON (sorted keys).

    Equal configs hash alike across runs and machines; the class name is not part of it.
    """
    return hashlib.sha256(_canonical_json(obj).encode("utf-8")).hexdigest()[:16]


def _toml_key(key: str) -> str:
    return key if _BARE_TOML_KEY.fullmatch(key) else json.dumps(key, ensure_ascii=False)


def _inline(value: Any, null: str | None = None) -> str:
    """A plain value as a TOML literal (``null`` spells ``None``, which TOML lacks)."""
    if value is None:
        if null is None:
            raise ConfigError("TOML cannot express a null value here")
        return null
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(value, list):
        return "[" + ", ".join(_inline(v, null) for v in value) + "]"
    if isinstance(value, dict):
        items = ", ".join(f"{_toml_key(k)} = {_inline(v, null)}" for k, v in value.items())
        return "{" + items + "}"
    raise TypeError(f"cannot write {value!r} as TOML")


def _toml_table(table: Mapping[str, Any], path: list[str], lines: list[str]) -> None:
    if path:
        if lines:
            lines.append("")
        lines.append("[" + ".".join(_toml_key(p) for p in path) + "]")
    for key, value in table.items():
        if value is not None and not isinstance(value, dict):
            lines.append(f"{_toml_key(key)} = {_inline(value)}")
    for key, value in table.items():
        if isinstance(value, dict):
            _toml_table(value, [*path, key], lines)


def to_toml(obj: Any) -> str:
    """A config as TOML text that :func:`load` reads back to an equal config.

    ``None`` values are left out (TOML has no null), so a field that is ``None`` but whose
    default is not cannot be written: that raises :class:`ConfigError` (use JSON).
    """
    lines: list[str] = []
    _toml_table(to_dict(obj), [], lines)
    text = "\n".join(lines) + "\n"
    if _canonical_json(from_dict(type(obj), tomllib.loads(text))) != _canonical_json(obj):
        raise ConfigError(
            f"{type(obj).__name__} cannot be written exactly as TOML (a null field whose default"
            " is not null?); save it as JSON"
        )
    return text


# --- overrides ------------------------------------------------------------------------------


def _accepts_str(tp: Any) -> bool:
    for member in _union_members(tp) or (tp,):
        if member is str or member is Any:
            return True
        if isinstance(member, type) and issubclass(member, PurePath):
            return True
        if get_origin(member) is Literal and any(isinstance(a, str) for a in get_args(member)):
            return True
    return False


def _accepts_none(tp: Any) -> bool:
    return tp is Any or tp is _NoneType or _NoneType in (_union_members(tp) or ())


def _parse_override(tp: Any, raw: str, where: str, meta: Mapping[str, Any]) -> Any:
    """Parse an override's text as a TOML value and convert it for a field of type ``tp``.

    Text that is not TOML is taken as a bare string where the field accepts strings, and
    ``null`` / ``none`` mean ``None`` where it accepts ``None``.
    """
    try:
        document = tomllib.loads(f"v = {raw}")
        parsed_ok = set(document) == {"v"}
    except tomllib.TOMLDecodeError:
        parsed_ok = False
    if not parsed_ok:
        if raw.lower() in _NULL_WORDS and _accepts_none(tp):
            return None
        if _accepts_str(tp):
            return _convert(tp, raw, where, meta, coerce=True)
        raise _type_error(where, tp, raw, " (not a TOML value)")
    value = document["v"]
    try:
        return _convert(tp, value, where, meta, coerce=True)
    except ConfigError:
        if _accepts_str(tp) and not isinstance(value, str):  # name=123 for a str field
            return _convert(tp, raw, where, meta, coerce=True)
        raise


def _override(obj: Any, segments: list[str], depth: int, raw: str, key: str) -> Any:
    cls = type(obj)
    fields = _init_fields(cls)
    name = segments[depth]
    here = ".".join(segments[: depth + 1])
    if name not in fields:
        raise _unknown_key(here, name, fields)
    f = fields[name]
    tp = _hints(cls)[name]
    current = getattr(obj, name)
    rest = segments[depth + 1 :]
    inner = _single_member(tp)
    if not rest:
        new = _parse_override(tp, raw, here, f.metadata)
    elif _is_config_class(inner):
        if not isinstance(current, inner):
            raise ConfigError(f"{key}: {here} is null; set the whole table, e.g. {here}={{...}}")
        new = _override(current, segments, depth + 1, raw, key)
    elif _is_mapping_type(inner) and len(rest) == 1:
        args = get_args(inner)
        entry = _parse_override(args[1] if len(args) == 2 else Any, raw, key, f.metadata)
        new = {**(current or {}), rest[0]: entry}
    elif _is_mapping_type(inner):
        args = get_args(inner)
        entry_type = _expected(args[1]) if len(args) == 2 else "a value"
        raise ConfigError(f"{key}: {here}.{rest[0]} is {entry_type}; it has no sub-keys")
    else:
        raise ConfigError(f"{key}: {here} is {_expected(tp)}; it has no sub-keys")
    try:
        return dataclasses.replace(obj, **{name: new})
    except ValueError as exc:  # __post_init__ rejected the combination
        raise ConfigError(f"{key}: {exc}") from exc


def apply_overrides(obj: T, overrides: Iterable[str]) -> T:
    """A copy of ``obj`` with ``dotted.key=value`` overrides applied in order.

    Values are TOML literals: ``pose.distance_scale=[1.0, 1.2]``, ``sun.enabled=false``,
    ``name="abc"`` (or bare ``name=abc``), ``lr=3e-4``, ``scene.sun={enabled=false}`` (a table
    replaces the whole sub-config; missing keys take defaults), ``loss.weights.mask=2.0`` (one
    entry of a ``dict`` field), ``elevation=null`` (``None``). Unknown keys and bad values raise
    :class:`ConfigError` naming the key.
    """
    _require_instance(obj, "apply_overrides")
    if isinstance(overrides, str):
        raise TypeError("apply_overrides: pass a list of 'key=value' strings, not one string")
    for item in overrides:
        key, sep, raw = item.partition("=")
        segments = [s.strip() for s in key.split(".")]
        key = ".".join(segments)
        if not all(segments):
            raise ConfigError(f"override {item!r}: expected KEY=VALUE, KEY a dotted field name "
                              "(e.g. sun.enabled=false)")
        if not sep:
            raise ConfigError(f"override {item!r}: no '='; expected {key}=VALUE")
        obj = _override(obj, segments, 0, raw.strip(), key)
    return obj


# --- documentation --------------------------------------------------------------------------


@cache
def _own_field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings written in ``cls``'s own class body (not its bases)."""
    try:
        source = inspect.getsource(cls)
    except (OSError, TypeError):  # defined in a REPL or built dynamically
        return {}
    try:
        body = ast.parse(textwrap.dedent(source)).body
    except SyntaxError:  # a multi-line string defeated dedent; indent under a block instead
        body = ast.parse("if True:\n" + source).body[0].body  # type: ignore[attr-defined]
    classdef = next((node for node in body if isinstance(node, ast.ClassDef)), None)
    if classdef is None:
        return {}
    docs: dict[str, str] = {}
    for node, after in zip(classdef.body, classdef.body[1:], strict=False):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            docs[node.target.id] = inspect.cleandoc(after.value.value)
    return docs


def field_docs(cls: type) -> dict[str, str]:
    """Each field's documentation: the string literal on the line after it, in field order.

    Fields of dataclass bases are included; undocumented fields are left out. Returns ``{}``
    when the source is unavailable.
    """
    if not _is_config_class(cls):
        raise TypeError(f"field_docs: expected a config dataclass, got {cls!r}")
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if _is_config_class(klass):
            docs.update(_own_field_docs(klass))
    return {f.name: docs[f.name] for f in dataclasses.fields(cls) if f.name in docs}


def _summary(doc: str) -> str:
    """The first paragraph of a docstring on one line."""
    return " ".join(doc.split("\n\n", 1)[0].split())


def _note(tp: Any, meta: Mapping[str, Any]) -> str:
    notes = []
    limits = meta.get(_BOUNDS_KEY)
    if limits is not None:
        notes.append(limits.describe())
    inner = _single_member(tp)
    if get_origin(inner) is Literal:
        notes.append(_expected(inner))
    return f"({'; '.join(notes)})" if notes else ""


def _describe_rows(cls: type, instance: Any, prefix: str, rows: list[tuple[str, str]]) -> None:
    hints = _hints(cls)
    docs = field_docs(cls)
    for name, f in _init_fields(cls).items():
        tp = hints[name]
        value = _default_of(f) if instance is None else getattr(instance, name)
        inner = _single_member(tp)
        if _is_config_class(inner) and (value is dataclasses.MISSING or isinstance(value, inner)):
            nested = None if value is dataclasses.MISSING else value
            _describe_rows(inner, nested, f"{prefix}{name}.", rows)
            continue
        shown = (
            "<required>" if value is dataclasses.MISSING else _inline(_to_plain(tp, value), "null")
        )
        comment = " ".join(p for p in (_summary(docs.get(name, "")), _note(tp, f.metadata)) if p)
        rows.append((f"{prefix}{name} = {shown}", comment))


def describe(config: Any) -> str:
    """Every field as ``dotted.name = value  # doc (bounds)``, one per line, for ``--help``.

    Given a class, shows the defaults; given an instance, its values. Values are written as
    :func:`apply_overrides` accepts them.
    """
    cls = config if isinstance(config, type) else type(config)
    if not _is_config_class(cls):
        raise TypeError(f"describe: expected a config dataclass or instance, got {config!r}")
    rows: list[tuple[str, str]] = []
    _describe_rows(cls, None if isinstance(config, type) else config, "", rows)
    width = min(max((len(left) for left, _ in rows), default=0), 48)
    return "\n".join(f"{left:<{width}}  # {doc}" if doc else left for left, doc in rows)
