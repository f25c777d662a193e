"""One dataset shard as the learner reads it, checked before and after its arrays are read.

A shard is an HDF5 file of `acoustic_sim.datasets.shards` (the one interface between simulation
and learning), and the learner trusts nothing in it. Before any array is read: the file is a
regular file; it holds no link, external or virtual dataset (those read other files, anywhere on
the machine); the datasets read are stored under HDF5's Fletcher-32 checksum, which our writer
sets on every dataset, so damage is found on read; their types and shapes are the writer's; the
attributes that identify the shard (plan id, variant, shard index) are there. After: energyscapes
are finite and fit float16 (the type the learner holds them in), labels are 0 or 1, scenario
indices name one of the shard's scenarios and every episode is one contiguous run of frames.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from .inputs import regular_file
from .odometry import planar

FORMAT = "sonar2lidar-dataset"  # written by acoustic_sim.datasets.shards; the file format is the interface
FORMAT_VERSION = 2  # written by this version: energyscape (frame, elevation, range, azimuth), elevation_deg
READABLE_VERSIONS = (1, 2)  # 1: energyscape (frame, range, azimuth), one slice at 0 deg elevation
FLOAT16_MAX = float(np.finfo(np.float16).max)  # 65,504
# The datasets read and their dtype kinds (numpy: f float, i/u integer, b bool)
READ = {
    "energyscape": "fiu",
    "lidar/image": "fiub",
    "episode": "iu",
    "scenario": "iu",
    "range_m": "f",
    "azimuth_rad": "f",
}
ALSO_READ = {
    "time": "f",
    "pose": "f",
    "elevation_deg": "f",
}  # frame times (learn.ros for `predict --mcap`), sensor poses (memory)
MIN_GRID_CELLS = 7  # learn.metrics.ssim's window: a smaller grid fails in every validation
REDO = "regenerate it with `python -m acoustic_sim generate`, or move it out of the folder"


class DataError(ValueError):
    """A dataset that cannot be read as asked (missing, foreign, other version, inconsistent)."""


@dataclass(frozen=True)
class ShardHeader:
    """What a shard says of itself, read without its arrays.

    Attributes:
        path: The shard.
        plan_id, variant, index: The run (plan), physics variant and shard number that wrote it.
        frames, range_count, azimuth_count: Energyscape shape (T, E, R, A) without E.
        elevation_deg: The beams' elevations (E,) [deg]; (0.0,) for format 1's one level slice.
        scenarios: Scenario names the `scenario` dataset indexes.
        config: The settings it was simulated with.
        file_id: (device, inode): two names of one file (a link) share it.
        read_bytes: Bytes of its energyscapes and labels as stored (read whole, then converted).
    """

    path: Path
    plan_id: str
    variant: str
    index: int
    frames: int
    range_count: int
    azimuth_count: int
    scenarios: list[str]
    config: dict
    file_id: tuple[int, int]
    read_bytes: int
    elevation_deg: tuple[float, ...] = (0.0,)


@dataclass
class ShardArrays:
    """A shard's arrays as the learner holds them: energyscape (T, E, R, A) float16, label (T, R, A)
    uint8, episode and scenario (T,) int64, range_m (R,) [m], azimuth_rad (A,) [rad], pose (T, 3)
    planar sensor poses (x [m], y [m], yaw [rad]; `learn.odometry`), None where the shard has none."""

    energyscape: np.ndarray
    label: np.ndarray
    episode: np.ndarray
    scenario: np.ndarray
    range_m: np.ndarray
    azimuth_rad: np.ndarray
    pose: np.ndarray | None = None


def open_shard(path: Path) -> h5py.File:
    """The shard open for reading (a regular file: a FIFO would block h5py forever)."""
    regular_file(path, "shard")
    try:
        return h5py.File(path, "r")
    except OSError as err:
        first = str(err).strip().splitlines()[0]
        raise DataError(f"{path} is not a readable HDF5 file ({first}): {REDO}") from None


def read_header(path: Path) -> ShardHeader:
    """The shard's identity and shapes; refuses a foreign, linked or unchecksummed layout."""
    path = Path(path)
    with open_shard(path) as f:
        try:
            return _header(f, path)
        except OSError as err:  # an unreadable attribute or object header
            first = str(err).strip().splitlines()[0]
            raise DataError(f"{path} is damaged ({first}): {REDO}") from None


