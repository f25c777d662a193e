"""The configuration tree: `section.field=value` settings, their refusals, and that the configs a
run used are the ones its shards and manifest record (one pipeline, no hand-written copies)."""

import dataclasses
import json

import h5py
import numpy as np
import pytest

from acoustic_sim.config import (
    MAX_BOUNCES,
    NOISE_CODES,
    NOISE_KINDS,
    ConfigError,
    LidarConfig,
    PolarGrid,
    ProcessingConfig,
    SimConfig,
    SonarConfig,
    TracerConfig,
)
from acoustic_sim.datasets.suites import SUITES, Physics, rig
from acoustic_sim.engine.beamform import energyscape
from acoustic_sim.engine.kernels import common as common_kernels
from acoustic_sim.engine.kernels import paths as path_kernels
from acoustic_sim.settings import apply_settings


def test_settings_reach_every_level_of_the_tree():
    """Each level is reached (`none` and `None` clear fields that were set); a preset by name gives
    its beam pattern (64 x 1024 beams over 360 x 45 deg, 0.3-100 m) in place of the Hokuyo's."""
    got = apply_settings(
        SimConfig(tracer=TracerConfig(edge_width_m=0.004)),  # none must clear it (None is the default)
        [
            "tracer.max_bounces=1",
            "tracer.scattering=false",
            "tracer.edge_width_m=none",
            "processing.grid.range_max_m=4",
            "processing.lowpass_hz=None",
            "processing.normalise=db",
            "processing.elevation_deg=[0, 10]",
            "sonar.atmosphere.temperature_c=30",
            "lidar.noise=gaussian",
            "lidar.noise_m=0.02",
        ],
    )
    assert got.tracer == TracerConfig(max_bounces=1, scattering=False)
    assert got.processing.grid.range_max_m == 4.0 and got.processing.grid.range_count == 190
    assert got.processing.lowpass_hz is None and got.processing.normalise == "db"
    assert got.processing.elevation_deg == (0.0, 10.0)
    assert got.sonar.atmosphere.temperature_c == 30.0 and got.sonar.microphones_m == SonarConfig.ertis().microphones_m
    assert (got.lidar.noise, got.lidar.noise_m) == ("gaussian", 0.02)
    multibeam = apply_settings(SimConfig(), ["lidar=multibeam_64x1024"]).lidar
    assert (multibeam.azimuth_count, multibeam.elevation_count, multibeam.beam_count) == (1024, 64, 65536)
    assert (multibeam.azimuth_min_deg, multibeam.azimuth_max_deg) == (-180.0, 180.0 - 360.0 / 1024)
    assert (multibeam.elevation_min_deg, multibeam.elevation_max_deg) == (-22.5, 22.5)
    assert (multibeam.range_min_m, multibeam.range_max_m) == (0.3, 100.0)
    assert SimConfig().lidar == LidarConfig.hokuyo_ust20lx() and SimConfig().lidar.beam_count == 1081  # replaced
    assert apply_settings(SimConfig(), []) == SimConfig()


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("tracer.max_bounces=11", "0..10"),
        ("tracer.max_bounces=1.5", "not a valid"),
        ("tracer.table_size=1000", "power of two"),
        ("tracer.ray_count=0", "ray_count"),
        ("tracer.rays=5", "has no field 'rays'"),
        ("processing.normalise=log", "not a valid"),
        ("processing.speed_of_sound=nan", "finite"),
        ("processing.grid.range_max_m=0.1", "range_min_m < range_max_m"),
        ("processing.grid=1", "preset"),
        ("lidar=velodyne", "hokuyo_ust20lx, multibeam_64x1024"),
        ("lidar.noise=pink", "not a valid"),
        ("tracer.max_bounces.x=1", "a value, not a section"),
        ("tracer.max_bounces", "section.field=value"),
        ("=3", "section.field=value"),
    ],
)
def test_bad_settings_are_refused_by_name(setting, message):
    with pytest.raises(ConfigError, match="--set") as err:
        apply_settings(SimConfig(), [setting])
    assert message in str(err.value)


