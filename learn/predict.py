"""Run a checkpoint on dataset shards or on energyscapes from recorded signals.

The .npz holds the predicted images and the scans read from them as a LiDAR would: per beam
(azimuth column) the range of the nearest cell at or above the checkpoint's calibrated return
threshold, inf where there is none.

Recorded data: process the microphone signals with `acoustic_sim.engine.beamform.energyscape` (same
grid as training, one ping per frame at the training frame rate) and save the result as a
.npy (N, R, A) (or (N, E, R, A) at the model's elevations) in time order; every window of K
consecutive frames gets a prediction.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from clitools import counted
from clitools.outputs import atomic_output, check_output

from .checkpoint import load_checkpoint
from .data import DataConfig, Frames, Windows, load_frames, recorded_path
from .evaluate import check_grid, model_predictor, model_windows, return_threshold
from .inputs import check_fits, npy_header, read_json
from .models import ModelConfig, trained_elevations
from .scan import first_return_ranges


def read_input(source: Path, ckpt: dict) -> Frames:
    """The frames `predict` runs on: a dataset folder's, or the energyscapes of a `.npy` file."""
    if source.suffix == ".npy":
        return _frames_from_array(source, ckpt)
    if source.suffix == ".mcap":
        raise ValueError(f"--input {source} is an MCAP bag: `learn predict --stream` reads bags, frame by frame")
    if source.suffix == ".npz" or source.is_file():
        raise ValueError(
            f"--input {source} is a file, not a .npy: give a dataset folder, or energyscapes (N, R, A) (or (N, E, R, "
            "A) at the model's E elevations) saved with numpy.save as a .npy"
        )
    return load_frames(source)


def _frames_from_array(path: Path, ckpt: dict) -> Frames:
    """Energyscapes (N, R, A), or (N, E, R, A), of a `.npy`, held as float32: each is normalised
    to its own peak (`learn.data.normalise`), so any scale is right, and float32 holds any that
    float16 cannot (above 65,504). Their elevations are those its `.json` records (`import
    --format pdm` writes it), else the checkpoint's. Header, size and values are checked before
    and after reading."""
    shape, dtype = npy_header(path, "--input")  # a regular file whose header fits its size
    if dtype.kind not in "fiu":
        raise ValueError(f"--input {path}: energyscapes must be real numbers, got dtype {dtype}")
    grid = (len(ckpt["range_m"]), len(ckpt["azimuth_rad"]))
    elevation_deg = _recorded_elevations(path.with_suffix(".json")) or trained_elevations(
        ckpt["model_config"].get("elevation_deg")
    )
    frame = (len(elevation_deg), *grid)
    if not (shape[1:] == frame or (len(elevation_deg) == 1 and shape[1:] == grid)) or len(shape) < 3:
        expected = f"(N, {grid[0]}, {grid[1]})" if len(elevation_deg) == 1 else f"(N, {', '.join(map(str, frame))})"
        raise ValueError(f"--input {path}: expected energyscapes {expected}, got {shape}")
    n = shape[0]
    check_fits(
        n
        * grid[0]
        * grid[1]
        * (4 * len(elevation_deg) + 1 + 4),  # float32 frames, uint8 labels, one batch's worth at most again
        f"--input {path} ({n:,} energyscapes of {grid[0]} x {grid[1]})",
        "predict a shorter stretch at a time (split the array)",
    )
    with np.errstate(over="ignore", invalid="ignore"):  # beyond float32's range becomes inf: refused below
        energyscape = np.array(np.load(path, mmap_mode="r"), dtype=np.float32)  # a copy; no pickles: objects refused
    bad = int(np.count_nonzero(~np.isfinite(energyscape)))
    if bad:
        hint = {
            np.dtype(np.float16): "float16 overflows to inf above 65,504: save energyscapes as float32",
            np.dtype(np.float64): "values beyond float32's 3.4e38 count too: scale the energyscapes down",
        }.get(dtype, "pass finite energyscapes")
        raise ValueError(f"--input {path}: {bad:,} of its values are NaN or inf: {hint}")
    return Frames(
        energyscape=energyscape.reshape(n, *frame),
        label=np.zeros((n, *grid), np.uint8),
        episode=np.zeros(n, np.int64),
        scenario=np.zeros(n, np.int64),
        scenarios=["recorded"],
        range_m=np.asarray(ckpt["range_m"], dtype=np.float64),
        azimuth_rad=np.asarray(ckpt["azimuth_rad"], dtype=np.float64),
        info={"folder": recorded_path(path)},
        elevation_deg=elevation_deg,
    )


