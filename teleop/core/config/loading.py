"""Loading: a TOML table to typed sections (every value coerced to its field's type,
unknown and missing keys refused, a misspelt key given a suggestion, a range error given
the value), ``--set`` overrides, and :func:`load_config`, the one way a service gets its
:class:`Config`."""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import tomllib
import types
import typing
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from teleop.core.config.base import DEFAULT_CONFIG_FILE, ConfigError, require
from teleop.core.config.whole import Config

_T = TypeVar("_T")

# How close a misspelt key must be to a real one to be suggested (difflib ratio, 0-1).
SUGGESTION_CUTOFF = 0.6
# First characters of a --set value meant as a TOML literal (list, table, string).
TOML_OPENERS = ("[", "{", '"', "'")


def _coerce(value: Any, annotation: Any, key: str) -> Any:
    """Convert a TOML value to the field's annotated type, or raise ConfigError."""
    origin = typing.get_origin(annotation)
    if dataclasses.is_dataclass(annotation):
        require(isinstance(value, Mapping), f"{key}: expected a table")
        return _build(annotation, value, key)
    if annotation is bool:
        require(isinstance(value, bool), f"{key}: expected true or false, got {value!r}")
        return value
    if annotation is int:
        require(
            isinstance(value, int) and not isinstance(value, bool), f"{key}: expected an integer"
        )
        return value
    if annotation is float:
        require(
            isinstance(value, int | float) and not isinstance(value, bool),
            f"{key}: expected a number, got {value!r}",
        )
        require(math.isfinite(value), f"{key}: must be finite")
        return float(value)
    if annotation is str:
        require(isinstance(value, str), f"{key}: expected a string, got {value!r}")
        return value
    if origin is tuple:
        require(isinstance(value, list | tuple), f"{key}: expected a list")
        args = typing.get_args(annotation)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
        require(len(value) == len(args), f"{key}: expected {len(args)} items")
        return tuple(
            _coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
        )
    if origin in (typing.Union, types.UnionType):
        raise ConfigError(f"{key}: unsupported union type")
    return value


def _fields(cls: type, table: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    """The constructor arguments of dataclass ``cls`` from ``table``: no unknown key, no
    missing key without a default, every value coerced to its field's type."""
    hints = typing.get_type_hints(cls)
    fields = dataclasses.fields(cls)
    where = prefix or "config"
    names = [f.name for f in fields]
    unknown = sorted(set(table) - set(names))
    require(
        not unknown, f"{where}: unknown key(s) {', '.join(map(_with_suggestion(names), unknown))}"
    )
    missing = [
        f.name
        for f in fields
        if f.name not in table
        and f.default is dataclasses.MISSING
        and f.default_factory is dataclasses.MISSING
    ]
    require(not missing, f"{where}: missing key(s) {', '.join(missing)}")
    return {
        name: _coerce(value, hints[name], f"{prefix}.{name}" if prefix else name)
        for name, value in table.items()
    }


def _with_suggestion(names: Sequence[str]) -> Callable[[str], str]:
    """``key`` -> ``key (did you mean X?)`` when one of ``names`` is close to it."""

    def suggest(key: str) -> str:
        close = difflib.get_close_matches(key, names, n=1, cutoff=SUGGESTION_CUTOFF)
        return f"{key} (did you mean {close[0]}?)" if close else key

    return suggest


# A value shown in an error message: scalars and short lists, not whole sections.
_SHOWN_VALUE_TYPES = (bool, int, float, str, tuple)


def _with_value(message: str, kwargs: Mapping[str, Any]) -> str:
    """Append the offending value to a range error that starts with the field's dotted
    name (``run.duration_s > 0`` -> ``... (got -3.0)``), when it was given."""
    match = re.match(r"([A-Za-z_][\w.]*)", message)
    if match is None or "got " in message:
        return message
    name = match.group(1).rsplit(".", 1)[-1]
    value = kwargs.get(name, _MISSING)
    if value is _MISSING or not isinstance(value, _SHOWN_VALUE_TYPES):
        return message
    return f"{message} (got {value!r})"


_MISSING = object()


def _build(cls: type, table: Mapping[str, Any], prefix: str) -> Any:
    kwargs = _fields(cls, table, prefix)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(_with_value(str(exc), kwargs)) from None


def build(cls: type[_T], table: Mapping[str, Any], prefix: str) -> _T:
    """A ``cls`` dataclass from a parsed TOML table, checked as the config's sections are.

    Unknown keys, missing keys (fields without a default) and mistyped values are errors
    naming ``prefix.key``; a value the dataclass itself refuses (its ``__post_init__``) is
    an error prefixed with ``prefix``. Other TOML files (scenarios) load through this.
    """
    kwargs = _fields(cls, table, prefix)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{prefix}: {_with_value(str(exc), kwargs)}") from exc


def _parse_override(text: str) -> tuple[list[str], Any]:
    key, sep, raw = text.partition("=")
    require(bool(sep) and bool(key.strip()), f"--set {text!r}: expected dotted.key=value")
    raw = raw.strip()
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError as exc:
        if raw[:1] in TOML_OPENERS:  # meant as a TOML literal: say what is wrong with it
            raise ConfigError(
                f"--set {key.strip()}={raw}: not valid TOML ({exc}); e.g. [0.1, 0.0, 0.3], "
                '"text", true'
            ) from None
        value = raw  # a bare word: taken as a string
    return key.strip().split("."), value


def _merge_override(table: dict[str, Any], path: list[str], value: Any) -> None:
    node = table
    for part in path[:-1]:
        node = node.setdefault(part, {})
        require(isinstance(node, dict), f"--set {'.'.join(path)}: {part} is not a table")
    node[path[-1]] = value


def read_toml(path: Path, error: type[ConfigError] = ConfigError) -> dict[str, Any]:
    """A TOML file as a table; ``error`` (a ConfigError) names the file on any problem."""
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError as exc:
        raise error(f"{path.name} not found: {path}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: {exc}") from exc


def load_config(path: str | Path | None = None, overrides: Iterable[str] = ()) -> Config:
    """Read a TOML config (default ``deploy/teleop.toml``), apply ``--set`` overrides.

    Missing keys take the dataclass defaults; unknown keys are an error, so a typo in
    a key never passes silently.
    """
    config_path = Path(path) if path is not None else DEFAULT_CONFIG_FILE
    table: dict[str, Any] = {}
    if path is not None or config_path.exists():
        table = read_toml(config_path)
    for text in overrides:
        keys, value = _parse_override(text)
        _merge_override(table, keys, value)
    try:
        return _build(Config, table, "")
    except TypeError as exc:
        raise ConfigError(str(exc)) from exc
