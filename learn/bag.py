"""MCAP bags in and out for `learn predict --stream` (extra `ros`: the `mcap` and
`mcap-ros2-support` packages; learn never imports the simulator, so what its exporter writes is
read here again, and tests/test_predict_stream.py holds the two sides equal).

In: sonar frames as `sensor_msgs/Image` 32FC1 on /sonar/energyscape (row i range bin i from near
to far, column j azimuth j from the grid's minimum, as `python -m acoustic_sim export --format
mcap` writes them) and the sensor's poses as `tf2_msgs/TFMessage` on /tf (a parent frame, world or
odom, to the images' frame). A frame's pose is the transform stamped as the image, or the two
around it interpolated; a recording whose images fall outside its /tf has no poses. A new drive
starts wherever no image came for DRIVE_GAP_S.

Out: the predicted scans as LaserScans on /scan_pred and the poses used on /tf, so Foxglove
shows the predicted scan in the world.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import MissingExtra
from .data import DataError, Frames, recorded_path
from .inputs import TooLarge, check_fits, regular_file
from .odometry import planar
from .ros import EPISODE_GAP_S, LASER_SCAN, laser_scan

IMAGE_TOPIC, TF_TOPIC = "/sonar/energyscape", "/tf"
DRIVE_GAP_S = EPISODE_GAP_S / 2  # the exporter leaves EPISODE_GAP_S between drives; frames come every 0.1 s
INSTALL = "pip install -e '.[ros]'"

_TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
_HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
_SEPARATOR = "=" * 80 + "\n"
TF_MESSAGE = (
    "geometry_msgs/TransformStamped[] transforms\n"
    + _SEPARATOR
    + "MSG: geometry_msgs/TransformStamped\nstd_msgs/Header header\nstring child_frame_id\n"
    + "geometry_msgs/Transform transform\n"
    + _SEPARATOR
    + _HEADER
    + _SEPARATOR
    + _TIME
    + _SEPARATOR
    + "MSG: geometry_msgs/Transform\ngeometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n"
    + _SEPARATOR
    + "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
    + _SEPARATOR
    + "MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
)


@dataclass
class Recording:
    """A drive (or several) to stream, in time order.

    Attributes:
        frames: The frames (labels all 0: a recording has no LiDAR truth); pose planar or None.
        stamps: (T,) int64 stamp of each frame [ns].
        transforms: (T, 4, 4) sensor-to-`parent` pose of each frame, None where there are none.
        parent, sensor: Frame ids of the poses' frame and of the sensor.
        note: Why there are no poses (empty where there are).
    """

    frames: Frames
    stamps: np.ndarray
    transforms: np.ndarray | None
    parent: str = "world"
    sensor: str = "sensor"
    note: str = ""


def read_bag(path: str | Path, range_m, azimuth_rad) -> Recording:
    """The sonar frames and poses of an MCAP bag on the grid (range_m, azimuth_rad) a checkpoint
    reads; refused naming the file where it is not an MCAP file, holds no frames, or frames of
    another encoding or size."""
    try:
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory
    except ImportError:
        raise MissingExtra(f"reading an MCAP bag needs the `ros` extra: {INSTALL}") from None
    path = regular_file(path, "--input")
    grid = (len(range_m), len(azimuth_rad))
    images, frame_ids, tf = [], set(), []
    try:
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            _check_size(reader, path, grid)
            for _, channel, _, message in reader.iter_decoded_messages(topics=[IMAGE_TOPIC, TF_TOPIC]):
                if channel.topic == IMAGE_TOPIC:
                    images.append((_stamp(message.header), _pixels(message, path, grid)))
                    frame_ids.add(message.header.frame_id)
                else:
                    tf += [
                        (_stamp(t.header), t.header.frame_id, t.child_frame_id, t.transform) for t in message.transforms
                    ]
    except (DataError, TooLarge, OSError):
        raise
    except Exception as err:  # the mcap readers raise many kinds on a damaged or foreign file
        text = str(err).strip().splitlines()
        raise ValueError(
            f"--input {path} is not an MCAP bag this learner can read ({text[0] if text else err!r})"
        ) from None
    if not images:
        raise DataError(
            f"--input {path} holds no {IMAGE_TOPIC} messages (sensor_msgs/Image 32FC1, as `python -m acoustic_sim "
            "export --format mcap` writes them)"
        )
    if len(frame_ids) > 1:
        raise DataError(f"--input {path}: the {IMAGE_TOPIC} images name {len(frame_ids)} frames {sorted(frame_ids)}")
    order = np.argsort([s for s, _ in images], kind="stable")
    stamps = np.array([images[i][0] for i in order], np.int64)
    energy = np.stack([images[i][1] for i in order])
    sensor = frame_ids.pop()
    transforms, parent, note = _poses(tf, sensor, stamps)
    episode = np.cumsum(np.r_[0, np.diff(stamps) >= DRIVE_GAP_S * 1e9]).astype(np.int64)
    frames = Frames(
        energyscape=energy[:, None],  # one elevation: the level slice
        label=np.zeros(energy.shape, np.uint8),
        episode=episode,
        scenario=np.zeros(len(stamps), np.int64),
        scenarios=["recorded"],
        range_m=np.asarray(range_m, np.float64),
        azimuth_rad=np.asarray(azimuth_rad, np.float64),
        info={"folder": recorded_path(path)},
        pose=None if transforms is None else planar(transforms),
    )
    return Recording(frames, stamps, transforms, parent or "world", sensor, note)


def _check_size(reader, path: Path, grid: tuple[int, int]) -> None:
    """Refuse a bag whose frames, as its summary counts them, would not fit in memory."""
    summary = reader.get_summary()
    if summary is None or summary.statistics is None:
        return  # an unindexed bag: it is read as it comes
    ids = [i for i, c in summary.channels.items() if c.topic == IMAGE_TOPIC]
    count = sum(summary.statistics.channel_message_counts.get(i, 0) for i in ids)
    check_fits(
        count * grid[0] * grid[1] * 9,  # float32 frames as read and stacked, uint8 labels
        f"--input {path} ({count:,} sonar frames of {grid[0]} x {grid[1]})",
        "split the bag (`mcap filter --start/--end`) and predict a stretch at a time",
    )


def _stamp(header) -> int:
    return int(header.stamp.sec) * 10**9 + int(header.stamp.nanosec)


def _pixels(image, path: Path, grid: tuple[int, int]) -> np.ndarray:
    """An Image message's energyscape (R, A) float32, refused where not 32FC1 on the grid."""
    stamp = f"{image.header.stamp.sec}.{image.header.stamp.nanosec:09d} s"
    if image.encoding != "32FC1":
        raise DataError(f"--input {path}: the {IMAGE_TOPIC} image at {stamp} is {image.encoding!r}, not 32FC1")
    if (image.height, image.width) != grid:
        raise DataError(
            f"--input {path}: the {IMAGE_TOPIC} image at {stamp} is {image.height} x {image.width}, but the model "
            f"reads {grid[0]} ranges x {grid[1]} azimuths"
        )
    data = bytes(image.data)
    if image.step != 4 * image.width or len(data) != image.step * image.height:
        raise DataError(
            f"--input {path}: the {IMAGE_TOPIC} image at {stamp} has {len(data)} bytes, not {4 * grid[0] * grid[1]}"
        )
    pixels = np.frombuffer(data, ">f4" if image.is_bigendian else "<f4").reshape(grid).astype(np.float32)
    if not np.isfinite(pixels).all():
        raise DataError(f"--input {path}: the {IMAGE_TOPIC} image at {stamp} holds NaN or inf values")
    return pixels


