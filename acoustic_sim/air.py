"""Air and the call, in numpy only: speed of sound, ISO 9613-1 absorption, the emitted FM sweep.

Configs (config.py) and the recorder (signals.py) both read these; keeping them here, free of
Warp and of the configs, is what keeps those two modules out of an import circle.
"""

from __future__ import annotations

import numpy as np


def speed_of_sound(temperature_c: float) -> float:
    """Speed of sound in dry air [m/s]: c = 331.3 sqrt(1 + T / 273.15), T in degrees Celsius."""
    if temperature_c <= -273.15:
        raise ValueError(f"temperature {temperature_c} C is below absolute zero")
    return 331.3 * float(np.sqrt(1.0 + temperature_c / 273.15))


def air_absorption_db_per_m(
    frequency_hz: np.ndarray | float,
    *,
    temperature_c: float = 20.0,
    relative_humidity: float = 50.0,
    pressure_kpa: float = 101.325,
) -> np.ndarray:
    """Pure-tone atmospheric absorption coefficient [dB/m] by ISO 9613-1:1993, equations (3)-(5) and B.1.

    Args:
        frequency_hz: Frequencies [Hz], any shape.
        temperature_c: Air temperature [deg C].
        relative_humidity: Relative humidity [%], 0-100.
        pressure_kpa: Ambient pressure [kPa].

    Returns:
        Absorption [dB/m], same shape as `frequency_hz`. Amplitude decays as 10^(-alpha r / 20).
    """
    if not 0.0 <= relative_humidity <= 100.0:
        raise ValueError(f"relative_humidity must lie in [0, 100] %, got {relative_humidity}")
    if pressure_kpa <= 0:
        raise ValueError(f"pressure_kpa must be positive, got {pressure_kpa}")
    f = np.asarray(frequency_hz, dtype=np.float64)
    t = temperature_c + 273.15
    t_ref, t_triple, p_ref = 293.15, 273.16, 101.325
    p_rel = pressure_kpa / p_ref
    # Molar concentration of water vapour [%] from relative humidity (ISO 9613-1 annex B).
    saturation = 10.0 ** (-6.8346 * (t_triple / t) ** 1.261 + 4.6151)
    h = relative_humidity * saturation / p_rel
    f_oxygen = p_rel * (24.0 + 4.04e4 * h * (0.02 + h) / (0.391 + h))
    f_nitrogen = p_rel * (t / t_ref) ** -0.5 * (9.0 + 280.0 * h * np.exp(-4.170 * ((t / t_ref) ** (-1.0 / 3.0) - 1.0)))
    return (
        8.686
        * f**2
        * (
            1.84e-11 / p_rel * (t / t_ref) ** 0.5
            + (t / t_ref) ** -2.5
            * (
                0.01275 * np.exp(-2239.1 / t) / (f_oxygen + f**2 / f_oxygen)
                + 0.1068 * np.exp(-3352.0 / t) / (f_nitrogen + f**2 / f_nitrogen)
            )
        )
    )


def chirp(
    *,
    start_frequency_hz: float,
    stop_frequency_hz: float,
    duration_s: float,
    sample_rate_hz: float,
    sweep: str = "hyperbolic",
    taper_fraction: float = 0.1,
) -> np.ndarray:
    """FM sweep with Hann tapers at both ends, float64, shape (round(duration * rate) + 1,).

    Samples run from t = 0 to t = duration inclusive (1126 samples for 2.5 ms at 450 kHz).

    "hyperbolic" (linear-period, Doppler tolerant, as the eRTIS uses): the period changes linearly
    with time, so the instantaneous frequency is f(t) = f0 f1 T / (f1 T + (f0 - f1) t).
    "linear": f(t) = f0 + (f1 - f0) t / T. `taper_fraction` of the samples at each end get the
    rising / falling half of a Hann window.
    """
    if sweep not in ("hyperbolic", "linear"):
        raise ValueError(f"sweep must be 'hyperbolic' or 'linear', got {sweep!r}")
    if min(start_frequency_hz, stop_frequency_hz) <= 0 or duration_s <= 0:
        raise ValueError("chirp frequencies and duration must be positive")
    if max(start_frequency_hz, stop_frequency_hz) >= sample_rate_hz / 2:
        raise ValueError(
            f"chirp reaches {max(start_frequency_hz, stop_frequency_hz)} Hz, above the "
            f"Nyquist frequency {sample_rate_hz / 2} Hz"
        )
    if not 0.0 <= taper_fraction <= 0.5:
        raise ValueError(f"taper_fraction must lie in [0, 0.5], got {taper_fraction}")
    count = round(duration_s * sample_rate_hz) + 1
    if count < 2:
        raise ValueError(
            f"a call of duration_s {duration_s:g} at sample_rate_hz {sample_rate_hz:g} has {count} sample; "
            "give at least two sample periods"
        )
    t = np.arange(count) / sample_rate_hz
    f0, f1, big_t = start_frequency_hz, stop_frequency_hz, duration_s
    if sweep == "linear" or f0 == f1:
        phase = 2 * np.pi * (f0 * t + 0.5 * (f1 - f0) / big_t * t**2)
    else:
        # Phase = 2 pi * integral of f(t) dt for the linear-period sweep.
        k = (f0 - f1) / (f1 * big_t)
        phase = 2 * np.pi * f0 / k * np.log1p(k * t)
    signal = np.sin(phase)
    ramp = round(taper_fraction * count)
    if ramp > 0:
        window = 0.5 - 0.5 * np.cos(np.pi * np.arange(ramp) / ramp)
        signal[:ramp] *= window
        signal[count - ramp :] *= window[::-1]
    return signal


def instantaneous_frequency(
    start_frequency_hz: float, stop_frequency_hz: float, duration_s: float, t: np.ndarray, *, sweep: str = "hyperbolic"
) -> np.ndarray:
    """Instantaneous frequency [Hz] of `chirp` at times t [s]."""
    f0, f1 = start_frequency_hz, stop_frequency_hz
    t = np.asarray(t, dtype=np.float64)
    if sweep == "linear":
        return f0 + (f1 - f0) * t / duration_s
    return f0 * f1 * duration_s / (f1 * duration_s + (f0 - f1) * t)
