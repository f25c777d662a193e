"""Energyscapes: point reflectors image where they are; the beam pattern is the array factor."""

from pathlib import Path

import numpy as np
import pytest

import acoustic_sim as sim
import scenes
from acoustic_sim.engine.beamform import energyscape
from acoustic_sim.engine.paths import KIND_SPECULAR, Arrivals
from acoustic_sim.engine.signals import record

CONFIG = sim.SonarConfig.ertis()
C = CONFIG.atmosphere.speed_of_sound


def unit(azimuth_deg, elevation_deg=0.0):
    """Unit vectors (..., 3) towards (azimuth, elevation) in the sensor frame (x ahead, y left, z up)."""
    az, el = np.broadcast_arrays(np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def reflectors(ranges_m, azimuths_deg, elevations_deg=0.0):
    """One echo per ping from a point reflector at (range, azimuth, elevation): its image source
    lies at twice the range (path emitter -> reflector -> array, emitter taken at the array)."""
    r = np.asarray(ranges_m, dtype=np.float64)
    source = 2 * r[:, None] * unit(np.broadcast_to(azimuths_deg, r.shape), elevations_deg)
    n = len(r)
    return Arrivals(
        pose_index=np.arange(n),
        delay_s=2 * r / C,
        direction=source / (2 * r[:, None]),
        amplitude=1.0 / (2 * r),
        order=np.ones(n, np.int64),
        kind=np.full(n, KIND_SPECULAR),
        source_m=source,
        length_m=2 * r,
        point_m=source / 2,
    )


def test_point_reflectors_image_at_their_range_and_azimuth(device):
    """Reflectors at 9 azimuths (-80..80 deg) x 3 ranges (1, 2.5, 4 m), with air absorption and
    noise 30 dB down: each energyscape peaks within one 2 cm range bin and 2 deg of the truth."""
    azimuths = np.tile(np.arange(-80.0, 81.0, 20.0), 3)
    ranges = np.repeat([1.0, 2.5, 4.0], 9)
    signals = record(reflectors(ranges, azimuths), CONFIG, noise="gaussian", snr_db=30.0, seed=0, device=device)
    images = energyscape(signals, CONFIG, device=device)
    grid = sim.PolarGrid()
    for image, r, az in zip(images, ranges, azimuths, strict=True):
        i, j = np.unravel_index(np.argmax(image), image.shape)
        assert abs(grid.range_m[i] - r) <= grid.range_bin_m, (r, az, grid.range_m[i])
        assert abs(np.rad2deg(grid.azimuth_rad[j]) - az) <= 2.0, (r, az, np.rad2deg(grid.azimuth_rad[j]))


def test_point_reflectors_image_at_their_range_azimuth_and_elevation(device):
    """Reflectors below (a floor-like -17 deg, -25 deg), at and above (10, 20, 25 deg) the array's
    horizon, at 1-4 m and -50..45 deg azimuth, with air absorption and noise 30 dB down, beamformed
    at elevations -30..30 deg in 5 deg steps: each (E, R, A) energyscape peaks within one 2 cm range
    bin, 2 deg of azimuth and, in elevation, on the beam nearest the truth (within half a step)."""
    ranges = np.array([1.0, 2.0, 1.5, 2.5, 3.0, 1.2, 3.5, 4.0])
    azimuths = np.array([0.0, 30.0, -40.0, 15.0, -20.0, 45.0, -50.0, 5.0])
    elevations = np.array([-17.0, -17.0, 20.0, 10.0, -25.0, 0.0, 25.0, -8.0])
    signals = record(
        reflectors(ranges, azimuths, elevations), CONFIG, noise="gaussian", snr_db=30.0, seed=0, device=device
    )
    grid = sim.PolarGrid(azimuth_min_deg=-60.0, azimuth_max_deg=60.0)
    beams = np.arange(-30.0, 31.0, 5.0)
    images = energyscape(signals, CONFIG, grid=grid, elevation_deg=tuple(beams), device=device)
    assert images.shape == (len(ranges), len(beams), *grid.shape)
    for image, r, az, el in zip(images, ranges, azimuths, elevations, strict=True):
        e, i, j = np.unravel_index(np.argmax(image), image.shape)
        got = (grid.range_m[i], np.rad2deg(grid.azimuth_rad[j]), beams[e])
        assert abs(got[0] - r) <= grid.range_bin_m, ((r, az, el), got)
        assert abs(got[1] - az) <= 2.0, ((r, az, el), got)
        assert abs(got[2] - el) <= 2.5, ((r, az, el), got)


def test_a_traced_small_sphere_images_at_its_range_and_azimuth(device):
    """A 2 cm brick sphere alone in free space, seen at 9 azimuths (-80..80 deg) x 3 ranges
    (1, 2.5, 4 m) to its near surface: trace -> record -> energyscape peaks within one range bin and
    2 deg of that point. The sensor's heading varies per pose so facets do not line up. A faceted
    sphere has almost no exact specular path, so the echo is its scattered part (kind 1)."""
    import trimesh

    from scenes.scene import assemble

    radius = 0.02
    scene = assemble([(trimesh.creation.icosphere(subdivisions=3, radius=radius), "brick")], name="sphere")
    azimuths = np.tile(np.arange(-80.0, 81.0, 20.0), 3)
    ranges = np.repeat([1.0, 2.5, 4.0], 9)
    yaw = 0.7 * np.arange(len(ranges))
    heading = yaw + np.deg2rad(azimuths)  # world direction from the sensor to the sphere's centre
    poses = scenes.poses(-(ranges + radius)[:, None] * np.c_[np.cos(heading), np.sin(heading)], yaw)
    sonar = sim.Sonar(CONFIG, max_bounces=0, ray_count=200_000, device=device)
    arrivals = sonar.trace(scene, poses)
    assert np.array_equal(np.unique(arrivals.pose_index), np.arange(len(poses)))
    images = sonar.energyscape(sonar.record(arrivals, pose_count=len(poses), noise="gaussian", snr_db=30.0, seed=0))
    grid = sim.PolarGrid()
    for image, r, az in zip(images, ranges, azimuths, strict=True):
        i, j = np.unravel_index(np.argmax(image), image.shape)
        assert abs(grid.range_m[i] - r) <= grid.range_bin_m, (r, az, grid.range_m[i])
        assert abs(np.rad2deg(grid.azimuth_rad[j]) - az) <= 2.0, (r, az, np.rad2deg(grid.azimuth_rad[j]))


def array_factor(look, source, mics, freqs, weights):
    """Broadband delay-and-sum response to a far-field source, written directly:
    |sum_f w(f) sum_m exp(2 pi i f (tau_m(u) - tau_m(u0)))| / (M sum_f w), tau_m = m . u / c, for
    look directions u (L, 3) and the source's direction u0 (3,)."""
    dtau = (look - source) @ mics.T / 343.0  # (L, M)
    phase = np.exp(2j * np.pi * freqs[None, None, :] * dtau[:, :, None])
    return np.abs((phase.sum(axis=1) * weights).sum(axis=1)) / (len(mics) * weights.sum())


def call_band():
    """Frequencies [Hz] of the beamformer's band (20-55 kHz) and the call's power at each."""
    freqs = np.fft.rfftfreq(8192, 1 / 450e3)
    weights = np.abs(np.fft.rfft(CONFIG.chirp.samples(), 8192)) ** 2
    keep = (freqs > 20e3) & (freqs < 55e3)
    return freqs[keep], weights[keep]


def test_beam_pattern_is_the_delay_and_sum_array_factor(device):
    """A far reflector at 20 deg (3 m): the energyscape across azimuth at its range equals the
    analytic broadband array factor of the 32 microphones weighted by the call's power spectrum,
    within 1 dB wherever the pattern is above -15 dB; main lobe ~5-11 deg wide at -3 dB."""
    grid = sim.PolarGrid(range_min_m=2.99, range_max_m=3.01, range_bin_m=0.02)
    signals = record(reflectors([3.0], [20.0]), CONFIG, absorption=False, device=device)
    got = energyscape(signals, CONFIG, grid=grid, lowpass_hz=None, device=device)[0, 0]
    got_db = 20 * np.log10(got / got.max())
    looks = unit(np.rad2deg(grid.azimuth_rad))
    ref = array_factor(looks, unit(20.0), np.asarray(CONFIG.microphones_m), *call_band())
    ref_db = 20 * np.log10(ref / ref.max())
    loud = ref_db > -15
    assert np.abs(got_db[loud] - ref_db[loud]).max() < 1.0
    width = np.ptp(np.rad2deg(grid.azimuth_rad)[got_db > -3])
    assert 4.0 <= width <= 12.0


def test_elevation_beam_pattern_is_the_delay_and_sum_array_factor(device):
    """Far reflectors (3 m) at (azimuth, elevation) (0, 0), (0, -17) (a floor seen from 0.3 m at
    1 m) and (30, 20), scanned over elevations -60..60 deg in 2 deg steps at the source's azimuth:
    the energyscape at its range equals the analytic broadband array factor of the array (planar
    in y-z, 3.8 cm tall) within 1 dB wherever the pattern is above -15 dB; it peaks within one
    step of the source; its main lobe is 10-16 deg wide at -3 dB (~12 deg: lambda / 3.8 cm at 40 kHz)."""
    sources = np.array([(0.0, 0.0), (0.0, -17.0), (30.0, 20.0)])  # (azimuth, elevation) [deg]
    elevations = np.arange(-60.0, 61.0, 2.0)
    at_3m = dict(range_min_m=2.99, range_max_m=3.01, range_bin_m=0.02)
    grid = sim.PolarGrid(**at_3m, azimuth_min_deg=0.0, azimuth_max_deg=30.0, azimuth_step_deg=30.0)  # 2 azimuths
    signals = record(reflectors([3.0] * 3, sources[:, 0], sources[:, 1]), CONFIG, absorption=False, device=device)
    got = energyscape(signals, CONFIG, grid=grid, lowpass_hz=None, elevation_deg=tuple(elevations), device=device)
    assert got.shape == (3, len(elevations), 1, 2)
    mics = np.asarray(CONFIG.microphones_m)
    for image, (az, el) in zip(got, sources, strict=True):
        column = int(np.argmin(np.abs(np.rad2deg(grid.azimuth_rad) - az)))
        pattern = image[:, 0, column]
        got_db = 20 * np.log10(pattern / pattern.max())
        ref = array_factor(unit(az, elevations), unit(az, el), mics, *call_band())
        ref_db = 20 * np.log10(ref / ref.max())
        loud = ref_db > -15
        assert np.abs(got_db[loud] - ref_db[loud]).max() < 1.0, (az, el, np.round(got_db - ref_db, 1))
        assert abs(elevations[np.argmax(pattern)] - el) <= 2.0, (az, el, elevations[np.argmax(pattern)])
        assert 10.0 <= np.ptp(elevations[got_db > -3]) <= 16.0, (az, el, elevations[got_db > -3])


def reference_ping() -> np.ndarray:
    """One deterministic ping, float32 (32, 16384), made with numpy alone (no simulator code but the
    call): the call from three far-field directions at whole-sample delays (2 r - m . u) / c, one
    below and one above the horizon, plus noise from the legacy RandomState, whose stream never changes."""
    fs, call = CONFIG.chirp.sample_rate_hz, CONFIG.chirp.samples()
    mics = np.asarray(CONFIG.microphones_m)
    ping = 0.005 * np.random.RandomState(0).standard_normal((len(mics), CONFIG.record_samples))
    for r, az, el in [(1.2, 20.0, 0.0), (2.0, -35.0, -17.0), (3.1, 50.0, 15.0)]:
        starts = np.rint((2 * r - mics @ unit(az, el)) / C * fs).astype(int)
        for m, start in enumerate(starts):
            ping[m, start : start + len(call)] += call / (2 * r)
    return ping.astype(np.float32)


# The default energyscape (N, R, A) of reference_ping() made by main at 7ca5c6c, before issue 40 touched
# the beamformer: every 3rd range bin and azimuth, float32 (80, 61). Rewrite it (only on purpose) with
# `python -m tests.test_beamform`.
DEFAULT_REFERENCE = Path(__file__).parent / "reference" / "default_energyscape.npy"
REFERENCE_STRIDE = 3


def test_default_elevation_is_the_zero_slice_of_any_elevation_sequence(device):
    """The default scalar elevation 0 gives (N, R, A), equal bit for bit to the E = 1 image of
    elevation_deg=(0.0,) and to the 0 deg image of (-20, 0, 20): adding elevations changes no beam."""
    ping = reference_ping()
    scalar = energyscape(ping, CONFIG, device=device)
    one = energyscape(ping, CONFIG, elevation_deg=(0.0,), device=device)
    three = energyscape(ping, CONFIG, elevation_deg=(-20.0, 0.0, 20.0), device=device)
    assert scalar.shape == (1, *sim.PolarGrid().shape)
    assert one.shape == (1, 1, *scalar.shape[1:]) and three.shape == (1, 3, *scalar.shape[1:])
    assert np.array_equal(scalar, one[:, 0])
    assert np.array_equal(scalar, three[:, 1])
    assert not np.allclose(three[:, 0], three[:, 1], rtol=0.1)  # the other slices are other beams


def test_default_energyscape_matches_the_stored_reference(device):
    """The default processing of reference_ping() equals the energyscape main made before issue 40
    (tests/reference/default_energyscape.npy) within 1e-4 of its peak. Float32 rounding passes on any
    device (the same chain in float64 differs from the CPU's by 1.8e-5 of the peak); another envelope
    filter window (7e-3), a steering or range scale off by 1e-4 (3e-4, 2e-3) or a lost range
    interpolation do not."""
    got = energyscape(reference_ping(), CONFIG, device=device)[0, ::REFERENCE_STRIDE, ::REFERENCE_STRIDE]
    want = np.load(DEFAULT_REFERENCE)
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-4 * want.max())


