"""The model with memory (`learn.memory`) and odometry (`learn.odometry`), against independent
references: the resampling against a float64 transform of a point echo, the drift model against
its analytic spread, and a model that must use the pose to answer (a wall heard only before the
sensor turned away from it)."""

import math

import numpy as np
import pytest
import torch

from learn.data import DataConfig, Frames, Windows
from learn.memory import polar_warp
from learn.models import ModelConfig, build_model, predict_image
from learn.odometry import OdometryNoise, compose, noisy_drive, noisy_window, relative

RANGE = np.linspace(0.25, 4.0, 16)  # [m]
AZIMUTH = np.deg2rad(np.arange(-90, 91, 10.0))
EXTENT = torch.tensor([RANGE[0], RANGE[-1], AZIMUTH[0], AZIMUTH[-1]])


def _cell_of(point_xy: np.ndarray) -> tuple[float, float]:
    """(range, azimuth) of a point in a sensor frame, float64."""
    return float(np.hypot(*point_xy)), float(np.arctan2(point_xy[1], point_xy[0]))


@pytest.mark.parametrize("pose", [(0.3, -0.2, 0.4), (-0.5, 0.6, -0.9), (0.0, 0.0, 0.35)])
def test_warp_puts_a_past_echo_where_the_point_is_now(pose):
    """A point echo in a past frame lands, after the warp, at the cell where a float64 rigid
    transform says that point lies from the label frame; with the yaw off by 25 degrees it does not."""
    past = np.array(pose)  # the past sensor in the label frame
    r_i, a_j = 7, 9  # the echo's cell in the past frame
    local = RANGE[r_i] * np.array([math.cos(AZIMUTH[a_j]), math.sin(AZIMUTH[a_j])])
    c, s = math.cos(past[2]), math.sin(past[2])
    world = past[:2] + np.array([c * local[0] - s * local[1], s * local[0] + c * local[1]])
    want_r, want_a = _cell_of(world)

    frames = torch.zeros(1, 1, len(RANGE), len(AZIMUTH))
    frames[0, 0, r_i, a_j] = 1.0

    def peak(p):
        motion = torch.tensor([[[*p, 1.0]]], dtype=torch.float32)
        warped, seen = polar_warp(frames, motion, EXTENT)
        i, j = np.unravel_index(int(warped[0, 0].argmax()), warped.shape[-2:])
        return warped[0, 0].max().item(), RANGE[i], AZIMUTH[j], seen

    value, got_r, got_a, seen = peak(past)
    assert value > 0.2
    assert abs(got_r - want_r) <= (RANGE[1] - RANGE[0]) and abs(got_a - want_a) <= (AZIMUTH[1] - AZIMUTH[0]) + 1e-9
    wrong = peak((past[0], past[1], past[2] + math.radians(25)))
    assert abs(wrong[2] - want_a) > math.radians(15)
    # what the past sensor could not see is marked unseen: cells behind it, or beyond its range
    px = RANGE[:, None] * np.cos(AZIMUTH)
    py = RANGE[:, None] * np.sin(AZIMUTH)
    q = relative(np.stack([px, py, np.zeros_like(px)], -1), past)
    inside = (np.hypot(q[..., 0], q[..., 1]) <= RANGE[-1]) & (np.abs(np.arctan2(q[..., 1], q[..., 0])) <= AZIMUTH[-1])
    agree = (seen[0, 0].numpy() > 0) == inside
    assert agree.mean() > 0.97  # cells on the border may fall either way


