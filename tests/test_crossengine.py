"""The crossengine test set (pyroomacoustics' image sources): its LiDAR truth against the floor
plan, its echoes at the nearest wall, and a dataset that scores models but never trains them; its
rough-wall variant (`crossengine_rough`): scatterer echoes against pyroomacoustics and Lambert's
law, occlusion in the floor plan, oblique walls that echo, and the specular set left as it was."""

import dataclasses
import json

import numpy as np
import pytest

from acoustic_sim.config import LidarConfig, ProcessingConfig, SonarConfig
from acoustic_sim.datasets.suites import SUITES
from acoustic_sim.engine.beamform import energyscape
from acoustic_sim.engine.lidar import Lidar
from acoustic_sim.formats.crossengine import (
    FLOOR_PLANS,
    Room,
    draw_room,
    generate_crossengine,
    plan_crossengine,
    planner_scene,
    record_ping,
    scan_floor_plan,
)
from acoustic_sim.formats.rough_walls import band_limited_echoes, draw_rough_walls, in_sight, scatterer_paths
from scenes import pose, trajectory

from .crafted import damage_energyscape_chunk

L_ROOM = ((0.0, 0.0), (6.0, 0.0), (6.0, 3.0), (3.0, 3.0), (3.0, 5.0), (0.0, 5.0))


def _room(**changes) -> Room:
    values = dict(plan="l_room", corners=L_ROOM, height_m=3.0, wall_reflection=0.9, floor_reflection=0.0)
    values |= dict(ceiling_reflection=0.0, sensor_height_m=0.3, snr_db=60.0)
    return Room(**(values | changes))


def test_lidar_truth_is_the_floor_plan():
    """Hand-worked beams in an L-shaped room, through the notch and after a turn of the robot."""
    lidar = LidarConfig.hokuyo_ust20lx()
    az = np.rad2deg(lidar.azimuth_rad)
    beam = {a: int(np.argmin(np.abs(az - a))) for a in (-90, 0, 30, 90)}
    ranges = scan_floor_plan(np.array(L_ROOM), np.stack([pose(1, 1, 0), pose(1, 4, 0), pose(1, 1, np.pi / 2)]), lidar)
    assert ranges[0, beam[0]] == pytest.approx(5.0) and ranges[0, beam[90]] == pytest.approx(4.0)
    assert ranges[0, beam[-90]] == pytest.approx(1.0) and ranges[0, beam[30]] == pytest.approx(4.0)
    assert ranges[1, beam[0]] == pytest.approx(2.0)  # the notch's wall at x = 3
    assert ranges[2, beam[0]] == pytest.approx(4.0) and ranges[2, beam[-90]] == pytest.approx(5.0)


@pytest.mark.parametrize("plan", FLOOR_PLANS)
def test_every_floor_plan_gives_a_drive_inside_its_room(plan, device):
    """Inside a closed room every beam returns; the drive keeps its clearance from the walls; our
    LiDAR on the extruded room (Warp, its BVH) sees the walls where the plan puts them."""
    room = draw_room(plan, np.random.default_rng(3))
    scene = planner_scene(room)
    poses = trajectory(scene, frames=30, sensor_height=room.sensor_height_m, seed=3)
    lidar = LidarConfig.hokuyo_ust20lx()
    ranges = scan_floor_plan(np.array(room.corners), poses, lidar)
    assert np.isfinite(ranges).all() and ranges.min() > 0.3
    assert np.allclose(poses[:, 2, 3], room.sensor_height_m)
    np.testing.assert_allclose(Lidar(lidar, device=device).scan(scene, poses), ranges, atol=2e-4)


def test_strongest_echo_comes_from_the_nearest_wall(device):
    """Facing the wall x = 6 at 1.19 m (a range bin's centre; the others 1.4 m and more away,
    floor and ceiling absorbing): the energyscape's strongest cell is that wall's, in its range
    bin (2 cm: a timing error of half a bin fails) and straight ahead."""
    sonar, grid = SonarConfig.ertis(), ProcessingConfig().grid
    signals = record_ping(_room(), pose(4.81, 1.4, 0.0, 0.3), sonar, np.random.default_rng(0))
    image = energyscape(signals[None], sonar, ProcessingConfig(), device=device)[0]
    r, a = np.unravel_index(np.argmax(image), image.shape)
    assert grid.range_m[r] == pytest.approx(1.19, abs=0.005)
    assert np.rad2deg(grid.azimuth_rad[a]) == pytest.approx(0.0, abs=3.0)


