"""Microphone signals against the call written in continuous time and delayed analytically."""

import numpy as np
import pytest
import warp as wp

import acoustic_sim as sim
from acoustic_sim.air import air_absorption_db_per_m
from acoustic_sim.engine.paths import KIND_SPECULAR, Arrivals
from acoustic_sim.engine.signals import record

CONFIG = sim.SonarConfig.ertis()
C = CONFIG.atmosphere.speed_of_sound
FS = CONFIG.chirp.sample_rate_hz


def call_at(t: np.ndarray) -> np.ndarray:
    """The 50 -> 25 kHz hyperbolic call at continuous times t [s] (0 outside 0..2.5 ms), tapers included."""
    f0, f1, big_t = 50e3, 25e3, 2.5e-3
    k = (f0 - f1) / (f1 * big_t)
    inside = (t >= 0) & (t <= big_t)
    tt = np.clip(t, 0, big_t)
    x = np.sin(2 * np.pi * f0 / k * np.log1p(k * tt))
    ramp = round(0.1 * 1126) / FS  # taper length in seconds
    rise = np.where(tt < ramp, 0.5 - 0.5 * np.cos(np.pi * tt / ramp), 1.0)
    fall = np.where(big_t - tt < ramp, 0.5 - 0.5 * np.cos(np.pi * (big_t - tt) / ramp), 1.0)
    return np.where(inside, x * rise * fall, 0.0)


def single_arrival(source, amplitude=0.5, extra=0.0):
    source = np.asarray(source, dtype=np.float64)[None]
    length = np.linalg.norm(source, axis=1) + extra
    return Arrivals(
        pose_index=np.zeros(1, np.int64),
        delay_s=length / C,
        direction=source / np.linalg.norm(source),
        amplitude=np.array([amplitude]),
        order=np.ones(1, np.int64),
        kind=np.full(1, KIND_SPECULAR),
        source_m=source,
        length_m=length,
        point_m=source,
    )


def test_near_field_delays_per_microphone(device):
    """A point echo 1.2 m ahead, 0.3 m left, 0.1 m up (near field for the 66 mm array): every
    microphone records the call delayed by |source - mic| / c to a fraction of a sample, with
    the arrival's amplitude (max error 1 % of the amplitude)."""
    source = np.array([1.2, 0.3, 0.1])
    got = record(single_arrival(source), CONFIG, absorption=False, device=device)
    assert got.shape == (1, 32, 16384) and got.dtype == np.float32
    t = np.arange(16384) / FS
    mics = np.asarray(CONFIG.microphones_m)
    for m in (0, 7, 19, 31):
        expected = 0.5 * call_at(t - np.linalg.norm(source - mics[m]) / C)
        assert np.abs(got[0, m] - expected).max() < 0.005


def test_channel_gain_and_delay_mismatch(device):
    """A mismatched array (per-microphone gain 0.5..1.5 and delay 0..20 us, fractions of a sample
    included): microphone m records gain_m times the call delayed by |source - mic| / c + delay_m
    (max error 1 % of the amplitude)."""
    rng = np.random.default_rng(3)
    gain, delay = rng.uniform(0.5, 1.5, 32), rng.uniform(0.0, 20e-6, 32)
    config = sim.SonarConfig.ertis(microphone_gain=tuple(gain), microphone_delay_s=tuple(delay))
    source = np.array([1.5, -0.4, 0.2])
    got = record(single_arrival(source), config, absorption=False, device=device)
    t = np.arange(16384) / FS
    mics = np.asarray(config.microphones_m)
    for m in (0, 11, 23, 31):
        expected = 0.5 * gain[m] * call_at(t - np.linalg.norm(source - mics[m]) / C - delay[m])
        assert np.abs(got[0, m] - expected).max() < 0.005 * gain[m]
    with pytest.raises(ValueError, match="microphone_gain"):
        sim.SonarConfig.ertis(microphone_gain=(1.0, 2.0))