def _header(f: h5py.File, path: Path) -> ShardHeader:
    fmt = _text(f.attrs.get("format"))
    if fmt != FORMAT:
        raise DataError(f"{path} is not a {FORMAT} shard (its format attribute is {fmt!r})")
    raw = f.attrs.get("format_version")
    version = _integer(raw)
    if version not in READABLE_VERSIONS:
        found = version if version is not None else repr(raw)
        raise DataError(
            f"{path} has format_version {found}; this learner reads {', '.join(map(str, READABLE_VERSIONS))}"
        )
    _refuse_foreign_storage(f, path)
    sets = {name: _dataset(f, name, path) for name in READ}
    for name in ALSO_READ:
        if name in f:
            _dataset(f, name, path)
    plan_id, variant, index = _text(f.attrs.get("plan_id")), _text(f.attrs.get("variant")), f.attrs.get("shard")
    if not plan_id or variant is None or _integer(index) is None:
        raise DataError(f"{path} lacks the plan_id, variant or shard attribute that says which run wrote it: {REDO}")
    scenarios = _json_attr(f, "scenarios", path, list)
    if not scenarios or not all(isinstance(s, str) for s in scenarios):
        raise DataError(f"{path}: the scenarios attribute is not a list of scenario names: {REDO}")
    energyscape, label = sets["energyscape"], sets["lidar/image"]
    elevation_deg = _elevations(f, path, version)
    layout = (
        "(frame, range, azimuth)" if version == 1 else f"(frame, elevation, range, azimuth), E = {len(elevation_deg)}"
    )
    fits = (
        energyscape.ndim == 3 if version == 1 else energyscape.ndim == 4 and energyscape.shape[1] == len(elevation_deg)
    )
    if not fits:
        raise DataError(f"{path}: energyscape has shape {energyscape.shape}, expected {layout}: {REDO}")
    frame_shape = (energyscape.shape[0], *energyscape.shape[-2:])  # (T, R, A)
    frames_shape = frame_shape[:1]
    shapes = {
        "lidar/image": (label.shape == frame_shape, f"{frame_shape}, energyscape's frames, ranges and azimuths"),
        "episode": (sets["episode"].shape == frames_shape, f"{frames_shape}, one per frame"),
        "scenario": (sets["scenario"].shape == frames_shape, f"{frames_shape}, one per frame"),
        "range_m": (sets["range_m"].shape == frame_shape[1:2], f"{frame_shape[1:2]}, energyscape's ranges"),
        "azimuth_rad": (sets["azimuth_rad"].shape == frame_shape[2:], f"{frame_shape[2:]}, its azimuths"),
    }
    for name, (fits, expected) in shapes.items():
        if not fits:
            raise DataError(f"{path}: {name} has shape {sets[name].shape}, expected {expected}: {REDO}")
    if frame_shape[0] == 0:
        raise DataError(f"{path} holds no frames (an empty shard): {REDO}")
    if min(frame_shape[1:]) < MIN_GRID_CELLS:
        raise DataError(
            f"{path}: its grid of {frame_shape[1]} ranges x {frame_shape[2]} azimuths is smaller than the "
            f"{MIN_GRID_CELLS} x {MIN_GRID_CELLS} cells the image metrics (SSIM's window) need: {REDO}"
        )
    stat = os.stat(path)
    return ShardHeader(
        path=path,
        plan_id=plan_id,
        variant=variant,
        index=_integer(index),
        frames=frame_shape[0],
        range_count=frame_shape[1],
        azimuth_count=frame_shape[2],
        scenarios=scenarios,
        config=_json_attr(f, "config", path, dict),
        file_id=(stat.st_dev, stat.st_ino),
        read_bytes=energyscape.size * energyscape.dtype.itemsize + label.size * label.dtype.itemsize,
        elevation_deg=elevation_deg,
    )