def test_absent_frames_are_unseen():
    frames = torch.ones(1, 2, len(RANGE), len(AZIMUTH))
    motion = torch.tensor([[[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]])
    warped, seen = polar_warp(frames, motion, EXTENT)
    assert seen[0, 0].sum() == 0 and warped[0, 0].abs().sum() == 0
    assert seen[0, 1].mean() > 0.99 and torch.allclose(warped[0, 1], frames[0, 1], atol=1e-5)


def test_relative_and_compose_invert_each_other():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    np.testing.assert_allclose(compose(b, relative(a, b))[:, :2], a[:, :2], atol=1e-12)
    wrapped = np.angle(np.exp(1j * (compose(b, relative(a, b))[:, 2] - a[:, 2])))
    np.testing.assert_allclose(wrapped, 0, atol=1e-12)


def _straight(distance: float, steps: int) -> np.ndarray:
    return np.c_[np.linspace(0, distance, steps + 1), np.zeros(steps + 1), np.zeros(steps + 1)]


def test_drift_grows_with_distance_and_turn_as_the_model_says():
    """5 % drift: along-track error std 0.05 x distance, heading error std 0.05 rad/m x distance
    on a straight drive; 0.05 x angle on a turn in place (4,000 drives each; the sample std of a
    normal lies within 6 % of the true one with near certainty at that count)."""
    noise, rng, draws = OdometryNoise.from_drift(0.05), np.random.default_rng(0), 4000
    line = _straight(2.0, 40)
    ends = np.array([noisy_drive(line, noise, rng)[-1] for _ in range(draws)])
    assert abs(ends[:, 2].std() / (0.05 * 2.0) - 1) < 0.06
    # along-track: the scale error alone (a heading error bends the path, shortening it by ~D h^2 / 3)
    assert abs(ends[:, 0].std() / (0.05 * 2.0) - 1) < 0.06
    turn = np.c_[np.zeros(31), np.zeros(31), np.linspace(0, 3.0, 31)]
    yaws = np.array([noisy_drive(turn, noise, rng)[-1, 2] for _ in range(draws)])
    error = np.angle(np.exp(1j * (yaws - 3.0)))  # yaw is reported within (-pi, pi]
    assert abs(error.std() / (0.05 * 3.0) - 1) < 0.06
    assert np.allclose(noisy_drive(line, OdometryNoise(), rng), line)


def test_a_window_drifts_as_a_drive_does():
    """`noisy_window` (per window, chained outwards from the label frame) spreads the pose of a
    frame 2 m back as `noisy_drive` spreads a drive's end after 2 m."""
    noise, draws = OdometryNoise.from_drift(0.05), 4000
    line = torch.tensor(_straight(2.0, 20) - [2.0, 0, 0], dtype=torch.float64)  # the label frame last
    motion = line.expand(draws, -1, -1)
    moved = noisy_window(motion, 20, noise, torch.Generator().manual_seed(0))
    assert torch.equal(moved[:, 20], motion[:, 20])
    assert abs(float(moved[:, 0, 2].std()) / (0.05 * 2.0) - 1) < 0.06
    assert abs(float(moved[:, 0, 0].std()) / (0.05 * 2.0) - 1) < 0.06


def _turning_drives(count: int, rng: np.random.Generator):
    """Drives of 12 frames turning in place by 8 degrees a frame, each with a reflector at a random
    range straight ahead of the first pose. It echoes only within 20 degrees of the sensor's
    heading (met edge-on beyond, a specular wall is silent); the LiDAR label sees it at any
    azimuth in view. A ghost echo at a random cell in every frame stands for multipath."""
    steps = 12
    t = len(RANGE), len(AZIMUTH)
    energy, label, pose, episode = [], [], [], []
    for k in range(count):
        target = RANGE[rng.integers(3, 14)]
        for i in range(steps):
            yaw = math.radians(8 * i)
            e, y = rng.uniform(0, 0.05, t).astype(np.float32), np.zeros(t, np.uint8)
            j = int(np.argmin(np.abs(AZIMUTH + yaw)))  # the target's azimuth from this pose
            r = int(np.argmin(np.abs(RANGE - target)))
            y[r, j] = 1
            if abs(yaw) <= math.radians(20):
                e[r, j] = 1.0
            e[rng.integers(t[0]), rng.integers(t[1])] = 1.0
            energy.append(e), label.append(y), pose.append((0.0, 0.0, yaw)), episode.append(k)
    return Frames(
        np.array(energy, np.float16),
        np.array(label),
        np.array(episode),
        np.zeros(len(episode), np.int64),
        ["turn"],
        RANGE,
        AZIMUTH,
        {"folder": "turning drives"},
        np.array(pose),
    )


def test_memory_finds_a_wall_heard_only_before_the_turn_and_needs_the_pose():
    """Trained on turning drives, polar_memory marks the reflector in frames where it is silent
    (heard only before the sensor turned away) at the right cell; the same frames given with the
    motion of a sensor that did not turn do not give it."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    data = DataConfig(frames=1, label="last", history=8)
    model = build_model(ModelConfig(name="polar_memory", frames=1, history=8, width=8, extent=tuple(EXTENT.tolist())))
    train = Windows(_turning_drives(48, rng), data, odometry=True)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(80):
        (x, motion), y = train.batch(rng.integers(len(train), size=32))
        loss = torch.nn.functional.binary_cross_entropy_with_logits(model(x, motion), y, pos_weight=torch.tensor(5.0))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    model.eval()
    test = Windows(_turning_drives(16, np.random.default_rng(1)), data, odometry=True)
    # frames 4-10: the reflector turned > 20 deg away, its last echo (frame 2) still in the history
    silent = np.flatnonzero(np.tile((np.arange(12) >= 4) & (np.arange(12) <= 10), 16))
    (x, motion), y = test.batch(silent)
    with torch.no_grad():
        found = predict_image(model, (x, motion))
        still = motion.clone()
        still[..., :3] = 0  # odometry of a sensor that did not move
        unmoved = predict_image(model, (x, still))
    true = y > 0.5
    recall = float((found[true] >= 0.5).float().mean())
    wrong_pose_recall = float((unmoved[true] >= 0.5).float().mean())
    false_cells = float((found[~true] >= 0.5).float().sum()) / len(silent)
    print(f"recall {recall:.3f}, with the wrong motion {wrong_pose_recall:.3f}, false cells {false_cells:.2f}")
    assert recall > 0.8, recall
    assert wrong_pose_recall < 0.3, wrong_pose_recall
    assert false_cells < 1.0, false_cells


def _shard(folder, poses: np.ndarray, config: dict):
    """A 12-frame shard written by the simulator's shard writer (nothing simulated)."""
    import dataclasses

    from acoustic_sim.config import SimConfig
    from acoustic_sim.datasets.shards import ShardFrames, write_shard

    grid = dataclasses.replace(SimConfig().processing.grid, range_max_m=0.5, azimuth_min_deg=-5, azimuth_max_deg=5)
    shape, count = grid.shape, len(poses)
    frames = ShardFrames(
        energyscape=[np.ones((count, *shape))],
        lidar_ranges=[np.full((count, 5), 1.0)],
        lidar_image=[np.zeros((count, *shape))],
        pose=[poses],
        time=[np.arange(count) * 0.1],
        episode=[np.zeros(count)],
        scenario=[np.zeros(count)],
    )
    attrs = {
        "plan_id": "x",
        "variant": "",
        "shard": 0,
        "config": config,
        "episodes": [{"index": 0}],
        "scenarios": ["a"],
    }
    folder.mkdir(parents=True)
    write_shard(folder / "shard-00000.h5", frames, attrs=attrs, range_m=grid.range_m, azimuth_rad=grid.azimuth_rad)
    return folder


def test_poses_reach_the_windows_and_a_recording_without_odometry_has_none(tmp_path):
    """A shard's 4 x 4 poses become planar poses of its frames; a CHIRP import that had no
    odometry (its config says the poses are identities) has none, and a model with memory is
    refused on it with a line that says why, while a model without memory reads it."""
    from learn.data import DataError, load_frames

    yaw = np.linspace(0, 1, 12)
    poses = np.tile(np.eye(4), (12, 1, 1))
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    poses[:, 0, 3], poses[:, 1, 3] = np.arange(12) * 0.03, 1.0
    frames = load_frames(_shard(tmp_path / "sim", poses, {}))
    np.testing.assert_allclose(frames.pose, np.c_[np.arange(12) * 0.03, np.ones(12), yaw], atol=1e-12)
    imported = {"poses": "identity (no odometry synced to the pings)"}
    frames = load_frames(_shard(tmp_path / "rec", np.tile(np.eye(4), (12, 1, 1)), imported))
    assert frames.pose is None
    config = DataConfig(frames=1, label="last", history=2)
    with pytest.raises(DataError, match="holds no poses"):
        Windows(frames, config, odometry=True)
    x, _ = Windows(frames, DataConfig(frames=1, label="last")).batch([0, 1])
    assert x.shape[:3] == (2, 1, 1)
