"""Sensor model of the sonar: the call, air, microphone geometry and emitter directivity.

References are independent of our code: published ISO 9613-1 figures, air absorption built from
relaxation physics (tests/reference/air_absorption.py), the textbook speed of
sound, the zeros of J1, and a frequency estimate made from the chirp's zero crossings.
"""

import dataclasses

import numpy as np
import pytest

import acoustic_sim as sim
from acoustic_sim.air import air_absorption_db_per_m, chirp, instantaneous_frequency, speed_of_sound
from acoustic_sim.array import ertis_microphones, piston_directivity
from tests.reference.air_absorption import air_absorption_db_per_m as reference_absorption


@pytest.mark.parametrize(
    "frequency_hz, expected_db_per_m, rel",
    [
        (1e3, 4.66e-3, 0.01),  # ISO 9613-1 Table 1, 20 C, 50 % RH: 4.66 dB/km
        (8e3, 105e-3, 0.01),  # ... 105 dB/km
        (25e3, 0.73, 0.01),  # eRTIS band, ../shared/DESIGN.md: ~0.73, 1.66, 2.61 dB/m
        (50e3, 1.66, 0.01),
        (80e3, 2.61, 0.01),
    ],
)
def test_air_absorption_matches_published_values(frequency_hz, expected_db_per_m, rel):
    assert air_absorption_db_per_m(frequency_hz) == pytest.approx(expected_db_per_m, rel=rel)


@pytest.mark.parametrize("temperature_c, relative_humidity", [(20.0, 50.0), (5.0, 20.0), (35.0, 80.0), (10.0, 90.0)])
def test_air_absorption_at_ultrasound_matches_relaxation_physics(temperature_c, relative_humidity):
    """ISO 9613-1 tabulates only up to 10 kHz; at 20, 40 and 80 kHz its formula is checked against
    the oxygen and nitrogen relaxation terms built from first principles (tests/reference)."""
    f = np.array([20e3, 40e3, 80e3])
    got = air_absorption_db_per_m(f, temperature_c=temperature_c, relative_humidity=relative_humidity)
    np.testing.assert_allclose(got, reference_absorption(f, temperature_c, relative_humidity), rtol=3e-3)


def test_air_absorption_trends():
    """More absorption at higher frequency; bad humidity is an error."""
    f = np.array([20e3, 40e3, 80e3])
    assert np.all(np.diff(air_absorption_db_per_m(f)) > 0)
    with pytest.raises(ValueError, match="relative_humidity"):
        air_absorption_db_per_m(40e3, relative_humidity=120.0)


def test_speed_of_sound():
    """331.3 m/s at 0 C and 343.2 m/s at 20 C; below absolute zero is an error."""
    assert speed_of_sound(0.0) == pytest.approx(331.3)
    assert speed_of_sound(20.0) == pytest.approx(343.21, abs=0.01)
    assert sim.AtmosphereConfig(temperature_c=20.0).speed_of_sound == pytest.approx(343.21, abs=0.01)
    with pytest.raises(ValueError):
        speed_of_sound(-300.0)


def zero_crossing_frequency(signal: np.ndarray, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Frequency from the spacing of upward zero crossings (linear interpolation), at their midpoints."""
    i = np.flatnonzero((signal[:-1] < 0) & (signal[1:] >= 0))
    t = (i + signal[i] / (signal[i] - signal[i + 1])) / rate
    return 0.5 * (t[1:] + t[:-1]), 1.0 / np.diff(t)


@pytest.mark.parametrize("sweep", ["hyperbolic", "linear"])
def test_chirp_frequency_law(sweep):
    """50 -> 25 kHz in 2.5 ms at 450 kHz: 1126 samples; the zero-crossing frequency follows the
    sweep law within 0.5 % away from the tapers; the hyperbolic sweep's period grows linearly."""
    cfg = sim.ChirpConfig(sweep=sweep)
    x = cfg.samples()
    assert x.shape == (1126,) and cfg.sample_count == 1126
    t, f = zero_crossing_frequency(x, cfg.sample_rate_hz)
    inner = (t > 0.1 * 2.5e-3) & (t < 0.9 * 2.5e-3)
    t, f = t[inner], f[inner]
    law = instantaneous_frequency(50e3, 25e3, 2.5e-3, t, sweep=sweep)
    np.testing.assert_allclose(f, law, rtol=0.005)
    if sweep == "hyperbolic":
        slope, intercept = np.polyfit(t, 1.0 / f, 1)
        np.testing.assert_allclose(1.0 / f, slope * t + intercept, rtol=0.005)
        assert slope == pytest.approx((1 / 25e3 - 1 / 50e3) / 2.5e-3, rel=0.01)


def test_chirp_tapers_and_errors():
    """10 % Hann tapers: the ends start and finish at zero and the middle has unit amplitude."""
    x = chirp(start_frequency_hz=50e3, stop_frequency_hz=25e3, duration_s=2.5e-3, sample_rate_hz=450e3)
    ramp = round(0.1 * 1126)
    assert abs(x[0]) < 1e-12 and np.abs(x[-3:]).max() < 0.01
    assert np.abs(x[ramp:-ramp]).max() == pytest.approx(1.0, abs=1e-3)
    assert np.abs(x[:20]).max() < 0.1
    with pytest.raises(ValueError, match="Nyquist"):
        sim.ChirpConfig(start_frequency_hz=250e3)
    with pytest.raises(ValueError, match="sweep"):
        sim.ChirpConfig(sweep="cubic")


def test_ertis_array_geometry():
    """32 microphones in the x = 0 plane, centred, spanning 66.5 x 37.6 mm, >= 6.8 mm apart."""
    mics = ertis_microphones()
    assert mics.shape == (32, 3) and not mics.flags.writeable
    np.testing.assert_allclose(mics[:, 0], 0.0)
    np.testing.assert_allclose(mics.mean(axis=0), 0.0, atol=1e-4)
    np.testing.assert_allclose(np.ptp(mics[:, 1:], axis=0), [0.0665, 0.0376], atol=1e-4)
    gaps = np.linalg.norm(mics[:, None] - mics[None], axis=-1) + np.eye(32)
    assert gaps.min() >= 0.0068 - 1e-4
    cfg = sim.SonarConfig.ertis()
    assert cfg.microphone_count == 32 and cfg.emitter_m == (0.0, 0.0, 0.05)
    assert cfg.record_samples == 16384 and cfg.record_duration_s == pytest.approx(0.036409, abs=1e-6)


def test_sonar_config_validation():
    with pytest.raises(ValueError, match="microphones_m"):
        sim.SonarConfig(microphones_m=((0.0, 0.0, 0.0),))
    with pytest.raises(ValueError, match="record_samples"):
        sim.SonarConfig.ertis(record_samples=100)
    assert dataclasses.asdict(sim.SonarConfig.ertis())["chirp"]["sweep"] == "hyperbolic"


def test_piston_directivity_zeros_and_axis():
    """1 on axis; first null where k a sin(theta) = 3.8317 (first zero of J1); symmetric."""
    c, f, a = 343.0, 40e3, 0.01
    theta_null = np.arcsin(3.8317 / (2 * np.pi * f / c * a))
    assert piston_directivity(0.0, f, a, c) == pytest.approx(1.0)
    assert abs(piston_directivity(theta_null, f, a, c)) < 1e-4
    assert piston_directivity(0.3, f, a, c) == pytest.approx(piston_directivity(-0.3, f, a, c))
    assert 0 < piston_directivity(0.5 * theta_null, f, a, c) < 1
