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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from clitools import counted
from clitools.outputs import atomic_output, check_output

from .checkpoint import check_grid, load_checkpoint, return_threshold
from .data import DataConfig, Frames, load_frames, recorded_path
from .evaluate import model_predictor, model_windows
from .inputs import check_fits, npy_header, read_json
from .models import ModelConfig, trained_elevations
from .predict_pictures import has_lidar_truth, picture_indices, plot_windows
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


@dataclass(frozen=True)
class PredictionRun:
    """What one `learn predict` run read and wrote, for the lines it ends with.

    Attributes:
        out: The .npz written.
        png: The picture written, None where none was asked for.
        mcap: The bag written, None where none was asked for.
        frame: The label frame each prediction is for, shape (N,).
        frames_per_window: K, the consecutive frames each prediction reads.
        beams: Azimuth beams of each scan.
        threshold: Return threshold the scans were read at.
        threshold_given: True: `--threshold`'s; False: the checkpoint's calibrated one.
        elevation_deg: The elevations [deg] the model read.
        lidar_truth: Whether the input holds LiDAR truth (the picture then draws it).
        streamed: Run frame by frame (`--stream`; its bag also holds the poses on /tf).
    """

    out: Path
    png: Path | None
    mcap: Path | None
    frame: np.ndarray
    frames_per_window: int
    beams: int
    threshold: float
    threshold_given: bool
    elevation_deg: tuple[float, ...]
    lidar_truth: bool
    streamed: bool = False


def predict(checkpoint, source, out, **options) -> Path:
    """`run_predict`, returning the .npz's path alone."""
    return run_predict(checkpoint, source, out, **options).out


def run_predict(
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
) -> PredictionRun:
    """Predictions of every window, saved as .npz (the suffix is added if `out` lacks it):
    "prediction" (windows, R, A) float16 images,
    "ranges" (windows, A) float32 scans [m] (inf = no return), "threshold", "frame" (the label
    frame of each window), "range_m", "azimuth_rad". `threshold` overrides the checkpoint's.
    `png`: also draw four of them (`learn.predict_pictures`: beside their truth where the data
    holds one). `mcap`: also write the scans as ROS 2 LaserScans on /scan_pred (see `learn.ros`).
    `progress`: a progress bar over the windows, then the files. Each file is written under a
    temporary name and renamed when whole (`clitools.outputs`): an existing one is replaced only
    with `overwrite`, an input never (both refused before any work). Returns what was written."""
    out = Path(out)
    out = out if out.suffix == ".npz" else out.with_name(out.name + ".npz")  # numpy appends it anyway
    inputs = [checkpoint, source]
    _check_outputs(out, png, mcap, overwrite=overwrite, inputs=inputs)
    model, ckpt = load_checkpoint(checkpoint, device)
    given, threshold = threshold is not None, return_threshold(ckpt, threshold, str(checkpoint))
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
        bar = files.enter_context(writing_bar([out, png, mcap], progress))

        def temporary(path) -> Path:
            return files.enter_context(atomic_output(path, overwrite=overwrite, inputs=inputs))

        if mcap:
            _write_scans(temporary(mcap), source, frames, ranges, labelled)
            bar.update(1)
        np.savez_compressed(
            temporary(out),
            prediction=images,
            ranges=ranges,
            threshold=threshold,
            frame=labelled,
            range_m=frames.range_m,
            azimuth_rad=frames.azimuth_rad,
        )
        bar.update(1)
        if png:
            plot_windows(temporary(png), windows, images, threshold)
            bar.update(1)
    return PredictionRun(
        out=out,
        png=Path(png) if png else None,
        mcap=Path(mcap) if mcap else None,
        frame=labelled,
        frames_per_window=config.frames,
        beams=len(frames.azimuth_rad),
        threshold=threshold,
        threshold_given=given,
        elevation_deg=tuple(windows.elevation_deg),
        lidar_truth=has_lidar_truth(frames),
    )


def writing_bar(paths: list, progress: bool) -> tqdm:
    """A progress bar over the files of `paths` given (None: not asked for), each counted once
    written: a long drive's .npz takes a while to compress."""
    count = sum(1 for p in paths if p)
    return tqdm(total=count, desc="writing", unit="file", disable=not progress, leave=False)


def _write_scans(path: Path, source: Path, frames: Frames, ranges: np.ndarray, labelled: np.ndarray) -> None:
    """The scans as ROS 2 LaserScans, stamped as the dataset's frames (or the drive of a .npy)."""
    from .ros import FRAME_S, dataset_stamps, drive_stamps, write_scans

    if source.suffix == ".npy":  # one drive at the training frame rate
        stamps = drive_stamps(frames.episode, np.arange(len(frames.episode)) * FRAME_S)
    else:
        stamps = dataset_stamps(source)
    write_scans(path, ranges, stamps[labelled], frames.range_m, frames.azimuth_rad)


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


def prediction_summary(run: PredictionRun, source: str | Path, seconds: float) -> str:
    """The lines `learn predict` ends with: how many frames of `source` it predicted, which, on how
    many beams, at which threshold and whence, in how long [s]; the windows they read (and their
    elevations, where more than one); then each other file written and what it holds."""
    count = len(run.frame)
    which = f"label frames {run.frame.min()}..{run.frame.max()}; " if count else ""
    whence = "given with --threshold" if run.threshold_given else "the checkpoint's calibrated one"
    windows = (
        f"  read {counted(count, 'window')} of {counted(run.frames_per_window, 'frame')} (one per frame predicted)"
    )
    if len(run.elevation_deg) > 1:
        windows += f" at elevations {', '.join(f'{e:g}' for e in run.elevation_deg)} deg"
    lines = [
        f"wrote {run.out}: LiDAR images and scans for {counted(count, 'frame')} of {source} "
        f"({which}{run.beams} beams, return threshold {run.threshold:.2f}, {whence}) in {seconds:.1f} s",
        windows,
    ]
    if run.png:
        drawn = counted(len(picture_indices(count)) if count else 0, "prediction")
        truth = " and LiDAR truth" if run.lidar_truth else " (no LiDAR truth in this data: the predicted scans alone)"
        lines.append(f"wrote {run.png}: {drawn} beside their sonar input{truth}")
    if run.mcap:
        tf = " and the poses on /tf" if run.streamed else ""
        lines.append(f"wrote {run.mcap}: the scans as ROS 2 LaserScans on /scan_pred{tf}")
    return "\n".join(lines)
