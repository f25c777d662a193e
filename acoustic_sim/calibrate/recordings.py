"""Recorded pings for a calibration: poses and microphone signals from a .npz, two .npy files or a
dataset made with `generate --signals`."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def load_recordings(
    path, pings: int | None = None, episode: int | None = None, poses_path=None
) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 4, 4) and microphone signals (N, mics, samples) float32 of recorded pings, from a
    .npz holding `poses` and `signals`, a .npy of signals with a .npy of their poses (`poses_path`),
    or a dataset folder (or one shard) made with `generate --signals`: the frames of one `episode`
    (one room; required where the data hold several). With `pings`, at most that many, evenly
    spaced."""
    path = Path(path)
    if (path.suffix == ".npy") != (poses_path is not None):
        raise ValueError(f"{path}: signals in a .npy need their poses in a .npy too (--poses), and only they do")
    if path.suffix == ".npz":
        poses, signals = _npz_recordings(path)
    elif path.suffix == ".npy":
        poses, signals = _checked_recordings(np.load(poses_path), np.load(path), f"{path} and {poses_path}")
    elif path.is_dir() or path.suffix == ".h5":
        poses, signals = _shard_recordings(path, episode)
    else:
        raise ValueError(
            f"{path}: recordings come as a .npz with `poses` (N, 4, 4) and `signals` (N, mics, samples), a .npy of "
            "signals with a .npy of poses (--poses), or a dataset folder (or shard) made with generate --signals"
        )
    if pings is not None and pings < len(poses):
        if pings < 1:
            raise ValueError(f"pings must be >= 1, got {pings}")
        chosen = np.linspace(0, len(poses) - 1, pings).round().astype(int)
        poses, signals = poses[chosen], signals[chosen]
    return poses, signals


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
