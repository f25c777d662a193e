"""The occupancy-grid baselines of `learn evaluate`: what a robotics engineer would write instead of
a learned memory, on the same windows and the same odometry.

Two grids (`learn.occupancy`), each a fresh log-odds grid per drive in the world frame, read out
as a scan from the label frame's pose after that frame's scan went in:
- fed with the echo peak of every frame (the strongest echo of each beam, if strong enough: the
  classic sonar readout, `learn.scan.echo_peak_image`, as `learn.evaluate`'s echo-peak baseline);
- fed with a model's scan of every window's label frame (a model without memory, read at its
  calibrated threshold), so the grid adds memory to it.
Their images are made once for all windows of the drives scored, and handed to the scoring as a
predictor that looks them up by window (`by_window`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from .data import Windows, normalise
from .occupancy import occupancy_scans
from .scan import echo_peak_image, first_return_ranges


class WindowImages:
    """Predicted images looked up by window index: (B,) indices -> (B, 1, R, A)."""

    def __init__(self, images: dict[int, np.ndarray], device):
        self.images, self.device = images, device

    def by_window(self, indices) -> torch.Tensor:
        rows = [self.images[int(i)] for i in np.asarray(torch.as_tensor(indices).cpu())]
        return torch.from_numpy(np.stack(rows)[:, None]).to(self.device)


def scan_images(ranges: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """Scans (B, A) [m] (inf = no return) -> 0/1 images (B, R, A) with the return's range bin set
    (the bin whose centre is nearest; none beyond the grid's last bin)."""
    edges = np.r_[range_m[0] - (range_m[1] - range_m[0]) / 2, (range_m[1:] + range_m[:-1]) / 2, np.inf]
    image = np.zeros((len(ranges), len(range_m), ranges.shape[1]), np.float32)
    b, a = np.nonzero(np.isfinite(ranges) & (ranges <= range_m[-1] + (range_m[-1] - range_m[-2]) / 2))
    image[b, np.searchsorted(edges, ranges[b, a], side="right") - 1, a] = 1.0
    return image


def grid_predictors(
    windows: Windows, indices: np.ndarray, feeders: dict[str, tuple[Callable, float, Windows]], echo_level: float
) -> dict[str, WindowImages]:
    """{name: WindowImages} of the grid fed by echo peaks and of one grid per feeder (a model's
    predictor, its threshold and its windows), for the windows `indices`."""
    frames, config = windows.frames, windows.config
    episodes = np.unique(windows.episode[indices])
    rows = np.flatnonzero(np.isin(frames.episode, episodes))  # whole drives, contiguous
    own = {int(f): k for k, f in enumerate(rows)}  # frame -> row of the drives' arrays
    every = np.flatnonzero(np.isin(windows.episode, episodes))
    label_rows = np.array([own[int(f)] for f in windows.starts[every] + config.label_offset])
    feeds = {"occupancy grid (echo peak)": _echo_peak_scans(windows, rows, echo_level)}
    for name, (predict, threshold, their_windows) in feeders.items():
        scans = np.full((len(rows), len(frames.azimuth_rad)), np.nan)
        scans[label_rows] = _model_scans(predict, their_windows, every, threshold)
        feeds[f"occupancy grid ({name})"] = scans
    range_max = float(frames.range_m[-1] + (frames.range_m[-1] - frames.range_m[-2]) / 2)
    out = {}
    for name, scans in feeds.items():
        read = occupancy_scans(scans, frames.pose[rows], frames.episode[rows], frames.azimuth_rad, range_max)
        images = scan_images(read[label_rows], frames.range_m)
        out[name] = WindowImages(dict(zip(every.tolist(), images, strict=True)), windows.device)
    return out


def _echo_peak_scans(windows: Windows, rows: np.ndarray, level: float, batch: int = 256) -> np.ndarray:
    """Each frame's echo peak as a scan: the range of each beam's strongest cell where it lies
    within `level` of the frame's normalised peak (the echo-peak baseline), else inf."""
    frames, out = windows.frames, []
    range_m = torch.as_tensor(frames.range_m, device=windows.device)
    for start in range(0, len(rows), batch):
        level_slice = frames.energyscape[rows[start : start + batch], frames.level : frames.level + 1]  # (B, 1, R, A)
        energy = torch.from_numpy(level_slice).to(windows.device)
        image = echo_peak_image(normalise(energy, windows.config.floor_db), level)[:, 0]  # (B, R, A)
        out.append(first_return_ranges(image, range_m).cpu().numpy())
    return np.concatenate(out)


def _model_scans(predict: Callable, windows: Windows, indices: np.ndarray, threshold: float, batch: int = 32):
    """The model's scan of each window's label frame at `threshold`, (len(indices), A)."""
    range_m = torch.as_tensor(windows.frames.range_m, device=windows.device)
    out = []
    with torch.no_grad():
        for start in range(0, len(indices), batch):
            x, _ = windows.batch(indices[start : start + batch])
            image = predict(x).float()[:, 0]
            out.append(first_return_ranges(image, range_m, threshold=threshold).cpu().numpy())
    return np.concatenate(out)
