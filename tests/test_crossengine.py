"""The crossengine test set (pyroomacoustics' image sources): its LiDAR truth against the floor
plan, its echoes at the nearest wall, and a dataset that scores models but never trains them."""

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
    planner_scene,
    record_ping,
    scan_floor_plan,
)
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
    assert frames.energyscape.shape == (6, *ProcessingConfig().grid.shape) and frames.label.sum() > 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["suite"] == "crossengine" and "never train" in manifest["use"]
    assert summary["shards_written"] == 1
    assert generate_crossengine(out, frames=6, seed=0, device=device, progress=False)["shards_skipped"] == 1
    assert learn_main(["train", "--data", str(out), "--out", str(tmp_path / "run")]) == 2
    assert "never train on it" in capsys.readouterr().err
    assert main(["generate", "--suite", "crossengine", "--out", str(out), "--set", "tracer.max_bounces=1"]) == 2
    assert "--set does not apply" in capsys.readouterr().err
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