def test_impulses_of_many_echoes_match_a_per_tap_reference(device):
    """Three pings of up to 60 echoes each (one ping silent), a mismatched array and air
    absorption: the fixed-point impulse rows equal the fractional-delay taps written out in
    float64 for every echo, microphone and tap, within the float32 rounding of the delay
    (2e-3 of the amplitude). Catches a tap, microphone row or ping row put in the wrong place.
    Echoes within 1e-3 sample of a whole sample at some microphone are left out: there float32
    and float64 may round to neighbouring samples, whose (equally valid) filters differ."""
    from acoustic_sim.engine.signals import FRACTION_STEPS, Recorder, echo_buffer, fractional_delay_table

    rng = np.random.default_rng(11)
    gain, delay = rng.uniform(0.5, 1.5, 32), rng.uniform(0.0, 20e-6, 32)
    config = sim.SonarConfig.ertis(microphone_gain=tuple(gain), microphone_delay_s=tuple(delay))
    mics = np.asarray(config.microphones_m)
    pose = np.repeat([0, 2], [60, 35])  # ping 1 has no echo
    source = rng.uniform([0.3, -2, -1], [4, 2, 1], (len(pose), 3))
    extra = np.where(rng.random(len(pose)) < 0.5, rng.uniform(0, 3, len(pose)), 0.0)
    path = extra[:, None] + np.linalg.norm(source[:, None] - mics[None], axis=2)
    at = path * FS / C + delay[None] * FS  # (echo, mic) arrival in samples
    clear = (np.abs(at - np.round(at)) > 1e-3).all(axis=1)
    pose, source, extra, path, at = pose[clear], source[clear], extra[clear], path[clear], at[clear]
    n = len(pose)
    length = np.linalg.norm(source, axis=1) + extra
    amplitude = rng.uniform(0.01, 1.0, n)
    arrivals = Arrivals(
        pose_index=pose,
        delay_s=length / C,
        direction=source / np.linalg.norm(source, axis=1, keepdims=True),
        amplitude=amplitude,
        order=np.ones(n, np.int64),
        kind=np.full(n, KIND_SPECULAR),
        source_m=source,
        length_m=length,
        point_m=source,
    )
    rec = Recorder(config, device=device)
    got = rec.impulses([echo_buffer(arrivals, 3, rec.device)], 3).numpy().astype(np.float64) / 2.0**32

    taps = fractional_delay_table(config).astype(np.float64)
    count = taps.shape[1]
    expected = np.zeros_like(got)
    first = np.floor(at).astype(int)
    v = (at - first) * FRACTION_STEPS
    i = np.minimum(v.astype(int), FRACTION_STEPS - 1)
    w = (1 - (v - i))[..., None] * taps[i] + (v - i)[..., None] * taps[i + 1]  # (echo, mic, tap)
    centre_hz = 0.5 * (config.chirp.start_frequency_hz + config.chirp.stop_frequency_hz)
    nepers_per_m = air_absorption_db_per_m(centre_hz) * np.log(10) / 20  # ISO 9613-1 at the call's centre
    scale = amplitude[:, None] * gain[None] * np.exp(-nepers_per_m * path)
    rows = pose[:, None] * 32 + np.arange(32)[None]
    columns = rec.block + first[..., None] - count // 2 + 1 + np.arange(count)
    np.add.at(expected, (rows[..., None].repeat(count, -1), columns), w * scale[..., None])
    assert np.abs(expected).max() > 0.1 and not got[32:64].any()
    np.testing.assert_allclose(got, expected, rtol=0, atol=2e-3)