def test_bad_signals():
    with pytest.raises(ValueError, match="shape"):
        energyscape(np.zeros((1, 5, 100)), CONFIG)
    with pytest.raises(ValueError, match="NaN"):
        energyscape(np.full((32, 2000), np.nan), CONFIG)
    with pytest.raises(ValueError, match="overflows"):
        energyscape(np.full((32, 2000), 1e39), CONFIG)  # float32 would turn it into inf, then NaN
    for dtype in (np.complex64, object, bool):
        with pytest.raises(ValueError, match="real numbers"):
            energyscape(np.zeros((32, 2000), dtype=dtype), CONFIG)
    with pytest.raises(ValueError, match="fewer than the call's 1126"):
        energyscape(np.zeros((32, 500)), CONFIG)


def test_baseband_processing_equals_a_full_rate_reference(device):
    """Three echoes and noise: the energyscape (no low-pass) equals a full-rate numpy matched filter,
    delay-and-sum and analytic envelope at every baseband sample, within 0.5 % of the peak."""
    from tests.reference.beamform import full_rate_envelope

    signals = record(reflectors([1.3, 2.1, 3.7], [-35.0, 10.0, 62.0]), CONFIG, noise="gaussian", seed=3, device=device)
    ping = signals.sum(axis=0)  # one ping with all three echoes
    step = 343.0 * 8 / 450e3 / 2  # range between baseband samples (decimation 8, c = 343 m/s in processing)
    # Bin centres on baseband samples: (i + 0.5) steps from range_min.
    grid = sim.PolarGrid(range_min_m=99.5 * step, range_max_m=1499.5 * step, range_bin_m=step, azimuth_step_deg=5.0)
    got = energyscape(ping, CONFIG, grid=grid, lowpass_hz=None, device=device)[0]
    ref = full_rate_envelope(ping, CONFIG.microphones_m, CONFIG.chirp.samples(), 450e3, grid.azimuth_rad, (20e3, 55e3))
    sample = np.rint(grid.range_m / step).astype(int) * 8
    want = ref[:, sample].T  # (R, A)
    assert got.shape == want.shape
    assert np.abs(got - want).max() < 0.005 * want.max()