def test_limits_come_from_one_place():
    """The tracer's kernels store MAX_BOUNCES + 1 planes per path, and the suite's physics takes
    its limits from TracerConfig (a Sonar built by hand and a suite agree)."""
    assert path_kernels.MAX_ORDER == MAX_BOUNCES + 1
    Physics(max_bounces=MAX_BOUNCES)
    for bad in ({"max_bounces": MAX_BOUNCES + 1}, {"ray_count": 0}, {"edge_width_m": -0.1}, {"sonar_noise": "pink"}):
        with pytest.raises(ValueError):
            Physics(**bad)
    assert Physics(max_bounces=2, ray_count=500).tracer() == TracerConfig(max_bounces=2, ray_count=500)


def test_noise_kinds_have_the_kernels_codes():
    """Every noise kind the configs accept maps to the code the kernels compare with."""
    assert set(NOISE_CODES) == set(NOISE_KINDS)
    for kind, code in NOISE_CODES.items():
        assert getattr(common_kernels, f"NOISE_{kind.upper()}") == code


def test_edge_band_defaults_to_half_a_wavelength():
    """Half a wavelength at the call's centre (37.5 kHz) in dry air at 20 C: c = sqrt(gamma R T / M)
    = 343.2 m/s, 4.58 mm."""
    sonar = SonarConfig.ertis()
    c = np.sqrt(1.4 * 8.314462 * 293.15 / 0.0289647)
    assert TracerConfig().edge_width_for(sonar) == pytest.approx(0.5 * c / 37.5e3, rel=2e-4)
    assert TracerConfig(edge_width_m=0.0).edge_width_for(sonar) == 0.0


def test_processing_config_and_keywords_give_the_same_energyscape(device):
    """The grid and low-pass given as a ProcessingConfig or as keywords reach the beamformer alike:
    both equal a full-rate numpy matched filter, delay-and-sum and envelope (tests/reference) on a
    grid of baseband samples (5 deg, 0.06-0.48 m), within 0.5 % of the peak; the default low-pass
    differs from it (so the setting is not ignored)."""
    from tests.reference.beamform import full_rate_envelope

    rng = np.random.default_rng(0)
    config = SonarConfig.ertis()
    signals = rng.normal(0.0, 1.0, (1, config.microphone_count, 2048))
    step = 343.0 * 8 / 450e3 / 2  # range between baseband samples (decimation 8, 343 m/s in processing)
    grid = PolarGrid(range_min_m=30.5 * step, range_max_m=250.5 * step, range_bin_m=step, azimuth_step_deg=5.0)
    by_config = energyscape(signals, config, ProcessingConfig(grid=grid, lowpass_hz=None), device=device)
    by_keywords = energyscape(signals, config, grid=grid, lowpass_hz=None, device=device)
    assert by_config.shape == by_keywords.shape == (1, *grid.shape) == (1, 220, 37)
    ref = full_rate_envelope(
        signals[0], config.microphones_m, config.chirp.samples(), 450e3, grid.azimuth_rad, (20e3, 55e3)
    )
    want = ref[:, np.rint(grid.range_m / step).astype(int) * 8].T  # (R, A)
    for got in (by_config[0], by_keywords[0]):
        assert np.abs(got - want).max() < 0.005 * want.max()
    lowpassed = energyscape(signals, config, ProcessingConfig(grid=grid), device=device)[0]
    assert np.abs(lowpassed - want).max() > 0.05 * want.max()


