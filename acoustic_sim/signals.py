"""Signals and propagation in air: the emitted call, speed of sound and ISO 9613-1 absorption."""

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


# Path lengths [m] at which frequency-dependent absorption is applied exactly. An arrival's
# absorption at the band centre is exact; the rest is interpolated linearly between the two
# nearest of these lengths (error < 0.05 dB in the eRTIS band).
ABSORPTION_LENGTHS_M = np.array([0.0, 1.5, 3.0, 4.5, 6.0, 7.5, 9.0, 10.5, 12.0, 13.5])


def record(
    arrivals,
    config,
    *,
    pose_count: int | None = None,
    absorption: bool = True,
    noise: str = "none",
    snr_db: float = 40.0,
    seed: int = 0,
    half_taps: int = 8,
    device=None,
) -> np.ndarray:
    """Microphone signals of the pings whose echoes `arrivals` holds: float32 (N, mics, samples).

    Each arrival is the emitted call, scaled by its amplitude and delayed to every microphone
    by (path to its source point + |source - mic|) / c: exact near-field fractional delays
    (Lanczos-windowed sinc impulses on a Warp device), then one FFT convolution with the call
    per ping. Air absorption (ISO 9613-1) acts per frequency. Noise: "gaussian" (white) or
    "uniform" (as in the paper) with standard deviation set so that the strongest sample of
    the ping is `snr_db` above it.

    Args:
        arrivals: `Arrivals` from `Sonar.trace`.
        config: The `SonarConfig` that traced them.
        pose_count: Number of pings (default: the highest pose index + 1).
    """
    import warp as wp

    from .kernels import signals as kernels

    if noise not in ("none", "gaussian", "uniform"):
        raise ValueError(f"noise must be 'none', 'gaussian' or 'uniform', got {noise!r}")
    count = int(pose_count if pose_count is not None else (arrivals.pose_index.max() + 1 if len(arrivals) else 1))
    if len(arrivals) and arrivals.pose_index.max() >= count:
        raise ValueError(f"arrivals refer to pose {arrivals.pose_index.max()}, but pose_count is {count}")
    chirp_cfg, atm = config.chirp, config.atmosphere
    c, fs, samples = atm.speed_of_sound, chirp_cfg.sample_rate_hz, config.record_samples
    mics = np.asarray(config.microphones_m, dtype=np.float64)
    amplitude = arrivals.amplitude.astype(np.float64)
    centre_hz = 0.5 * (chirp_cfg.start_frequency_hz + chirp_cfg.stop_frequency_hz)
    absorb = {
        "temperature_c": atm.temperature_c,
        "relative_humidity": atm.relative_humidity,
        "pressure_kpa": atm.pressure_kpa,
    }
    if absorption:
        amplitude = amplitude * 10.0 ** (-air_absorption_db_per_m(centre_hz, **absorb) * arrivals.length_m / 20.0)
        lengths = ABSORPTION_LENGTHS_M
        position = np.interp(arrivals.length_m, lengths, np.arange(len(lengths)))
        lower = np.minimum(np.floor(position).astype(np.int64), len(lengths) - 2)
        weight = position - lower
        # Each arrival is split between its two neighbouring lengths, weighted linearly.
        pick = np.r_[np.arange(len(arrivals)), np.arange(len(arrivals))]
        length_class = np.r_[lower, lower + 1]
        amplitude = np.r_[amplitude * (1.0 - weight), amplitude * weight]
        classes = len(lengths)
    else:
        pick = np.arange(len(arrivals))
        length_class = np.zeros(len(arrivals), dtype=np.int64)
        classes = 1
    source = arrivals.source_m[pick]
    extra = (arrivals.length_m - np.linalg.norm(arrivals.source_m, axis=1))[pick]
    row_base = ((arrivals.pose_index[pick] * classes + length_class) * len(mics)).astype(np.int32)

    device = wp.get_device(device)
    impulses = wp.zeros((count * classes * len(mics), samples), dtype=float, device=device)
    if len(arrivals):
        with wp.ScopedDevice(device):
            wp.launch(
                kernels.accumulate_impulses,
                dim=(len(pick), len(mics)),
                inputs=[
                    wp.array(row_base, dtype=wp.int32),
                    wp.array(source.astype(np.float32), dtype=wp.vec3),
                    wp.array(extra.astype(np.float32), dtype=float),
                    wp.array(amplitude.astype(np.float32), dtype=float),
                    wp.array(mics.astype(np.float32), dtype=wp.vec3),
                    fs / c,
                    half_taps,
                ],
                outputs=[impulses],
            )
    impulses = impulses.numpy().reshape(count, classes, len(mics), samples)

    call = chirp_cfg.samples()
    nfft = 1 << int(np.ceil(np.log2(samples + len(call) - 1)))
    freqs = np.fft.rfftfreq(nfft, 1.0 / fs)
    transfer = np.broadcast_to(np.fft.rfft(call, nfft), (classes, len(freqs))).copy()
    if absorption:
        excess = air_absorption_db_per_m(freqs, **absorb) - air_absorption_db_per_m(centre_hz, **absorb)
        transfer *= 10.0 ** (-excess[None, :] * ABSORPTION_LENGTHS_M[:, None] / 20.0)
    signals = np.empty((count, len(mics), samples), dtype=np.float32)
    for p in range(count):  # one ping at a time keeps the FFT buffers small
        spectrum = np.einsum("kmf,kf->mf", np.fft.rfft(impulses[p], nfft), transfer)
        signals[p] = np.fft.irfft(spectrum, nfft)[:, :samples]
    if noise != "none":
        rng = np.random.default_rng(seed)
        peak = np.abs(signals).max(axis=(1, 2), keepdims=True)
        std = peak * 10.0 ** (-snr_db / 20.0)
        if noise == "gaussian":
            signals += (std * rng.standard_normal(signals.shape)).astype(np.float32)
        else:
            signals += (std * np.sqrt(3.0) * rng.uniform(-1.0, 1.0, signals.shape)).astype(np.float32)
    return signals