if __name__ == "__main__":  # rewrite the stored default energyscape (see DEFAULT_REFERENCE)
    image = energyscape(reference_ping(), CONFIG, device="cpu")[0, ::REFERENCE_STRIDE, ::REFERENCE_STRIDE]
    np.save(DEFAULT_REFERENCE, np.ascontiguousarray(image, dtype=np.float32))
    print(f"wrote {DEFAULT_REFERENCE}: {image.shape}, peak {image.max():.4g}")


def test_call_spectrum_by_fft_equals_the_direct_sum():
    """The matched filter's spectrum of the call, taken from one FFT, against the sum that defines
    it at each band frequency (a wrong sign, offset or FFT length breaks it)."""
    from acoustic_sim.engine.beamform import call_spectrum

    rng = np.random.default_rng(7)
    call = rng.standard_normal(301)
    points, shift = 1024, 0.2137
    offsets = np.concatenate([np.arange(0, 40), np.arange(-40, 0), [511, -512]])
    n = np.arange(len(call))
    direct = np.exp(-2j * np.pi * (shift + offsets[:, None] / points) * n[None, :]) @ call
    np.testing.assert_allclose(call_spectrum(call, shift, offsets, points), direct, rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="cannot hold"):
        call_spectrum(call, shift, offsets, 256)
