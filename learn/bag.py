"""MCAP bags in and out for `learn predict --stream` (extra `ros`: the `mcap` and
`mcap-ros2-support` packages; learn never imports the simulator, so what its exporter writes is
read here again, and tests/test_predict_stream.py holds the two sides equal).

In: sonar frames as `sensor_msgs/Image` 32FC1 (row i range bin i from near to far, column j
azimuth j from the grid's minimum, as `python -m acoustic_sim export --format mcap` writes them):
on /sonar/energyscape for data of one elevation (read as the level slice, 0 deg), or one topic per
elevation, /sonar/energyscape/elevation_<angle>_deg (`topic_elevation`), whose images of one ping
share its stamp; and the sensor's poses as `tf2_msgs/TFMessage` on /tf (a parent frame, world or
odom, to the images' frame). A frame's pose is the transform stamped as the image, or the two
around it interpolated; a recording whose images fall outside its /tf has no poses. A new drive
starts wherever no image came for DRIVE_GAP_S.

Out: the predicted scans as LaserScans on /scan_pred and the poses used on /tf, so Foxglove
shows the predicted scan in the world.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import MissingExtra
from .data import DataError, Frames, recorded_path
from .inputs import TooLarge, check_fits, regular_file
from .odometry import planar
from .ros import EPISODE_GAP_S, LASER_SCAN, laser_scan

IMAGE_TOPIC, TF_TOPIC = "/sonar/energyscape", "/tf"
ELEVATION_TOPIC = re.compile(re.escape(IMAGE_TOPIC) + r"/elevation_(?P<angle>[^/]*)_deg")
_ANGLE = re.compile(r"m?[0-9]+(p[0-9]+)?")  # the exporter's spelling: m for the minus, p for the point
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


def topic_elevation(topic: str) -> float | None:
    """The elevation [deg] of the energyscapes on an Image topic, as the exporter names its topics
    (`acoustic_sim.formats.mcap_export.energyscape_topics`, restated here): IMAGE_TOPIC holds the
    level slice (0 deg) alone; IMAGE_TOPIC/elevation_<angle>_deg
    one of several, the angle spelt with `m` for its minus and `p` for its point
    (elevation_m20_deg: -20, elevation_12p5_deg: 12.5). None for any other topic (/tf, /scan, an
    image_transport topic such as IMAGE_TOPIC/compressed); ValueError for an elevation topic whose
    angle does not read."""
    if topic == IMAGE_TOPIC:
        return 0.0
    match = ELEVATION_TOPIC.fullmatch(topic)
    if match is None:
        return None
    if not _ANGLE.fullmatch(match["angle"]):
        raise ValueError(
            f"the topic {topic} names no angle (expected {IMAGE_TOPIC}/elevation_<angle>_deg with the angle in "
            "digits, m for a minus and p for a point: elevation_m20_deg, elevation_12p5_deg)"
        )
    return float(match["angle"].replace("m", "-").replace("p", ".")) + 0.0  # + 0.0: m0 is 0


def read_bag(path: str | Path, range_m, azimuth_rad) -> Recording:
    """The sonar frames and poses of an MCAP bag on the grid (range_m, azimuth_rad) a checkpoint
    reads, its elevations in increasing order; refused naming the file where it is not an MCAP
    file, holds no frames, frames of another encoding or size, both image layouts, or elevation
    topics that do not hold one image per ping each (naming the topic)."""
    try:
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory
    except ImportError:
        raise MissingExtra(f"reading an MCAP bag needs the `ros` extra: {INSTALL}") from None
    path = regular_file(path, "--input")
    grid = (len(range_m), len(azimuth_rad))
    images, angles, frame_ids, tf = {}, {}, set(), []  # images: {topic: [(stamp, (R, A) pixels)]}
    try:
        with open(path, "rb") as f:
            reader, decode = make_reader(f), _Decoder(DecoderFactory())
            summary = reader.get_summary()
            topics = None  # an unindexed bag: every message is looked at, only ours decoded
            if summary is not None:
                topics = [c.topic for c in summary.channels.values() if _elevation(c.topic, path) is not None]
                if summary.statistics is not None:
                    _check_size(summary, topics, path, grid)
                topics += [TF_TOPIC]
            for schema, channel, message in reader.iter_messages(topics=topics):
                if channel.topic == TF_TOPIC:
                    transforms = decode(schema, channel, message).transforms
                    tf += [(_stamp(t.header), t.header.frame_id, t.child_frame_id, t.transform) for t in transforms]
                    continue
                if channel.topic not in angles:
                    angles[channel.topic] = _elevation(channel.topic, path)
                if angles[channel.topic] is not None:
                    image = decode(schema, channel, message)
                    pixels = _pixels(image, channel.topic, path, grid)
                    images.setdefault(channel.topic, []).append((_stamp(image.header), pixels))
                    frame_ids.add(image.header.frame_id)
    except (DataError, TooLarge, OSError):
        raise
    except Exception as err:  # the mcap readers raise many kinds on a damaged or foreign file
        text = str(err).strip().splitlines()
        raise ValueError(
            f"--input {path} is not an MCAP bag this learner can read ({text[0] if text else err!r})"
        ) from None
    topics = _image_topics(images, angles, path)
    if len(frame_ids) > 1:
        raise DataError(f"--input {path}: the sonar images name {len(frame_ids)} frames {sorted(frame_ids)}")
    stamps, energy = _pings(images, topics, path, grid)
    sensor = frame_ids.pop()
    transforms, parent, note = _poses(tf, sensor, stamps)
    episode = np.cumsum(np.r_[0, np.diff(stamps) >= DRIVE_GAP_S * 1e9]).astype(np.int64)
    frames = Frames(
        energyscape=energy,
        label=np.zeros((len(stamps), *grid), np.uint8),
        episode=episode,
        scenario=np.zeros(len(stamps), np.int64),
        scenarios=["recorded"],
        range_m=np.asarray(range_m, np.float64),
        azimuth_rad=np.asarray(azimuth_rad, np.float64),
        info={"folder": recorded_path(path)},
        pose=None if transforms is None else planar(transforms),
        elevation_deg=tuple(angles[t] for t in topics),
    )
    return Recording(frames, stamps, transforms, parent or "world", sensor, note)


class _Decoder:
    """Decodes the ROS 2 messages of a bag, a decoder per channel (only those read are decoded:
    a bag may hold messages of types this reader has no definition for)."""

    def __init__(self, factory):
        self.factory, self.decoders = factory, {}

    def __call__(self, schema, channel, message):
        if channel.id not in self.decoders:
            decoder = self.factory.decoder_for(channel.message_encoding, schema)
            if decoder is None:
                raise ValueError(f"{channel.topic} is encoded as {channel.message_encoding!r}, not ROS 2's cdr")
            self.decoders[channel.id] = decoder
        return self.decoders[channel.id](message.data)


def _elevation(topic: str, path: Path) -> float | None:
    """`topic_elevation`, refused naming the bag."""
    try:
        return topic_elevation(topic)
    except ValueError as err:
        raise DataError(f"--input {path}: {err}") from None


def _image_topics(images: dict, angles: dict, path: Path) -> list[str]:
    """The image topics read, in increasing elevation; refused where there are none, where both
    layouts (IMAGE_TOPIC and per-elevation topics) are mixed, or where two name one angle."""
    if not images:
        raise DataError(
            f"--input {path} holds no sonar images: sensor_msgs/Image 32FC1 on {IMAGE_TOPIC}, or one topic per "
            f"elevation {IMAGE_TOPIC}/elevation_<angle>_deg, as `python -m acoustic_sim export --format mcap` "
            "writes them"
        )
    if IMAGE_TOPIC in images and len(images) > 1:
        others = sorted(t for t in images if t != IMAGE_TOPIC)
        raise DataError(
            f"--input {path} holds images on {IMAGE_TOPIC} and on the elevation topics {others}: one bag holds "
            f"one layout; keep one (`mcap filter --exclude-topic-regex`)"
        )
    topics = sorted(images, key=lambda t: angles[t])
    for below, above in itertools.pairwise(topics):
        if angles[below] == angles[above]:
            raise DataError(f"--input {path}: the topics {below} and {above} name one elevation, {angles[below]:g} deg")
    return topics


def _pings(images: dict, topics: list[str], path: Path, grid: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(T,) int64 stamps [ns] and (T, E, R, A) float32 energyscapes of the pings, in time order:
    image k of each topic (in stamp order) is elevation e of ping k. Refused naming the topic
    where one holds another count of images, or stamps them otherwise, than the first."""
    first = topics[0]
    order = {t: np.argsort([s for s, _ in images[t]], kind="stable") for t in topics}
    stamps = np.array([images[first][i][0] for i in order[first]], np.int64)
    for topic in topics[1:]:
        if len(images[topic]) != len(stamps):
            raise DataError(
                f"--input {path}: {topic} holds {len(images[topic])} images, {first} {len(stamps)}: every elevation "
                "of a ping needs its image"
            )
        theirs = np.array([images[topic][i][0] for i in order[topic]], np.int64)
        if (differ := np.flatnonzero(theirs != stamps)).size:
            k = int(differ[0])
            raise DataError(
                f"--input {path}: {topic}'s image {k} (in time order) is stamped {_seconds(theirs[k])}, {first}'s "
                f"{_seconds(stamps[k])}: the images of one ping, one per elevation, share its stamp"
            )
    energy = np.empty((len(stamps), len(topics), *grid), np.float32)
    for e, topic in enumerate(topics):
        for k, i in enumerate(order[topic]):
            energy[k, e] = images[topic][i][1]
    return stamps, energy


