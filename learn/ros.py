"""Predicted scans as ROS 2 `sensor_msgs/LaserScan` messages on /scan_pred in an MCAP file (extra
`ros`), stamped as `python -m acoustic_sim export --format mcap` stamps the same dataset's frames,
so Foxglove shows them over the true /scan. `learn` never imports the simulator: the message
definition and the stamp rule are restated here, and a test holds the two sides equal."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from . import MissingExtra

STAMP_START_S = 1_700_000_000
EPISODE_GAP_S = 1.0
FRAME_S = 0.1  # recorded energyscapes (.npy) carry no times: 10 Hz, the training frame rate
SENSOR_FRAME = "sensor"
LASER_SCAN = (
    "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n"
    "float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\n"
    "float32[] ranges\nfloat32[] intensities\n"
    + "=" * 80
    + "\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    + "=" * 80
    + "\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
)


def drive_stamps(episode: np.ndarray, time_s: np.ndarray) -> np.ndarray:
    """Nanosecond stamps of frames in file order: each episode's own times, episodes end to end
    EPISODE_GAP_S apart, after STAMP_START_S (a new episode wherever `episode` changes)."""
    stamps, offset, end = np.empty(len(time_s), np.int64), 0.0, -EPISODE_GAP_S
    for i in range(len(time_s)):
        if i == 0 or episode[i] != episode[i - 1]:
            offset = end + EPISODE_GAP_S - time_s[i]
        end = time_s[i] + offset
        stamps[i] = STAMP_START_S * 10**9 + round(end * 1e9)
    return stamps


def dataset_stamps(folder: str | Path) -> np.ndarray:
    """Stamps of every frame of a dataset folder, from its shards' `time` and `episode` (each
    shard's `time` checked: present, one finite time per frame)."""
    from .data import shard_paths
    from .shardfile import REDO, DataError, open_shard

    keys, times = [], []
    for i, path in enumerate(shard_paths(folder)):
        with open_shard(path) as f:
            episode, time = f["episode"][:], f.get("time")
            if not isinstance(time, h5py.Dataset) or time.shape != episode.shape:
                found = "no time dataset" if time is None else f"time of shape {getattr(time, 'shape', None)}"
                raise DataError(f"{path} has {found}, not one time per frame, which --mcap stamps scans with: {REDO}")
            time = time[:]
        if not np.isfinite(time).all():
            raise DataError(f"{path}: time holds NaN or inf, which cannot stamp a scan (--mcap): {REDO}")
        keys += [(i, int(e)) for e in episode]
        times.append(time)
    index = {key: n for n, key in enumerate(dict.fromkeys(keys))}
    return drive_stamps(np.array([index[k] for k in keys]), np.concatenate(times))


def write_scans(out: str | Path, ranges: np.ndarray, stamps: np.ndarray, range_m, azimuth_rad) -> Path:
    """LaserScans (one per row of `ranges`, inf = no return) on /scan_pred at `stamps` [ns]."""
    try:
        from mcap_ros2.writer import Writer
    except ImportError:
        raise MissingExtra("--mcap needs the `ros` extra: pip install -e '.[ros]'") from None
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef("sensor_msgs/msg/LaserScan", LASER_SCAN)
        for k, (scan, stamp) in enumerate(zip(ranges, stamps, strict=True)):
            message = laser_scan(scan, int(stamp), range_m, azimuth_rad)
            writer.write_message("/scan_pred", schema, message, log_time=int(stamp), sequence=k)
        writer.finish()
    return out


def laser_scan(scan, stamp: int, range_m, azimuth_rad, frame: str = SENSOR_FRAME) -> dict:
    """One LaserScan message: `scan` (A,) ranges [m] (inf = no return) at `stamp` [ns] in `frame`."""
    azimuth_rad, range_m = np.asarray(azimuth_rad, np.float64), np.asarray(range_m, np.float64)
    return {
        "header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": frame},
        "angle_min": float(azimuth_rad[0]),
        "angle_max": float(azimuth_rad[-1]),
        "angle_increment": float((azimuth_rad[-1] - azimuth_rad[0]) / (len(azimuth_rad) - 1)),
        "time_increment": 0.0,
        "scan_time": FRAME_S,
        "range_min": float(range_m[0]),
        "range_max": float(range_m[-1]),
        "ranges": np.asarray(scan, np.float32).tolist(),
        "intensities": [],
    }
