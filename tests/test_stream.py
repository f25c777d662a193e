"""Streaming inference (`learn.stream`) against batched inference: a drive stepped frame by frame
gives, for every window, the image that `learn.data.Windows.batch` + `predict_image` give that
window, history frames from before the drive began absent in both; and the refusals."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from learn.data import DataConfig, Frames, Windows
from learn.models import ModelConfig, build_model, predict_image
from learn.scan import first_return_ranges
from learn.stream import Stream

RANGE = np.linspace(0.25, 4.0, 16)  # [m]
AZIMUTH = np.deg2rad(np.arange(-90, 91, 10.0))
EXTENT = (RANGE[0], RANGE[-1], AZIMUTH[0], AZIMUTH[-1])
EPISODES = (23, 3, 12)  # frames per drive; the second is shorter than a window of 5
THRESHOLD = 0.5


def _drives(seed: int = 0, elevation_deg=(0.0,)) -> Frames:
    """Drives of random energyscapes (float16, a few strong echoes each, at every elevation)
    along random walks that turn: every frame differs, so reading a wrong frame or pose changes
    the prediction."""
    rng = np.random.default_rng(seed)
    energy, pose, episode = [], [], []
    for k, count in enumerate(EPISODES):
        at = np.array([3.0 * k, -1.0, 0.3 * k])
        for _ in range(count):
            e = rng.uniform(0, 0.1, (len(elevation_deg), len(RANGE), len(AZIMUTH)))
            for slice_ in e:
                slice_[rng.integers(len(RANGE), size=4), rng.integers(len(AZIMUTH), size=4)] = rng.uniform(1, 50, 4)
            energy.append(e), pose.append(at.copy()), episode.append(k)
            at += [0.15 * math.cos(at[2]), 0.15 * math.sin(at[2]), rng.normal(0, 0.2)]
    n = len(episode)
    return Frames(
        np.array(energy, np.float16),
        np.zeros((n, len(RANGE), len(AZIMUTH)), np.uint8),
        np.array(episode),
        np.zeros(n, np.int64),
        ["walk"],
        RANGE,
        AZIMUTH,
        {"folder": "random walks"},
        np.array(pose),
        elevation_deg,
    )


def _model(name: str, data: DataConfig, seed: int = 0, elevation_deg=(0.0,)):
    """A randomly initialised network and the checkpoint dict a Stream reads."""
    torch.manual_seed(seed)
    config = ModelConfig(
        name=name, frames=data.frames, width=4, history=data.history, extent=EXTENT, elevation_deg=elevation_deg
    )
    if name != "polar_memory":
        config = dataclasses.replace(config, extent=None)
    model = build_model(config).eval()
    # He initialisation everywhere and no prior bias: the image then moves with the frames (at the
    # shipped initialisation it sits near sigmoid(log 0.01 / 0.99) whatever they hold)
    for layer in model.modules():
        if isinstance(layer, torch.nn.Conv2d):
            torch.nn.init.kaiming_normal_(layer.weight)
            if layer.bias is not None:
                torch.nn.init.zeros_(layer.bias)
    ckpt = {
        "data_config": dataclasses.asdict(data),
        "model_config": dataclasses.asdict(config),
        "range_m": RANGE.tolist(),
        "azimuth_rad": AZIMUTH.tolist(),
        "threshold": THRESHOLD,
    }
    return model, ckpt


def _batched(model, frames: Frames, data: DataConfig) -> dict[int, np.ndarray]:
    """{label frame: image as predict saves it (float16)} of every window, in one batch."""
    windows = Windows(frames, data, odometry=data.history > 0 or getattr(model, "odometry", False))
    x, _ = windows.batch(np.arange(len(windows)))
    with torch.no_grad():
        images = predict_image(model, x).float().clamp(0, 1)[:, 0].half().numpy()
    return dict(zip((windows.starts + data.label_offset).tolist(), images, strict=True))


def _streamed(stream: Stream, frames: Frames, *, poses: bool = True) -> dict[int, tuple]:
    """{frame: (image, ranges, pose)} of a stream stepped over every frame, reset at each new drive."""
    got, first = {}, 0
    for t in range(len(frames)):
        if t and frames.episode[t] != frames.episode[t - 1]:
            stream.reset()
            first = t
        result = stream.step(frames.energyscape[t], frames.pose[t] if poses else None)
        if result is not None:
            assert first + result.frame not in got
            got[first + result.frame] = (result.image, result.ranges, result.pose)
        else:
            assert t - first < stream.config.frames - 1  # None only while the first window fills
    return got


CASES = {
    "memory_middle": ("polar_memory", DataConfig(frames=5, label="middle", history=3, history_stride=3)),
    "memory_last": ("polar_memory", DataConfig(frames=3, label="last", history=4, history_stride=2)),
    "unet_middle": ("polar_unet", DataConfig(frames=5, label="middle")),
    "memory_elevations": (
        "polar_memory",
        DataConfig(frames=3, label="middle", history=2, history_stride=2),
        (-20, 0, 20),
    ),
    "unet_elevations": ("polar_unet", DataConfig(frames=3, label="last"), (-10.0, 10.0)),
}


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_streaming_equals_batched_for_every_window(case):
    """Every window of three drives (23, 3 and 12 frames), the first windows
    of a drive (history absent) included: the streamed image equals the batched one (to float16
    rounding, which both apply), for the same label frames; the scan is the image's nearest cell
    >= threshold per beam; the pose is the label frame's."""
    name, data, *elevations = CASES[case]
    elevation_deg = tuple(elevations[0]) if elevations else (0.0,)
    frames = _drives(elevation_deg=elevation_deg)
    model, ckpt = _model(name, data, elevation_deg=elevation_deg)
    want = _batched(model, frames, data)
    got = _streamed(Stream(model, ckpt), frames)
    assert sorted(got) == sorted(want)
    assert len(want) == sum(max(0, n - data.frames + 1) for n in EPISODES)
    for frame, (image, ranges, pose) in got.items():
        np.testing.assert_allclose(image.astype(np.float32), want[frame].astype(np.float32), atol=1e-3, err_msg=frame)
        scan = first_return_ranges(torch.from_numpy(image.astype(np.float32))[None], RANGE, threshold=THRESHOLD)
        np.testing.assert_array_equal(ranges, scan[0].float().numpy())
        np.testing.assert_array_equal(pose, frames.pose[frame])
    spread = np.ptp([np.asarray(v, np.float32) for v in want.values()], axis=0)
    assert spread.max() > 0.02  # the windows' images differ (20 x the tolerance): a wrong frame read can fail


