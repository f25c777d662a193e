"""CHIRP in and out: the HDF5 recording format of the eRTIS lab (Cosys-Lab Hybrid In-air sonar
Recording Package), whose reader `cosys-chirppy` (extra `chirp`, CC BY-NC-SA) defines a valid file.

    python -m acoustic_sim export DATASET --format chirp --out sim.h5   # a dataset made with --signals
    python -m acoustic_sim import REC.h5 --format chirp --out data/rec    # a recording -> our shards

CHIRP's microphone array is the reference sensor: each of its captures (one ping) is a reference
capture, at a Unix time, and every other sensor is synced to them. Frames are X forward, Y left,
Z up, with the origin at the array; `to_origin` 4x4 transforms place each sensor.

Export writes one file per dataset with `format`, `format_version`, `reference_sensor` and
`n_reference_captures` at the root and, under `sensors/`, all 1:1 with the pings
(sync_mode "reference_capture"):
  acoustic_sensor_00      signals (N, samples, mics) float32, the sample rate, and the array's
                          nominal positions, as the processing assumes them
                          (calibration/receiver_relative_translations)
  acoustic_transmitter_00 the call (signals) at the emitter's position
  lidar_00                x, y, z, intensity points in the sensor frame, NaN-padded (points,
                          point_counts); a beam without a return is no point; intensity 1 (the
                          simulator has none)
  odometry_00             the poses (position, orientation [x, y, z, w], yaw); base_link is the
                          sensor frame (transforms/base_link_to_origin = identity); no velocities
Times are the drive's, stamped as `mcap_export.frame_stamps` stamps them.

Import processes the reference sensor's signals with our processing (`beamform.energyscape`, the
rig's call, grid and elevations) using the file's microphone positions and sample rate; a sample
rate other than the call's is refused (set `--set sonar.chirp.*` to the call that was recorded).
`--set processing.elevation_deg=[-20,0,20]` gives each ping one image per elevation, as generate
does: shards of (ping, elevation, range, azimuth) with their `elevation_deg` axis. The LiDAR
label is a 2D scan taken from the 3D points: moved into the sonar's frame with the file's
transforms, the points within `plane_tolerance_m` of the sonar's plane (|z|) are binned to the
beams of the rig's LiDAR azimuths (nearest beam, elevation 0) and each beam keeps its nearest
point inside the LiDAR's range limits; then `lidar_image` makes the label as the simulator does.
Poses come from the first odometry sensor through the file's base_link transform (identity
when there is none). A pause longer than `episode_gap_s` between pings starts a new episode
(windows never cross it); each episode is one shard.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
import warnings
from pathlib import Path

import h5py
import numpy as np

from clitools.outputs import KeptErrorFile, atomic_folder, atomic_output, check_output

from ..config import ChirpConfig, LidarConfig, SonarConfig
from ..datasets.shards import COMPRESSION, check_outside, finite_poses, one_run_shards
from ..engine.lidar import lidar_image, ranges_to_points
from . import EPISODE_GAP_S, PLANE_TOLERANCE_M, chirp_input
from .chirp_dataset import ImportedPings, write_card, write_manifest, write_shards
from .mcap_export import frame_stamps

FORMAT, FORMAT_VERSION = "chirp", "2.1"
ACOUSTIC, TRANSMITTER, LIDAR, ODOMETRY = "acoustic_sensor_00", "acoustic_transmitter_00", "lidar_00", "odometry_00"
BLOCK = 64  # pings read and processed at once


# ---------------------------------------------------------------------------------------- export


def _read_drive(shards: list[Path]) -> dict:
    """Everything of a dataset but its signals (ranges, poses, times, episode per frame, the rig),
    checking that every shard holds signals and that all share one rig."""
    drive, keys, sim = {"ranges": [], "pose": [], "time": []}, [], None
    for i, path in enumerate(shards):
        with h5py.File(path, "r") as f:
            if "signals" not in f:
                raise ValueError(
                    f"{path} holds no microphone signals: a CHIRP file carries the signals, so generate the "
                    "dataset with --signals"
                )
            config = json.loads(f.attrs["config"])["sim"]
            if sim is not None and config != sim:
                raise ValueError(f"{path} was simulated with another rig than {shards[0].name}: one file, one rig")
            sim = config
            want = (f["pose"].shape[0], len(config["sonar"]["microphones_m"]), config["sonar"]["record_samples"])
            if f["signals"].shape != want:
                raise ValueError(
                    f"{path} holds signals of shape {f['signals'].shape}, not (frames, microphones, samples) = {want} "
                    "as its rig says; the shard is damaged"
                )
            drive["ranges"].append(f["lidar/ranges"][:])
            drive["pose"].append(finite_poses(f, path))
            drive["time"].append(f["time"][:])
            keys += [(i, int(e)) for e in f["episode"][:]]  # episodes restart in every shard
    index = {key: n for n, key in enumerate(dict.fromkeys(keys))}
    return {k: np.concatenate(v) for k, v in drive.items()} | {
        "episode": np.array([index[k] for k in keys]),
        "sim": sim,
    }


def _sensor(f: h5py.File, name: str, kind: str, to_origin: np.ndarray, stamps: np.ndarray, **attrs) -> h5py.Group:
    """sensors/<name>, one capture per ping, placed by `to_origin` (4x4, sensor -> origin)."""
    group = f.create_group(f"sensors/{name}")
    group.attrs.update(sensor_type=kind, sync_mode="reference_capture", reference_frame="origin", **attrs)
    group.create_dataset("calibration/to_origin", data=to_origin)
    group.create_dataset("data/timestamps", data=stamps)
    return group


def _points(ranges: np.ndarray, lidar: LidarConfig) -> tuple[np.ndarray, np.ndarray]:
    """Scans (N, beams) -> x, y, z, intensity points (N, most returns, 4) float32, returns first
    and NaN after, and the number of returns per scan."""
    points = ranges_to_points(ranges, lidar).astype(np.float32)  # NaN where a beam has no return
    found = np.isfinite(points[..., 0])
    counts = found.sum(axis=1).astype(np.int32)
    cloud = np.full((len(points), max(int(counts.max(initial=0)), 1), 4), np.nan, np.float32)
    for k in range(len(points)):
        cloud[k, : counts[k], :3], cloud[k, : counts[k], 3] = points[k, found[k]], 1.0
    return cloud, counts


def _write_chirp(f: h5py.File, shards: list[Path], drive: dict, *, source: str, check_disk) -> int:
    """The CHIRP file's content into the open file `f`; `check_disk()` (raising on a failed write)
    is called after each block of signals. Returns the number of LiDAR points."""
    from scipy.spatial.transform import Rotation

    sonar, n = drive["sim"]["sonar"], len(drive["time"])
    stamps = frame_stamps(drive["episode"], drive["time"]) / 1e9  # Unix seconds, float64 (0.24 us steps)
    cloud, counts = _points(drive["ranges"], LidarConfig(**drive["sim"]["lidar"]))
    mics, poses = np.asarray(sonar["microphones_m"], dtype=np.float64), drive["pose"]
    rate, samples = float(sonar["chirp"]["sample_rate_hz"]), int(sonar["record_samples"])
    emitter = np.eye(4)
    emitter[:3, 3] = sonar["emitter_m"]
    f.attrs.update(format=FORMAT, format_version=FORMAT_VERSION, reference_sensor=ACOUSTIC)
    f.attrs.update(n_reference_captures=n, source=source)
    acoustic = _sensor(f, ACOUSTIC, "acoustic_sensor", np.eye(4), stamps, sample_rate_hz=rate)
    acoustic.attrs["num_channels"] = len(mics)
    acoustic.create_dataset("calibration/receiver_relative_translations", data=mics)
    signals = acoustic.create_dataset(
        "data/signals", (n, samples, len(mics)), np.float32, chunks=(1, samples, len(mics)), **COMPRESSION
    )
    done = 0
    for path in shards:
        with h5py.File(path, "r") as shard:
            for first in range(0, len(shard["signals"]), BLOCK):  # (ping, mic, sample) -> (ping, sample, mic)
                block = shard["signals"][first : first + BLOCK].astype(np.float32).transpose(0, 2, 1)
                signals[done : done + len(block)] = block
                done += len(block)
                check_disk()
    call = ChirpConfig(**sonar["chirp"]).samples().astype(np.float32)
    _sensor(f, TRANSMITTER, "acoustic_transmitter", emitter, stamps, sample_rate_hz=rate).create_dataset(
        "data/signals", data=call
    )
    lidar = _sensor(f, LIDAR, "lidar", np.eye(4), stamps, max_points=cloud.shape[1])
    lidar.create_dataset("data/points", data=cloud, chunks=(1, *cloud.shape[1:]), **COMPRESSION)
    lidar.create_dataset("data/point_counts", data=counts)
    odometry = _sensor(f, ODOMETRY, "odometry", np.eye(4), stamps, source="simulation")
    unknown = np.full((n, 3), np.nan)  # velocities are not simulated
    for key, value in {
        "position": poses[:, :3, 3],
        "orientation": Rotation.from_matrix(poses[:, :3, :3]).as_quat(),  # x, y, z, w
        "yaw": np.arctan2(poses[:, 1, 0], poses[:, 0, 0]),
        "linear_velocity": unknown,
        "angular_velocity": unknown,
        "pose_covariance": np.zeros((n, 6, 6)),  # the simulated pose is exact
        "twist_covariance": np.full((n, 6, 6), np.nan),
    }.items():
        odometry.create_dataset(f"data/{key}", data=value)
    f.create_dataset("transforms/base_link_to_origin", data=np.eye(4))  # the robot is the sensor
    return int(counts.sum())


def export_chirp(dataset: str | Path, out: str | Path, *, overwrite: bool = False) -> dict:
    """Write every frame of a dataset folder generated with `--signals` as one CHIRP file.

    `out` is written under a temporary name and renamed when whole (`clitools.outputs`): an
    existing file is replaced only with `overwrite`, a file of the dataset never. A failed write
    (a full disk) is one OSError naming `out`, and leaves nothing behind."""
    from .. import __version__

    folder, out = Path(dataset), Path(out)
    check_output(out, overwrite=overwrite, inputs=[folder])  # refused before any reading
    shards = one_run_shards(folder)  # each checked: foreign, damaged, repeated files are refused naming them
    drive = _read_drive(shards)
    check_outside(folder, out)
    source = f"sonar2lidar {__version__} simulation of {folder}"
    with atomic_output(out, overwrite=overwrite, inputs=[folder]) as tmp:
        # A failed write inside HDF5 makes its close fail half way, and the objects left behind
        # crash the process when freed; so HDF5 writes through a file that keeps the first error
        # and drops the rest, closes cleanly, and the error is raised after.
        sink = KeptErrorFile(tmp)
        try:
            with h5py.File(sink, "w") as f:
                points = _write_chirp(f, shards, drive, source=source, check_disk=lambda: sink.raise_kept(out))
        finally:
            sink.close()
        sink.raise_kept(out)
    return {"out": str(out), "frames": len(drive["time"]), "shards": len(shards), "points": points}


# ---------------------------------------------------------------------------------------- import


def planar_scan(points: np.ndarray, lidar: LidarConfig, *, plane_tolerance_m: float = PLANE_TOLERANCE_M) -> np.ndarray:
    """A 2D scan from 3D points in the sonar's frame: the points with |z| <= plane_tolerance_m,
    each given to the nearest azimuth of `lidar`'s beams; per beam the nearest point's range in
    the xy plane, within the LiDAR's range limits.

    Args:
        points: x, y, z [m], shape (P, >=3); NaN rows are ignored.
        lidar: The scan's beams (its azimuths; elevations are not used).

    Returns:
        Ranges [m], float32 (lidar.azimuth_count,); inf = no point.
    """
    x, y, z = np.asarray(points, dtype=np.float64)[:, :3].T
    with np.errstate(invalid="ignore"):
        near = np.abs(z) <= plane_tolerance_m  # False for NaN
    r, azimuth = np.hypot(x[near], y[near]), np.rad2deg(np.arctan2(y[near], x[near]))
    count = lidar.azimuth_count
    if count < 2:
        raise ValueError("a 2D scan from points needs a LiDAR of two or more beams (lidar.azimuth_count)")
    step = (lidar.azimuth_max_deg - lidar.azimuth_min_deg) / (count - 1)
    # Degrees past the first beam, wrapped so that any sector (also one across +-180 deg) bins
    # alike and a point half a step before the first beam still falls on it.
    past = np.mod(azimuth - lidar.azimuth_min_deg + step / 2, 360.0) - step / 2
    beam = np.rint(past / step).astype(np.int64)
    if count * step >= 360.0 - 1e-9:  # a full circle: the last beam's neighbour is the first
        beam %= count
    keep = (beam >= 0) & (beam < count) & (r >= lidar.range_min_m) & (r <= lidar.range_max_m)
    ranges = np.full(count, np.inf)
    np.minimum.at(ranges, beam[keep], r[keep])
    return ranges.astype(np.float32)


def _warn_if_other_call(data, chirp, path) -> None:
    """Our matched filter uses the rig's call: say so when the file's transmitter emitted another."""
    transmitter = next(iter(data.get_sensors_by_type("acoustic_transmitter")), None)
    emitted = None if transmitter is None else transmitter.get_emitted_signal()
    if emitted is None:
        return
    ours = chirp.samples()
    emitted = np.asarray(emitted, dtype=np.float64).reshape(-1)
    same = len(emitted) == len(ours) and np.dot(emitted, ours) >= 0.99 * np.linalg.norm(emitted) * np.linalg.norm(ours)
    if not same:
        warnings.warn(
            f"{path}: its transmitter emitted another call ({len(emitted)} samples) than the rig's "
            f"({len(ours)}); the matched filter uses the rig's: give the recorded call with --set sonar.chirp.*",
            stacklevel=3,
        )


def episodes_of(stamps: np.ndarray, gap_s: float) -> np.ndarray:
    """Episode index per ping: a new episode wherever the time since the previous ping is over
    `gap_s` [s]."""
    return np.concatenate([[0], np.cumsum(np.diff(stamps) > gap_s)]).astype(np.int64)


def _check_import(path: Path, out: Path, rig) -> None:
    """Refuse, before reading any ping, an --out that is not empty and a file that is not CHIRP or
    does not hold its own data (`chirp_input.check_file`)."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a new folder for the dataset")
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"--out {out} is not an empty folder; choose a new one")
    chirp_input.check_file(path)