def test_the_test_set_scores_models_but_never_trains_them(tmp_path, device, capsys):
    from acoustic_sim.cli import main
    from learn.cli import main as learn_main
    from learn.data import load_frames

    out = tmp_path / "ce"
    summary = generate_crossengine(out, frames=6, seed=0, device=device, progress=False)
    frames = load_frames(out)
    assert frames.energyscape.shape == (6, 1, *ProcessingConfig().grid.shape) and frames.label.sum() > 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["suite"] == "crossengine" and "never train" in manifest["use"]
    assert summary["shards_written"] == 1
    assert generate_crossengine(out, frames=6, seed=0, device=device, progress=False)["shards_skipped"] == 1
    assert learn_main(["train", "--data", str(out), "--out", str(tmp_path / "run")]) == 2
    assert "never train on it" in capsys.readouterr().err
    assert main(["generate", "--suite", "crossengine", "--out", str(out), "--set", "tracer.max_bounces=1"]) == 2
    assert "only processing.elevation_deg applies" in capsys.readouterr().err
    names = {s.name for suite in SUITES.values() for s in suite.scenarios}
    assert not names & set(FLOOR_PLANS)


def test_the_test_set_is_made_resumed_and_repaired_as_generate_does(tmp_path, device, monkeypatch):
    """Two 3-frame drives, one shard each, by generate's machinery: plan.json (its plan id in every
    shard) and the card; a run killed while writing the second shard keeps the first, and the
    rerun writes only the second; a shard with flipped bytes is moved aside and written again,
    equal to the first; a rerun with other settings is refused."""

    import acoustic_sim.datasets.runner as runner
    from acoustic_sim.datasets.shards import DatasetError, read_attrs
    from learn.data import load_frames

    out, real_write = tmp_path / "ce", runner.write_shard

    def dying_write(path, frames, **kwargs):
        if path.name == "shard-00001.h5":
            raise KeyboardInterrupt
        real_write(path, frames, **kwargs)

    def make():
        return generate_crossengine(out, frames=6, seed=1, device=device, progress=False, episode_frames=3)

    monkeypatch.setattr(runner, "write_shard", dying_write)
    with pytest.raises(KeyboardInterrupt):
        make()
    assert sorted(p.name for p in out.glob("shard-*")) == ["shard-00000.h5"]
    first = (out / "shard-00000.h5").stat().st_mtime_ns
    monkeypatch.setattr(runner, "write_shard", real_write)
    summary = make()
    assert (summary["shards_written"], summary["shards_skipped"]) == (1, 1)
    assert (out / "shard-00000.h5").stat().st_mtime_ns == first
    plan = json.loads((out / "plan.json").read_text())
    assert plan["suite"] == "crossengine" and (plan["frames"], plan["shards"], plan["seed"]) == (6, 2, 1)
    assert {read_attrs(p)["plan_id"] for p in out.glob("shard-*.h5")} == {plan["plan_id"]}
    assert "never train" in (out / "README.md").read_text() and (out / "card.png").stat().st_size > 10_000
    original = load_frames(out)
    assert list(original.episode) == [0, 0, 0, 1, 1, 1]
    assert [original.scenarios[k] for k in original.scenario] == ["l_room"] * 3 + ["t_room"] * 3

    shard = out / "shard-00001.h5"
    damage_energyscape_chunk(shard)
    with pytest.warns(UserWarning, match="writing the shard again"):
        summary = make()
    assert summary["shards_written"] == 1 and (out / "shard-00001.h5.damaged").exists()
    repaired = load_frames(out)
    np.testing.assert_array_equal(repaired.energyscape, original.energyscape)
    np.testing.assert_array_equal(repaired.label, original.label)
    with pytest.raises(DatasetError, match="other settings"):
        generate_crossengine(out, frames=6, seed=2, device=device, progress=False, episode_frames=3)


