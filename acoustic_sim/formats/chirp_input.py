"""What a CHIRP file must be before `chirp.import_chirp` or `calibrate` reads its pings, and how
they are read: the reference reader (`open_chirp`, the `chirp` extra), the file's array as our
sonar (`recorded_sonar`) and its pings as a calibration's recordings (`chirp_recordings`).

A recording comes from elsewhere, so nothing in it is taken on trust: the file is a regular one
(a FIFO would never end) and holds its own data (an HDF5 external link, external or virtual
dataset can read any file on this machine), checked with h5py before the CHIRP reader opens it;
its microphones (`microphones`) have real signals, finite positions and a positive sample rate,
one increasing time per ping (`ping_stamps`), and a ping count this machine's memory and the
output's disk can take (`check_room`: a header may claim a billion pings never written).
Sensors synced to the pings are read a capture a ping (`capture`: a file holding fewer captures
than pings is named), and odometry gives finite poses (`recorded_poses`).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import h5py
import numpy as np

from clitools.limits import check_fits, check_memory, free_disk_bytes, input_file

from ..config import SonarConfig
from ..datasets.plan import frame_bytes
from ..extras import MissingExtra

MOST_OBJECTS = 100_000  # groups and datasets a recording may hold (one per sensor stream: tens)
MOST_CALIBRATION_VALUES = 1_000_000  # a calibration dataset (transforms, positions) is read whole on opening
BLOCK_COPIES = 4  # a block of pings in memory: as read, as float32, transposed, and the beamformer's work


def check_file(path: Path) -> None:
    """A regular HDF5 file of format "chirp" whose objects all live inside it and whose
    calibration is of calibration's size; ValueError naming the file and the object otherwise."""
    input_file(path, what="CHIRP file", max_bytes=math.inf)  # read lazily: its claims are checked, not its size
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise ValueError(f"{path} is not a readable HDF5 file ({str(err).splitlines()[0]})") from None
    with f:
        kind = f.attrs.get("format")
        kind = kind.decode() if isinstance(kind, bytes) else kind
        if kind != "chirp":
            raise ValueError(f"{path} is not a CHIRP file (its format attribute is {kind!r}, not 'chirp')")
        _check_objects(f, path)


def _check_objects(f: h5py.File, path: Path) -> None:
    """Walk every link of the file (not following any out of it): refuse external links,
    external and virtual datasets, and calibration datasets too large to be calibration."""
    pending, seen = [f], set()
    while pending:
        group = pending.pop()
        for name in group:
            link = group.get(name, getlink=True)
            where = f"{group.name.rstrip('/')}/{name}"
            if isinstance(link, h5py.ExternalLink):
                _refuse(path, where, f"an external link to {link.filename}:{link.path}")
            if isinstance(link, h5py.SoftLink):
                continue  # a name for an object inside the file, walked where it lives
            item = group[name]
            address = h5py.h5o.get_info(item.id).addr  # hard links to one object: walk it once
            if address in seen:
                continue
            seen.add(address)
            if len(seen) > MOST_OBJECTS:
                raise ValueError(f"{path} holds more than {MOST_OBJECTS:,} HDF5 objects; is it a recording?")
            if isinstance(item, h5py.Group):
                pending.append(item)
                continue
            if item.is_virtual:
                files = sorted({source.file_name for source in item.virtual_sources()})
                _refuse(path, where, f"a virtual dataset reading {', '.join(files)}")
            if item.external:
                _refuse(path, where, f"an external dataset reading {', '.join(str(e[0]) for e in item.external)}")
            if "/calibration/" in where and item.size > MOST_CALIBRATION_VALUES:
                raise ValueError(
                    f"{path}: {where} holds {item.size:,} values ({item.shape}); calibration is matrices and positions"
                )


def _refuse(path: Path, where: str, what: str) -> None:
    raise ValueError(
        f"{path}: {where} is {what}; an imported recording must hold its own data (these can read any file on "
        "this machine): copy the data into the file (h5repack, or h5py) and import that"
    )


