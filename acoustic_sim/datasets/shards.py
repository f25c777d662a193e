"""HDF5 dataset shards: the one interface between simulation and learning.

A shard holds whole episodes (robot drives). It is written under a temporary name and renamed
only when complete, so a file with the final name is always whole; a write that fails (a full
disk) removes the temporary file. Every dataset carries an HDF5 Fletcher-32 checksum, so a shard
damaged later fails `verify_shard` (and any read) instead of feeding wrong numbers to training.
Layout (all plain HDF5, readable with h5py or MATLAB's h5read):

    shard-00000.h5   attrs: format, format_version, frame_count, plan_id, suite, variant,
                            config (JSON), episodes (JSON), scenarios (JSON), package_version
      energyscape     float16 (frame, elevation, range, azimuth)   beamformed echo envelope
      elevation_deg   float64 (elevation,) the beams' elevations [deg] (one: a horizontal slice)
      lidar/ranges    float32 (frame, beam) [m], miss = inf
      lidar/image     uint8   (frame, range, azimuth)   1 where a LiDAR return falls
      pose            float64 (frame, 4, 4) sensor-to-world
      time            float64 (frame,) [s] since the episode's start
      episode         int32   (frame,) global episode index; windows never cross one
      scenario        int16   (frame,) index into the `scenarios` attribute
      range_m         float64 (range,) bin centres;  azimuth_rad float64 (azimuth,)
      signals         float16 (frame, mic, sample)  optional
      arrivals/...    optional, one row per echo with its `frame`
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from clitools.limits import input_file
from clitools.outputs import KeptErrorFile

FORMAT = "sonar2lidar-dataset"
FORMAT_VERSION = 2  # 2: energyscape (frame, elevation, range, azimuth) and elevation_deg
READABLE_VERSIONS = (1, 2)  # 1: energyscape (frame, range, azimuth), one slice at 0 deg
CHECKSUM = {"fletcher32": True}  # an HDF5 built-in filter: h5py and MATLAB verify it on every read
COMPRESSION = {"compression": "gzip", "compression_opts": 1, "shuffle": True, **CHECKSUM}  # MATLAB reads gzip


class DatasetError(ValueError):
    """A dataset folder or shard that cannot be used as asked (foreign, corrupt, other version)."""


@dataclass
class ShardFrames:
    """Frames of one shard, in episode order, ready to write."""

    energyscape: list[np.ndarray] = field(default_factory=list)
    lidar_ranges: list[np.ndarray] = field(default_factory=list)
    lidar_image: list[np.ndarray] = field(default_factory=list)
    pose: list[np.ndarray] = field(default_factory=list)
    time: list[np.ndarray] = field(default_factory=list)
    episode: list[np.ndarray] = field(default_factory=list)
    scenario: list[np.ndarray] = field(default_factory=list)
    signals: list[np.ndarray] = field(default_factory=list)
    arrivals: list[dict] = field(default_factory=list)

    @property
    def frame_count(self) -> int:
        return sum(len(e) for e in self.episode)


def write_shard(
    path: Path,
    frames: ShardFrames,
    *,
    attrs: dict,
    range_m: np.ndarray,
    azimuth_rad: np.ndarray,
    elevation_deg=(0.0,),
    threads: int | None = None,
) -> None:
    """Write a complete shard: to `<name>.tmp` first, then an atomic rename onto `path`. On any
    error (a full or read-only disk) the file is closed and the temporary removed. Energyscapes
    come (frame, elevation, range, azimuth), or (frame, range, azimuth) for one elevation. Chunks
    are compressed in `threads` threads (default: this process's cores, `devices.cpu_cores`)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with KeptErrorFile(tmp) as sink:  # HDF5 crashes after a failed write: it never sees one
            axes = (np.atleast_1d(elevation_deg), range_m, azimuth_rad)
            _write(sink, frames, attrs=attrs, axes=axes, threads=threads)
        sink.raise_kept(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)


def _write(
    tmp: Path | KeptErrorFile, frames: ShardFrames, *, attrs: dict, axes: tuple[np.ndarray, ...], threads: int | None
) -> None:
    def cat(parts: list[np.ndarray]) -> np.ndarray:  # one part (a shard from shared memory): no copy
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    energyscape = cat(frames.energyscape).astype(np.float16, copy=False)  # float16 from the sonar already
    if energyscape.ndim == 3:
        energyscape = energyscape[:, None]
    if energyscape.shape[1:] != tuple(map(len, axes)):
        raise ValueError(
            f"energyscapes of shape {energyscape.shape} do not match (elevation, range, azimuth) axes of "
            f"{tuple(map(len, axes))}"
        )
    elevation_deg, range_m, azimuth_rad = axes
    with h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["frame_count"] = frames.frame_count
        for key, value in attrs.items():
            f.attrs[key] = json.dumps(value) if isinstance(value, dict | list) else value
        escape = _rows(f, "energyscape", energyscape, threads)
        escape.attrs["dims"] = "frame, elevation, range, azimuth"
        escape.attrs["description"] = "beamformed echo envelope (linear, pressure re the call at 1 m)"
        elevation = f.create_dataset("elevation_deg", data=np.asarray(elevation_deg, np.float64), **CHECKSUM)
        elevation.attrs["units"] = "deg, 0 level, + up"
        f.create_dataset("range_m", data=range_m, **CHECKSUM).attrs["units"] = "m"
        f.create_dataset("azimuth_rad", data=azimuth_rad, **CHECKSUM).attrs["units"] = "rad, 0 ahead, + to the left"
        ranges = f.create_dataset("lidar/ranges", data=cat(frames.lidar_ranges).astype(np.float32), **COMPRESSION)
        ranges.attrs["units"] = "m, inf = no return"
        image = _rows(f, "lidar/image", cat(frames.lidar_image).astype(np.uint8), threads)
        image.attrs["dims"] = "frame, range, azimuth"
        image.attrs["description"] = "1 where a LiDAR return falls in the cell (the label)"
        f.create_dataset("pose", data=cat(frames.pose), **CHECKSUM).attrs["description"] = "4x4 sensor-to-world, z up"
        f.create_dataset("time", data=cat(frames.time), **CHECKSUM).attrs["units"] = "s since the episode's start"
        f.create_dataset("episode", data=cat(frames.episode).astype(np.int32), **CHECKSUM)
        f.create_dataset("scenario", data=cat(frames.scenario).astype(np.int16), **CHECKSUM)
        if frames.signals:
            _rows(f, "signals", cat(frames.signals).astype(np.float16), threads)
            f["signals"].attrs["dims"] = "frame, microphone, sample"
        if frames.arrivals:
            group = f.create_group("arrivals")
            for key in frames.arrivals[0]:
                group.create_dataset(key, data=cat([a[key] for a in frames.arrivals]), **COMPRESSION)
            group.attrs["description"] = "one row per echo; `frame` indexes the shard's frames"


def _rows(f: h5py.File, name: str, array: np.ndarray, threads: int | None) -> h5py.Dataset:
    """A compressed dataset chunked by frame, its chunks compressed in `threads` threads (`chunks`;
    None: on every core)."""
    from ..devices import cpu_cores
    from .chunks import write_rows

    dataset = f.create_dataset(name, shape=array.shape, dtype=array.dtype, chunks=(1, *array.shape[1:]), **COMPRESSION)
    write_rows(dataset, array, threads or cpu_cores())
    return dataset


REQUIRED = ("energyscape", "lidar/ranges", "lidar/image", "pose", "time", "episode", "scenario")
"""The datasets every shard holds, one row per frame (and the axes `range_m`, `azimuth_rad`)."""


def read_attrs(path: Path) -> dict:
    """The root attributes of a shard (JSON ones decoded), after checking that it is a regular
    file of our format and version holding every dataset of the layout, one row per frame."""
    path = Path(path)
    try:
        input_file(path, what="shard", max_bytes=math.inf)  # a FIFO named like a shard would never open
    except (OSError, ValueError) as err:
        raise DatasetError(str(err)) from None
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise DatasetError(f"{path} is not a readable HDF5 file ({str(err).strip().splitlines()[0]})") from None
    with f:
        attrs = {k: v for k, v in f.attrs.items()}
        missing = [k for k in (*REQUIRED, "range_m", "azimuth_rad") if k not in f]
        lengths = {len(f[k]) for k in REQUIRED if k in f and f[k].ndim}
    if attrs.get("format") != FORMAT:
        raise DatasetError(f"{path} is not a {FORMAT} shard (format attribute {attrs.get('format')!r})")
    version = int(attrs.get("format_version", -1))
    if version not in READABLE_VERSIONS:
        raise DatasetError(
            f"{path} has format_version {version}; this version of sonar2lidar reads {READABLE_VERSIONS}"
        )
    if missing or lengths != {int(attrs.get("frame_count", -1))}:
        raise DatasetError(f"{path} is incomplete or corrupt (missing {missing}, frame counts {sorted(lengths)})")
    for key in ("config", "episodes", "scenarios"):
        if key in attrs:
            try:
                attrs[key] = json.loads(attrs[key])
            except (TypeError, ValueError, RecursionError) as err:
                raise DatasetError(
                    f"{path}: its `{key}` attribute is not valid JSON ({err}); the shard is damaged"
                ) from None
    return attrs


def dataset_shards(folder: str | Path) -> list[Path]:
    """The shards of a dataset folder, in order, each checked by `read_attrs` (a foreign, damaged
    or partial file is refused naming it, before a reader trips over a missing dataset)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder} is not a folder; give a dataset folder (with shard-*.h5 files)")
    shards = sorted(folder.glob("shard-*.h5"))
    if not shards:
        variants = sorted(p.parent.name for p in folder.glob("*/shard-*.h5"))
        if variants:  # a suite of several variants writes one dataset a sub-folder
            listed = ", ".join(sorted(set(variants)))
            raise DatasetError(f"{folder} holds no shard-*.h5 files; its variants ({listed}) are datasets: give one")
        raise DatasetError(f"{folder} holds no shard-*.h5 files")
    for path in shards:
        attrs = read_attrs(path)
        if not isinstance(attrs.get("config"), dict):
            raise DatasetError(f"{path} has no `config` attribute (its rig as JSON); the shard is damaged")
    return shards


def one_run_shards(folder: str | Path) -> list[Path]:
    """`dataset_shards` of a folder an export reads as one drive: every shard of one run (one
    plan id) and none twice (a copy or a link would repeat its frames)."""
    folder = Path(folder)
    shards, seen = dataset_shards(folder), {}
    for path in shards:
        attrs = read_attrs(path)
        key = (attrs.get("plan_id"), attrs.get("shard"))
        if key in seen:
            raise DatasetError(
                f"{path} repeats {seen[key].name} (plan {key[0]}, shard {key[1]}): a copy or a link; keep one of them"
            )
        seen[key] = path
    plans = sorted({plan for plan, _ in seen}, key=str)
    if len(plans) > 1:
        raise DatasetError(
            f"{folder} holds shards of {len(plans)} runs (plans {', '.join(map(str, plans))}); a dataset folder holds "
            "one run: move the others to a folder of their own"
        )
    return shards


def check_outside(folder: str | Path, out: str | Path) -> None:
    """Refuse an export's `out` inside the dataset folder it reads: the file would become part
    of the dataset (one named like a shard breaks it; any other is mixed into what readers see)."""
    if Path(os.path.realpath(out)).is_relative_to(os.path.realpath(folder)):
        raise DatasetError(f"--out {out} lies inside the dataset {folder} being exported; write it elsewhere")


def finite_poses(f: h5py.File, path: Path) -> np.ndarray:
    """The shard's poses (frames, 4, 4), refused naming the first frame whose pose is not finite."""
    poses = f["pose"][:]
    bad = np.flatnonzero(~np.isfinite(poses).reshape(len(poses), -1).all(axis=1))
    if len(bad):
        raise DatasetError(f"{path}: the pose of frame {bad[0]} is not finite; the shard is damaged")
    return poses


def energyscapes(f: h5py.File, rows=slice(None)) -> tuple[np.ndarray, np.ndarray]:
    """A shard's energyscapes (frames, elevation, range, azimuth) and their elevations (E,) [deg],
    from either layout (format 1 held one slice at 0 deg, (frame, range, azimuth))."""
    energy = f["energyscape"][rows]
    if int(f.attrs.get("format_version", -1)) == 1:
        return energy[:, None], np.zeros(1)
    if "elevation_deg" not in f or energy.ndim != 4:
        raise DatasetError(f"{f.filename}: a format-2 shard without its (frame, elevation, range, azimuth) layout")
    return energy, f["elevation_deg"][:]


def verify_shard(path: Path) -> None:
    """Read every dataset of a shard in full, so HDF5 checks each chunk's checksum (and that it
    decompresses); raises DatasetError naming the first damaged dataset."""
    path = Path(path)
    where = "its metadata"
    try:
        with h5py.File(path, "r") as f:
            names: list[str] = []
            f.visit(lambda name: names.append(name) if isinstance(f[name], h5py.Dataset) else None)
            for where in names:
                dataset = f[where]
                if dataset.ndim == 0:
                    dataset[()]
                for start in range(0, len(dataset) if dataset.ndim else 0, 64):  # bounded memory
                    dataset[start : start + 64]
    except OSError as err:
        first = str(err).strip().splitlines()[0]
        raise DatasetError(f"{path} is damaged (in {where}: {first})") from None