def test_the_specular_recording_is_what_it_was():
    """The specular variant did not change with the rough one: two pings in a fixed room from a
    fixed generator give the checksums measured on the specular code before the rough variant
    was added (sha256 of both pings' float32 bytes then: d0607dda53d6...bcdb1effe4db91e29). A change
    of the generator's draws (the noise) or of the walls' reflection moves them by far more than
    the tolerance."""
    room = _room(floor_reflection=0.7, ceiling_reflection=0.6, snr_db=25.0)
    sonar, rng = SonarConfig.ertis(), np.random.default_rng(11)
    first = record_ping(room, pose(2.0, 1.5, 0.4, 0.3), sonar, rng).astype(np.float64)
    second = record_ping(room, pose(2.5, 1.0, -0.2, 0.3), sonar, rng).astype(np.float64)
    weights = np.random.default_rng(0).standard_normal(first.shape)
    assert np.sum(first**2) == pytest.approx(6404103.60487108, rel=1e-6)
    assert np.sum(first * weights) == pytest.approx(-3799.3043049748, rel=1e-6)
    assert np.sum(second * weights) == pytest.approx(-3740.8963908838846, rel=1e-6)


def test_scatterer_echoes_are_pyroomacoustics_direct_paths():
    """`band_limited_echoes` of one path (delay r / c, gain 1 / r) is what pyroomacoustics records
    for the direct path of a source r away (anechoic: image order 0), at 5 cm, 2.4 m and 5.7 m:
    same units, same time origin, within 1 % of the peak."""
    pra = pytest.importorskip("pyroomacoustics")
    from acoustic_sim.formats.crossengine import SAMPLE_RATE_HZ

    sonar = SonarConfig.ertis()
    call, samples = sonar.chirp.samples(), sonar.record_samples
    shell = pra.Room.from_corners(np.array([[0, 0], [10, 0], [10, 10], [0, 10]]).T, fs=SAMPLE_RATE_HZ, max_order=0)
    shell.extrude(4.0)
    source, mics = np.array([1.0, 1.0, 1.0]), np.array([[1.05, 1.0, 1.0], [3.0, 2.3, 1.4], [4.1234, 5.77, 1.1]])
    shell.add_source(source, signal=call)
    shell.add_microphone_array(mics.T)
    shell.simulate()
    start = pra.constants.get("frac_delay_length") // 2
    reference = shell.mic_array.signals[:, start : start + samples]
    distance = np.linalg.norm(mics - source, axis=1)
    ours = band_limited_echoes(
        (distance / shell.c)[None], 1.0 / distance[None], call, sample_rate_hz=SAMPLE_RATE_HZ, samples=samples
    )
    for mic in range(len(mics)):
        peak = np.abs(reference[mic]).max()
        assert np.abs(ours[mic, : reference.shape[1]] - reference[mic]).max() < 0.01 * peak


def test_scattered_energy_is_lamberts():
    """Emitter and microphone together 0.5 m from the middle of a 5 m x 5 m wall: the echo energy
    of its scatterers, sum of gain^2, is Lambert's backscatter from a plane,
    s R^2 / (2 D^2) = 0.3 * 0.81 / 0.5 = 0.486 (the wall beyond 2.5 m would add 0.2 %); 10,000
    scatterers per m^2 so that the speckle's spread is under 2 %."""
    corners = np.array([(0.0, 0.0), (5.0, 0.0), (5.0, 5.0), (0.0, 5.0)])
    walls = draw_rough_walls(
        corners, 5.0, 0.9, np.random.default_rng(4), density_per_m2=1e4, scattering_range=(0.3, 0.3)
    )
    sensor = np.array([0.5, 2.5, 2.5])
    index, delay, gain = scatterer_paths(walls, sensor, sensor[None], speed_of_sound=343.0, reach_m=100.0)
    on_wall = walls.wall[index] == 3  # x = 0
    assert np.sum(gain[on_wall] ** 2) == pytest.approx(0.3 * 0.81 / (2 * 0.5**2), rel=0.06)
    np.testing.assert_allclose(delay[:, 0], 2 * np.linalg.norm(walls.position_m[index] - sensor, axis=1) / 343.0)