def _elevations(f: h5py.File, path: Path, version: int) -> tuple[float, ...]:
    """The beams' elevations [deg]: format 1 holds one level slice; format 2 says which, each
    finite, in [-90, 90] and increasing (the order models read them in)."""
    if version == 1:
        return (0.0,)
    if "elevation_deg" not in f:
        raise DataError(f"{path} (format 2) has no elevation_deg axis: {REDO}")
    values = _dataset(f, "elevation_deg", path)[()]
    if values.ndim != 1 or not len(values) or not np.all(np.abs(values) <= 90) or np.any(np.diff(values) <= 0):
        raise DataError(f"{path}: elevation_deg {values!r} is not increasing angles in [-90, 90] deg: {REDO}")
    return tuple(float(v) for v in values)


def _refuse_foreign_storage(f: h5py.File, path: Path) -> None:
    """Refuse links (soft ones name other objects, external ones other files) and external or
    virtual datasets anywhere in the file: an HDF5 file may read any file on the machine."""
    links: list[tuple[str, int]] = []
    f.id.links.visit(lambda name, info: links.append((name.decode(errors="replace"), info.type)) and None, info=True)
    for name, kind in links:
        if kind != h5py.h5l.TYPE_HARD:
            link = f.get(name, getlink=True)
            external = isinstance(link, h5py.ExternalLink)
            target = f"{link.filename}:{link.path}" if external else getattr(link, "path", "?")
            raise DataError(
                f"{path}: {name} is a link to {target}, not data stored in the shard; links are refused (they can "
                f"read any file): {REDO}"
            )
    foreign: list[str] = []

    def visit(name: str, item) -> None:
        if isinstance(item, h5py.Dataset) and not foreign:
            if item.external:
                foreign.append(f"{name} is an HDF5 external dataset reading {', '.join(e[0] for e in item.external)}")
            elif item.is_virtual:
                sources = sorted({s.file_name for s in item.virtual_sources()})
                foreign.append(f"{name} is an HDF5 virtual dataset reading {', '.join(sources)}")

    f.visititems(visit)
    if foreign:
        raise DataError(f"{path}: {foreign[0]}; such datasets are refused (they can read any file): {REDO}")


def _dataset(f: h5py.File, name: str, path: Path) -> h5py.Dataset:
    """The dataset `name`: present, numeric, under the Fletcher-32 checksum."""
    item = f.get(name)
    if not isinstance(item, h5py.Dataset):
        what = "is a group" if item is not None else "is missing"
        raise DataError(f"{path}: the {name} dataset {what} (an incomplete or foreign shard): {REDO}")
    if item.dtype.kind not in {**READ, **ALSO_READ}[name]:
        raise DataError(f"{path}: {name} has dtype {item.dtype}, not the numbers the writer stores: {REDO}")
    if not item.fletcher32:
        raise DataError(
            f"{path}: {name} is stored without the Fletcher-32 checksum our writer sets, so damage could not be "
            f"found: {REDO}"
        )
    return item


def read_arrays(header: ShardHeader, seen_episodes: dict[int, Path]) -> ShardArrays:
    """The shard's arrays, their values checked (see the module docstring); `seen_episodes` maps
    the episodes of shards read before to their shard (an episode lies in one shard) and gains
    this shard's."""
    path = header.path
    with open_shard(path) as f:
        arrays = {}
        for name in (*READ, *(["pose"] if _has_poses(f, header) else [])):
            try:
                arrays[name] = f[name][()]
            except OSError as err:  # a checksum or decompression failure
                first = str(err).strip().splitlines()[0]
                raise DataError(f"{path}: {name} is damaged ({first}): {REDO}") from None
    for name in ("range_m", "azimuth_rad"):
        axis = arrays[name]
        if not (np.isfinite(axis).all() and (np.diff(axis) > 0).all()):
            raise DataError(f"{path}: {name} is not a finite, increasing axis: {REDO}")
    energyscape = arrays["energyscape"]
    return ShardArrays(
        energyscape=as_float16(
            energyscape[:, None] if energyscape.ndim == 3 else energyscape, f"{path}: energyscape", REDO
        ),
        label=_labels(arrays["lidar/image"], path),
        episode=_episodes(arrays["episode"], path, seen_episodes),
        scenario=_scenarios(arrays["scenario"], header),
        range_m=arrays["range_m"].astype(np.float64),
        azimuth_rad=arrays["azimuth_rad"].astype(np.float64),
        pose=_poses(arrays["pose"], path, header.frames) if "pose" in arrays else None,
    )