def microphones(data, call_rate_hz: float, path: Path) -> tuple[object, np.ndarray, float]:
    """The file's reference sensor (else its first acoustic sensor), checked to hold signals, one
    position per channel and our call's sample rate; returns it, the microphone positions
    (channels, 3) [m] and the sample rate [Hz]."""
    # Sensors are tested against None: chirppy's sensors have a length, so an empty one is falsy.
    acoustic = data.sensors.get(str(data.reference_sensor))
    if acoustic is None:
        acoustic = next(iter(data.get_sensors_by_type("acoustic_sensor")), None)
    if acoustic is None or acoustic.signals is None or acoustic.get_receiver_positions() is None:
        raise ValueError(
            f"{path} holds no microphone data (an acoustic_sensor with data/signals and "
            "calibration/receiver_relative_translations)"
        )
    _, _, channels = check_signals(acoustic, path)
    mics = np.asarray(acoustic.get_receiver_positions())
    if mics.dtype.kind not in "fiu" or not np.isfinite(mics).all():
        raise ValueError(f"{path}: {acoustic.name}'s microphone positions are not finite numbers ({mics.dtype})")
    mics, rate = mics.astype(np.float64), sample_rate(acoustic, path)
    if mics.shape != (channels, 3):
        raise ValueError(f"{path}: {channels} microphone channels but positions of shape {mics.shape}")
    if abs(rate - call_rate_hz) > 1e-6 * call_rate_hz:
        raise ValueError(
            f"{path}: the microphones were sampled at {rate:g} Hz, but our call is sampled at {call_rate_hz:g} Hz; "
            f"give the recorded call with --set sonar.chirp.sample_rate_hz={rate:g} (and its frequencies)"
        )
    return acoustic, mics, rate


def ping_stamps(acoustic, path: Path) -> np.ndarray:
    """Unix time of each ping [s], float64 (pings,), checked to increase."""
    stamps = np.asarray(acoustic.get_timestamps(), dtype=np.float64)
    if len(stamps) != acoustic.signals.shape[0] or not np.all(np.diff(stamps) > 0):
        raise ValueError(f"{path}: {acoustic.name}'s timestamps are not one increasing time per ping")
    return stamps


def check_signals(acoustic, path: Path) -> tuple[int, int, int]:
    """The reference sensor's signals: a (pings, samples, channels) dataset of real numbers with
    one timestamp per ping; returns its shape."""
    signals = acoustic.signals
    if signals.ndim != 3:
        raise ValueError(
            f"{path}: {acoustic.name}'s signals have shape {signals.shape}; CHIRP stores them as "
            "(pings, samples, channels)"
        )
    if signals.dtype.kind == "c":
        raise ValueError(
            f"{path}: {acoustic.name}'s signals are complex ({signals.dtype}); import takes the real microphone "
            "samples (as recorded): store their real part (or whatever real signal was recorded) and import that"
        )
    if signals.dtype.kind not in "fiu":
        raise ValueError(f"{path}: {acoustic.name}'s signals are {signals.dtype}, not real numbers")
    stamps = acoustic.timestamps
    if stamps is None or stamps.shape != signals.shape[:1] or stamps.dtype.kind not in "fiu":
        shape = None if stamps is None else stamps.shape
        raise ValueError(
            f"{path}: {acoustic.name} has timestamps of shape {shape} for {signals.shape[0]:,} pings; "
            "CHIRP gives one time (Unix seconds) per ping"
        )
    if signals.shape[0] == 0:
        raise ValueError(f"{path}: {acoustic.name} holds no pings (its signals have 0 captures); nothing to import")
    return signals.shape


def sample_rate(acoustic, path: Path) -> float:
    """The sensor's sample_rate_hz attribute as a positive, finite number [Hz]."""
    value = acoustic.sample_rates
    try:
        rate = float(np.asarray(value).item())
    except (TypeError, ValueError):
        rate = math.nan
    if not (math.isfinite(rate) and rate > 0):
        shown = repr(value) if isinstance(value, str | bytes) or np.ndim(value) else value
        raise ValueError(
            f"{path}: {acoustic.name}'s sample_rate_hz is {shown}; a recording needs its sample rate, a positive "
            "number of Hz: fix that attribute"
        )
    return rate


def check_room(shape: tuple[int, int, int], rig, out: Path, path: Path, *, block: int) -> None:
    """Refuse a recording whose pings this machine cannot hold in memory (the energyscapes,
    labels and poses of all its pings, and `block` pings of signals) or the disk of `out` cannot
    take, before anything is read: a header may claim pings that were never written."""
    pings, samples, channels = shape
    disk, memory = frame_bytes(rig, keep_signals=False)
    check_memory(
        pings * memory + BLOCK_COPIES * min(block, pings) * samples * channels * 4,  # float32 samples
        what=f"{path}: {pings:,} pings of {samples:,} samples x {channels} channels",
        advice="import a shorter recording (split it), or on a machine with more memory",
    )
    check_fits(
        pings * disk,
        available=free_disk_bytes(out),
        what=f"the dataset of {pings:,} pings",
        room=f"free on the disk of {out}",
        advice="give another --out",
    )


def capture(sensor, index: int, path: Path) -> dict:
    """Capture `index` of a sensor synced to the pings; ValueError naming the file and sensor when
    the file holds fewer captures than pings (or a part of one is missing)."""
    try:
        return sensor.at_reference_capture(index)
    except (IndexError, KeyError, ValueError) as err:
        raise ValueError(
            f"{path}: {sensor.name} has no whole capture for ping {index} ({type(err).__name__}: {err}); CHIRP "
            "gives a sensor synced to the pings one capture per ping"
        ) from None


