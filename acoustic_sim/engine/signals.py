"""Recording echoes: each arrival as the call delayed to every microphone, absorbed by air, plus noise
(the call and the air themselves are in air.py)."""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..air import air_absorption_db_per_m
from ..config import NOISE_CODES, NOISE_KINDS
from ..devices import cpu_cores, device_calls, warp_device
from .kernels import signals as kernels
from .seeds import ping_seeds

# Fractional-delay filter of a recorded echo: the fewest taps (of DELAY_TAPS_CHOICES) whose
# in-band error is at most DELAY_ERROR (-60 dB), and steps of the sample fraction between the rows
# of its table. Each tap is one atomic add per echo and microphone, the record stage's main cost:
# the eRTIS call (25-50 kHz at 450 kHz) needs 4 (error 7.9e-4; 8 taps give 2.8e-4).
DELAY_TAPS_CHOICES = (4, 6, 8)
DELAY_ERROR = 1e-3
DELAY_ERROR_MAX = 5e-3  # accepted, with the most taps, for wider bands
FRACTION_STEPS = 32
# Smallest FFT of an absorption node [samples]: kernels.NODE_BLOCKS blocks of 1,024 samples (larger
# for calls longer than half of it).
NODE_FFT_MIN_SIZE = 4096
# GPU recording (`kernels.row_accumulation`): threads of a block, and the most samples of a
# microphone row it sums in shared memory (int32: 64 KB, two blocks per SM of an H100; int64 sums
# took 1.5-2x as long: benchmarks/results/record_kernels/, sonar_cuda_same_job/run6_row_sums_32bit/).
ROW_BLOCK_DIM = 1024
# CUDA launch bounds of the row kernel: two blocks per SM, so at most 32 registers a thread (it
# would take 55 and run one block per SM: 0.89x the time at 100k rays on an H100, 0.83x at 20k, with
# 80 bytes spilled; benchmarks/results/record_kernels/).
ROW_LAUNCH_BOUNDS = (ROW_BLOCK_DIM, 2)
ROW_CHUNK_MAX = 16384
ROW_SHARED_SPARE = 8192  # [bytes] of a block's shared memory left to Warp's own use
ROW_SAMPLE_BYTES = 4


def row_chunk(samples: int, shared_bytes: int, sample_bytes: int = ROW_SAMPLE_BYTES) -> int:
    """Samples of a microphone row one block of `kernels.row_accumulation` sums, with
    `shared_bytes` of shared memory a block: a power of two that covers `samples` where that
    fits (up to ROW_CHUNK_MAX), else the largest that does."""
    budget = (shared_bytes - ROW_SHARED_SPARE) // sample_bytes
    chunk = min(ROW_CHUNK_MAX, 1 << max(int(samples) - 1, 1).bit_length())
    while chunk > budget and chunk > 256:
        chunk //= 2
    return chunk


def fractional_delay_table(config) -> np.ndarray:
    """Band-limited fractional-delay filters, float32 (FRACTION_STEPS + 1, taps).

    Row j is the least-squares FIR (taps at offsets k - taps / 2 + 1 - j / FRACTION_STEPS
    samples from the true arrival time) with response 1 up to 8 kHz above the call's band and 0
    from 40 kHz above it, the in-band part weighted 1000 times more. Echoes interpolate the rows
    linearly. `taps` is the first of DELAY_TAPS_CHOICES whose worst in-band error is at most
    DELAY_ERROR; a band too wide for that gets the most taps if they stay within DELAY_ERROR_MAX.
    """
    chirp = config.chirp
    return _delay_table(chirp.sample_rate_hz, chirp.start_frequency_hz, chirp.stop_frequency_hz).copy()