def _poses(tf: list, sensor: str, stamps: np.ndarray) -> tuple[np.ndarray | None, str | None, str]:
    """(T, 4, 4) pose of the sensor at each stamp from the /tf transforms to it, its parent frame,
    and why there are none (a (None, None, reason) where the /tf cannot give every frame one)."""
    mine = [t for t in tf if t[2] == sensor]
    if not mine:
        return None, None, f"no {TF_TOPIC} transform to the sonar's frame {sensor!r}"
    parents = sorted({t[1] for t in mine})
    if len(parents) > 1:
        return None, None, f"{TF_TOPIC} gives the sonar's frame {sensor!r} {len(parents)} parents {parents}"
    mine.sort(key=lambda t: t[0])
    at = np.array([t[0] for t in mine], np.int64)
    translation = np.array([[t[3].translation.x, t[3].translation.y, t[3].translation.z] for t in mine])
    rotation = np.array([[t[3].rotation.x, t[3].rotation.y, t[3].rotation.z, t[3].rotation.w] for t in mine])
    outside = int(np.count_nonzero((stamps < at[0]) | (stamps > at[-1])))
    if outside:
        return None, None, f"{outside} of {len(stamps)} sonar frames lie outside the time span of its {TF_TOPIC}"
    after = np.clip(np.searchsorted(at, stamps, side="left"), 0, len(at) - 1)  # first transform at or after
    before = np.where(at[after] == stamps, after, np.maximum(after - 1, 0))
    span = (at[after] - at[before]).astype(np.float64)
    w = np.where(span > 0, (stamps - at[before]) / np.where(span > 0, span, 1.0), 0.0)[:, None]
    q0, q1 = rotation[before], rotation[after]
    q1 = np.where(np.sum(q0 * q1, -1, keepdims=True) < 0, -q1, q1)  # the short way round
    pose = np.tile(np.eye(4), (len(stamps), 1, 1))
    pose[:, :3, :3] = quaternion_matrix((1 - w) * q0 + w * q1)  # normalised there: nlerp
    pose[:, :3, 3] = (1 - w) * translation[before] + w * translation[after]
    return pose, parents[0], ""


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) x, y, z, w (any norm > 0) -> rotation matrices (..., 3, 3)."""
    q = np.asarray(q, np.float64)
    x, y, z, w = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_quaternion(m: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) x, y, z, w with w >= 0
    (Shepperd's method: from the largest of the four diagonal sums, never a small divisor)."""
    m = np.asarray(m, np.float64)
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    forms = np.stack(
        [
            np.stack([m21 - m12, m02 - m20, m10 - m01, 1 + m00 + m11 + m22], -1),
            np.stack([1 + m00 - m11 - m22, m01 + m10, m02 + m20, m21 - m12], -1),
            np.stack([m01 + m10, 1 - m00 + m11 - m22, m12 + m21, m02 - m20], -1),
            np.stack([m02 + m20, m12 + m21, 1 - m00 - m11 + m22, m10 - m01], -1),
        ],
        -2,
    )  # (..., 4 forms, 4): form k holds 4 q_k q (q_w for form 0)
    diagonal = np.stack([forms[..., 0, 3], forms[..., 1, 0], forms[..., 2, 1], forms[..., 3, 2]], -1)
    best = np.take_along_axis(forms, diagonal.argmax(-1)[..., None, None], -2)[..., 0, :]
    q = best / np.linalg.norm(best, axis=-1, keepdims=True)
    return np.where(q[..., 3:] < 0, -q, q)


