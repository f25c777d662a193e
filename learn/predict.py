"""Run a checkpoint on dataset shards or on energyscapes from recorded signals.

The .npz holds the predicted images and the scans read from them as a LiDAR would: per beam
(azimuth column) the range of the nearest cell at or above the checkpoint's calibrated return
threshold, inf where there is none.

Recorded data: process the microphone signals with `acoustic_sim.engine.beamform.energyscape` (same
grid as training, one ping per frame at the training frame rate) and save the result as a
.npy (N, R, A) in time order; every window of K consecutive frames gets a prediction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from clitools import counted

from .checkpoint import load_checkpoint
from .data import DataConfig, Frames, Windows, load_frames, recorded_path
from .evaluate import check_grid, model_predictor, return_threshold
from .scan import first_return_ranges


def _frames_from_array(path: Path, ckpt: dict) -> Frames:
    energyscape = np.load(path)  # allow_pickle stays False: an object array is refused, not unpickled
    if not (np.issubdtype(energyscape.dtype, np.floating) or np.issubdtype(energyscape.dtype, np.integer)):
        raise ValueError(f"{path}: energyscapes must be real numbers, got dtype {energyscape.dtype}")
    shape = (len(ckpt["range_m"]), len(ckpt["azimuth_rad"]))
    if energyscape.ndim != 3 or energyscape.shape[1:] != shape:
        raise ValueError(f"{path}: expected energyscapes (N, {shape[0]}, {shape[1]}), got {energyscape.shape}")
    if not np.isfinite(energyscape).all():
        raise ValueError(f"{path}: energyscapes contain NaN or inf")
    n = len(energyscape)
    return Frames(
        energyscape=energyscape.astype(np.float16),
        label=np.zeros((n, *shape), np.uint8),
        episode=np.zeros(n, np.int64),
        scenario=np.zeros(n, np.int64),
        scenarios=["recorded"],
        range_m=np.asarray(ckpt["range_m"]),
        azimuth_rad=np.asarray(ckpt["azimuth_rad"]),
        info={"folder": recorded_path(path)},
    )


def predict(
    checkpoint,
    source,
    out,
    *,
    device: str = "cpu",
    batch_size: int = 32,
    png: str | None = None,
    threshold: float | None = None,
    mcap: str | None = None,
    progress: bool = False,
) -> Path:
    """Predictions of every window, saved as .npz (the suffix is added if `out` lacks it; the path
    written is returned): "prediction" (windows, R, A) float16 images,
    "ranges" (windows, A) float32 scans [m] (inf = no return), "threshold", "frame" (the label
    frame of each window), "range_m", "azimuth_rad". `threshold` overrides the checkpoint's.
    `mcap`: also write the scans as ROS 2 LaserScans on /scan_pred (see `learn.ros`). `progress`:
    a progress bar over the windows."""
    model, ckpt = load_checkpoint(checkpoint, device)
    threshold = return_threshold(ckpt, threshold)
    source = Path(source)
    frames = _frames_from_array(source, ckpt) if source.suffix == ".npy" else load_frames(source)
    check_grid(frames, ckpt)
    config = DataConfig(**ckpt["data_config"])
    windows = Windows(frames, config, device)
    run = model_predictor(model)
    preds, ranges = [], []
    bar = tqdm(total=len(windows), desc="predicting", unit="win", disable=not progress, leave=False)
    with torch.no_grad(), bar:
        for start in range(0, len(windows), batch_size):
            x, _ = windows.batch(np.arange(start, min(start + batch_size, len(windows))))
            bar.update(len(x))
            image = run(x).float().clamp(0, 1)[:, 0].half()  # as saved: the scans read the saved images
            ranges.append(first_return_ranges(image.float(), frames.range_m, threshold=threshold).float().cpu().numpy())
            preds.append(image.cpu().numpy())
    labelled = windows.starts + config.label_offset  # the frame each prediction is for
    if mcap:
        from .ros import FRAME_S, dataset_stamps, drive_stamps, write_scans

        if source.suffix == ".npy":  # one drive at the training frame rate
            stamps = drive_stamps(frames.episode, np.arange(len(frames.episode)) * FRAME_S)
        else:
            stamps = dataset_stamps(source)
        write_scans(mcap, np.concatenate(ranges), stamps[labelled], frames.range_m, frames.azimuth_rad)
    out = Path(out)
    out = out if out.suffix == ".npz" else out.with_name(out.name + ".npz")  # numpy appends it anyway
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out,
        prediction=np.concatenate(preds),
        ranges=np.concatenate(ranges),
        threshold=threshold,
        frame=labelled,
        range_m=frames.range_m,
        azimuth_rad=frames.azimuth_rad,
    )
    if png:
        from .plots import plot_examples

        images, rows = np.concatenate(preds), []
        for i in np.unique(np.linspace(0, len(windows) - 1, 4).round().astype(int)):  # spread over the drive
            x, y = windows.batch([i])
            rows.append(
                {
                    "title": f"frame {windows.starts[i] + config.label_offset}",
                    "sonar": x[0, 0, config.label_offset].cpu().numpy(),
                    "truth": y[0, 0].cpu().numpy(),
                    "pred": images[i].astype(np.float32),
                }
            )
        plot_examples(rows, frames.range_m, frames.azimuth_rad, png, threshold=threshold)
    return out


def prediction_summary(out: str | Path, source: str | Path, seconds: float) -> str:
    """One line on what `predict` wrote to `out` (.npz): how many frames of `source` it predicted,
    which, on how many beams, at which threshold, and how long it took [s]."""
    with np.load(out) as saved:
        frame, beams, threshold = saved["frame"], len(saved["azimuth_rad"]), float(saved["threshold"])
    which = f"label frames {frame.min()}..{frame.max()}; " if len(frame) else ""
    return (
        f"wrote {out}: LiDAR images and scans for {counted(len(frame), 'frame')} of {source} "
        f"({which}{beams} beams, return threshold {threshold:.2f}) in {seconds:.1f} s"
    )
