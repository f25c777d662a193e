"""`section.field=value` settings applied to a tree of frozen dataclasses: the `--set` grammar.

A setting names a field of a tree of frozen dataclasses by its path from the root
(`tracer.max_bounces=1`, `processing.grid.range_max_m=4`, `train.lr=3e-4`) and gives its value as
text, read as the field's type:

- int: an integer (`3`, `-2`), or a number with an integral value (`1e3`, `2.0`).
- float: any number (`3e-4`, `-2`, `.5`); `nan` and `inf` are read as numbers, so the config
  itself refuses them by name.
- bool: `true` or `false` (any case); `1`, `0`, `yes` and `no` are refused.
- Optional fields (`X | None`, `Literal[None, ...]`): `none` or `null` (any case) is None.
- Literal: one of its choices, bare (`db`) or quoted (`"db"`).
- str: the text as it stands, or unquoted when quoted.
- tuple: a JSON list (`[0, 10]`, nested `[[0, 0, 0], [0.1, 0, 0]]`), each item read as its type.
- A union (`float | tuple[float, ...]`): the first of its types that reads the text.
- A section (a field holding a dataclass) takes the name of a preset, one of its class's public
  classmethods (`lidar=multibeam_64x1024`, `augment=none`).

A setting that cannot be applied raises SettingsError (a ValueError) naming the setting: an unknown
section or field (listing those there are), a value not of the field's type (saying what it
takes), or the config's own refusal of the value.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from collections.abc import Iterable
from typing import Literal

NONE_WORDS = ("none", "null")
BOOL_WORDS = {"true": True, "false": False}


class SettingsError(ValueError):
    """A setting that cannot be applied: its form, an unknown name, or a value the field refuses."""


def apply_settings(root, settings: Iterable[str]):
    """A copy of `root` (a frozen dataclass) with each `path=value` setting applied in turn.

    Args:
        root: The root of a tree of frozen dataclasses (e.g. SimConfig, LearnConfig).
        settings: Settings such as "tracer.max_bounces=1", "train.lr=3e-4" or "lidar=multibeam_64x1024".

    Returns:
        The new root; every config on the path was rebuilt, so each checked its fields again.

    Raises:
        SettingsError: naming the setting, for a malformed setting, an unknown section or field (with
            the names there are), a value not of the field's type, or the config's own refusal.
    """
    for setting in [settings] if isinstance(settings, str) else settings:
        path, sep, text = setting.partition("=")
        if not sep or not path.strip():
            sections = ", ".join(f.name for f in dataclasses.fields(root))
            raise SettingsError(f"--set wants section.field=value (sections: {sections}), got {setting!r}")
        root = _replace(root, path.strip().split("."), [], text.strip(), setting)
    return root


def _replace(config, names: list[str], above: list[str], text: str, setting: str):
    """`config` with the field at `names` (below the sections `above`) set from `text`."""
    fields = [f.name for f in dataclasses.fields(config)]
    name = names[0]
    if name not in fields:
        where = f"{'.'.join(above)} has no field" if above else "there is no section"
        raise SettingsError(
            f"--set {setting!r}: {where} {name!r}; {'it has' if above else 'the sections are'} {', '.join(fields)}"
        )
    current = getattr(config, name)
    if len(names) > 1:
        if not dataclasses.is_dataclass(current):
            raise SettingsError(f"--set {setting!r}: {'.'.join([*above, name])} is a value, not a section")
        value = _replace(current, names[1:], [*above, name], text, setting)
    elif dataclasses.is_dataclass(current):
        value = _preset(type(current), text, setting, ".".join([*above, name]))
    else:
        try:
            value = read_value(text, typing.get_type_hints(type(config))[name])
        except SettingsError as err:
            raise SettingsError(f"--set {setting!r}: {err}") from None
    try:
        return dataclasses.replace(config, **{name: value})
    except (TypeError, ValueError) as err:  # the config's own checks
        raise SettingsError(f"--set {setting!r}: {err}") from None


def _preset(cls, name: str, setting: str, path: str):
    """`cls.name()` for a preset classmethod such as LidarConfig.multibeam_64x1024."""
    presets = sorted(k for k, v in vars(cls).items() if isinstance(v, classmethod) and not k.startswith("_"))
    if not presets:
        raise SettingsError(f"--set {setting!r}: {path} is a section without presets: give {path}.field=value")
    if name not in presets:
        choices = ", ".join(presets)
        raise SettingsError(f"--set {setting!r}: a section takes a preset ({choices}) or section.field=value")
    return getattr(cls, name)()


def read_value(text: str, hint):
    """`text` (from a command line) as a value of the type `hint`.

    Args:
        text: The value as written, e.g. "3", "1e3", "true", "none", "db", "[0, 10]".
        hint: A type: bool, int, float, str, a Literal, a tuple type, or a union of them (with None).

    Returns:
        The value: None, bool, int, float, str or a (nested) tuple.

    Raises:
        SettingsError: `text` is not a value of `hint`; the message says what it takes.
    """
    text = text.strip()
    options = _options(hint)
    if text.lower() in NONE_WORDS and None in options:
        return None
    for option in options:
        try:
            return _from_text(text, option)
        except (ValueError, TypeError):
            continue
    raise SettingsError(f"{text!r} is not a valid value: give {describe(hint)}")


def describe(hint) -> str:
    """What a value of `hint` looks like, for error messages: "an integer", "none or a number"."""
    options = _options(hint)
    if len(options) > 1:
        return " or ".join(describe(o) for o in options)
    (hint,) = options
    if hint is None:
        return "none"
    if typing.get_origin(hint) is Literal:
        return "one of " + ", ".join("none" if c is None else repr(c) for c in typing.get_args(hint))
    if typing.get_origin(hint) is tuple:
        items = typing.get_args(hint)
        if len(items) == 2 and items[1] is Ellipsis:
            return f"a list like [1, 2], each item {describe(items[0])}"
        return f"a list of {len(items)} items: " + ", ".join(describe(i) for i in items)
    words = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    return words.get(hint, getattr(hint, "__name__", str(hint)))


def _options(hint) -> list:
    """The types a value of `hint` may have, None for NoneType; Literal choices of None apart."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return [o for arg in typing.get_args(hint) for o in _options(arg)]
    if hint is type(None) or hint is None:
        return [None]
    if typing.get_origin(hint) is Literal and None in typing.get_args(hint):
        others = tuple(c for c in typing.get_args(hint) if c is not None)
        return [Literal[others], None] if others else [None]
    return [hint]