def _has_poses(f: h5py.File, header: ShardHeader) -> bool:
    """Whether the shard holds its frames' poses: a CHIRP recording imported without odometry
    stores identities, and says so in its config."""
    return "pose" in f and not str(header.config.get("poses", "")).startswith("identity")


def _poses(pose: np.ndarray, path: Path, frames: int) -> np.ndarray:
    """4 x 4 sensor-to-world poses -> planar (T, 3), refused where not finite or not (T, 4, 4)."""
    if pose.shape != (frames, 4, 4):
        raise DataError(f"{path}: pose has shape {pose.shape}, expected ({frames}, 4, 4): {REDO}")
    if not np.isfinite(pose).all():
        raise DataError(f"{path}: pose holds NaN or inf values: {REDO}")
    return planar(pose)


def as_float16(values: np.ndarray, what: str, advice: str) -> np.ndarray:
    """`values` as float16, refused (with the figure) where they are not finite or beyond
    float16's range (65,504), which the cast would turn into inf."""
    if values.dtype.kind == "f":
        bad = int(np.count_nonzero(~np.isfinite(values)))
        if bad:
            raise DataError(f"{what} holds {bad:,} NaN or inf values: {advice}")
    peak = max(float(values.max()), -float(values.min())) if values.size else 0.0
    if peak > FLOAT16_MAX:
        raise DataError(f"{what} holds values above float16's {FLOAT16_MAX:,.0f} (max {peak:.3g}): {advice}")
    return values.astype(np.float16, copy=False)


def _labels(label: np.ndarray, path: Path) -> np.ndarray:
    outside = ~((label == 0) | (label == 1))  # NaN is neither
    if outside.any():
        frame = int(np.argwhere(outside)[0][0])
        value = label[frame][outside[frame]][0].item()
        raise DataError(
            f"{path}: lidar/image holds {value!r} at frame {frame} ({int(outside.sum()):,} of its cells are outside "
            f"{{0, 1}} or NaN); the label is a 0/1 image: {REDO}"
        )
    return label.astype(np.uint8, copy=False)


def _episodes(episode: np.ndarray, path: Path, seen: dict[int, Path]) -> np.ndarray:
    episode = episode.astype(np.int64)
    starts = np.flatnonzero(np.r_[True, episode[1:] != episode[:-1]])
    runs = episode[starts]
    if len(np.unique(runs)) != len(runs):
        raise DataError(f"{path}: an episode's frames are split in two runs (episode ids {runs.tolist()[:8]}): {REDO}")
    shared = sorted(seen.keys() & set(runs.tolist()))
    if shared:
        raise DataError(
            f"{path}: episode {shared[0]} is also in {seen[shared[0]]}; a drive lies in one shard, so the folder mixes "
            "shards of different runs, or copies: keep one run's shards per folder"
        )
    seen.update(dict.fromkeys(runs.tolist(), path))
    return episode


def _scenarios(scenario: np.ndarray, header: ShardHeader) -> np.ndarray:
    scenario = scenario.astype(np.int64)
    outside = (scenario < 0) | (scenario >= len(header.scenarios))
    if outside.any():
        frame, count = int(np.argmax(outside)), len(header.scenarios)
        raise DataError(
            f"{header.path}: scenario holds index {scenario[frame].item()} at frame {frame}, outside "
            f"0..{count - 1} (its scenarios attribute names {count}): {REDO}"
        )
    return scenario


def _text(value) -> str | None:
    """A string attribute (h5py may give str, bytes or a numpy string), else None."""
    if isinstance(value, bytes | np.bytes_):
        return value.decode(errors="replace")
    return str(value) if isinstance(value, str) else None


def _integer(value) -> int | None:
    """An integer attribute (int or numpy integer), else None."""
    return int(value) if isinstance(value, int | np.integer) and not isinstance(value, bool) else None


def _json_attr(f: h5py.File, key: str, path: Path, kind: type):
    text = _text(f.attrs.get(key))
    if text is None:
        raise DataError(f"{path} has no {key} attribute (an incomplete or foreign shard): {REDO}")
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        raise DataError(
            f"{path}: its {key} attribute is not valid JSON (line {err.lineno}, column {err.colno}: {err.msg}): {REDO}"
        ) from None
    if not isinstance(value, kind):
        raise DataError(f"{path}: its {key} attribute is a JSON {type(value).__name__}, not a {kind.__name__}: {REDO}")
    return value
