"""Reading configuration: YAML files and typed dataclasses, with errors that name the field.

Every config error says *where* (``scenario.sites[1].cells[0].pci``) and *what* is wrong, so a
user fixes the file without reading code.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import re
import reprlib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import yaml


T = TypeVar("T")
_YAML11_EXPONENT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


class ConfigError(ValueError):
    """A configuration value is missing, malformed or out of range; the message names it."""


MAX_CONFIG_BYTES = 16 * 2**20  # a config file larger than this is no config (ours are a few kB)


def read_config_bytes(path: str | Path, where: str | None = None) -> bytes:
    """The bytes of a config file, read once (a FIFO or a process substitution cannot be read
    twice: whatever else needs them, a hash for the provenance, takes these), at most
    :data:`MAX_CONFIG_BYTES`; ConfigError naming the file on any problem."""
    where = where or str(path)
    try:
        with open(path, "rb") as handle:
            data = handle.read(MAX_CONFIG_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(f"{where}: file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{where}: a directory, not a file") from None
    except OSError as error:
        raise ConfigError(f"{where}: cannot read ({error.strerror or error})") from None
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{where}: larger than {MAX_CONFIG_BYTES // 2**20} MiB: not a config file")
    return data


def load_yaml(path: str | Path, where: str | None = None) -> dict[str, Any]:
    """Load a YAML mapping with ``yaml.safe_load``; raise :class:`ConfigError` on any problem."""
    where = where or str(path)
    return parse_yaml(read_config_bytes(path, where), where)


def parse_yaml(data: bytes | str, where: str) -> dict[str, Any]:
    """A YAML mapping from a config's bytes or text (what :func:`load_yaml` reads), through every
    guard: ``safe_load``, UTF-8, a mapping at the top, string keys, bounded nesting and alias
    expansion (:func:`check_tree`). The one way the project parses YAML: ConfigError naming
    ``where`` on any problem."""
    if isinstance(data, bytes):
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as error:
            raise ConfigError(f"{where}: not UTF-8 text (byte {error.object[error.start]:#04x} at offset "
                              f"{error.start}): not a YAML file?") from None
    else:
        text = data
    if len(text) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{where}: larger than {MAX_CONFIG_BYTES // 2**20} MiB: not a config file")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        position = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(error, "problem", None) or str(error)
        raise ConfigError(f"{where}: invalid YAML{position}: {problem}") from None
    except RecursionError:
        raise ConfigError(f"{where}: nested too deeply to read (more than Python's recursion limit)") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping at the top level, got {type(data).__name__}")
    check_tree(data, where)
    return data


MAX_DEPTH = 64  # levels of nesting a config may have (ours use 5)
MAX_VALUES = 1_000_000  # values a config may expand to through YAML aliases (ours hold a few hundred)


def check_tree(value: object, where: str) -> int:
    """How many values a parsed document (YAML, JSON) expands to; ConfigError naming ``where``
    and the place for a key that is not a string, nesting deeper than ``MAX_DEPTH`` or more
    than ``MAX_VALUES`` values (see :func:`_check_tree`)."""
    return _check_tree(value, where, 0, {})


def _check_tree(value: object, where: str, depth: int, sizes: dict[int, int]) -> int:
    """How many values ``value`` expands to; ConfigError for a mapping key that is not a string
    (the loaders look keys up by name), nesting deeper than ``MAX_DEPTH``, or more than
    ``MAX_VALUES`` values: YAML aliases nested in aliases (a "billion laughs" file) expand
    exponentially wherever the value is later walked or printed. Each shared node is counted
    once (``sizes``, by id), so the check itself stays linear in the file."""
    if not isinstance(value, (dict, list)):
        return 1
    if id(value) in sizes:
        return sizes[id(value)]
    if depth >= MAX_DEPTH:
        raise ConfigError(f"{where}: nested more than {MAX_DEPTH} levels deep")
    if isinstance(value, dict):
        for key in value:
            if not isinstance(key, str):
                raise ConfigError(f"{where}: key {reprlib.repr(key)} is not a string (quote it)")
        items = [(f"{where}.{key}", item) for key, item in value.items()]
    else:
        items = [(f"{where}[{i}]", item) for i, item in enumerate(value)]
    total = 1
    for at, item in items:
        total += _check_tree(item, at, depth + 1, sizes)
        if total > MAX_VALUES:
            raise ConfigError(f"{where}: expands to more than {MAX_VALUES:,} values (aliases nested in aliases?)")
    sizes[id(value)] = total
    return total


def require_mapping(value: object, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}: expected a mapping, got {type(value).__name__}")
    return value


def require_list(value: object, where: str) -> list[Any]:
    if not isinstance(value, list):
        raise ConfigError(f"{where}: expected a list, got {type(value).__name__}")
    return value


def _coerce(value: Any, annotation: Any, where: str) -> Any:
    """Check ``value`` against a simple type annotation (numbers, str, bool, optionals, tuples)."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(annotation)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _coerce(value, option, where)
            except ConfigError as error:
                errors.append(str(error))
        raise ConfigError(errors[0] if len(errors) == 1 else f"{where}: {reprlib.repr(value)} has the wrong type")
    if origin is tuple:
        items = typing.get_args(annotation)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {type(value).__name__}")
        if len(items) == 2 and items[1] is Ellipsis:
            return tuple(_coerce(v, items[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(items):
            raise ConfigError(f"{where}: expected {len(items)} values, got {len(value)}")
        return tuple(_coerce(v, t, f"{where}[{i}]") for i, (v, t) in enumerate(zip(value, items)))
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {reprlib.repr(value)}")
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{where}: expected an integer, got {reprlib.repr(value)}")
        return value
    if annotation is float:
        if isinstance(value, str) and _YAML11_EXPONENT.fullmatch(value.strip()):
            value = float(value)  # PyYAML (YAML 1.1) reads 3.84e6, without a dot or sign, as text
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {reprlib.repr(value)}")
        if not math.isfinite(value):
            raise ConfigError(f"{where}: must be a finite number, got {reprlib.repr(value)}")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {reprlib.repr(value)}")
        return value
    return value


def build_dataclass(cls: type[T], data: object, where: str) -> T:
    """Instantiate dataclass ``cls`` from a mapping, checking keys, types and finiteness.

    Unknown keys are rejected (a typo must not silently fall back to a default); errors from
    the dataclass's own ``__post_init__`` checks are re-raised prefixed with ``where``.
    """
    mapping = require_mapping(data, where)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(mapping) - set(fields))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} "
            f"(known: {', '.join(sorted(fields))})"
        )
    kwargs = {}
    for name, field in fields.items():
        if name not in mapping:
            if field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{where}.{name}: required but missing")
            continue
        kwargs[name] = _coerce(mapping[name], hints[name], f"{where}.{name}")
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as error:
        raise ConfigError(f"{where}: {error}") from None


def choice_name(value: object) -> str:
    """A config's choice (an enum: the dataset's ``Channel``, the model's ``Fusion``, ``Head``) as
    YAML and JSON records hold it, by its value; TypeError for anything else (``json.dumps``'s
    ``default``)."""
    if isinstance(value, enum.Enum):
        return value.value
    raise TypeError(f"{type(value).__name__} is not JSON serializable")
