"""Windows of K consecutive frames from dataset shards (no warp: shards are plain HDF5)."""

from __future__ import annotations

import numpy as np


def window_starts(episode: np.ndarray, frames: int) -> np.ndarray:
    """First frame of every window of `frames` consecutive frames that stays inside one episode.

    Args:
        episode: Episode index per frame, shape (T,); frames of one episode are contiguous.
        frames: Window length K >= 1.

    Returns:
        Start indices s, int64: frames s .. s + K - 1 all belong to episode[s].
    """
    episode = np.asarray(episode)
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    if episode.ndim != 1:
        raise ValueError(f"episode must be 1-D, got shape {episode.shape}")
    if len(episode) < frames:
        return np.zeros(0, dtype=np.int64)
    # A window is valid when no episode boundary lies between its first and last frame.
    boundary = np.concatenate([[0], np.cumsum(episode[1:] != episode[:-1])])
    starts = np.arange(len(episode) - frames + 1)
    return starts[boundary[starts] == boundary[starts + frames - 1]].astype(np.int64)