def test_walls_hidden_in_the_floor_plan_are_silent():
    """In the L room: from (5, 1) the far wall x = 0 and the notch's underside y = 3 are seen;
    the upper arm's wall y = 5 lies behind the notch, and the notch's wall x = 3 turns its back.
    From (1, 4) in the upper arm the floor-plan's wall x = 6 at y = 2 hides behind the notch,
    the wall y = 0 at x = 5 does not."""
    corners = np.array(L_ROOM)
    points = np.array([(0.0, 4.0), (4.0, 3.0), (2.0, 5.0), (3.0, 4.0), (6.0, 2.0), (5.0, 0.0)])
    wall = np.array([5, 2, 4, 3, 1, 0])
    seen_from_arm = in_sight(corners, wall[:4], points[:4], np.array([5.0, 1.0]))
    seen_from_upper_arm = in_sight(corners, wall[4:], points[4:], np.array([1.0, 4.0]))
    assert seen_from_arm.tolist() == [True, True, False, False]
    assert seen_from_upper_arm.tolist() == [False, True]


def test_rough_walls_keep_1_minus_s_of_the_energy_specular():
    """With rough walls of s = 0.36 (and no scatterers) the walls' image sources are those of a
    wall with 0.8 of the reflection coefficient; the noise draws are the specular set's."""
    room = _room(floor_reflection=0.5, snr_db=30.0)
    sonar, at = SonarConfig.ertis(), pose(2.0, 1.5, 0.4, 0.3)
    walls = draw_rough_walls(np.array(L_ROOM), 3.0, 0.9, np.random.default_rng(0), scattering_range=(0.36, 0.36))
    walls = dataclasses.replace(
        walls, position_m=walls.position_m[:0], wall=walls.wall[:0], amplitude=walls.amplitude[:0]
    )
    rough = record_ping(room, at, sonar, np.random.default_rng(0), walls)
    plain = record_ping(dataclasses.replace(room, wall_reflection=0.9 * 0.8), at, sonar, np.random.default_rng(0))
    np.testing.assert_allclose(rough, plain, rtol=1e-5, atol=1e-5 * np.abs(plain).max())


def _wedge_room() -> tuple:
    """A 24 m x 22 m hall around the origin with a wedge from its south wall, whose face lies 1.5 m
    from the origin with its normal towards azimuth -100 degrees, cut to the azimuths -70 to -50
    (incidence 30 to 50 degrees seen from the origin); the wedge's sides turn their backs on the
    origin (reflex corners), the hall's walls are beyond the recording's reach."""

    def at(azimuth_deg):
        return np.array([np.cos(np.deg2rad(azimuth_deg)), np.sin(np.deg2rad(azimuth_deg))])

    near, far = 1.5 / np.cos(np.deg2rad(30)) * at(-70), 1.5 / np.cos(np.deg2rad(50)) * at(-50)
    down_near = near + (12 + near[1]) / np.sin(np.deg2rad(65)) * at(-65)  # to the south wall y = -12
    down_far = far + (12 + far[1]) / np.sin(np.deg2rad(55)) * at(-55)
    corners = [(-10, -12), down_near, near, far, down_far, (14, -12), (14, 10), (-10, 10)]
    return tuple((round(float(x), 4), round(float(y), 4)) for x, y in corners)


def _echo_peaks(image: np.ndarray, range_m: np.ndarray, near_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The classic readout: each beam's strongest cell beyond `near_m` (the emitter's direct sound
    fills the first 0.4 m of every beam in every variant), a return where it reaches 4x the
    image's median there (its noise floor). Returns the range [m] and whether it is a return, (A,)."""
    beyond = image[range_m > near_m]
    strongest = beyond.argmax(axis=0)
    return range_m[range_m > near_m][strongest], beyond.max(axis=0) >= 4.0 * np.median(beyond)