def write_bag(path, ranges, scan_stamps, range_m, azimuth_rad, *, transforms, tf_stamps, parent, sensor) -> Path:
    """Scans (S, A) on /scan_pred at `scan_stamps` [ns] in the sensor frame and, where given,
    the poses (T, 4, 4) sensor-to-`parent` on /tf at `tf_stamps` [ns], in time order."""
    try:
        from mcap_ros2.writer import Writer
    except ImportError:
        raise MissingExtra(f"--mcap needs the `ros` extra: {INSTALL}") from None
    messages = [
        (int(t), 1, "/scan_pred", laser_scan(r, int(t), range_m, azimuth_rad, sensor))
        for r, t in zip(ranges, scan_stamps, strict=True)
    ]
    if transforms is not None:
        quaternion = matrix_quaternion(transforms[:, :3, :3])
        for pose, q, t in zip(transforms, quaternion, tf_stamps, strict=True):
            x, y, z = (float(v) for v in pose[:3, 3])
            transform = {
                "header": {"stamp": {"sec": int(t) // 10**9, "nanosec": int(t) % 10**9}, "frame_id": parent},
                "child_frame_id": sensor,
                "transform": {
                    "translation": {"x": x, "y": y, "z": z},
                    "rotation": dict(zip("xyzw", (float(v) for v in q), strict=True)),
                },
            }
            messages.append((int(t), 0, TF_TOPIC, {"transforms": [transform]}))  # a frame's pose before its scan
    messages.sort(key=lambda m: m[:2])
    with open(path, "wb") as stream:
        writer = Writer(stream)
        schemas = {
            "/scan_pred": writer.register_msgdef("sensor_msgs/msg/LaserScan", LASER_SCAN),
            TF_TOPIC: writer.register_msgdef("tf2_msgs/msg/TFMessage", TF_MESSAGE),
        }
        for k, (stamp, _, topic, message) in enumerate(messages):
            writer.write_message(topic, schemas[topic], message, log_time=stamp, sequence=k)
        writer.finish()
    return Path(path)
