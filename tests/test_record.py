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


def random_echoes(rng, pings: int, slots: int, mic_position: np.ndarray, loud: float = 1.0):
    """Echoes from 1 mm to 13 m in random slot order, some amplitudes 0 (amplitudes up to
    `loud`), the first-tap sample of each on each microphone, without channel delays."""
    direction = rng.normal(size=(pings, slots, 3))
    direction /= np.linalg.norm(direction, axis=2, keepdims=True)
    near = rng.random((pings, slots, 1)) < 0.05
    source = direction * np.where(
        near, rng.uniform(0.001, 0.05, (pings, slots, 1)), rng.uniform(0.02, 8.0, (pings, slots, 1))
    )
    extra = np.where(~near[..., 0] & (rng.random((pings, slots)) < 0.5), rng.uniform(0.0, 5.0, (pings, slots)), 0.0)
    amplitude = np.where(rng.random((pings, slots)) < 0.1, 0.0, rng.uniform(1e-4, loud, (pings, slots)))
    path = extra[..., None] + np.linalg.norm(source[:, :, None] - mic_position, axis=3)
    return source, extra, amplitude, path


def test_row_blocks_sum_the_impulses_of_per_echo_atomics_in_their_units(device):
    """The GPU's kernel (a block sums a stretch of a microphone row in 32-bit shared memory, in
    units of 2^-k per stretch) against the CPU's (one 64-bit global atomic per tap, 2^-32), launched
    alike: each sample within its taps' count of one 2^-k unit of the CPU's, and the same bits in
    the stretches quiet enough for k = 32 (ping 0, amplitudes below 1e-6). 3 pings of 3,000 echoes,
    one ping's count short of its slots and one's beyond them; 31 microphones in rows of 32 with
    their own gains and delays (some negative, so taps fall before sample 0), a record that ends
    inside a chunk and taps beyond its end; ping 2 adds 300 echoes of amplitude 4 at one point,
    whose sums (~1,800) would overflow 32 bits in the CPU's units, on both sides of a stretch's start
    (so both stretches must know of them). On the CPU the block's threads run
    as cooperative fibers, so its barrier and thread stride are exercised too."""
    from acoustic_sim.engine.echoes import PointEchoes
    from acoustic_sim.engine.kernels import signals as kernels
    from acoustic_sim.engine.signals import ROW_BLOCK_DIM, ROW_LAUNCH_BOUNDS, Recorder

    rng = np.random.default_rng(5)
    rec = Recorder(CONFIG, device=device)
    pings, slots, mics, rows = 3, 3300, 31, 32
    samples, chunk = CONFIG.record_samples - 1007, 3000  # 5 chunks, the last one partial
    mic_position = np.asarray(CONFIG.microphones_m)[:mics]
    source, extra, amplitude, _ = random_echoes(rng, pings, slots, mic_position)
    amplitude[0] *= 1e-6
    # 300 echoes of one point heard ~3 samples before stretch 2 starts: taps on both sides of it
    point = np.array([1.0, 0.1, 0.05]) / np.linalg.norm([1.0, 0.1, 0.05]) * (2 * kernels.STRETCH - 3) * C / FS
    source[2, :300], extra[2, :300], amplitude[2, :300] = point, 0.0, 4.0
    count = np.array([slots, slots - 700, slots + 50])  # the last beyond its slots: only the slots count
    gain, delay = rng.uniform(0.5, 1.5, mics), rng.uniform(-40.0, 20.0, mics)  # [samples]
    path = extra[..., None] + np.linalg.norm(source[:, :, None] - mic_position, axis=3)
    lowest = (np.floor(path * FS / C + delay) - 1).astype(int)  # the first of 4 taps
    live = (amplitude > 0) & (np.arange(slots) < count[:, None])
    assert (lowest[live] < 0).any() and (lowest[live] + 3 >= samples).any()
    reach = np.linalg.norm(mic_position, axis=1).max() * FS / C + np.abs(delay).max() + 6
    with wp.ScopedDevice(device):
        echoes = PointEchoes(
            source=wp.array(source.astype(np.float32), dtype=wp.vec3),
            extra_length=wp.array(extra.astype(np.float32), dtype=float),
            amplitude=wp.array(amplitude.astype(np.float32), dtype=float),
            count=wp.array(count.astype(np.int32), dtype=wp.int32),
            order=wp.zeros((pings, slots), dtype=wp.int32),
        )
        taps_inputs = [
            wp.array(mic_position.astype(np.float32), dtype=wp.vec3),
            wp.array(gain.astype(np.float32), dtype=float),
            wp.array(delay.astype(np.float32), dtype=float),
            FS / C,
            rec._absorption_per_m,
            rec._taps,
            samples,
            rec.block,
        ]
        # The slots in three buffers, as the tracer hands them over; each counts the slots after
        # its first, so the first two count beyond their slots (only their slots count)
        buffers = []
        for first, last in ((0, 1000), (1000, 2800), (2800, slots)):
            part = kernels.EchoRows()
            part.source, part.extra_length = echoes.source[:, first:last], echoes.extra_length[:, first:last]
            part.amplitude = echoes.amplitude[:, first:last]
            part.count = wp.array(np.maximum(count - first, 0).astype(np.int32), dtype=wp.int32)
            buffers.append(part)
        stretches = -(-samples // kernels.STRETCH)
        bounds, exponents = wp.zeros((pings, stretches), dtype=wp.int64), wp.empty((pings, stretches), dtype=wp.int32)
        largest = float(gain.max() * np.abs(rec._taps.numpy()).max())
        shape = (pings * rows, rec.block + CONFIG.record_samples + rec._size)
        per_echo, per_row = wp.zeros(shape, dtype=wp.int64), wp.zeros(shape, dtype=wp.int64)
        per_echo_inputs = [echoes.source, echoes.extra_length, echoes.amplitude, echoes.count, *taps_inputs]
        wp.launch(kernels.accumulate_echoes, dim=(pings, slots, mics), inputs=per_echo_inputs, outputs=[per_echo])
        blocks, wp.config.enable_cpu_blocks = wp.config.enable_cpu_blocks, True
        try:
            wp.launch_tiled(
                kernels.stretch_bounds(stretches),
                dim=[pings, kernels.BOUND_SPLITS],
                inputs=[*buffers, FS / C, float(reach)],
                outputs=[bounds],
                block_dim=kernels.BOUND_BLOCK_DIM,
            )
            wp.launch(kernels.stretch_exponents, dim=exponents.shape, inputs=[bounds, largest], outputs=[exponents])
            wp.launch_tiled(
                kernels.row_accumulation(chunk, stretches, ROW_LAUNCH_BOUNDS),
                dim=[pings, mics, -(-samples // chunk)],
                inputs=[*buffers, *taps_inputs, exponents],
                outputs=[per_row],
                block_dim=ROW_BLOCK_DIM,
            )
        finally:
            wp.config.enable_cpu_blocks = blocks
    expected, got, k = per_echo.numpy(), per_row.numpy(), exponents.numpy()
    written = np.nonzero(expected.any(axis=0))[0] - rec.block
    assert written.min() == 0 and written.max() == samples - 1  # the row's ends are reached
    assert not expected[rows - 1 :: rows].any() and expected.any(axis=1).sum() == pings * mics  # row 32 unused
    assert (k[0] == 32).all() and k[1].max() < 32 and k[2].min() < k[1].min()  # the 300 echoes: coarser
    assert np.abs(expected[2 * rows :]).max() > 2**31  # they overflow 32 bits in the CPU's units
    loud = np.abs(expected[2 * rows :, rec.block : rec.block + samples]) > 2**31
    assert {1, 2} <= set(np.nonzero(loud.any(axis=0))[0] // kernels.STRETCH)  # in both stretches
    # Taps per sample: each (echo, microphone) adds 4 taps from its first one on (counted one
    # sample wider each side: float32 may round the first tap's sample the other way).
    taps = np.zeros((pings, rows, samples), np.int64)
    p, s, m = np.nonzero(live[..., None] & np.ones(mics, bool))
    for j in range(-1, 5):
        n = lowest[p, s, m] + j
        inside = (n >= 0) & (n < samples)
        np.add.at(taps, (p[inside], m[inside], n[inside]), 1)
    unit = 2.0 ** (32 - np.repeat(k, kernels.STRETCH, axis=1)[:, :samples])  # CPU units per GPU unit
    columns = slice(rec.block, rec.block + samples)
    difference = np.abs(got[:, columns] - expected[:, columns]).reshape(pings, rows, samples)
    assert (difference <= taps * unit[:, None]).all()
    np.testing.assert_array_equal(got[:rows], expected[:rows])  # ping 0: k = 32, the same bits
    assert not got[:, : rec.block].any() and not got[:, rec.block + samples :].any()


def test_stretch_units_leave_no_32_bit_sum_room_to_overflow(device):
    """`Recorder.sum_exponents` against every tap of 2 pings of random echoes (one of them 10^4
    times louder, the other with 200 loud echoes of one point across a stretch's start) on the
    eRTIS's microphones: in each stretch, the largest possible |sum| of a
    sample (every |tap| added) stays below 2^31 in that stretch's units, and every unit is at most
    1e-6 of the ping's largest possible |sample| (the stretches bound the summed |amplitude| of all
    echoes that can reach them, which is coarser than a sample's own sum needs)."""
    from acoustic_sim.engine.echoes import PointEchoes
    from acoustic_sim.engine.kernels import signals as kernels
    from acoustic_sim.engine.signals import Recorder

    rng = np.random.default_rng(8)
    rec = Recorder(CONFIG, device=device)
    mics = np.asarray(CONFIG.microphones_m)
    source, extra, amplitude, path = random_echoes(rng, 2, 4000, mics)
    amplitude[1] *= 1e4
    # 200 loud echoes of one point heard 15 samples before stretch 3 starts at the array's origin, later on
    # some microphones: both stretches must count them
    point = np.array([0.5, -0.8, 0.3]) / np.linalg.norm([0.5, -0.8, 0.3]) * (3 * kernels.STRETCH - 15) * C / FS
    source[0, :200], extra[0, :200], amplitude[0, :200] = point, 0.0, 50.0
    path = extra[..., None] + np.linalg.norm(source[:, :, None] - mics, axis=3)
    with wp.ScopedDevice(device):
        echoes = PointEchoes(
            source=wp.array(source.astype(np.float32), dtype=wp.vec3),
            extra_length=wp.array(extra.astype(np.float32), dtype=float),
            amplitude=wp.array(amplitude.astype(np.float32), dtype=float),
            count=wp.array(np.array([4000, 4000], np.int32), dtype=wp.int32),
            order=wp.zeros((2, 4000), dtype=wp.int32),
        )
        blocks, wp.config.enable_cpu_blocks = wp.config.enable_cpu_blocks, True
        try:
            k = rec.sum_exponents(rec.echo_rows([echoes], 2), 2).numpy()
        finally:
            wp.config.enable_cpu_blocks = blocks
    samples = CONFIG.record_samples
    delay = path * FS / C + CONFIG.channel_delay_s()[None, None] * FS
    worst = np.zeros((2, len(mics), samples + 8))
    p, s, m = np.indices(delay.shape).reshape(3, -1)
    first = np.floor(delay.ravel()).astype(int) - 1
    largest = np.abs(CONFIG.channel_gain()).max() * np.abs(rec._taps.numpy()).max()
    for j in range(4):
        n = np.clip(first + j, 0, samples + 7)
        np.add.at(worst, (p, m, n), np.abs(amplitude[p, s]) * largest)
    worst = worst[:, :, :samples].max(axis=1)  # (ping, sample)
    stretch = np.arange(samples) // kernels.STRETCH
    units = 2.0 ** k[:, stretch]
    assert (worst * units < 2**31).all()
    assert (k < 32).any() and (k[1] < k[0]).all()
    # Fine enough: a unit is at most 1e-6 (-120 dB) of the ping's largest possible |sample|.
    assert (2.0 ** -k.astype(float) <= 1e-6 * worst.max(axis=1, keepdims=True)).all()


def test_row_chunks_fit_the_shared_memory_of_a_block():
    """A block sums a whole 16,384-sample row of 32-bit sums with the 227 KB of an H100, the 163 KB of
    an A100 or the 99 KB of a consumer GPU, half of it with 48 KB, and no more than a short record
    needs; 64-bit sums took twice the memory."""
    from acoustic_sim.engine.signals import row_chunk

    assert row_chunk(16384, 227 * 1024) == row_chunk(16384, 99 * 1024) == 16384
    assert row_chunk(16384, 48 * 1024) == 8192 and row_chunk(16384, 24 * 1024) == 4096
    assert row_chunk(5000, 227 * 1024) == 8192 and row_chunk(40000, 227 * 1024) == 16384
    assert row_chunk(16384, 99 * 1024, sample_bytes=8) == 8192
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


def test_ping_seeds_are_numpys_seed_sequence():
    """Each ping's noise seed is the first word of numpy's SeedSequence([seed, ping]) (its lowest
    31 bits), for seeds of one to five 32-bit words (five: the pool of four overflows) and pings
    up to 2**32 - 1; computed for all pings at once, where one SeedSequence per ping is the reference."""
    from acoustic_sim.engine.seeds import ping_seeds

    pings = np.r_[0, 1, np.random.default_rng(0).integers(2, 2**32 - 1, 40), 2**32 - 1]
    for seed in (0, 1, 2**32 - 1, 2**32, 2**63 - 1, 2**130 + 11, 987_654_321):
        want = [np.random.SeedSequence([seed, int(p)]).generate_state(1)[0] & 0x7FFFFFFF for p in pings]
        got = ping_seeds(seed, pings)
        assert got.dtype == np.int32
        np.testing.assert_array_equal(got, want)
    assert ping_seeds(5, range(3, 3)).shape == (0,)


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


def test_office_pings_record_and_image_alike_with_32_bit_row_sums(device):
    """Issue 42's tolerance for the GPU's row sums: 4 office pings at 3 bounces (rough walls:
    thousands of scattered echoes a ping), recorded with 32-bit row sums and with exact 64-bit
    atomics on the same device, then beamformed: signals within 1e-5 of each ping's peak (2e-6
    measured on the CPU), the energyscapes' largest difference 1e-5 of their peak (4e-7), the same
    strongest range bin at every azimuth where its peak stands out, and the noise's level
    unchanged. On the CPU the row kernel runs as cooperative fibers."""
    import scenes
    from acoustic_sim.engine.signals import echo_buffer, recorder

    sonar = sim.Sonar(CONFIG, max_bounces=3, ray_count=4000, device=device)
    poses = np.stack([scenes.pose(2.0 + 0.8 * i, 2.0 + 0.4 * i, 0.3, 0.5 * i) for i in range(4)])
    arrivals = sonar.trace(scenes.office(seed=0), poses)
    assert np.bincount(arrivals.pose_index).min() > 2000
    rec = recorder(CONFIG, True, str(sonar.device))
    echoes = [echo_buffer(arrivals, 4, sonar.device)]
    blocks, wp.config.enable_cpu_blocks = wp.config.enable_cpu_blocks, True
    try:
        impulses = {rows: rec.impulses(echoes, 4, row_sums=rows) for rows in (True, False)}
    finally:
        wp.config.enable_cpu_blocks = blocks
    assert (impulses[True].numpy() != impulses[False].numpy()).any()  # the 32-bit units are coarser
    signals, images = {}, {}
    for rows, made in impulses.items():
        rec.impulses = lambda *args, made=made, **kwargs: made  # the rest of the recording as it is
        try:
            signals[rows] = {
                noise: rec(echoes, 4, noise=noise, seeds=np.arange(4, dtype=np.int32)).numpy()
                for noise in ("none", "gaussian")
            }
        finally:
            del rec.impulses
        images[rows] = sonar.energyscape(signals[rows]["none"])
    peak = np.abs(signals[False]["none"]).max(axis=(1, 2), keepdims=True)
    assert (np.abs(signals[True]["none"] - signals[False]["none"]) <= 1e-5 * peak).all()
    noise = {rows: (signals[rows]["gaussian"] - signals[rows]["none"]).std() for rows in (True, False)}
    assert noise[True] == pytest.approx(noise[False], rel=1e-5)
    exact, summed = images[False], images[True]
    assert np.abs(summed - exact).max() <= 1e-5 * exact.max()
    clear = exact.max(axis=1) > 2 * np.median(exact, axis=1)  # (ping, azimuth) with a standing peak
    assert clear.mean() > 0.5
    np.testing.assert_array_equal(summed.argmax(axis=1)[clear], exact.argmax(axis=1)[clear])
