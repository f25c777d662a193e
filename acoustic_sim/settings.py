"""`section.field=value` settings (the CLIs' `--set`) applied to the SimConfig tree: the grammar is
`configtree`'s, the one `python -m learn` uses too; here its refusals are ConfigErrors."""

from __future__ import annotations

from collections.abc import Iterable

import configtree

from .config import ConfigError


def apply_settings(config, settings: Iterable[str]):
    """A copy of `config` with each `section.field=value` applied (e.g. "tracer.max_bounces=1",
    "processing.grid.range_max_m=4", "sonar.atmosphere.temperature_c=30", "lidar=multibeam_64x1024");
    values are read as the field's type (see `configtree`). Unknown names and unreadable or
    out-of-range values raise ConfigError naming the setting."""
    try:
        return configtree.apply_settings(config, settings)
    except configtree.SettingsError as err:
        raise ConfigError(str(err)) from None