def _energyscapes(acoustic, sonar: SonarConfig, processing, path: Path, *, device) -> np.ndarray:
    """Our processing of every ping of the sensor, BLOCK pings at once: float16 (pings, E, R, A),
    E the elevations of `processing` (1 for one angle); signals it refuses (NaN, overflowing) are
    named by file, sensor and pings."""
    from ..engine.beamform import energyscape

    count, shape = acoustic.signals.shape[0], (np.size(processing.elevation_deg), *processing.grid.shape)
    energy = np.empty((count, *shape), np.float16)
    for first in range(0, count, BLOCK):  # (ping, sample, mic) -> (ping, mic, sample)
        block = np.asarray(acoustic.signals[first : first + BLOCK], dtype=np.float32).transpose(0, 2, 1)
        try:
            images = energyscape(block, sonar, processing, device=device)  # (n, R, A) or (n, E, R, A)
            energy[first : first + len(block)] = images.reshape(len(block), *shape)
        except ValueError as err:
            last = first + len(block) - 1
            raise ValueError(f"{path}: {acoustic.name}'s pings {first}..{last}: {err}") from None
    return energy


def _lidar_truth(
    data, acoustic, planar: LidarConfig, count: int, plane_tolerance_m: float, path: Path
) -> tuple[np.ndarray, str | None]:
    """The 2D scan of each ping (`planar_scan` of the first LiDAR's points moved into the sonar's
    frame), float32 (count, beams) [m], and the LiDAR's name; all inf and None without one."""
    ranges = np.full((count, planar.azimuth_count), np.inf, np.float32)
    scanner = next(iter(data.get_sensors_by_type("lidar")), None)
    if scanner is None:
        return ranges, None
    try:
        move = data.get_transform(scanner.name, acoustic.name)  # LiDAR frame -> sonar frame
    except (ValueError, KeyError) as err:  # numpy's LinAlgError is a ValueError
        raise ValueError(f"{path}: no transform from {scanner.name} to {acoustic.name} ({err})") from None
    if not (np.isfinite(move).all() and abs(np.linalg.det(move[:3, :3])) > 1e-9):
        raise ValueError(
            f"{path}: the transform from {scanner.name} to {acoustic.name} (their calibration/to_origin) is not a "
            f"finite rigid transform ({np.array2string(move[:3, :3].ravel(), precision=3)}); fix the file's "
            "calibration"
        )
    found = 0  # points of any height
    for i in range(count):
        xyz = np.asarray(chirp_input.capture(scanner, i, path)["points"], dtype=np.float64)[:, :3]
        found += int(np.isfinite(xyz).all(axis=1).sum())
        ranges[i] = planar_scan(xyz @ move[:3, :3].T + move[:3, 3], planar, plane_tolerance_m=plane_tolerance_m)
    if not found:
        raise ValueError(f"{path}: {scanner.name} holds no points in its {count} captures; it cannot label the pings")
    if not np.isfinite(ranges).any():
        raise ValueError(
            f"{path}: none of the {found:,} points of {scanner.name} lies within {plane_tolerance_m:g} m of the "
            "sonar's plane (and the LiDAR's range limits); widen --plane-tolerance if the LiDAR is mounted higher"
        )
    return ranges, scanner.name


