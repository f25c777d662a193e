"""The picture `learn predict --png` draws: four predictions spread over the input, each beside its
sonar frame, and beside its LiDAR truth where the data holds one (`learn.plots.plot_examples`).

Data without LiDAR truth carries labels that are all empty: a .npy of energyscapes, an MCAP bag
(its /sonar images alone are read) and a CHIRP recording imported without a LiDAR all come with
zero labels. Drawing those as truth would paint every predicted return "off / false", which reads
as a wrong model where there is only nothing to compare with; such data is drawn without truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .data import DataConfig, Frames, Windows, normalise

PICTURE_ROWS = 4
"""Predictions drawn, evenly spread over the input (fewer where it has fewer)."""


def has_lidar_truth(frames: Frames) -> bool:
    """Whether `frames` hold LiDAR truth: a label with a return somewhere. A dataset with a LiDAR
    has returns in its labels (a CHIRP import refuses a LiDAR none of whose points reach the
    sonar's plane); every frame's label empty is data recorded without one."""
    return bool(frames.label.any())


def picture_indices(count: int) -> np.ndarray:
    """Which of `count` predictions the picture draws: PICTURE_ROWS evenly spread, first and last included."""
    return np.unique(np.linspace(0, count - 1, PICTURE_ROWS).round().astype(int))


def plot_windows(path: Path, windows: Windows, images: np.ndarray, threshold: float) -> None:
    """`learn predict`'s picture: predictions `images` (N, R, A) of `windows`, read at `threshold`."""
    from .plots import plot_examples

    truth, rows, offset = has_lidar_truth(windows.frames), [], windows.config.label_offset
    for i in picture_indices(len(windows)):
        x, y = windows.batch([i])
        frames = x[0] if isinstance(x, tuple) else x  # a model with memory also reads the motion
        rows.append(
            {
                "title": f"frame {windows.starts[i] + offset}",
                "sonar": frames[0, windows.level, windows.config.anchor].cpu().numpy(),
                "truth": y[0, 0].cpu().numpy() if truth else None,
                "pred": images[i].astype(np.float32),
            }
        )
    plot_examples(rows, windows.frames.range_m, windows.frames.azimuth_rad, path, threshold=threshold)


def plot_stream(
    path: Path, frames: Frames, config: DataConfig, labelled: np.ndarray, images: np.ndarray, threshold: float
) -> None:
    """`learn predict --stream`'s picture: scans `images` (N, R, A) for the frames `labelled` (N,)
    of `frames`, each beside the sonar frame it is for and, where the data holds one, its truth."""
    from .plots import plot_examples

    truth, rows = has_lidar_truth(frames), []
    for i in picture_indices(len(labelled)):
        frame = int(labelled[i])
        sonar = normalise(torch.from_numpy(np.asarray(frames.energyscape[frame])), config.floor_db)[frames.level]
        rows.append(
            {
                "title": f"frame {frame}",
                "sonar": sonar.numpy(),
                "truth": frames.label[frame].astype(np.float32) if truth else None,
                "pred": images[i].astype(np.float32),
            }
        )
    plot_examples(rows, frames.range_m, frames.azimuth_rad, path, threshold=threshold)
