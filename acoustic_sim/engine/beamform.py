"""From microphone signals to an energyscape: matched filter, delay-and-sum, envelope, range grid.

Works on simulated and on recorded signals: pass the array geometry and call that recorded them.
Everything runs in Warp kernels, on the CPU or a GPU, on batches of pings:

1. complex baseband: the band around the call's centre frequency f0 shifted to 0 Hz, low-passed
   and decimated (to 56.25 kHz for the eRTIS call), one FFT per microphone;
2. per frequency bin: matched filter (the call's conjugate spectrum) and delay-and-sum with
   far-field delays, exact phase shifts at each bin's true frequency;
3. one inverse FFT per beam: its magnitude is the envelope of the matched-filtered beam;
4. zero-phase FIR low-pass of the envelope and linear interpolation to the range bins.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import warp as wp
from scipy import signal as sps

from ..config import ProcessingConfig, SonarConfig
from ..devices import device_calls, warp_device
from .kernels import beamform as kernels
from .signals import tile_block_dim

FLOOR_DB = -60.0  # lowest value of a "db" energyscape
ENVELOPE_BLOCK_DIM = 256  # threads per beam row in the envelope kernel: one per range bin of the default grid (240)
LOOKS_PER_BLOCK = 8  # look directions of a block of the GPU's delay-and-sum (`kernels.delay_and_sum_tiles`)


class Beamformer:
    """Energyscapes of signal batches on a Warp device (see `energyscape` for the arguments)."""

    def __init__(
        self,
        config: SonarConfig,
        *,
        samples: int,
        processing: ProcessingConfig | None = None,
        call: np.ndarray | None = None,
        device=None,
    ):
        processing = processing or ProcessingConfig()
        self.config = config
        self.processing = processing
        self.grid = processing.grid
        self.samples = int(samples)
        self.normalise = processing.normalise
        self.device = warp_device(device)
        self.elevations_deg = np.atleast_1d(np.asarray(processing.elevation_deg, dtype=np.float64))
        self._scalar_elevation = np.ndim(processing.elevation_deg) == 0
        speed_of_sound, lowpass_hz = processing.speed_of_sound, processing.lowpass_hz
        fs = config.chirp.sample_rate_hz
        call = config.chirp.samples() if call is None else np.asarray(call, dtype=np.float64)
        if call.ndim != 1 or len(call) < 2 or not np.isfinite(call).all():
            raise ValueError("call must be a finite 1-D waveform of at least 2 samples")

        # Band kept around the call: its sweep plus 5 kHz each side.
        low = max(min(config.chirp.start_frequency_hz, config.chirp.stop_frequency_hz) - 5e3, 0.0)
        high = max(config.chirp.start_frequency_hz, config.chirp.stop_frequency_hz) + 5e3
        centre, width = 0.5 * (low + high), high - low
        self.decimation = 1
        while fs / (2 * self.decimation) >= 1.6 * width:
            self.decimation *= 2
        rate = fs / self.decimation
        self.baseband_samples = -(-self.samples // self.decimation)
        needed = self.baseband_samples + -(-len(call) // self.decimation) + 16
        self.size = 1 << int(np.ceil(np.log2(needed)))
        if self.size > 8192:
            raise ValueError(
                f"{self.samples} samples need a {self.size}-point baseband FFT; at most 8192 fit one GPU block: "
                "process the recording in shorter pieces"
            )

        # Anti-alias low-pass for the decimation, shifted to the centre frequency.
        if self.decimation > 1:
            taps_count, beta = sps.kaiserord(60.0, (rate - width) / (0.5 * fs))
            taps = sps.firwin(taps_count | 1, 0.5 * rate, window=("kaiser", beta), fs=fs)
        else:
            taps = np.ones(1)
        offsets = np.arange(len(taps)) - len(taps) // 2
        shifted = taps * np.exp(-2j * np.pi * centre * offsets / fs)

        freqs = centre + np.fft.fftfreq(self.size, 1.0 / rate)
        band = np.flatnonzero((freqs >= low) & (freqs <= high))
        # Correlation with the call (its spectrum at each bin's true frequency, conjugated), with
        # the scale that makes the envelope that of the full-rate analytic matched-filter output.
        offsets = np.rint(np.fft.fftfreq(self.size) * self.size).astype(np.int64)[band]
        spectrum = call_spectrum(call, centre / fs, offsets, self.size * self.decimation)
        matched = np.conj(spectrum) * 2.0 / (self.size * config.microphone_count)

        azimuth = self.grid.azimuth_rad
        elevation = np.deg2rad(self.elevations_deg)
        el, az = np.meshgrid(elevation, azimuth, indexing="ij")
        look = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
        mics = np.asarray(config.microphones_m, dtype=np.float64)
        delays = look @ mics.T / speed_of_sound  # a wave from u reaches mic m (m . u) / c early

        lowpass = np.ones(1)
        if lowpass_hz is not None:
            if not 0 < lowpass_hz < 0.5 * rate:
                raise ValueError(f"lowpass_hz must lie in (0, {0.5 * rate:g}) Hz, got {lowpass_hz}")
            lowpass = sps.firwin(2 * round(2.0 * rate / lowpass_hz) + 1, lowpass_hz, window="hamming", fs=rate)

        self._cycles_per_output = centre * self.decimation / fs
        self._samples_per_m = 2.0 * rate / speed_of_sound
        self._looks = len(look)
        with wp.ScopedDevice(self.device):
            self._taps = wp.array(np.stack([shifted.real, shifted.imag], -1).astype(np.float32), dtype=wp.vec2f)
            self._band_bin = wp.array(band.astype(np.int32), dtype=wp.int32)
            self._band_hz = wp.array(freqs[band].astype(np.float32), dtype=float)
            self._matched = wp.array(np.stack([matched.real, matched.imag], -1).astype(np.float32), dtype=wp.vec2f)
            self._delays = wp.array(delays.astype(np.float32), dtype=float)
            self._lowpass = wp.array(lowpass.astype(np.float32), dtype=float)
            self._range_m = wp.array(self.grid.range_m.astype(np.float32), dtype=float)
        self._fft = kernels.forward_fft(self.size)
        self._ifft = kernels.inverse_fft_magnitude(self.size)
        self._beamform = kernels.delay_and_sum(config.microphone_count)
        self._band_tiles = band_tiles(band, self.device)

    @property
    def output_shape(self) -> tuple[int, ...]:
        """Shape of one ping's energyscape: (R, A), or (E, R, A) for a sequence of elevations."""
        per = self.grid.shape
        return per if self._scalar_elevation else (len(self.elevations_deg), *per)

    def __call__(self, signals: wp.array) -> wp.array:
        """Energyscapes of a (pings, mics, samples) float32 device array: (pings * E, R, A)."""
        pings, mics, samples = signals.shape
        if mics != self.config.microphone_count or samples != self.samples:
            raise ValueError(f"signals must have shape (N, {self.config.microphone_count}, {self.samples})")
        elevations = len(self.elevations_deg)
        block = tile_block_dim(self.size)
        zeros, empty, launch, launch_tiled = device_calls(self.device)  # runs in worker threads too
        spectra = empty((pings * mics, self.size), dtype=wp.vec2f)
        launch(
            kernels.demodulate,
            dim=(pings, mics, self.size),
            inputs=[signals, samples, self._taps, wp.float64(self._cycles_per_output), self.decimation],
            outputs=[spectra],
        )
        launch_tiled(self._fft, dim=[pings * mics], outputs=[spectra], block_dim=block)  # in place
        beams = zeros((pings * self._looks, self.size), dtype=wp.vec2f)
        steering = [self._band_hz, self._matched, self._delays, pings]
        if self.device.is_cuda:  # a block per (tile of bins, looks), the pings' spectra staged in shared memory
            launch_tiled(
                kernels.delay_and_sum_tiles(mics, LOOKS_PER_BLOCK),
                dim=[self._band_tiles[0].shape[0], -(-self._looks // LOOKS_PER_BLOCK)],
                inputs=[spectra, *self._band_tiles, *steering],
                outputs=[beams],
                block_dim=kernels.TILE_BINS * LOOKS_PER_BLOCK,
            )
        else:
            launch(
                self._beamform,
                dim=(self._looks, self._band_bin.shape[0]),
                inputs=[spectra, self._band_bin, *steering],
                outputs=[beams],
            )
        del spectra
        envelope = empty((pings * self._looks, self.size), dtype=float)
        launch_tiled(self._ifft, dim=[pings * self._looks], inputs=[beams], outputs=[envelope], block_dim=block)
        del beams
        images = empty((pings * elevations, *self.grid.shape), dtype=float)
        envelope_inputs = [envelope, self.baseband_samples, self._lowpass, self._range_m, self._samples_per_m]
        if self.device.is_cuda:  # a block per beam row, the row in shared memory
            launch_tiled(
                kernels.envelope_rows(self.baseband_samples),
                dim=[images.shape[0] * images.shape[2]],
                inputs=envelope_inputs,
                outputs=[images],
                block_dim=ENVELOPE_BLOCK_DIM,
            )
        else:
            launch(
                kernels.envelope_on_grid,
                dim=(images.shape[0], images.shape[2], images.shape[1]),
                inputs=[*envelope_inputs, elevations],
                outputs=[images],
            )
        if self.normalise is not None:
            peak = zeros(pings, dtype=float)
            launch(
                kernels.image_peak,
                dim=(images.shape[0], kernels.PEAK_LANES),
                inputs=[images, elevations],
                outputs=[peak],
            )
            launch(
                kernels.scale_images,
                dim=images.shape,
                inputs=[peak, elevations, int(self.normalise == "db"), FLOOR_DB],
                outputs=[images],
            )
        return images


def band_tiles(band: np.ndarray, device) -> list[wp.array]:
    """`kernels.delay_and_sum_tiles`' tiles of the band's bins (ascending FFT columns, in one or
    two runs): each tile's first column, first band index and width, int32 device arrays."""
    runs = np.split(np.arange(len(band)), np.flatnonzero(np.diff(band) != 1) + 1)
    tiles = [run[i : i + kernels.TILE_BINS] for run in runs for i in range(0, len(run), kernels.TILE_BINS)]
    column = [band[t[0]] for t in tiles]
    index = [t[0] for t in tiles]
    width = [len(t) for t in tiles]
    return [wp.array(np.asarray(v, dtype=np.int32), dtype=wp.int32, device=device) for v in (column, index, width)]


def call_spectrum(call: np.ndarray, shift: float, offsets: np.ndarray, points: int) -> np.ndarray:
    """The call's spectrum sum_n call[n] exp(-2 pi i (shift + k / points) n) at integer offsets k
    (frequencies in cycles per sample): one `points`-point FFT of the call shifted down by `shift`
    (`points` >= len(call)). Summing it directly over a beamformer's band took 0.06-0.15 s of each
    process's first energyscape (2,549 bins x 1,126 samples), the FFT ~1 ms."""
    if points < len(call):
        raise ValueError(f"a {points}-point FFT cannot hold a {len(call)}-sample call")
    shifted = call * np.exp(-2j * np.pi * shift * np.arange(len(call)))
    return np.fft.fft(shifted, points)[np.mod(offsets, points)]


# Beamformers of recent settings (all arguments hashable: no custom call waveform).
_cached_beamformer = functools.lru_cache(maxsize=8)(Beamformer)


def beamformer(
    config: SonarConfig,
    *,
    samples: int,
    processing: ProcessingConfig | None = None,
    call: np.ndarray | None = None,
    device=None,
) -> Beamformer:
    """A Beamformer, reused across calls with the same settings (building one evaluates the call's
    spectrum and the steering weights); a custom `call` always builds a new one."""
    processing = processing or ProcessingConfig()
    if call is not None:
        return Beamformer(config, samples=samples, processing=processing, call=call, device=device)
    device = str(warp_device(device))
    return _cached_beamformer(config, samples=samples, processing=processing, device=device)


MAX_SIGNAL = 1e20
"""Largest |sample| energyscape accepts: matched filtering and beamforming sum ~1e6 products in
float32 (max 3.4e38), so samples far above this would overflow to inf."""


def energyscape(
    signals: np.ndarray,
    config: SonarConfig,
    processing: ProcessingConfig | None = None,
    *,
    call: np.ndarray | None = None,
    batch: int = 64,
    device=None,
    **settings,
) -> np.ndarray:
    """Energyscapes of pings: reflected energy over range x azimuth, float32 (N, R, A), or
    (N, E, R, A) for a sequence of E elevations.

    Processing as on the eRTIS: matched filter with the call; delay-and-sum beamforming with
    far-field delays (m . u) / c for each azimuth of the grid at the elevation; envelope
    (magnitude of the analytic beam signal); zero-phase low-pass; values at the range bins of
    the grid with range = c t / 2 (t from the start of the call).

    Args:
        signals: Microphone signals (N, M, S) or (M, S), in the order of `config.microphones_m`,
            sampled at `config.chirp.sample_rate_hz`.
        config: Array geometry and call of the recording.
        processing: Grid, speed of sound, elevation, low-pass and normalisation (see
            `ProcessingConfig`); default the eRTIS processing on the training grid. A sequence
            of elevations gives (N, E, R, A).
        call: The emitted waveform, if not the chirp of `config` (e.g. one measured on a sensor).
        batch: Pings processed at once.
        device: Warp device.
        **settings: ProcessingConfig fields to change, e.g. `grid=PolarGrid(...)`,
            `lowpass_hz=None`, `normalise="db"`, `speed_of_sound=340.0`.
    """
    processing = dataclasses.replace(processing or ProcessingConfig(), **settings)
    signals = np.asarray(signals)
    if signals.dtype.kind not in "fiu":  # complex, object, bool, strings: not microphone samples
        raise ValueError(f"signals must be real numbers (float or integer), got dtype {signals.dtype}")
    if signals.ndim == 2:
        signals = signals[None]
    mics = config.microphone_count
    if signals.ndim != 3 or signals.shape[1] != mics:
        raise ValueError(f"signals must have shape (N, {mics}, samples), got {signals.shape}")
    if not np.isfinite(signals).all():
        raise ValueError("signals contain NaN or inf")
    peak = float(np.abs(signals).max(initial=0.0))
    if peak > MAX_SIGNAL:
        raise ValueError(
            f"signals reach {peak:.3g}; above {MAX_SIGNAL:.0e} the float32 processing overflows: rescale them"
        )
    call_samples = config.chirp.sample_count if call is None else len(np.asarray(call))
    if signals.shape[2] < call_samples:
        raise ValueError(f"signals hold {signals.shape[2]} samples, fewer than the call's {call_samples}")
    device = warp_device(device)
    former = beamformer(config, samples=signals.shape[2], processing=processing, call=call, device=device)
    out = np.empty((len(signals), *former.output_shape), dtype=np.float32)
    with wp.ScopedDevice(device):
        for start in range(0, len(signals), batch):
            chunk = wp.array(np.ascontiguousarray(signals[start : start + batch], dtype=np.float32))
            out[start : start + len(chunk)] = former(chunk).numpy().reshape(len(chunk), *former.output_shape)
    return out
