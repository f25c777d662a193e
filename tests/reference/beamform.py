"""Full-rate numpy energyscape: matched filter, delay-and-sum and analytic envelope, nothing decimated.

An independent reference for acoustic_sim.engine.beamform, which works in a decimated complex baseband.
"""

import numpy as np


def full_rate_envelope(signals, mics, call, fs, azimuth_rad, band_hz, speed_of_sound=343.0):
    """Envelope of each matched-filtered delay-and-sum beam at every sample, shape (A, S).

    signals (M, S); beams steered in the horizontal plane with far-field delays (m . u) / c;
    spectrum kept within band_hz = (low, high), the analytic signal from its positive half.
    """
    samples = signals.shape[1]
    nfft = 1 << int(np.ceil(np.log2(samples + len(call))))
    freqs = np.fft.fftfreq(nfft, 1.0 / fs)
    keep = (freqs >= band_hz[0]) & (freqs <= band_hz[1])
    spectrum = np.fft.fft(signals, nfft)[:, keep] * np.conj(np.fft.fft(call, nfft))[keep]  # (M, F)
    look = np.c_[np.cos(azimuth_rad), np.sin(azimuth_rad), np.zeros_like(azimuth_rad)]
    delays = look @ np.asarray(mics).T / speed_of_sound  # (A, M)
    beams = np.zeros((len(azimuth_rad), nfft), dtype=np.complex128)
    for a, tau in enumerate(delays):
        beams[a, keep] = 2.0 * (spectrum * np.exp(-2j * np.pi * freqs[keep][None, :] * tau[:, None])).mean(axis=0)
    return np.abs(np.fft.ifft(beams, axis=1))[:, :samples]
