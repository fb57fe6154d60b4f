"""The one place a setting's meaning, unit and allowed values are written: on its config field.

A frozen config dataclass declares a user-facing field with :func:`setting` (its default, a
sentence of help, the unit, the bounds or the choices) and checks it in ``__post_init__`` with
:func:`check_settings`; the ROS parameter descriptors (``deepsync_ros.params``) and the command
line's flags (:func:`add_flag`) are generated from the same :class:`Setting`, so a range or a
help text is never written twice. A choice that is not a config field (the motion model) is a
standalone :class:`Setting` beside its registry.

Neutral ground: no project imports.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import reprlib
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

_SETTING = "deepsync.setting"  # the key of a field's metadata that holds its Setting


@dataclass(frozen=True)
class Setting:
    """What a user may set: ``name``, ``kind`` (bool, int, float or str), a sentence of ``help``,
    the ``unit``, inclusive ``bounds`` of a number (``open_low`` / ``open_high`` exclude an end),
    or the ``choices`` of a name (a registry: name -> what the config holds). ``sequence``: the
    value is a tuple of such values, each checked, ``length`` of them (None: any number)."""

    name: str
    kind: type
    help: str
    unit: str = ""
    bounds: tuple[float, float] | None = None
    open_low: bool = False
    open_high: bool = False
    choices: Mapping[str, Any] | None = None
    sequence: bool = False
    length: int | None = None

    @property
    def interval(self) -> str:
        """The bounds as a person reads them: ``[1, 1000]``, ``(0, 0.5)``, with the unit."""
        if self.bounds is None:
            return ""
        low, high = self.bounds
        text = f"{'(' if self.open_low else '['}{low:g}, {high:g}{')' if self.open_high else ']'}"
        return f"{text} {self.unit}".rstrip()

    @property
    def names(self) -> tuple[str, ...]:
        return () if self.choices is None else tuple(self.choices)

    @property
    def described(self) -> str:
        """The help with the unit, and each choice's own summary where its registry has one,
        as ``--help`` and ``ros2 param describe`` show it."""
        text = f"{self.help} [{self.unit}]" if self.unit else self.help
        summaries = {name: getattr(item, "summary", None) for name, item in (self.choices or {}).items()}
        if all(summaries.values()) and summaries:
            text += " " + "; ".join(f"{name}: {summary}" for name, summary in summaries.items()) + "."
        return text

    def name_of(self, value: object) -> object:
        """A config's value as a user writes it: a choice's name (the config may hold the
        registry's object), anything else as it is."""
        if self.choices is not None and not isinstance(value, str):
            return next((name for name, item in self.choices.items() if item is value), value)
        return value

    def check(self, value: object, name: str | None = None) -> None:
        """ValueError naming the setting (or ``name``) unless ``value`` is of its kind, finite,
        within its bounds and one of its choices (a name, or what a name stands for); of a
        sequence, unless it is a tuple of ``length`` such values."""
        name = name or self.name
        if self.sequence:
            if not isinstance(value, tuple) or (self.length is not None and len(value) != self.length):
                raise ValueError(f"{name} must be {self.length or 'a list of'} {self._kind_text(plural=True)}, got "
                                 f"{reprlib.repr(value)}")
            for item in value:
                self._check_one(item, name)
            return
        self._check_one(value, name)

    def _kind_text(self, plural: bool = False) -> str:
        if plural:
            return {bool: "true/false values", int: "integers", float: "numbers", str: "strings"}[self.kind]
        return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}[self.kind]

    def _check_one(self, value: object, name: str) -> None:
        if self.choices is not None:
            if value not in self.names and not any(value is item for item in self.choices.values()):
                raise ValueError(f"{name} must be one of {', '.join(self.names)}, got {reprlib.repr(value)}")
            return
        if self.kind is bool or self.kind is str:
            if not isinstance(value, self.kind):
                raise ValueError(f"{name} must be {self._kind_text()}, got {reprlib.repr(value)}")
            return
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (
                self.kind is int and not isinstance(value, int)):
            raise ValueError(f"{name} must be {self._kind_text()}, got {reprlib.repr(value)}")
        if isinstance(value, float) and not math.isfinite(value):  # an int is (and 10**400 overflows a float)
            raise ValueError(f"{name} must be a finite number, got {reprlib.repr(value)}")
        if self.bounds is not None:
            low, high = self.bounds
            above = value > low if self.open_low else value >= low
            below = value < high if self.open_high else value <= high
            if not (above and below):  # an int compares exactly (no float conversion)
                raise ValueError(f"{name} must be within {self.interval}, got {reprlib.repr(value)}")

    def parse(self, text: str) -> Any:
        """A command line's text as this setting's value (argparse's ``type``): ArgumentTypeError
        saying what is wrong."""
        try:
            value = self.kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{reprlib.repr(text)} is not "
                                             f"{'a whole number' if self.kind is int else 'a number'}") from None
        try:
            self.check(value)
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
        return value