def test_suite_settings_are_simulated_and_recorded(tmp_path, device):
    """A suite's settings change what is simulated (here the grid), enter the plan (another folder
    is another run), and the shard and manifest record the rig as it was simulated."""
    from acoustic_sim.datasets.generate import generate

    base = dataclasses.replace(SUITES["tiny"], episode_frames=2, variants={"": Physics(ray_count=500)})
    suite = dataclasses.replace(base, settings=("processing.grid.range_max_m=3", "processing.grid.azimuth_step_deg=2"))
    generate(suite, tmp_path / "d", frames=2, seed=1, device=device, progress=False)
    shard = next((tmp_path / "d").glob("shard-*.h5"))
    want = rig(suite.variants[""], suite.settings)
    with h5py.File(shard) as f:
        assert f["energyscape"].shape == (2, 1, *want.processing.grid.shape) == (2, 1, 140, 91)
        np.testing.assert_allclose(f["range_m"][:], 0.21 + 0.02 * np.arange(140))  # 2 cm bins, 0.2-3 m
        np.testing.assert_allclose(f["azimuth_rad"][:], np.deg2rad(np.arange(-90.0, 91.0, 2.0)))
        recorded = json.loads(f.attrs["config"])["sim"]
    manifest = json.loads((tmp_path / "d" / "manifest.json").read_text())
    assert recorded == manifest["sim"] == json.loads(json.dumps(want.to_dict()))
    assert recorded["processing"]["grid"] == {
        "range_min_m": 0.2,
        "range_max_m": 3.0,
        "range_bin_m": 0.02,
        "azimuth_min_deg": -90.0,
        "azimuth_max_deg": 90.0,
        "azimuth_step_deg": 2.0,
    }
    assert recorded["tracer"]["ray_count"] == 500 and recorded["tracer"]["max_bounces"] == Physics().max_bounces
    with pytest.raises(ConfigError, match="no field"):
        dataclasses.replace(base, settings=("tracer.rayz=1",))
    assert "settings" not in base.to_json() and suite.to_json()["settings"] == suite.settings


def test_physics_vary_draws_rig_fields_per_episode_and_records_them(tmp_path, device):
    """`Physics.vary` draws sonar and tracer fields per episode from its own stream (reproducible,
    within range), the episode is simulated with them (a drawn max_bounces of 0 gives the arrays
    of a variant with max_bounces 0) and its record holds them; variants without draws keep
    their plan ids."""
    from acoustic_sim.datasets.generate import generate

    vary = {"tracer.max_bounces": [0, 2], "sonar.emitter_radius_m": [0.001, 0.02]}
    physics = Physics(ray_count=500, vary=vary)
    draws = [physics.draw(rig(physics), np.random.default_rng([s, 3])) for s in range(20)]
    assert {d["tracer.max_bounces"] for _, d in draws} == {0, 1, 2}
    assert all(0.001 <= d["sonar.emitter_radius_m"] <= 0.02 for _, d in draws)
    drawn, again = physics.draw(rig(physics), np.random.default_rng([7, 3]))
    assert again == draws[7][1] and drawn.tracer.max_bounces == again["tracer.max_bounces"]
    assert drawn.sonar.emitter_radius_m == again["sonar.emitter_radius_m"]
    assert "vary" not in Physics().to_json() and physics.to_json()["vary"] == vary

    def shard(physics, name):
        suite = dataclasses.replace(SUITES["tiny"], episode_frames=2, variants={"": physics})
        generate(suite, tmp_path / name, frames=2, seed=1, device=device, progress=False)
        with h5py.File(next((tmp_path / name).glob("shard-*.h5"))) as f:
            return f["energyscape"][()], json.loads(f.attrs["episodes"])[0]

    flat, _ = shard(Physics(ray_count=500, max_bounces=0), "flat")
    deep, _ = shard(Physics(ray_count=500, max_bounces=3), "deep")
    drawn_flat, record = shard(Physics(ray_count=500, max_bounces=3, vary={"tracer.max_bounces": {"choice": [0]}}), "v")
    np.testing.assert_array_equal(drawn_flat, flat)
    assert not np.array_equal(deep, flat)  # so the comparison above can fail
    assert record["draws"] == {"tracer.max_bounces": 0} and record["tracer_config"]["max_bounces"] == 0


@pytest.mark.parametrize(
    "vary, message",
    [
        ({"tracer.max_bounces": [1, 99]}, "Physics.vary: --set 'tracer.max_bounces=99'"),
        ({"sonar.emitter_radius_m": {"choice": [0.01, 0.0]}}, "emitter_radius_m must be positive"),
        ({"processing.lowpass_hz": [500.0, 2000.0]}, "only fields under sonar or tracer vary"),
        ({"sonar.atmosphere.temperature_c": [0.0, 30.0]}, "Physics.temperature_c draws it"),
        ({"sonar.emitter_radius": [0.001, 0.01]}, "has no field 'emitter_radius'"),
        ({"tracer.ray_count": [100, 50]}, r"expected \[low, high\]"),
    ],
)
def test_bad_physics_ranges_are_refused_when_the_variant_is_made(vary, message):
    with pytest.raises(ValueError, match=message):
        Physics(vary=vary)
