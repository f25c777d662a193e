"""`section.field=value` settings (the CLIs' `--set`) applied to a tree of frozen config dataclasses."""

from __future__ import annotations

import dataclasses
import json
import typing
from collections.abc import Iterable
from typing import Literal

from .config import ConfigError


def apply_settings(config, settings: Iterable[str]):
    """A copy of `config` with each `section.field=value` applied (e.g. "tracer.max_bounces=1",
    "processing.grid.range_max_m=4", "sonar.atmosphere.temperature_c=30"). Values are read as the
    field's type: JSON numbers, booleans and lists, `none`, or a bare word for a string choice.
    Unknown names and unreadable or out-of-range values raise ConfigError naming the setting."""
    for setting in settings:
        path, sep, text = setting.partition("=")
        if not sep or not path.strip():
            raise ConfigError(f"--set wants section.field=value, got {setting!r}")
        config = _replace_path(config, path.strip().split("."), text.strip(), setting)
    return config


def _replace_path(config, names: list[str], text: str, setting: str):
    fields = {f.name: f for f in dataclasses.fields(config)}
    name = names[0]
    if name not in fields:
        where = type(config).__name__
        raise ConfigError(f"--set {setting!r}: {where} has no field {name!r}; it has {', '.join(fields)}")
    current = getattr(config, name)
    if len(names) > 1:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(f"--set {setting!r}: {name} is a value, not a section")
        value = _replace_path(current, names[1:], text, setting)
    elif dataclasses.is_dataclass(current):
        value = _preset(type(current), text, setting)
    else:
        value = _parse_value(text, typing.get_type_hints(type(config))[name], setting)
    try:
        return dataclasses.replace(config, **{name: value})
    except (TypeError, ValueError) as err:
        raise ConfigError(f"--set {setting!r}: {err}") from None


def _parse_value(text: str, hint, setting: str):
    """`text` as a value of the type `hint` (bool, int, float, str, Literal, Optional, tuples)."""
    if text.lower() in ("none", "null") and {None, type(None)} & set(typing.get_args(hint)):
        return None
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        value = text  # a bare word: a string choice
    options = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, type(int | None)) else (hint,)
    for option in options:
        if typing.get_origin(option) is Literal and value in typing.get_args(option):
            return value
        if option is bool and isinstance(value, bool):
            return value
        if option is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if option is float and isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        if option is float and isinstance(value, str) and value.lower() in ("nan", "inf", "-inf"):
            return float(value)  # JSON spells them NaN and Infinity; the config then refuses them by name
        if option is str and isinstance(value, str):
            return value
        if typing.get_origin(option) is tuple and isinstance(value, list):
            return tuple(tuple(v) if isinstance(v, list) else v for v in value)
    raise ConfigError(f"--set {setting!r}: {text!r} is not a valid {hint}")


def _preset(cls, name: str, setting: str):
    """`cls.name()` for a preset classmethod such as LidarConfig.multibeam_64x1024."""
    presets = sorted(k for k, v in vars(cls).items() if isinstance(v, classmethod) and not k.startswith("_"))
    if name not in presets:
        choices = ", ".join(presets) or "none"
        raise ConfigError(f"--set {setting!r}: a section takes a preset ({choices}) or section.field=value")
    return getattr(cls, name)()