def _recorded_elevations(sidecar: Path) -> tuple[float, ...] | None:
    """The elevations [deg] a `.npy`'s record says it was beamformed at, or None without one."""
    if not sidecar.is_file():
        return None
    record = read_json(sidecar, "--input's record", "fix or remove it (it says how the energyscapes were made)")
    values = record.get("elevation_deg")
    if values is None:
        return None
    try:
        return ModelConfig(elevation_deg=values).elevation_deg  # checked as a model's: increasing angles
    except ValueError as err:
        raise ValueError(f"--input's record {sidecar}: {err}") from None


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
    overwrite: bool = False,
    progress: bool = False,
) -> Path:
    """Predictions of every window, saved as .npz (the suffix is added if `out` lacks it; the path
    written is returned): "prediction" (windows, R, A) float16 images,
    "ranges" (windows, A) float32 scans [m] (inf = no return), "threshold", "frame" (the label
    frame of each window), "range_m", "azimuth_rad". `threshold` overrides the checkpoint's.
    `mcap`: also write the scans as ROS 2 LaserScans on /scan_pred (see `learn.ros`). `progress`:
    a progress bar over the windows. Each file is written under a temporary name and renamed when
    whole (`clitools.outputs`): an existing one is replaced only with `overwrite`, an input never
    (both refused before any work)."""
    out = Path(out)
    out = out if out.suffix == ".npz" else out.with_name(out.name + ".npz")  # numpy appends it anyway
    inputs = [checkpoint, source]
    _check_outputs(out, png, mcap, overwrite=overwrite, inputs=inputs)
    model, ckpt = load_checkpoint(checkpoint, device)
    threshold = return_threshold(ckpt, threshold, str(checkpoint))
    source = Path(source)
    frames = read_input(source, ckpt)
    check_grid(frames, ckpt)
    config = DataConfig(**ckpt["data_config"])
    windows = model_windows(frames, ckpt, device)  # with each frame's motion for a model with memory
    run = model_predictor(model)
    preds, ranges = [], []
    bar = tqdm(total=len(windows), desc="predicting", unit="win", disable=not progress, leave=False)
    with torch.no_grad(), bar:
        for start in range(0, len(windows), batch_size):
            chunk = np.arange(start, min(start + batch_size, len(windows)))
            x, _ = windows.batch(chunk)
            bar.update(len(chunk))
            image = run(x).float().clamp(0, 1)[:, 0].half()  # as saved: the scans read the saved images
            ranges.append(first_return_ranges(image.float(), frames.range_m, threshold=threshold).float().cpu().numpy())
            preds.append(image.cpu().numpy())
    labelled = windows.starts + config.label_offset  # the frame each prediction is for
    images, ranges = np.concatenate(preds), np.concatenate(ranges)
    with contextlib.ExitStack() as files:  # all written before any is renamed: a failure leaves none

        def temporary(path) -> Path:
            return files.enter_context(atomic_output(path, overwrite=overwrite, inputs=inputs))

        if mcap:
            _write_scans(temporary(mcap), source, frames, ranges, labelled)
        np.savez_compressed(
            temporary(out),
            prediction=images,
            ranges=ranges,
            threshold=threshold,
            frame=labelled,
            range_m=frames.range_m,
            azimuth_rad=frames.azimuth_rad,
        )
        if png:
            _plot(temporary(png), windows, images, threshold)
    return out


def _write_scans(path: Path, source: Path, frames: Frames, ranges: np.ndarray, labelled: np.ndarray) -> None:
    """The scans as ROS 2 LaserScans, stamped as the dataset's frames (or the drive of a .npy)."""
    from .ros import FRAME_S, dataset_stamps, drive_stamps, write_scans

    if source.suffix == ".npy":  # one drive at the training frame rate
        stamps = drive_stamps(frames.episode, np.arange(len(frames.episode)) * FRAME_S)
    else:
        stamps = dataset_stamps(source)
    write_scans(path, ranges, stamps[labelled], frames.range_m, frames.azimuth_rad)


def _plot(path: Path, windows: Windows, images: np.ndarray, threshold: float) -> None:
    """Four predictions spread over the drive, beside their sonar input and truth."""
    from .plots import plot_examples

    rows, offset = [], windows.config.label_offset
    for i in np.unique(np.linspace(0, len(windows) - 1, 4).round().astype(int)):
        x, y = windows.batch([i])
        frames = x[0] if isinstance(x, tuple) else x  # a model with memory also reads the motion
        rows.append(
            {
                "title": f"frame {windows.starts[i] + offset}",
                "sonar": frames[0, windows.level, windows.config.anchor].cpu().numpy(),
                "truth": y[0, 0].cpu().numpy(),
                "pred": images[i].astype(np.float32),
            }
        )
    plot_examples(rows, windows.frames.range_m, windows.frames.azimuth_rad, path, threshold=threshold)


def _check_outputs(out: Path, png, mcap, *, overwrite: bool, inputs: list) -> None:
    """Refuse, before any work, outputs that name one file twice, a picture without a suffix
    (its format), an existing file without `overwrite`, or an input."""
    given = [Path(p) for p in (out, png, mcap) if p]
    if len({os.path.realpath(p) for p in given}) < len(given):
        raise ValueError(f"--out, --png and --mcap name one file twice ({', '.join(map(str, given))})")
    if png and not Path(png).suffix:
        raise ValueError(f"--png {png} needs a suffix that names the picture's format (.png, .pdf, .svg)")
    for path in given:
        check_output(path, overwrite=overwrite, inputs=inputs)
    if png:  # after the outputs' checks: writing onto an input is the graver mistake
        from matplotlib.backend_bases import FigureCanvasBase

        formats = FigureCanvasBase.get_supported_filetypes()
        if Path(png).suffix[1:].lower() not in formats:
            raise ValueError(f"--png {png}: matplotlib draws no {Path(png).suffix} pictures; use .png, .pdf or .svg")


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
