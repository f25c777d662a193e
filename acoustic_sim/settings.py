"""`section.field=value` settings (the CLIs' `--set`) applied to the SimConfig tree: the grammar is
`clitools`'s, the one `python -m learn` uses too; here its refusals are ConfigErrors."""

from __future__ import annotations

from collections.abc import Iterable

import clitools

from .config import ConfigError


def apply_settings(config, settings: Iterable[str]):
    """A copy of `config` with each `section.field=value` applied (e.g. "tracer.max_bounces=1",
    "processing.grid.range_max_m=4", "sonar.atmosphere.temperature_c=30", "lidar=multibeam_64x1024");
    values are read as the field's type (see `clitools`). Unknown names and unreadable or
    out-of-range values raise ConfigError naming the setting."""
    try:
        return clitools.apply_settings(config, settings)
    except clitools.SettingsError as err:
        raise ConfigError(str(err)) from None