def setting(default: Any = dataclasses.MISSING, *, help: str, unit: str = "",
            bounds: tuple[float, float] | None = None, open_low: bool = False, open_high: bool = False,
            choices: Mapping[str, Any] | None = None, default_factory: Any = dataclasses.MISSING) -> Any:
    """A dataclass field that is a user-facing setting (see :class:`Setting`); its name and
    kind come from the field itself (:func:`settings`)."""
    described = {"help": help, "unit": unit, "bounds": bounds, "open_low": open_low, "open_high": open_high,
                  "choices": choices}
    return dataclasses.field(default=default, default_factory=default_factory, metadata={_SETTING: described})


def settings(cls: type) -> dict[str, Setting]:
    """Field name -> :class:`Setting`, for every field of dataclass ``cls`` declared with
    :func:`setting`, in declaration order."""
    return _settings(cls if isinstance(cls, type) else type(cls))


_CACHE: dict[type, dict[str, Setting]] = {}


def _settings(cls: type) -> dict[str, Setting]:
    if cls not in _CACHE:
        hints = typing.get_type_hints(cls)
        found = {}
        for field in dataclasses.fields(cls):
            if _SETTING in field.metadata:
                kind, shape = _shape(hints[field.name])
                found[field.name] = Setting(field.name, kind, **field.metadata[_SETTING], **shape)
        _CACHE[cls] = found
    return _CACHE[cls]


def _shape(annotation: Any) -> tuple[type, dict[str, Any]]:
    """A field annotation's kind (bool, int, float or str; ``int | None``: int; a registry's
    object: str, the name a user writes) and, for a tuple, ``sequence`` and its ``length``
    (``tuple[float, float]``: 2, ``tuple[int, ...]``: any)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        annotation = next(a for a in typing.get_args(annotation) if a is not type(None))
    shape: dict[str, Any] = {}
    if typing.get_origin(annotation) is tuple:
        items = typing.get_args(annotation)
        shape = {"sequence": True, "length": None if Ellipsis in items else len(items)}
        annotation = items[0]
    return (annotation if annotation in (bool, int, float, str) else str), shape


def of(cls: type, name: str) -> Setting:
    """The setting of ``cls``'s field ``name``; KeyError naming it if the field is not one."""
    try:
        return settings(cls)[name]
    except KeyError:
        raise KeyError(f"{cls.__name__}.{name} is not declared with deepsync.schema.setting") from None


def check_settings(config: object) -> None:
    """ValueError naming the first field of ``config`` whose value its :class:`Setting` refuses
    (None passes: an optional field left unset). Run from a frozen config's ``__post_init__``."""
    for name, described in settings(type(config)).items():
        value = getattr(config, name)
        if value is not None:
            described.check(value)


def resolve_choices(config: object) -> None:
    """Each choice field of frozen ``config`` given by its name (as YAML and files hold it)
    set to what the name stands for; after :func:`check_settings`, in ``__post_init__``."""
    for name, described in settings(type(config)).items():
        value = getattr(config, name)
        if described.choices is not None and isinstance(value, str) and value in described.choices:
            object.__setattr__(config, name, described.choices[value])


def add_flag(parser: argparse.ArgumentParser | argparse._ArgumentGroup, described: Setting, flag: str, *,
             default: Any = None, unset: str | None = None, **more: Any) -> argparse.Action:
    """A command-line flag for a setting: its type checks the bounds, its choices are the
    registry's, its help is the setting's with the default (``unset``: what no value means).
    The action remembers its setting (``action.setting``) for the test that no flag of a config
    field is written by hand."""
    if described.sequence:
        raise ValueError(f"{described.name}: a sequence setting is not a flag of its own")
    if described.choices is not None:
        more.update(choices=described.names, metavar=more.get("metavar", "NAME"))
    elif described.kind is bool:
        raise ValueError(f"{described.name}: a true/false setting is not a flag of its own")
    else:
        more["type"] = described.parse
    shown = described.name_of(default) if default is not None else None
    told = f"default {shown}" if unset is None else f"default: {unset}"
    bounds = f"; {described.interval}" if described.bounds is not None else ""
    text = described.described.replace(f" [{described.unit}]", "") if bounds else described.described
    action = parser.add_argument(flag, default=shown, help=f"{text.rstrip('.')} ({told}{bounds})", **more)
    action.setting = described
    return action