def _from_text(text: str, hint):
    """`text` as a value of one type (not a union); ValueError or TypeError when it is not one."""
    if typing.get_origin(hint) is tuple:
        value = json.loads(text)  # JSON reads NaN and Infinity too, so the config refuses them by name
        if not isinstance(value, list):
            raise TypeError("not a list")
        return _from_json(value, hint)
    if hint is bool:
        return BOOL_WORDS[text.lower()] if text.lower() in BOOL_WORDS else _refuse()
    if hint is int:
        return _integer(text)
    if hint is float:
        return float(text)  # "nan" and "inf" too: the config's own check names the field
    word = _unquoted(text)
    if hint is str:
        return word
    if typing.get_origin(hint) is Literal:
        for choice in typing.get_args(hint):
            if isinstance(choice, str) and word == choice:
                return choice
            if isinstance(choice, int) and not isinstance(choice, bool) and word == str(choice):
                return choice
    return _refuse()


def _from_json(value, hint):
    """An item of a JSON list as a value of `hint` (which may be a union)."""
    options = _options(hint)
    if value is None and None in options:
        return None
    for option in options:
        if option is None:
            continue
        if typing.get_origin(option) is tuple and isinstance(value, list):
            items = typing.get_args(option)
            if len(items) == 2 and items[1] is Ellipsis:
                return tuple(_from_json(v, items[0]) for v in value)
            if len(items) != len(value):
                continue
            return tuple(_from_json(v, i) for v, i in zip(value, items, strict=True))
        if isinstance(value, bool):
            if option is bool:
                return value
            continue  # a boolean is no number
        if option is float and isinstance(value, int | float):
            return float(value)
        if option is int and isinstance(value, int | float):
            return _integer(str(value))
        if option is str and isinstance(value, str):
            return value
        if typing.get_origin(option) is Literal and isinstance(value, str | int) and value in typing.get_args(option):
            return value
    raise ValueError(f"{json.dumps(value)} is not {describe(hint)}")


def _integer(text: str) -> int:
    """An int from "3", "-2", "1e3" or "2.0"; ValueError for "1.5", "nan" or a word."""
    try:
        return int(text)
    except ValueError:
        number = float(text)
        if not number.is_integer():
            raise
        return int(number)


def _unquoted(text: str) -> str:
    if len(text) >= 2 and text[0] == text[-1] == '"':
        return json.loads(text)
    if len(text) >= 2 and text[0] == text[-1] == "'":
        return text[1:-1]
    return text


def _refuse():
    raise ValueError("not of this type")