def recorded_poses(data, acoustic, count: int, path: Path) -> tuple[np.ndarray, str]:
    """Sonar-to-odom poses (count, 4, 4) from the first odometry sensor and the file's base_link
    transform, or identities with the reason."""
    from scipy.spatial.transform import Rotation

    identity = np.tile(np.eye(4), (count, 1, 1))
    odometry = next(iter(data.get_sensors_by_type("odometry")), None)
    if odometry is None or not odometry.can_align_to_reference:
        return identity, "identity (no odometry synced to the pings)"
    try:
        mount = data.get_transform(acoustic.name, "base_link")  # sonar frame -> robot frame
    except ValueError:
        return identity, "identity (no base_link transform: CHIRP before 2.1)"
    poses = np.empty((count, 4, 4))
    for i in range(count):
        sample = capture(odometry, i, path)
        position = np.asarray(sample["position"], dtype=np.float64)
        turn = np.asarray(sample["orientation"], dtype=np.float64)
        if position.shape != (3,) or turn.shape != (4,) or not np.isfinite([*position, *turn]).all() or not turn.any():
            raise ValueError(
                f"{path}: {odometry.name}'s pose at ping {i} is not a finite position and a non-zero quaternion "
                f"(position {position}, orientation {turn}); fix the odometry, or remove it to import without poses"
            )
        base = np.eye(4)
        base[:3, :3] = Rotation.from_quat(turn).as_matrix()
        base[:3, 3] = position
        poses[i] = base @ mount
    return poses, f"{odometry.name} (base_link in its odom frame)"


def chirppy():
    try:
        import chirppy
    except ImportError:
        raise MissingExtra(
            "reading CHIRP files needs the `chirp` extra (cosys-chirppy, CC BY-NC-SA): pip install -e '.[chirp]'"
        ) from None
    return chirppy


def recorded_sonar(sonar: SonarConfig, mics: np.ndarray, samples: int, source: str) -> SonarConfig:
    """The rig's sonar with the file's microphones, taken as nominal (no gains or delays), and
    record length; ValueError naming `source` (file and sensor) when the sonar cannot be one."""
    if samples < sonar.chirp.sample_count:
        raise ValueError(
            f"{source}: its pings hold {samples:,} samples, fewer than the call's {sonar.chirp.sample_count:,}; "
            "give the recorded call with --set sonar.chirp.*"
        )
    mic_rows = tuple(tuple(float(v) for v in row) for row in mics)
    try:
        return dataclasses.replace(
            sonar, microphones_m=mic_rows, microphone_gain=(), microphone_delay_s=(), record_samples=samples
        )
    except ValueError as err:  # e.g. microphones all at one point
        raise ValueError(f"{source}: {err}") from None


def open_chirp(path: Path):
    """The reference reader's dataset of a checked CHIRP file; its refusal named as ours."""
    reader = chirppy()
    try:
        return reader.CHIRPDataset(path)
    except (KeyError, ValueError, OSError) as err:
        raise ValueError(f"{path}: the CHIRP reader cannot open it ({type(err).__name__}: {err})") from None


def chirp_recordings(
    path: str | Path, sonar: SonarConfig, pings: int | None = None
) -> tuple[np.ndarray, np.ndarray, SonarConfig]:
    """A CHIRP file's pings as `calibrate`'s recordings: their poses (N, 4, 4) in the odometry's
    frame, their signals (N, microphones, samples) float32, and `sonar` with the file's microphone
    positions and record length. With `pings` (>= 1), only that many, evenly spaced, are read.
    Refused without odometry synced to the pings: a fit needs each ping's place in the room."""
    path = Path(path)
    check_file(path)
    with open_chirp(path) as data:
        try:
            acoustic, mics, _ = microphones(data, sonar.chirp.sample_rate_hz, path)
            count = len(ping_stamps(acoustic, path))
            recorded = recorded_sonar(sonar, mics, acoustic.signals.shape[1], f"{path}: {acoustic.name}")
            poses, source = recorded_poses(data, acoustic, count, path)
            chosen = np.arange(count)
            if pings is not None:
                chosen = np.unique(np.linspace(0, count - 1, min(pings, count)).round().astype(int))
            _, samples, channels = acoustic.signals.shape
            check_memory(  # read whole (as float32, then transposed): a file may hold hours of pings
                2.0 * len(chosen) * samples * channels * 4,
                what=f"{len(chosen):,} pings of {path.name}",
                advice="fit to fewer of them (--pings N)",
            )
            signals = np.asarray(acoustic.signals[chosen], dtype=np.float32).transpose(0, 2, 1)
        except KeyError as err:
            raise ValueError(f"{path}: the file lacks part of the CHIRP format ({err}); is it whole?") from None
    if source.startswith("identity"):
        raise ValueError(f"{path}: its pings have no poses ({source}); calibrate needs where each ping was made")
    return poses[chosen], signals, recorded