def test_rough_walls_echo_at_oblique_incidence(device):
    """A wall face 1.5 m from the sensor seen at 30-50 degrees incidence (azimuth -70 to -50, its
    foot at -100 off the face; floor and ceiling absorbing, every other wall out of reach): the
    echo peak finds nothing there in the specular variant (a mirror sends an oblique ping away)
    and a return in every beam in the rough one (s = 0.25), each on the face's span of ranges,
    over 40 % (12 of 21 here) within the scoring's 0.1 m of the face in their own beam (the
    array's ~12 degree beam also hears the brighter, less oblique part of the face), and the
    strongest within 3 range bins of the face at its azimuth."""
    corners = _wedge_room()
    room = _room(plan="hall", corners=corners, floor_reflection=0.0, snr_db=40.0)
    walls = draw_rough_walls(np.array(corners), 3.0, 0.9, np.random.default_rng(1), scattering_range=(0.25, 0.25))
    sonar, grid, at = SonarConfig.ertis(), ProcessingConfig().grid, pose(0.0, 0.0, 0.0, 0.3)
    signals = [record_ping(room, at, sonar, np.random.default_rng(0), rough) for rough in (None, walls)]
    mirror, rough = energyscape(np.stack(signals), sonar, ProcessingConfig(), device=device)
    azimuth = np.rad2deg(grid.azimuth_rad)
    band = (azimuth >= -70.5) & (azimuth <= -49.5)
    face = 1.5 / np.cos(np.deg2rad(azimuth[band] + 100.0))  # the face's range in each beam of the band

    _, found = _echo_peaks(mirror, grid.range_m)
    assert not found[band].any()
    ranges, found = _echo_peaks(rough, grid.range_m)
    assert found[band].all()
    assert np.all((ranges[band] > face.min() - 0.1) & (ranges[band] < face.max() + 0.1))
    assert np.mean(np.abs(ranges[band] - face) <= 0.1) > 0.4
    beyond = grid.range_m > 0.5  # the direct sound's
    r, a = np.unravel_index(np.argmax(rough[beyond][:, band]), (beyond.sum(), band.sum()))
    assert abs(grid.range_m[beyond][r] - face[a]) <= 3 * grid.range_bin_m


def test_the_rough_set_is_its_own_suite_on_the_same_drives(tmp_path, device, capsys):
    """`generate --suite crossengine_rough`: its manifest and card name it and its walls (density,
    range of s); each episode record holds the drawn s; the rooms, poses and LiDAR truth are
    those of `crossengine` with the same seed, the echoes are not; `learn train` refuses it."""
    import h5py

    from acoustic_sim.cli import main
    from learn.cli import main as learn_main

    rough_out, mirror_out = tmp_path / "rough", tmp_path / "mirror"
    argv = ["generate", "--suite", "crossengine_rough", "--frames", "2", "--device", device, "--quiet"]
    assert main([*argv, "--out", str(rough_out)]) == 0
    generate_crossengine(mirror_out, frames=2, seed=0, device=device, progress=False)
    manifest = json.loads((rough_out / "manifest.json").read_text())
    assert manifest["suite"] == "crossengine_rough" and "never train" in manifest["use"]
    card = (rough_out / "README.md").read_text()
    assert "rough walls" in card and "500 per m^2" in card and "[0.1, 0.4]" in card
    with h5py.File(rough_out / "shard-00000.h5") as rough, h5py.File(mirror_out / "shard-00000.h5") as mirror:
        (record,), (plain,) = json.loads(rough.attrs["episodes"]), json.loads(mirror.attrs["episodes"])
        assert 0.1 <= record.pop("wall_scattering") <= 0.4 and record.pop("scatterer_density_per_m2") == 500.0
        assert record.pop("scatterer_count") > 1000 and record == plain
        np.testing.assert_array_equal(rough["pose"][()], mirror["pose"][()])
        np.testing.assert_array_equal(rough["lidar/ranges"][()], mirror["lidar/ranges"][()])
        assert not np.array_equal(rough["energyscape"][()], mirror["energyscape"][()])
    assert learn_main(["train", "--data", str(rough_out), "--out", str(tmp_path / "run")]) == 2
    assert "crossengine_rough test set" in capsys.readouterr().err
    assert main([*argv, "--out", str(rough_out), "--set", "tracer.max_bounces=1"]) == 2
    assert "only processing.elevation_deg applies" in capsys.readouterr().err


