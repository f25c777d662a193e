"""From microphone signals to an energyscape: matched filter, delay-and-sum, envelope, range grid.

Works on simulated and on recorded signals: pass the array geometry and call that recorded them.
This first implementation runs in numpy (FFT-based, on the host); a Warp version for GPU batches
is to come.
"""

from __future__ import annotations

import numpy as np
from scipy import signal as sps

from .config import PolarGrid, SonarConfig


def energyscape(
    signals: np.ndarray,
    config: SonarConfig,
    *,
    grid: PolarGrid | None = None,
    speed_of_sound: float = 343.0,
    elevation_deg: float = 0.0,
    lowpass_hz: float | None = 1e3,
    decimation: int = 10,
    normalise: str | None = None,
) -> np.ndarray:
    """Energyscapes of pings: reflected energy over range x azimuth, float32 (N, R, A).

    Processing as on the eRTIS: matched filter with the call; delay-and-sum beamforming with
    far-field delays (m . u) / c for each azimuth of `grid` at `elevation_deg`; envelope
    (magnitude of the analytic beam signal); zero-phase low-pass at `lowpass_hz` (None: off);
    decimation by `decimation` (3.81 mm range steps at 450 kHz); resampling to the range bins of
    `grid` with range = c t / 2.

    Args:
        signals: Microphone signals (N, M, S) or (M, S), in the order of `config.microphones_m`.
        config: Array geometry, call (and its sample rate) of the recording.
        grid: Output grid; default `PolarGrid()` (0.2-5 m x -90..90 deg).
        speed_of_sound: Used for the steering delays and the range axis [m/s].
        normalise: None, or "max" to scale each energyscape to a maximum of 1.
    """
    grid = grid or PolarGrid()
    signals = np.asarray(signals)
    if signals.ndim == 2:
        signals = signals[None]
    mics = np.asarray(config.microphones_m, dtype=np.float64)
    if signals.ndim != 3 or signals.shape[1] != len(mics):
        raise ValueError(f"signals must have shape (N, {len(mics)}, samples), got {signals.shape}")
    if not np.isfinite(signals).all():
        raise ValueError("signals contain NaN or inf")
    if normalise not in (None, "max"):
        raise ValueError(f"normalise must be None or 'max', got {normalise!r}")
    fs = config.chirp.sample_rate_hz
    call = config.chirp.samples()
    samples = signals.shape[2]
    # FFT length: long enough for a linear correlation, and a multiple of the decimation so the
    # envelope can be formed directly at the decimated rate from the band's spectrum.
    block = decimation * 512
    nfft = block * int(np.ceil((samples + len(call)) / block))
    small = nfft // decimation
    freqs = np.fft.rfftfreq(nfft, 1.0 / fs)
    low = min(config.chirp.start_frequency_hz, config.chirp.stop_frequency_hz) - 5e3
    high = max(config.chirp.start_frequency_hz, config.chirp.stop_frequency_hz) + 5e3
    band = np.flatnonzero((freqs >= max(low, 0.0)) & (freqs <= high))
    if len(band) > small:
        raise ValueError(f"the call's band does not fit a decimation by {decimation}")
    matched = np.conj(np.fft.rfft(call, nfft))[band]

    azimuth = grid.azimuth_rad
    elevation = np.deg2rad(elevation_deg)
    look = np.stack(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.full_like(azimuth, np.sin(elevation)),
        ],
        axis=1,
    )  # (A, 3)
    delays = look @ mics.T / speed_of_sound  # (A, M): a wave from u reaches mic m (m . u)/c early
    steering = np.exp(-2j * np.pi * freqs[band][None, None, :] * delays[:, :, None]) / len(mics)  # (A, M, F)

    decimated_rate = fs / decimation
    t = np.arange(small) / decimated_rate
    range_axis = speed_of_sound * t / 2.0
    sos = sps.butter(4, lowpass_hz, fs=decimated_rate, output="sos") if lowpass_hz else None
    out = np.empty((len(signals), *grid.shape), dtype=np.float32)
    for p, ping in enumerate(signals):
        spectrum = np.fft.rfft(ping.astype(np.float64), nfft)[:, band] * matched  # (M, F)
        beams = np.einsum("mf,amf->af", spectrum, steering)  # (A, F)
        # Analytic signal of each beam at the decimated rate, with the band shifted to start at
        # 0 Hz: the shift multiplies the signal by a unit phase, which the magnitude removes.
        baseband = np.zeros((len(azimuth), small), dtype=np.complex128)
        baseband[:, : len(band)] = 2.0 * beams
        envelope = np.abs(np.fft.ifft(baseband, axis=1)) / decimation  # same scale as a full-rate IFFT
        if sos is not None:
            envelope = sps.sosfiltfilt(sos, envelope, axis=1)
        image = np.stack([np.interp(grid.range_m, range_axis, row) for row in envelope], axis=1)  # (R, A)
        if normalise == "max":
            image = image / max(float(image.max()), 1e-30)
        out[p] = image
    return out
