"""Every float field of every configuration refuses NaN and inf with a ConfigError that names it
(range checks alone let NaN through: every comparison with it is False)."""

import dataclasses
import math

import numpy as np
import pytest

from acoustic_sim import AtmosphereConfig, ChirpConfig, ConfigError, LidarConfig, PolarGrid, SonarConfig
from acoustic_sim.datasets.suites import Physics

BASES = {
    "PolarGrid": PolarGrid(),
    "LidarConfig": LidarConfig.hokuyo_ust20lx(),
    "ChirpConfig": ChirpConfig(),
    "AtmosphereConfig": AtmosphereConfig(),
    "SonarConfig": SonarConfig.ertis(),
    "Physics": Physics(),
}


def _float_fields():
    for name, base in BASES.items():
        for f in dataclasses.fields(base):
            value = getattr(base, f.name)
            numeric = isinstance(value, float) or (
                isinstance(value, tuple) and value and all(isinstance(v, float | int) for v in np.ravel(value))
            )
            if numeric and not isinstance(value, bool):
                yield name, f.name


CASES = [(n, f, bad) for n, f in _float_fields() for bad in (math.nan, math.inf)]


def _with(value, bad):
    """`value` with `bad` in place of its first number (same shape for tuples)."""
    if isinstance(value, float):
        return bad
    flat = np.array(value, dtype=float)
    flat.reshape(-1)[0] = bad
    return tuple(map(tuple, flat)) if flat.ndim == 2 else tuple(flat)


@pytest.mark.parametrize(("config", "field", "bad"), CASES, ids=[f"{n}.{f}={b}" for n, f, b in CASES])
def test_non_finite_field_is_refused(config, field, bad):
    base = BASES[config]
    with pytest.raises(ConfigError, match=rf"{config}\.{field} must be finite"):
        dataclasses.replace(base, **{field: _with(getattr(base, field), bad)})


def test_every_config_has_float_fields_under_test():
    """The enumeration above is not empty for any config (a test that cannot fail is a defect)."""
    assert {n for n, _, _ in CASES} == set(BASES) and len(CASES) >= 40
