"""Energyscapes: point reflectors image where they are; the beam pattern is the array factor."""

import numpy as np
import pytest

import acoustic_sim as sim
import scenes
from acoustic_sim.engine.beamform import energyscape
from acoustic_sim.engine.paths import KIND_SPECULAR, Arrivals
from acoustic_sim.engine.signals import record

CONFIG = sim.SonarConfig.ertis()
C = CONFIG.atmosphere.speed_of_sound


def reflectors(ranges_m, azimuths_deg):
    """One echo per ping from a point reflector at (range, azimuth), elevation 0: its image source
    lies at twice the range (path emitter -> reflector -> array, emitter taken at the array)."""
    r = np.asarray(ranges_m, dtype=np.float64)
    a = np.deg2rad(azimuths_deg)
    source = 2 * r[:, None] * np.c_[np.cos(a), np.sin(a), np.zeros_like(a)]
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
    images = energyscape(signals, CONFIG)
    grid = sim.PolarGrid()
    for image, r, az in zip(images, ranges, azimuths, strict=True):
        i, j = np.unravel_index(np.argmax(image), image.shape)
        assert abs(grid.range_m[i] - r) <= grid.range_bin_m, (r, az, grid.range_m[i])
        assert abs(np.rad2deg(grid.azimuth_rad[j]) - az) <= 2.0, (r, az, np.rad2deg(grid.azimuth_rad[j]))


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


def array_factor(azimuth_rad, source_azimuth_rad, mics, freqs, weights):
    """Broadband delay-and-sum response to a far-field source, written directly:
    |sum_f w(f) sum_m exp(2 pi i f (tau_m(theta) - tau_m(theta0)))| / (M sum_f w), tau_m = m . u / c."""
    u = np.c_[np.cos(azimuth_rad), np.sin(azimuth_rad), np.zeros_like(azimuth_rad)]
    u0 = np.array([np.cos(source_azimuth_rad), np.sin(source_azimuth_rad), 0.0])
    dtau = (u - u0) @ mics.T / 343.0  # (A, M)
    phase = np.exp(2j * np.pi * freqs[None, None, :] * dtau[:, :, None])
    return np.abs((phase.sum(axis=1) * weights).sum(axis=1)) / (len(mics) * weights.sum())


def test_beam_pattern_is_the_delay_and_sum_array_factor(device):
    """A far reflector at 20 deg (3 m): the energyscape across azimuth at its range equals the
    analytic broadband array factor of the 32 microphones weighted by the call's power spectrum,
    within 1 dB wherever the pattern is above -15 dB; main lobe ~5-11 deg wide at -3 dB."""
    grid = sim.PolarGrid(range_min_m=2.99, range_max_m=3.01, range_bin_m=0.02)
    signals = record(reflectors([3.0], [20.0]), CONFIG, absorption=False, device=device)
    got = energyscape(signals, CONFIG, grid=grid, lowpass_hz=None)[0, 0]
    got_db = 20 * np.log10(got / got.max())
    call = CONFIG.chirp.samples()
    freqs = np.fft.rfftfreq(8192, 1 / 450e3)
    weights = np.abs(np.fft.rfft(call, 8192)) ** 2
    keep = (freqs > 20e3) & (freqs < 55e3)
    ref = array_factor(grid.azimuth_rad, np.deg2rad(20.0), np.asarray(CONFIG.microphones_m), freqs[keep], weights[keep])
    ref_db = 20 * np.log10(ref / ref.max())
    loud = ref_db > -15
    assert np.abs(got_db[loud] - ref_db[loud]).max() < 1.0
    width = np.ptp(np.rad2deg(grid.azimuth_rad)[got_db > -3])
    assert 4.0 <= width <= 12.0


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
