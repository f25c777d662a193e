"""A dataset as ROS 2 messages in an MCAP file, without a ROS install (extra `ros`: the `mcap` and
`mcap-ros2-support` packages), for Foxglove or `ros2 bag play`:

    python -m acoustic_sim export DATASET --format mcap --out drive.mcap

Per frame: `sensor_msgs/LaserScan` on /scan (the LiDAR's ranges), `sensor_msgs/Image` on
/sonar/energyscape (32FC1: row i is range bin i from near to far, column j azimuth j of the grid
from its minimum, -90 deg on the right) and `tf2_msgs/TFMessage` on /tf (world -> sensor, the
frame's pose). A dataset of several elevations (`processing.elevation_deg` a list) gets one Image
topic per elevation instead, named by `energyscape_topics` (-20, 0, 20 deg:
/sonar/energyscape/elevation_m20_deg, .../elevation_0_deg, .../elevation_20_deg); a dataset of
one elevation, at whatever angle, keeps /sonar/energyscape. Stamps: the drive's own times after a
fixed start (STAMP_START_S, 2023-11-14), the episodes one after another with a second between
them, so the file always reads the same.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from clitools.outputs import atomic_output, check_output

from ..datasets.shards import DatasetError, check_outside, energyscapes, finite_poses, one_run_shards
from ..extras import MissingExtra

ENERGYSCAPE_TOPIC = "/sonar/energyscape"
STAMP_START_S = 1_700_000_000
EPISODE_GAP_S = 1.0
WORLD_FRAME, SENSOR_FRAME = "world", "sensor"

_TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
_HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
_SEPARATOR = "=" * 80 + "\n"


def _msgdef(fields: str, *dependencies: str) -> str:
    """A ROS 2 message definition as MCAP's ros2msg schema encoding stores it: the message, then
    each type it uses after a separator line."""
    return fields + "".join(_SEPARATOR + d for d in dependencies)


# The standard interfaces' fields (sensor_msgs, tf2_msgs, geometry_msgs, std_msgs, builtin_interfaces).
LASER_SCAN = _msgdef(
    "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n"
    "float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\n"
    "float32[] ranges\nfloat32[] intensities\n",
    _HEADER,
    _TIME,
)
IMAGE = _msgdef(
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
    "uint32 step\nuint8[] data\n",
    _HEADER,
    _TIME,
)
TF_MESSAGE = _msgdef(
    "geometry_msgs/TransformStamped[] transforms\n",
    "MSG: geometry_msgs/TransformStamped\nstd_msgs/Header header\nstring child_frame_id\n"
    "geometry_msgs/Transform transform\n",
    _HEADER,
    _TIME,
    "MSG: geometry_msgs/Transform\ngeometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n",
    "MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
)


def _header(stamp_ns: int, frame: str) -> dict:
    return {"stamp": {"sec": stamp_ns // 10**9, "nanosec": stamp_ns % 10**9}, "frame_id": frame}


def frame_stamps(episode: np.ndarray, time_s: np.ndarray) -> np.ndarray:
    """Nanosecond stamps (int64) of frames in file order: each episode's own times, episodes laid
    end to end EPISODE_GAP_S apart, after STAMP_START_S. A new episode starts wherever `episode`
    changes."""
    stamps, offset, end = np.empty(len(time_s), np.int64), 0.0, -EPISODE_GAP_S
    for i in range(len(time_s)):
        if i == 0 or episode[i] != episode[i - 1]:
            offset = end + EPISODE_GAP_S - time_s[i]
        end = time_s[i] + offset
        stamps[i] = STAMP_START_S * 10**9 + round(end * 1e9)  # in integers: 1.7e18 ns is beyond float64
    return stamps


def energyscape_topics(elevation_deg) -> list[str]:
    """The Image topic of each elevation [deg]: ENERGYSCAPE_TOPIC for the level slice alone (the
    layout of datasets before elevations), else ENERGYSCAPE_TOPIC/elevation_<angle>_deg per
    elevation (one elevation other than 0 deg too, so a reader does not take it for 0), the
    angle in its shortest exact decimal with `m` for its minus and `p` for its point (ROS names
    hold letters, digits and underscores): -20 -> elevation_m20_deg, 12.5 -> elevation_12p5_deg."""
    if len(elevation_deg) == 1 and float(elevation_deg[0]) == 0.0:
        return [ENERGYSCAPE_TOPIC]
    angles = (np.format_float_positional(float(e) + 0.0, trim="-") for e in elevation_deg)  # + 0.0: no "-0"
    return [f"{ENERGYSCAPE_TOPIC}/elevation_{a.replace('-', 'm').replace('.', 'p')}_deg" for a in angles]


def _image_topics(shards: list[Path]) -> list[str]:
    """The Image topics of a run's energyscapes, refused naming the shard when an angle repeats (two
    images, one topic) or its elevations are not those of the first shard."""
    import h5py

    first = None
    for path in shards:
        with h5py.File(path, "r") as f:
            elevations = tuple(float(e) for e in energyscapes(f, slice(0, 0))[1])  # the axis alone, either format
        if len(set(elevations)) < len(elevations):
            raise DatasetError(
                f"{path}: its elevation_deg {list(elevations)} repeats an angle; MCAP export writes one Image topic "
                "per elevation, so generate the dataset with distinct angles"
            )
        if first is not None and elevations != first:
            raise DatasetError(f"{path} holds elevations {list(elevations)} [deg], its run's first shard {list(first)}")
        first = elevations
    return energyscape_topics(first)


def export_mcap(dataset: str | Path, out: str | Path, *, overwrite: bool = False) -> dict:
    """Write every frame of a dataset folder (shard-*.h5 in order) as ROS 2 messages to `out`,
    under a temporary name renamed when whole (`clitools.outputs`): an existing file is replaced
    only with `overwrite`, a file of the dataset never. Returns what was written, with its topics."""
    try:
        from mcap_ros2.writer import Writer
    except ImportError:
        raise MissingExtra("MCAP export needs the `ros` extra: pip install -e '.[ros]'") from None
    import h5py
    from scipy.spatial.transform import Rotation

    folder, out = Path(dataset), Path(out)
    check_output(out, overwrite=overwrite, inputs=[folder])  # refused before any reading
    shards = one_run_shards(folder)  # each checked: foreign, damaged, repeated files are refused naming them
    check_outside(folder, out)
    drive = []  # (shard, episode) and time of every frame, for the stamps
    for i, path in enumerate(shards):
        with h5py.File(path, "r") as f:
            drive += [((i, int(e)), float(t)) for e, t in zip(f["episode"][:], f["time"][:], strict=True)]
    keys = {key: n for n, key in enumerate(dict.fromkeys(k for k, _ in drive))}
    stamps = frame_stamps(np.array([keys[k] for k, _ in drive]), np.array([t for _, t in drive]))
    frames, images = 0, _image_topics(shards)  # one Image topic per elevation
    with atomic_output(out, overwrite=overwrite, inputs=[folder]) as tmp, open(tmp, "wb") as stream:
        writer = Writer(stream)
        schemas = {
            name: writer.register_msgdef(name, text)
            for name, text in (
                ("sensor_msgs/msg/LaserScan", LASER_SCAN),
                ("sensor_msgs/msg/Image", IMAGE),
                ("tf2_msgs/msg/TFMessage", TF_MESSAGE),
            )
        }
        for path in shards:
            with h5py.File(path, "r") as f:
                lidar = json.loads(f.attrs["config"])["sim"]["lidar"]
                ranges, poses = f["lidar/ranges"][:], finite_poses(f, path)
                energy = energyscapes(f)[0]  # (frame, elevation, range, azimuth), either format
            step = np.deg2rad((lidar["azimuth_max_deg"] - lidar["azimuth_min_deg"]) / (lidar["azimuth_count"] - 1))
            quaternions = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x, y, z, w
            for k in range(len(ranges)):
                stamp = int(stamps[frames])
                scan = {
                    "header": _header(stamp, SENSOR_FRAME),
                    "angle_min": float(np.deg2rad(lidar["azimuth_min_deg"])),
                    "angle_max": float(np.deg2rad(lidar["azimuth_max_deg"])),
                    "angle_increment": float(step),
                    "time_increment": 0.0,
                    "scan_time": 1.0 / lidar["rate_hz"],
                    "range_min": lidar["range_min_m"],
                    "range_max": lidar["range_max_m"],
                    "ranges": ranges[k].astype(np.float32).tolist(),
                    "intensities": [],
                }
                sonar = [(topic, _image(energy[k, j], stamp)) for j, topic in enumerate(images)]
                x, y, z = (float(v) for v in poses[k, :3, 3])
                qx, qy, qz, qw = (float(v) for v in quaternions[k])
                transform = {
                    "header": _header(stamp, WORLD_FRAME),
                    "child_frame_id": SENSOR_FRAME,
                    "transform": {
                        "translation": {"x": x, "y": y, "z": z},
                        "rotation": {"x": qx, "y": qy, "z": qz, "w": qw},
                    },
                }
                for topic, schema, message in (
                    ("/tf", "tf2_msgs/msg/TFMessage", {"transforms": [transform]}),
                    ("/scan", "sensor_msgs/msg/LaserScan", scan),
                    *((topic, "sensor_msgs/msg/Image", image) for topic, image in sonar),
                ):
                    writer.write_message(topic, schemas[schema], message, log_time=stamp, sequence=frames)
                frames += 1
        writer.finish()
    return {"out": str(out), "frames": frames, "shards": len(shards), "topics": ["/scan", *images, "/tf"]}


def _image(energy: np.ndarray, stamp_ns: int) -> dict:
    """A sensor_msgs/Image of one energyscape (range, azimuth): 32FC1, little-endian, a row per range bin."""
    image = energy.astype("<f4")
    return {
        "header": _header(stamp_ns, SENSOR_FRAME),
        "height": image.shape[0],
        "width": image.shape[1],
        "encoding": "32FC1",
        "is_bigendian": 0,
        "step": image.shape[1] * 4,
        "data": image.tobytes(),
    }