def test_the_set_beamforms_at_the_elevations_asked_and_nothing_else_changes(tmp_path, device):
    """`--set processing.elevation_deg=[...]` gives shards of those elevations whose level slice is
    the default set's, bit for bit (same rooms, drives and noise); any other --set is refused."""
    import h5py

    from acoustic_sim.cli import main

    base = ["generate", "--suite", "crossengine", "--frames", "2", "--device", device, "--quiet"]
    assert main([*base, "--out", str(tmp_path / "one")]) == 0
    assert main([*base, "--out", str(tmp_path / "three"), "--set", "processing.elevation_deg=[-20,0,20]"]) == 0
    with h5py.File(tmp_path / "one" / "shard-00000.h5") as one, h5py.File(tmp_path / "three" / "shard-00000.h5") as f:
        assert f["energyscape"].shape[1] == 3 and f["elevation_deg"][:].tolist() == [-20.0, 0.0, 20.0]
        np.testing.assert_array_equal(f["energyscape"][:, 1], one["energyscape"][:, 0])
        assert not np.array_equal(f["energyscape"][:, 0], f["energyscape"][:, 1])
    assert main([*base, "--out", str(tmp_path / "x"), "--set", "tracer.max_bounces=2"]) == 2


def test_the_set_keeps_its_recordings_for_calibrate(tmp_path, device):
    """`--signals` stores each ping's microphone signals (float16, as generate's), whose energyscapes
    are the set's, and `calibrate` reads them as one drive's recordings, in the room the episode's
    record describes (`--scene-from-data`: our LiDAR in it reads the set's floor-plan ranges); the
    set's plan without them is the one it always was."""
    import h5py

    from acoustic_sim.calibrate import load_recordings, recorded_scene
    from acoustic_sim.cli import main

    base = ["generate", "--suite", "crossengine", "--frames", "2", "--device", device, "--quiet"]
    assert main([*base, "--out", str(tmp_path / "kept"), "--signals"]) == 0
    assert main([*base, "--out", str(tmp_path / "plain")]) == 0
    shard = "shard-00000.h5"
    with h5py.File(tmp_path / "kept" / shard) as kept, h5py.File(tmp_path / "plain" / shard) as plain:
        signals = kept["signals"][:]
        assert signals.shape == (2, 32, SonarConfig.ertis().record_samples) and "signals" not in plain
        np.testing.assert_array_equal(kept["energyscape"][:], plain["energyscape"][:])
        again = energyscape(signals.astype(np.float32), SonarConfig.ertis(), ProcessingConfig(), device=device)
        peak = np.abs(plain["energyscape"][:]).max()
        assert np.abs(again[:, None] - plain["energyscape"][:]).max() < 0.01 * peak  # float16 signals
    poses, recorded = load_recordings(tmp_path / "kept", episode=0)
    assert poses.shape == (2, 4, 4) and np.array_equal(recorded, signals.astype(np.float32))
    # the room its record describes is the one recorded: our LiDAR in it reads the set's floor-plan truth
    room = recorded_scene(tmp_path / "kept", episode=0)
    with h5py.File(tmp_path / "kept" / shard) as kept:
        truth, record = kept["lidar/ranges"][:], json.loads(kept.attrs["episodes"])[0]
    ranges = Lidar(LidarConfig.hokuyo_ust20lx(), device=device).scan(room, poses)
    assert np.isfinite(truth).mean() > 0.5 and np.array_equal(np.isfinite(ranges), np.isfinite(truth))
    np.testing.assert_allclose(ranges[np.isfinite(truth)], truth[np.isfinite(truth)], atol=2e-3)
    assert room.mesh.bounds[1, 2] == pytest.approx(record["height_m"])  # floor to ceiling
    out = tmp_path / "fit" / "fit.json"
    argv = ["calibrate", str(tmp_path / "kept"), "--scene-from-data", "--rays", "3000", "--max-bounces", "1"]
    assert main([*argv, "--no-delays", "--device", device, "--out", str(out)]) == 0
    fit = json.loads(out.read_text())
    assert {"walls", "floor"} <= set(fit["classes"]) and fit["pings"] == 2
    assert main([*argv, "--scene", "office", "--device", device, "--out", str(tmp_path / "no.json")]) == 2
    plans = [json.loads((tmp_path / name / "plan.json").read_text())["plan_id"] for name in ("kept", "plain")]
    assert plans[0] != plans[1] and plans[1] == plan_crossengine(tmp_path / "x", frames=2)[0].plan_id