def test_a_stream_reading_another_history_does_not_match():
    """The comparison above sees which frames are read: a stream whose history stride is 2 where
    the windows' is 3 (the same weights) differs on windows that reach back into history."""
    data = CASES["memory_middle"][1]
    frames = _drives()
    model, ckpt = _model("polar_memory", data)
    want = _batched(model, frames, data)
    ckpt["data_config"] = dataclasses.asdict(dataclasses.replace(data, history_stride=2))
    got = _streamed(Stream(model, ckpt), frames)
    worst = max(np.abs(got[f][0].astype(np.float32) - want[f].astype(np.float32)).max() for f in want)
    assert worst > 1e-2, worst


def test_streams_a_4x4_pose_as_its_planar_pose():
    """A sensor-to-odom matrix gives the same scans as its (x, y, yaw)."""
    data = CASES["memory_last"][1]
    frames = _drives()
    model, ckpt = _model("polar_memory", data)
    planar, matrices = Stream(model, ckpt), Stream(model, ckpt)
    for t in range(12):
        x, y, yaw = frames.pose[t]
        pose = np.eye(4)
        pose[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        pose[:3, 3] = x, y, 0.4
        a, b = planar.step(frames.energyscape[t], frames.pose[t]), matrices.step(frames.energyscape[t], pose)
        if a is not None:
            np.testing.assert_allclose(a.image.astype(np.float32), b.image.astype(np.float32), atol=1e-3)
            np.testing.assert_allclose(b.pose, frames.pose[t], atol=1e-12)


def test_a_model_without_memory_streams_without_poses():
    name, data = CASES["unet_middle"]
    frames = _drives()
    model, ckpt = _model(name, data)
    got = _streamed(Stream(model, ckpt), frames, poses=False)
    want = _batched(model, frames, data)
    assert sorted(got) == sorted(want) and all(pose is None for _, _, pose in got.values())


def test_refusals_name_what_to_give():
    """A memory model without a pose, a pose of another shape, a frame on another grid or with
    NaN: one clear ValueError each, and the stream is as before (the next good frame goes on)."""
    data = CASES["memory_middle"][1]
    model, ckpt = _model("polar_memory", data)
    stream = Stream(model, ckpt)
    good = np.ones((len(RANGE), len(AZIMUTH)), np.float32)
    with pytest.raises(ValueError, match=r"memory .* reads each frame's odometry pose"):
        stream.step(good, None)
    with pytest.raises(ValueError, match=r"pose must be \(x, y, yaw\) or a 4 x 4"):
        stream.step(good, [0.0, 1.0])
    with pytest.raises(ValueError, match="energyscape has shape"):
        stream.step(np.ones((3, 4)), [0.0, 0.0, 0.0])
    bad = good.copy()
    bad[2, 3] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        stream.step(bad, [0.0, 0.0, 0.0])
    assert stream.count == 0