# Kept per call band: every episode of a suite that draws its air or microphones builds a new
# Recorder, and the fit (~130 least-squares solves) took ~5 ms of the rendering thread each time.
@functools.lru_cache(maxsize=8)
def _delay_table(fs: float, start_hz: float, stop_hz: float) -> np.ndarray:
    low, high = min(start_hz, stop_hz), max(start_hz, stop_hz)
    band = np.linspace(max(low - 8e3, 0.0), high + 8e3, 200)
    below = np.linspace(0.0, band[0], 40, endpoint=False)
    above = np.linspace(min(high + 48e3, 0.49 * fs), 0.5 * fs, 120)
    freqs = np.r_[below, band, above]
    weight = np.r_[np.full(len(below), 1e-3), np.ones(len(band)), np.full(len(above), 1e-3)]
    target = np.r_[np.ones(len(below) + len(band)), np.zeros(len(above))]
    in_band = (freqs >= low) & (freqs <= high)
    for taps in DELAY_TAPS_CHOICES:
        table = np.empty((FRACTION_STEPS + 1, taps))
        worst = 0.0
        for j, v in enumerate(np.linspace(0.0, 1.0, FRACTION_STEPS + 1)):
            offsets = np.arange(taps) - taps // 2 + 1 - v
            response = np.exp(-2j * np.pi * freqs[:, None] * offsets[None, :] / fs)
            system = np.r_[response.real, response.imag] * np.r_[weight, weight][:, None]
            table[j] = np.linalg.lstsq(system, np.r_[target * weight, np.zeros(len(freqs))], rcond=None)[0]
            worst = max(worst, float(np.abs(response[in_band] @ table[j] - 1.0).max()))
        if worst <= DELAY_ERROR:
            break
    if worst > DELAY_ERROR_MAX:
        raise ValueError(f"the call's band is too wide for {taps}-tap delay filters (error {worst:.1e})")
    return table.astype(np.float32)


@dataclass
class EchoBuffer:
    """Echoes of a batch of pings on a Warp device, (pings, slots) arrays; empty slots have amplitude 0.

    Attributes:
        source: Point the echo seems to come from, sensor frame [m] (vec3).
        extra_length: Path travelled before reaching `source` [m] (0 for image sources).
        amplitude: Pressure amplitude without air absorption.
        count: Slots in use per ping, int32 (pings,).
    """

    source: wp.array
    extra_length: wp.array
    amplitude: wp.array
    count: wp.array

    @property
    def slots(self) -> int:
        return self.source.shape[1]

    def rows(self, first: int, last: int) -> EchoBuffer:
        """The echoes of pings first..last-1 (views of the same device memory)."""
        if self.slots == 0:  # nothing to record (Warp cannot slice an array with an empty axis)
            return self
        part = (self.source, self.extra_length, self.amplitude, self.count)
        return EchoBuffer(*(a[first:last] for a in part))