def _check_size(summary, topics: list[str], path: Path, grid: tuple[int, int]) -> None:
    """Refuse a bag whose frames, as its summary counts them, would not fit in memory."""
    counts = {t: 0 for t in topics}
    for i, channel in summary.channels.items():
        if channel.topic in counts:
            counts[channel.topic] += summary.statistics.channel_message_counts.get(i, 0)
    images, pings = sum(counts.values()), max(counts.values(), default=0)
    check_fits(
        (images * 8 + pings) * grid[0] * grid[1],  # float32 images as read and stacked, uint8 labels
        f"--input {path} ({images:,} sonar images of {grid[0]} x {grid[1]})",
        "split the bag (`mcap filter --start/--end`) and predict a stretch at a time",
    )


def _stamp(header) -> int:
    return int(header.stamp.sec) * 10**9 + int(header.stamp.nanosec)


def _seconds(stamp_ns: int) -> str:
    return f"{int(stamp_ns) // 10**9}.{int(stamp_ns) % 10**9:09d} s"


def _pixels(image, topic: str, path: Path, grid: tuple[int, int]) -> np.ndarray:
    """An Image message's energyscape (R, A) float32, refused where not 32FC1 on the grid."""
    stamp = f"{image.header.stamp.sec}.{image.header.stamp.nanosec:09d} s"
    if image.encoding != "32FC1":
        raise DataError(f"--input {path}: the {topic} image at {stamp} is {image.encoding!r}, not 32FC1")
    if (image.height, image.width) != grid:
        raise DataError(
            f"--input {path}: the {topic} image at {stamp} is {image.height} x {image.width}, but the model "
            f"reads {grid[0]} ranges x {grid[1]} azimuths"
        )
    data = bytes(image.data)
    if image.step != 4 * image.width or len(data) != image.step * image.height:
        raise DataError(
            f"--input {path}: the {topic} image at {stamp} has {len(data)} bytes, not {4 * grid[0] * grid[1]}"
        )
    pixels = np.frombuffer(data, ">f4" if image.is_bigendian else "<f4").reshape(grid).astype(np.float32)
    if not np.isfinite(pixels).all():
        raise DataError(f"--input {path}: the {topic} image at {stamp} holds NaN or inf values")
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
