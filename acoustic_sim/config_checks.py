"""The checks every configuration class runs on itself when built: finite numbers and sizes that fit
in memory, refused as ConfigError naming the field (re-exported by `acoustic_sim.config`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from clitools.limits import check_memory


class ConfigError(ValueError):
    """A configuration value that is missing, non-finite or out of range."""


def check_memory_for(needed: float, what: str, advice: str) -> None:
    """Refuse a config whose sizes need more memory than this machine has free (ConfigError with
    both figures, before anything is allocated); `what` names the fields, `advice` says what to
    give instead. Each class counts the bytes the simulator holds per unit of its sizes, at least."""
    try:
        check_memory(needed, what=what, advice=advice)
    except ValueError as err:
        raise ConfigError(str(err)) from None


def check_finite(config) -> None:
    """Refuse NaN and inf in every float field of a config dataclass (and in float tuples and
    arrays), naming the field: comparisons with NaN are False, so range checks alone let it pass."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if isinstance(value, float | np.floating):
            numbers = np.float64(value)
        elif isinstance(value, np.ndarray) and value.dtype.kind in "fc":
            numbers = value
        elif isinstance(value, tuple | list) and value and all(isinstance(v, float | int) for v in np.ravel(value)):
            numbers = np.asarray(value, dtype=np.float64)
        else:
            continue  # ints, strings, flags, nested configs (checked when built), tables of other things
        if not np.isfinite(numbers).all():
            raise ConfigError(f"{type(config).__name__}.{f.name} must be finite, got {value!r}")