def tile_block_dim(size: int) -> int:
    """Threads per block for a tiled FFT of `size` points (sizes that compile on the H100)."""
    return int(np.clip(size // 16, 64, 512))


class Recorder:
    """Microphone signals of echo batches on a Warp device (see `record`).

    Air absorption: every echo is scaled by its exact absorption at the call's centre
    frequency; the rest (how it varies over the band) is applied per frequency through absorption
    nodes every 1,024 samples (0.78 m of path at 450 kHz), between which an echo's impulse is
    shared linearly by its arrival time (its path length is c times that time).
    """

    def __init__(self, config, *, absorption: bool = True, device=None):
        self.config = config
        self.device = warp_device(device)
        chirp_cfg, atm = config.chirp, config.atmosphere
        fs, c = chirp_cfg.sample_rate_hz, atm.speed_of_sound
        call = config.chirp.samples()
        size = NODE_FFT_MIN_SIZE
        while size // 2 < len(call) - 1:
            size *= 2
        self._size = size
        self.block = size // kernels.NODE_BLOCKS
        self.nodes = -(-config.record_samples // self.block) + 1
        freqs = np.abs(np.fft.fftfreq(size, 1.0 / fs))
        centre_hz = 0.5 * (chirp_cfg.start_frequency_hz + chirp_cfg.stop_frequency_hz)
        air = {"temperature_c": atm.temperature_c, "relative_humidity": atm.relative_humidity}
        air["pressure_kpa"] = atm.pressure_kpa
        centre_db = air_absorption_db_per_m(centre_hz, **air) if absorption else 0.0
        excess_db = air_absorption_db_per_m(freqs, **air) - centre_db if absorption else np.zeros(size)
        node_length = np.arange(self.nodes) * self.block / fs * c
        filters = np.fft.fft(call, size)[None, :] * 10.0 ** (-excess_db[None, :] * node_length[:, None] / 20.0)
        filters /= size * kernels.FIXED_POINT_SCALE
        hat = np.zeros(size)
        hat[: 2 * self.block] = 1.0 - np.abs(np.arange(2 * self.block) - self.block) / self.block
        self._absorption_per_m = float(centre_db) * np.log(10.0) / 20.0
        taps = fractional_delay_table(config)
        with wp.ScopedDevice(self.device):
            self._filters = wp.array(np.stack([filters.real, filters.imag], -1).astype(np.float32), dtype=wp.vec2f)
            self._hat = wp.array(hat[None].astype(np.float32), dtype=float)
            self._taps = wp.array(taps, dtype=float)
            self._mics = wp.array(np.asarray(config.microphones_m, dtype=np.float32), dtype=wp.vec3)
            self._mic_gain = wp.array(config.channel_gain().astype(np.float32), dtype=float)
            self._mic_delay = wp.array((config.channel_delay_s() * fs).astype(np.float32), dtype=float)
        # The GPU's 32-bit sums (kernels.stretch_bounds): how far from its arrival at the array's
        # origin an echo's taps can land on any microphone [samples], and the largest tap per unit
        # amplitude.
        spread_m = float(np.linalg.norm(np.asarray(config.microphones_m, dtype=np.float64), axis=1).max())
        self._reach = spread_m * fs / c + float(np.abs(config.channel_delay_s() * fs).max()) + taps.shape[1] + 2
        self._largest_gain_tap = float(np.abs(config.channel_gain()).max() * np.abs(taps).max())
        self._stretches = -(-config.record_samples // kernels.STRETCH)
        self._convolve = kernels.node_convolution(size)
        self._no_echoes = {}  # pings -> an empty EchoRows (echo_rows)

    def impulses(self, echoes, pings: int, *, row_sums: bool | None = None) -> wp.array:
        """The echoes' fractional-delay impulses, fixed point (2^32 per unit amplitude), int64.

        Row p * 2 * pairs + m is ping p's microphone m (pairs = ceil(mics / 2)); column
        `block` + n is sample n. Before them one block of zeros (node 0 reaches back one block),
        after them room for the last node's FFT. `row_sums` (default: on GPUs) sums each row in
        32-bit shared memory (`kernels.row_accumulation`: within a unit of 2^-29 of the summed
        |amplitude| near each sample of the exact sums), else every tap is a 64-bit atomic (the
        exact sums, the CPU's way: Warp's CPU tile memory is one per module, which threads
        recording at once would share).
        """
        cfg = self.config
        mics = cfg.microphone_count
        zeros, _, launch, launch_tiled = device_calls(self.device)
        impulses = zeros((pings * 2 * ((mics + 1) // 2), (self.nodes - 1) * self.block + self._size), dtype=wp.int64)
        row_sums = self.device.is_cuda if row_sums is None else row_sums
        echoes = [e for e in echoes if e.slots > 0]
        if row_sums:  # a block per stretch of a row, up to three buffers a launch: 32-bit atomics in shared memory
            shared = self.device.max_shared_memory_per_block if self.device.is_cuda else 64 * 1024
            chunk = row_chunk(cfg.record_samples, shared)
            for first in range(0, len(echoes), kernels.BUFFERS_PER_LAUNCH):
                rows = self.echo_rows(echoes[first : first + kernels.BUFFERS_PER_LAUNCH], pings)
                launch_tiled(
                    kernels.row_accumulation(chunk, self._stretches, ROW_LAUNCH_BOUNDS),
                    dim=[pings, mics, -(-cfg.record_samples // chunk)],
                    inputs=[*rows, *self._tap_inputs(), self.sum_exponents(rows, pings)],
                    outputs=[impulses],
                    block_dim=ROW_BLOCK_DIM,
                )
            return impulses
        for e in echoes:
            inputs = [e.source, e.extra_length, e.amplitude, e.count, *self._tap_inputs()]
            launch(kernels.accumulate_echoes, dim=(pings, e.slots, mics), inputs=inputs, outputs=[impulses])
        return impulses

    def _tap_inputs(self) -> list:
        """The arguments of the accumulation kernels after the echoes: microphones and taps."""
        cfg = self.config
        spm = cfg.chirp.sample_rate_hz / cfg.atmosphere.speed_of_sound
        inputs = [self._mics, self._mic_gain, self._mic_delay, spm, self._absorption_per_m, self._taps]
        return [*inputs, cfg.record_samples, self.block]

    def echo_rows(self, echoes, pings: int) -> list:
        """`kernels.BUFFERS_PER_LAUNCH` EchoRows of these buffers (at most that many), an empty
        buffer in the places of missing ones."""
        rows = []
        for e in echoes:
            r = kernels.EchoRows()
            r.source, r.extra_length, r.amplitude, r.count = e.source, e.extra_length, e.amplitude, e.count
            rows.append(r)
        if len(rows) < kernels.BUFFERS_PER_LAUNCH:
            if self._no_echoes.get(pings) is None:
                with wp.ScopedDevice(self.device):
                    r = kernels.EchoRows()
                    r.source, r.extra_length = wp.zeros((pings, 1), dtype=wp.vec3), wp.zeros((pings, 1), dtype=float)
                    r.amplitude, r.count = wp.zeros((pings, 1), dtype=float), wp.zeros(pings, dtype=wp.int32)
                self._no_echoes[pings] = r
            rows += [self._no_echoes[pings]] * (kernels.BUFFERS_PER_LAUNCH - len(rows))
        return rows

    def sum_exponents(self, rows, pings: int) -> wp.array:
        """k per (ping, stretch of kernels.STRETCH samples): the GPU sums that stretch's taps in
        units of 2^-k of unit amplitude, the finest (k <= 32) at which no sum there can overflow
        32 bits, from the |amplitude| of every echo of `rows` (`echo_rows`) that can reach it."""
        cfg = self.config
        zeros, empty, launch, launch_tiled = device_calls(self.device)
        bounds = zeros((pings, self._stretches), dtype=wp.int64)
        spm = cfg.chirp.sample_rate_hz / cfg.atmosphere.speed_of_sound
        launch_tiled(
            kernels.stretch_bounds(self._stretches),
            dim=[pings, kernels.BOUND_SPLITS],
            inputs=[*rows, spm, self._reach],
            outputs=[bounds],
            block_dim=kernels.BOUND_BLOCK_DIM,
        )
        exponents = empty((pings, self._stretches), dtype=wp.int32)
        launch(
            kernels.stretch_exponents, dim=exponents.shape, inputs=[bounds, self._largest_gain_tap], outputs=[exponents]
        )
        return exponents

    def __call__(
        self, echoes, pings: int, *, noise: str = "none", snr_db: float = 40.0, seeds: np.ndarray | None = None
    ) -> wp.array:
        """Signals (pings, mics, record_samples) float32 on the device."""
        if noise not in NOISE_KINDS:
            raise ValueError(f"noise must be one of {NOISE_KINDS}, got {noise!r}")
        cfg = self.config
        mics = cfg.microphone_count
        pairs = (mics + 1) // 2
        samples = cfg.record_samples
        zeros, empty, launch, launch_tiled = device_calls(self.device)  # runs in worker threads too
        impulses = self.impulses(echoes, pings)
        nodes = empty((pings * pairs * self.nodes, self._size), dtype=wp.vec2f)
        launch_tiled(
            self._convolve,
            dim=[pings * pairs, self.nodes],
            inputs=[impulses, self._hat, self._filters],
            outputs=[nodes],
            block_dim=tile_block_dim(self._size),
        )
        del impulses
        signals = empty((pings, mics, samples), dtype=float)
        launch(kernels.overlap_nodes, dim=signals.shape, inputs=[nodes, self.nodes, self.block], outputs=[signals])
        del nodes
        if noise != "none":
            if seeds is None or len(seeds) != pings:
                raise ValueError("noise needs one seed per ping")
            peak = zeros(pings, dtype=float)
            seed_array = wp.array(seeds, dtype=wp.int32, device=self.device)
            launch(kernels.peak_magnitude, dim=(pings, mics, kernels.PEAK_LANES), inputs=[signals], outputs=[peak])
            launch(
                kernels.add_noise,
                dim=signals.shape,
                inputs=[peak, seed_array, 10.0 ** (-snr_db / 20.0), NOISE_CODES[noise]],
                outputs=[signals],
            )
        return signals


@functools.lru_cache(maxsize=8)
def recorder(config, absorption: bool, device: str) -> Recorder:
    return Recorder(config, absorption=absorption, device=device)


def echo_buffer(arrivals, pings: int, device) -> EchoBuffer:
    """Upload `Arrivals` (numpy, any order) as an EchoBuffer with one row per ping."""
    pose = np.asarray(arrivals.pose_index, dtype=np.int64)
    counts = np.bincount(pose, minlength=pings).astype(np.int32)
    slots = int(counts.max()) if len(pose) else 0
    order = np.argsort(pose, kind="stable")
    column = np.arange(len(pose)) - np.repeat(np.cumsum(counts) - counts, counts)
    source = np.zeros((pings, slots, 3), np.float32)
    extra = np.zeros((pings, slots), np.float32)
    amplitude = np.zeros((pings, slots), np.float32)
    rows = pose[order]
    source[rows, column] = arrivals.source_m[order]
    extra[rows, column] = arrivals.length_m[order] - np.linalg.norm(arrivals.source_m[order], axis=1)
    amplitude[rows, column] = arrivals.amplitude[order]
    with wp.ScopedDevice(device):
        return EchoBuffer(
            source=wp.array(source, dtype=wp.vec3),
            extra_length=wp.array(extra, dtype=float),
            amplitude=wp.array(amplitude, dtype=float),
            count=wp.array(counts, dtype=wp.int32),
        )


def record(
    arrivals,
    config,
    *,
    pose_count: int | None = None,
    absorption: bool = True,
    noise: str = "none",
    snr_db: float = 40.0,
    seed: int = 0,
    device=None,
) -> np.ndarray:
    """Microphone signals of the pings whose echoes `arrivals` holds: float32 (N, mics, samples).

    Each echo is the emitted call, scaled by its amplitude and delayed to every microphone by
    (path to its source point + |source - mic|) / c: exact near-field fractional delays through
    band-limited filters that also carry ISO 9613-1 air absorption for that path length, summed
    as impulse responses and convolved with the call once per microphone (block FFTs on a Warp
    device). Noise: "gaussian" (white) or "uniform" (as in the paper) with standard deviation
    set so that the strongest sample of the ping is `snr_db` above it; each ping's noise comes
    from (seed, ping index).

    Args:
        arrivals: `Arrivals` from `Sonar.trace`.
        config: The `SonarConfig` that traced them.
        pose_count: Number of pings (default: the highest pose index + 1).
    """
    if noise not in NOISE_KINDS:
        raise ValueError(f"noise must be one of {NOISE_KINDS}, got {noise!r}")
    count = int(pose_count if pose_count is not None else (arrivals.pose_index.max() + 1 if len(arrivals) else 1))
    if len(arrivals) and arrivals.pose_index.max() >= count:
        raise ValueError(f"arrivals refer to pose {arrivals.pose_index.max()}, but pose_count is {count}")
    device = warp_device(device)
    rec = recorder(config, absorption, str(device))

    def pings(first: int, last: int) -> np.ndarray:
        mine = arrivals
        if (first, last) != (0, count):
            mine = arrivals.select((arrivals.pose_index >= first) & (arrivals.pose_index < last))
            mine.pose_index = mine.pose_index - first
        seeds = ping_seeds(seed, range(first, last))  # ping i's noise from (seed, i), however the pings are split
        signals = rec([echo_buffer(mine, last - first, device)], last - first, noise=noise, snr_db=snr_db, seeds=seeds)
        return signals.numpy().copy()

    # Warp runs a CPU launch on one core: there the pings are recorded in slices, in threads.
    threads = min(cpu_cores(), count) if device.is_cpu else 1
    if threads == 1:
        return pings(0, count)
    edges = np.linspace(0, count, threads + 1).round().astype(int).tolist()
    with ThreadPoolExecutor(threads) as pool:
        return np.concatenate(list(pool.map(pings, edges[:-1], edges[1:])))


PDM_BIT_ORDERS = ("lsb", "msb")


def pdm_to_pcm(
    raw: np.ndarray,
    *,
    channels: int = 32,
    pdm_rate_hz: float = 4.5e6,
    decimation: int = 10,
    cutoff_hz: float = 100e3,
    taps: int = 501,
    bit_order: str = "lsb",
) -> np.ndarray:
    """Decode 1-bit PDM microphone streams (as an eRTIS streams them) to PCM: float32 (channels, S // decimation).

    `raw` holds one word of `channels` bits per PDM sample, as unsigned integers (e.g. uint32 for
    32 channels) or as their little-endian bytes; bit i of a word is channel i ("lsb") or
    channel channels - 1 - i ("msb"). Each channel's bits become +-1, pass a linear-phase FIR
    low-pass (Hamming window, `taps` taps, -6 dB at `cutoff_hz`; the eRTIS passes 100 kHz) and
    are kept every `decimation`-th sample (4.5 MHz / 10 = 450 kHz), aligned so that output
    sample j is the signal at PDM sample j * decimation. A full-scale sine comes out with
    amplitude ~1.
    """
    from scipy.signal import firwin, upfirdn

    if channels < 1 or channels % 8:
        raise ValueError(f"channels must be a positive multiple of 8 (whole bytes per word), got {channels}")
    if bit_order not in PDM_BIT_ORDERS:
        raise ValueError(f"bit_order must be one of {PDM_BIT_ORDERS}, got {bit_order!r}")
    if decimation < 1 or not 0 < cutoff_hz < pdm_rate_hz / (2 * decimation) * 1.0001:
        raise ValueError(
            f"need decimation >= 1 and 0 < cutoff_hz <= the output Nyquist frequency "
            f"{pdm_rate_hz / (2 * decimation):.0f} Hz, got {decimation} and {cutoff_hz}"
        )
    if taps % 2 == 0 or (taps - 1) // 2 % decimation:
        raise ValueError(f"taps must be odd with (taps - 1) / 2 a multiple of decimation {decimation}, got {taps}")
    raw = np.asarray(raw)
    if raw.dtype.kind != "u":
        raise ValueError(f"raw PDM must be unsigned integers (words or bytes), got dtype {raw.dtype}")
    octets = np.ascontiguousarray(raw).astype(raw.dtype.newbyteorder("<"), copy=False).view(np.uint8)
    if octets.size % (channels // 8):
        raise ValueError(f"{octets.size} bytes are not whole words of {channels} bits")
    bits = np.unpackbits(octets.reshape(-1, channels // 8), axis=1, bitorder="little")  # (S, channels)
    if bit_order == "msb":
        bits = bits[:, ::-1]
    samples = len(bits)
    filt = firwin(taps, cutoff_hz, fs=pdm_rate_hz).astype(np.float32)
    pcm = upfirdn(filt, 2.0 * bits.T.astype(np.float32) - 1.0, down=decimation, axis=1)
    delay = (taps - 1) // 2 // decimation  # the FIR's group delay in output samples
    return np.ascontiguousarray(pcm[:, delay : delay + samples // decimation], dtype=np.float32)