def import_chirp(
    path: str | Path,
    out: str | Path,
    rig,
    *,
    plane_tolerance_m: float = PLANE_TOLERANCE_M,
    episode_gap_s: float = EPISODE_GAP_S,
    device=None,
) -> dict:
    """A CHIRP recording -> a dataset folder of our shards (one per episode), a manifest and a
    short card, for `learn evaluate` and `learn predict`; returns what was written.

    Args:
        path: The CHIRP file.
        out: A new or empty folder.
        rig: `SimConfig` whose call (sonar.chirp), processing (grid, elevations) and LiDAR
            azimuths are used; the file gives the microphone positions and the sample rate.
        plane_tolerance_m: Half-height of the slab around the sonar's plane (z = 0) whose LiDAR
            points make the 2D scan [m].
        episode_gap_s: A longer pause between pings starts a new episode [s].
    """
    t0, path, out = time.perf_counter(), Path(path), Path(out)
    for option, value in (("--plane-tolerance", plane_tolerance_m), ("--episode-gap", episode_gap_s)):
        if not value >= 0:  # NaN too: it compares false, so no point would be near and no pause long
            unit = "metres" if option == "--plane-tolerance" else "seconds"
            raise ValueError(f"{option} {value}: give a number of {unit} >= 0 (inf: no limit)")
    _check_import(path, out, rig)
    planar = dataclasses.replace(rig.lidar, elevation_min_deg=0.0, elevation_max_deg=0.0, elevation_count=1)
    with chirp_input.open_chirp(path) as data:
        try:
            acoustic, mics, rate = chirp_input.microphones(data, rig.sonar.chirp.sample_rate_hz, path)
            chirp_input.check_room(
                acoustic.signals.shape, dataclasses.replace(rig, lidar=planar), out, path, block=BLOCK
            )
            _warn_if_other_call(data, rig.sonar.chirp, path)
            stamps = chirp_input.ping_stamps(acoustic, path)
            sonar = chirp_input.recorded_sonar(rig.sonar, mics, acoustic.signals.shape[1], f"{path}: {acoustic.name}")
            energy = _energyscapes(acoustic, sonar, rig.processing, path, device=device)
            ranges, lidar_name = _lidar_truth(data, acoustic, planar, len(stamps), plane_tolerance_m, path)
            poses, pose_source = chirp_input.recorded_poses(data, acoustic, len(stamps), path)
        except KeyError as err:  # a dataset or attribute the format requires, missing
            raise ValueError(f"{path}: the file lacks part of the CHIRP format ({err}); is it whole?") from None
    rig = dataclasses.replace(rig, sonar=sonar, lidar=planar)
    grid, scenario = rig.processing.grid, path.stem
    options = {"plane_tolerance_m": plane_tolerance_m, "episode_gap_s": episode_gap_s}
    source = {"file": path.name, "bytes": path.stat().st_size, "pings": len(stamps), "first_unix_s": stamps[0]}
    plan_id = hashlib.sha256(json.dumps([source, options, rig.to_dict()], default=str).encode()).hexdigest()[:16]
    config = {"source": source, "import": options, "poses": pose_source, "sim": rig.to_dict()}
    pings = ImportedPings(
        stamps=stamps,
        energyscape=energy,
        elevation_deg=np.array(rig.processing.elevations_deg),
        lidar_ranges=ranges,
        lidar_image=lidar_image(ranges, planar, grid),
        pose=poses,
        episode=episodes_of(stamps, episode_gap_s),
    )
    try:
        with atomic_folder(out, overwrite=False, inputs=[path]) as stage:  # nothing under `out` until all is written
            entries = write_shards(stage, pings, grid, config, plan_id=plan_id, scenario=scenario)
            write_manifest(stage, entries, config, plan_id=plan_id, scenario=scenario, lidar=lidar_name)
            write_card(stage, pings, grid, config, lidar=lidar_name, microphones=len(mics), rate_hz=rate)
    except FileExistsError:  # another process wrote into --out meanwhile (not --overwrite's case: never for CHIRP)
        raise FileExistsError(
            f"--out {out} was filled by another process while this import ran; its files are kept: give a new --out"
        ) from None
    return {
        "out": str(out),
        "pings": len(stamps),
        "episodes": len(entries),
        "lidar": lidar_name,
        "returns_per_scan": float(np.isfinite(ranges).sum(axis=1).mean()),
        "poses": pose_source,
        "seconds": time.perf_counter() - t0,
    }