def test_row_blocks_sum_the_same_impulses_as_per_echo_atomics(device):
    """The GPU's kernel (a block sums a stretch of a microphone row in shared memory) against the
    CPU's (one global atomic per tap), launched alike, give the same fixed-point impulses bit for
    bit: 3 pings of 3,000 echoes from 1 mm to 13 m in random slot order, one ping's count short
    of its slots and one's beyond them, some amplitudes 0; 31 microphones in rows of 32 with their
    own gains and delays (some negative, so taps fall before sample 0), a record that ends inside
    a chunk and taps beyond its end. On the CPU the block's threads run as cooperative fibers, so
    its barrier and thread stride are exercised too."""
    from acoustic_sim.engine.echoes import PointEchoes
    from acoustic_sim.engine.kernels import signals as kernels
    from acoustic_sim.engine.signals import ROW_BLOCK_DIM, Recorder

    rng = np.random.default_rng(5)
    rec = Recorder(CONFIG, device=device)
    pings, slots, mics, rows = 3, 3000, 31, 32
    samples, chunk = CONFIG.record_samples - 1007, 3000  # 5 chunks, the last one partial
    direction = rng.normal(size=(pings, slots, 3))
    direction /= np.linalg.norm(direction, axis=2, keepdims=True)
    near = rng.random((pings, slots, 1)) < 0.05
    source = direction * np.where(
        near, rng.uniform(0.001, 0.05, (pings, slots, 1)), rng.uniform(0.02, 8.0, (pings, slots, 1))
    )
    extra = np.where(~near[..., 0] & (rng.random((pings, slots)) < 0.5), rng.uniform(0.0, 5.0, (pings, slots)), 0.0)
    amplitude = np.where(rng.random((pings, slots)) < 0.1, 0.0, rng.uniform(1e-4, 1.0, (pings, slots)))
    count = np.array([slots, slots - 700, slots + 50])  # the last beyond its slots: only the slots count
    mic_position = np.asarray(CONFIG.microphones_m)[:mics]
    gain, delay = rng.uniform(0.5, 1.5, mics), rng.uniform(-40.0, 20.0, mics)  # [samples]
    path = extra[..., None] + np.linalg.norm(source[:, :, None] - mic_position, axis=3)
    lowest = np.floor(path * FS / C + delay) - 1  # the first of 4 taps
    live = (amplitude > 0) & (np.arange(slots) < count[:, None])
    assert (lowest[live] < 0).any() and (lowest[live] + 3 >= samples).any()
    with wp.ScopedDevice(device):
        echoes = PointEchoes(
            source=wp.array(source.astype(np.float32), dtype=wp.vec3),
            extra_length=wp.array(extra.astype(np.float32), dtype=float),
            amplitude=wp.array(amplitude.astype(np.float32), dtype=float),
            count=wp.array(count.astype(np.int32), dtype=wp.int32),
            order=wp.zeros((pings, slots), dtype=wp.int32),
        )
        inputs = [
            echoes.source,
            echoes.extra_length,
            echoes.amplitude,
            echoes.count,
            wp.array(mic_position.astype(np.float32), dtype=wp.vec3),
            wp.array(gain.astype(np.float32), dtype=float),
            wp.array(delay.astype(np.float32), dtype=float),
            FS / C,
            rec._absorption_per_m,
            rec._taps,
            samples,
            rec.block,
        ]
        shape = (pings * rows, rec.block + CONFIG.record_samples + rec._size)
        per_echo, per_row = wp.zeros(shape, dtype=wp.int64), wp.zeros(shape, dtype=wp.int64)
        wp.launch(kernels.accumulate_echoes, dim=(pings, slots, mics), inputs=inputs, outputs=[per_echo])
        blocks, wp.config.enable_cpu_blocks = wp.config.enable_cpu_blocks, True
        try:
            wp.launch_tiled(
                kernels.row_accumulation(chunk),
                dim=[pings, mics, -(-samples // chunk)],
                inputs=inputs,
                outputs=[per_row],
                block_dim=ROW_BLOCK_DIM,
            )
        finally:
            wp.config.enable_cpu_blocks = blocks
    expected, got = per_echo.numpy(), per_row.numpy()
    written = np.nonzero(expected.any(axis=0))[0] - rec.block
    assert written.min() == 0 and written.max() == samples - 1  # the row's ends are reached
    assert not expected[rows - 1 :: rows].any() and expected.any(axis=1).sum() == pings * mics  # row 32 unused
    np.testing.assert_array_equal(got, expected)


def test_row_chunks_fit_the_shared_memory_of_a_block():
    """A block sums a whole 16,384-sample row with the 227 KB of an H100 or 163 KB of an A100,
    half of it with the 99 KB of a consumer GPU, and no more than a short record needs."""
    from acoustic_sim.engine.signals import row_chunk

    assert row_chunk(16384, 227 * 1024) == row_chunk(16384, 163 * 1024) == 16384
    assert row_chunk(16384, 99 * 1024) == 8192 and row_chunk(16384, 48 * 1024) == 4096
    assert row_chunk(5000, 227 * 1024) == 8192 and row_chunk(40000, 227 * 1024) == 16384
    assert row_chunk(16384, 0) == 256


def test_scattered_arrivals_add_their_path_to_the_source_point(device):
    """An arrival whose path reaches its source point after 2 m more arrives 2 m / c later."""
    near = record(single_arrival([1.0, 0.0, 0.0]), CONFIG, absorption=False, device=device)
    far = record(single_arrival([1.0, 0.0, 0.0], extra=2.0), CONFIG, absorption=False, device=device)
    shift = round(2.0 / C * FS)
    np.testing.assert_allclose(far[0, 3, shift + 100 : shift + 1200], near[0, 3, 100:1200], atol=0.01)


def test_air_absorption_per_frequency(device):
    """At 2.2, 6 and 8.3 m the echo's spectrum falls by ISO 9613-1's alpha(f) * length relative to
    no absorption, within 0.05 dB at 27, 35 and 45 kHz."""
    freqs = np.fft.rfftfreq(16384, 1 / FS)
    for length in (2.2, 6.0, 8.3):
        arrival = single_arrival([length, 0.0, 0.0], amplitude=1.0)
        dry = record(arrival, CONFIG, absorption=False, device=device)[0, 0]
        wet = record(arrival, CONFIG, absorption=True, device=device)[0, 0]
        ratio_db = 20 * np.log10(np.abs(np.fft.rfft(wet)) / np.abs(np.fft.rfft(dry)))
        for f in (27e3, 35e3, 45e3):
            i = np.argmin(np.abs(freqs - f))
            assert ratio_db[i] == pytest.approx(-air_absorption_db_per_m(f) * length, abs=0.05)


def test_noise_level_and_kind(device):
    """Gaussian noise 20 dB below the strongest sample; uniform noise stays within sqrt(3) std."""
    arrival = single_arrival([2.0, 0.0, 0.0], amplitude=1.0)
    clean = record(arrival, CONFIG, absorption=False, device=device)
    noisy = record(arrival, CONFIG, absorption=False, noise="gaussian", snr_db=20.0, seed=1, device=device)
    residual = noisy - clean
    assert residual.std() == pytest.approx(np.abs(clean).max() / 10.0, rel=0.02)
    flat = record(arrival, CONFIG, absorption=False, noise="uniform", snr_db=20.0, seed=1, device=device) - clean
    assert np.abs(flat).max() <= np.sqrt(3) * np.abs(clean).max() / 10.0 * 1.001
    with pytest.raises(ValueError, match="noise"):
        record(arrival, CONFIG, noise="pink")


@pytest.mark.parametrize(("chirp", "taps"), [(sim.ChirpConfig(), 4), (sim.ChirpConfig.band_20_80khz(), 6)])
def test_delay_filters_are_pure_delays_across_the_band(chirp, taps):
    """Each row of the fractional-delay table delays every tone of the call's band by its
    fraction of a sample: response exp(-2 pi i f tau) within -60 dB, with the fewest taps that
    allow it (each tap is an atomic add per echo and microphone)."""
    from acoustic_sim.engine.signals import FRACTION_STEPS, fractional_delay_table

    table = fractional_delay_table(sim.SonarConfig.ertis(chirp=chirp)).astype(np.float64)
    assert table.shape == (FRACTION_STEPS + 1, taps)
    f = np.linspace(chirp.stop_frequency_hz, chirp.start_frequency_hz, 101)[:, None]
    for j, fraction in enumerate(np.linspace(0.0, 1.0, FRACTION_STEPS + 1)):
        # tap k sits k - taps / 2 + 1 samples after the arrival's whole sample; the arrival is `fraction` after it
        offsets = np.arange(taps) - taps // 2 + 1 - fraction
        response = np.exp(-2j * np.pi * f * offsets / chirp.sample_rate_hz) @ table[j]
        assert np.abs(response - 1.0).max() < 1e-3
