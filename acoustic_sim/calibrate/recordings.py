"""Recorded pings for a calibration: poses and microphone signals from a .npz, two .npy files, a
CHIRP file or a dataset made with `generate --signals`; the sonar a CHIRP file was recorded with;
and the room a dataset's episode was recorded in."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..config import SonarConfig


def load_recordings(
    path, pings: int | None = None, episode: int | None = None, poses_path=None, sonar=None, frames=None
) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 4, 4) and microphone signals (N, mics, samples) float32 of recorded pings, from a
    .npz holding `poses` and `signals`, a .npy of signals with a .npy of their poses (`poses_path`),
    a CHIRP file (its odometry's poses; its call's sample rate checked against `sonar`'s, the
    eRTIS's by default), or a dataset folder (or one shard) made with `generate --signals`: the
    frames of one `episode` (one room; required where the data hold several). With `frames`
    (first, stop), only the pings first .. stop - 1 in recorded order (e.g. a drive's first two
    seconds, the rest kept for testing); with `pings`, at most that many of them, evenly spaced."""
    return recordings_and_sonar(path, pings, episode, poses_path, sonar, frames)[:2]


def recordings_and_sonar(
    path, pings: int | None = None, episode: int | None = None, poses_path=None, sonar=None, frames=None
) -> tuple[np.ndarray, np.ndarray, SonarConfig | None]:
    """`load_recordings`'s poses and signals, and the sonar they were recorded with: a CHIRP file's
    own microphones and record length (its pings carry them), else `sonar` itself; one read of
    the file for all three."""
    path = Path(path)
    if pings is not None and pings < 1:
        raise ValueError(f"pings must be >= 1, got {pings}")
    if (path.suffix == ".npy") != (poses_path is not None):
        raise ValueError(f"{path}: signals in a .npy need their poses in a .npy too (--poses), and only they do")
    if path.suffix == ".npz":
        poses, signals = _npz_recordings(path)
    elif path.suffix == ".npy":
        poses, signals = _checked_recordings(np.load(poses_path), np.load(path), f"{path} and {poses_path}")
    elif path.suffix == ".h5" and is_chirp(path):
        if frames is not None:
            raise ValueError(f"{path}: frames are chosen of a dataset, .npz or .npy; of a CHIRP file, give pings")
        from ..config import SonarConfig
        from ..formats.chirp_input import chirp_recordings

        return chirp_recordings(path, sonar or SonarConfig.ertis(), pings)
    elif path.is_dir() or path.suffix == ".h5":
        poses, signals = _shard_recordings(path, episode)
    else:
        raise ValueError(
            f"{path}: recordings come as a .npz with `poses` (N, 4, 4) and `signals` (N, mics, samples), a .npy of "
            "signals with a .npy of poses (--poses), a CHIRP file (.h5), or a dataset folder (or shard) made with "
            "generate --signals"
        )
    if frames is not None:
        first, stop = frames
        if not 0 <= first < stop <= len(poses):
            raise ValueError(f"{path}: frames {first}:{stop} are not within its {len(poses)} pings")
        poses, signals = poses[first:stop], signals[first:stop]
    if pings is not None and pings < len(poses):
        chosen = np.linspace(0, len(poses) - 1, pings).round().astype(int)
        poses, signals = poses[chosen], signals[chosen]
    return poses, signals, sonar


def is_chirp(path) -> bool:
    """Whether `path` is an HDF5 file of the CHIRP format (not one of our shards)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            kind = f.attrs.get("format")
    except OSError:
        return False
    return (kind.decode() if isinstance(kind, bytes) else kind) == "chirp"


def _npz_recordings(path) -> tuple[np.ndarray, np.ndarray]:
    with np.load(path) as data:
        missing = [k for k in ("poses", "signals") if k not in data]
        if missing:
            raise ValueError(f"{path} lacks {' and '.join(missing)}; it holds {', '.join(data.files) or 'nothing'}")
        return _checked_recordings(data["poses"], data["signals"], str(path))


def _checked_recordings(poses, signals, where: str) -> tuple[np.ndarray, np.ndarray]:
    poses, signals = np.asarray(poses, np.float64), np.asarray(signals, np.float32)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or signals.ndim != 3 or len(signals) != len(poses):
        raise ValueError(
            f"{where}: poses {poses.shape} and signals {signals.shape} must be (N, 4, 4) and (N, mics, samples)"
        )
    return poses, signals


def _shard_recordings(path, episode: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The poses and signals of one episode of a dataset folder or shard."""
    import h5py

    from ..datasets.shards import dataset_shards

    shards = dataset_shards(path) if path.is_dir() else [path]
    found = []
    for shard in shards:
        with h5py.File(shard, "r") as f:
            if "signals" not in f:
                raise ValueError(f"{shard} holds no microphone signals: make the dataset with generate --signals")
            episodes = f["episode"][()]
            if episode is None and len(set(episodes.tolist()) | {e for e, *_ in found}) > 1:
                listed = sorted(set(episodes.tolist()) | {e for e, *_ in found})
                raise ValueError(f"{path} holds episodes {listed[:10]}: give one (--episode), one room a fit")
            rows = episodes == (episodes[0] if episode is None else episode)
            if rows.any():
                found.append((int(episodes[rows][0]), f["pose"][rows], f["signals"][rows]))
    if not found:
        raise ValueError(f"{path} holds no frames of episode {episode}")
    poses = np.concatenate([p for _, p, _ in found]).astype(np.float64)
    signals = np.concatenate([s for _, _, s in found]).astype(np.float32)
    return poses, signals


def recorded_scene(path, episode: int | None = None):
    """The room of one episode (`--episode`; needed where the data hold several) of a dataset folder
    or shard, from its episode record: our suites' builder and its arguments, or another engine's
    floor plan (crossengine: its corners and height, open to the sky where its ceiling reflects
    nothing). Built with the builders' own materials: what a fit starts from, never what the
    recording holds."""
    import scenes

    from ..datasets.mesh_scenarios import MESH_BUILDER

    path = Path(path)
    records = episode_records(path)
    indices = sorted({record.get("index") for record in records})
    if episode is None and len(indices) > 1:
        raise ValueError(f"{path} holds episodes {indices[:10]}: give one (--episode), one room a fit")
    found = [r for r in records if episode is None or r.get("index") == episode]
    if not found:
        raise ValueError(f"{path} holds no record of episode {episode} (its episodes: {indices[:10]})")
    record = found[0]
    if record.get("builder") == MESH_BUILDER:
        raise ValueError(f"{path}: episode {record['index']} was drawn in a mesh file's room: give it with --mesh")
    if "builder" in record:
        return scenes.BUILDERS[record["builder"]](**record["scene_params"])
    if "corners" in record:  # another engine's extruded floor plan (formats.crossengine.Room)
        ceiling = None if record["ceiling_reflection"] == 0 else "ceiling_tile"
        corners, height = record["corners"], record["height_m"]
        return scenes.polygon_room(record["plan"], corners=corners, height=height, ceiling=ceiling)
    raise ValueError(f"{path}: episode {record.get('index')}'s record describes no room (no builder, no floor plan)")


def episode_records(path) -> list[dict]:
    """Every episode record of a dataset folder or one shard (its room, drive and draws)."""
    from ..datasets.shards import dataset_shards, read_attrs

    path = Path(path)
    shards = dataset_shards(path) if path.is_dir() else [path]
    return [record for shard in shards for record in read_attrs(shard).get("episodes", [])]
