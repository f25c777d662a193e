"""`learn predict --stream`: a checkpoint run frame by frame with state over a drive, as a robot
runs it (`learn.stream.Stream`), on a dataset folder (simulated, or an imported recording), a
.npy of energyscapes (no poses) or an MCAP bag (/sonar/energyscape, or a topic per elevation, and
/tf, `learn.bag`).

It writes what `learn predict` writes (the .npz, and with `mcap` the scans on /scan_pred), the
same windows' scans: each episode (each drive of a bag) is one stream, reset where the next
begins. Its MCAP also holds the poses used on /tf, so Foxglove shows the scans in the world.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from clitools.outputs import atomic_output

from .bag import Recording, read_bag, write_bag
from .checkpoint import check_grid, load_checkpoint
from .data import DataError, shard_paths, window_starts
from .elevations import elevation_rows
from .predict import PredictionRun, _check_outputs, read_input, writing_bar
from .predict_pictures import has_lidar_truth, plot_stream
from .stream import Stream


def predict_stream(checkpoint, source, out, **options) -> Path:
    """`run_predict_stream`, returning the .npz's path alone."""
    return run_predict_stream(checkpoint, source, out, **options).out


def run_predict_stream(
    checkpoint,
    source,
    out,
    *,
    device: str = "cpu",
    png: str | None = None,
    threshold: float | None = None,
    mcap: str | None = None,
    overwrite: bool = False,
    progress: bool = False,
) -> PredictionRun:
    """Stream every frame of `source` through the checkpoint and save the scans as `learn.predict.
    predict` saves them (the .npz's keys; `frame` is each scan's frame in the input's order): the
    arguments are predict's, and so is what it returns. A model with memory is refused, before
    any work, on data without poses."""
    out = Path(out)
    out = out if out.suffix == ".npz" else out.with_name(out.name + ".npz")
    inputs = [checkpoint, source]
    _check_outputs(out, png, mcap, overwrite=overwrite, inputs=inputs)
    model, ckpt = load_checkpoint(checkpoint, device)
    stream = Stream(model, ckpt, device, threshold=threshold)
    source = Path(source)
    drive = read_drive(source, ckpt)
    frames = drive.frames
    check_grid(frames, ckpt)
    if stream.uses_odometry and frames.pose is None:
        raise DataError(
            f"--input {source} holds no poses ({drive.note}), and {checkpoint} is a model with memory that needs "
            "them: use a model without memory (polar_unet), or a recording with odometry"
        )
    if len(window_starts(frames.episode, stream.config.frames)) == 0:
        raise DataError(f"no window of {stream.config.frames} frames fits in any drive of {source}")
    labelled, images, ranges = [], [], []
    first, rows = 0, elevation_rows(frames.elevation_deg, stream.elevation_deg)  # the model's elevations of the data's
    bar = tqdm(total=len(frames), desc="streaming", unit="frame", disable=not progress, leave=False)
    with bar:
        for t in range(len(frames)):
            if t and frames.episode[t] != frames.episode[t - 1]:  # a new drive: no memory of the last
                stream.reset()
                first = t
            pose = None if frames.pose is None else frames.pose[t]
            result = stream.step(frames.energyscape[t][rows], pose)
            bar.update(1)
            if result is not None:
                labelled.append(first + result.frame)
                images.append(result.image)
                ranges.append(result.ranges)
    labelled, images, ranges = np.array(labelled, np.int64), np.stack(images), np.stack(ranges)
    with contextlib.ExitStack() as files:  # all written before any is renamed: a failure leaves none
        bar = files.enter_context(writing_bar([out, png, mcap], progress))

        def temporary(path) -> Path:
            return files.enter_context(atomic_output(path, overwrite=overwrite, inputs=inputs))

        if mcap:
            write_bag(
                temporary(mcap),
                ranges,
                drive.stamps[labelled],
                frames.range_m,
                frames.azimuth_rad,
                transforms=drive.transforms,
                tf_stamps=drive.stamps,
                parent=drive.parent,
                sensor=drive.sensor,
            )
            bar.update(1)
        np.savez_compressed(
            temporary(out),
            prediction=images,
            ranges=ranges,
            threshold=stream.threshold,
            frame=labelled,
            range_m=frames.range_m,
            azimuth_rad=frames.azimuth_rad,
        )
        bar.update(1)
        if png:
            plot_stream(temporary(png), frames, stream.config, labelled, images, stream.threshold)
            bar.update(1)
    return PredictionRun(
        out=out,
        png=Path(png) if png else None,
        mcap=Path(mcap) if mcap else None,
        frame=labelled,
        frames_per_window=stream.config.frames,
        beams=len(frames.azimuth_rad),
        threshold=stream.threshold,
        threshold_given=threshold is not None,
        elevation_deg=tuple(stream.elevation_deg),
        lidar_truth=has_lidar_truth(frames),
        streamed=True,
    )


def read_drive(source: Path, ckpt: dict) -> Recording:
    """The frames of a dataset folder, a .npy or an MCAP bag, with each frame's stamp and pose."""
    if source.suffix == ".mcap":
        return read_bag(source, ckpt["range_m"], ckpt["azimuth_rad"])
    frames = read_input(source, ckpt)
    from .ros import FRAME_S, dataset_stamps, drive_stamps

    if source.suffix == ".npy":  # one drive at the training frame rate, no poses
        stamps = drive_stamps(frames.episode, np.arange(len(frames)) * FRAME_S)
        return Recording(frames, stamps, None, note="a .npy holds energyscapes alone")
    transforms = _shard_poses(source) if frames.pose is not None else None
    note = "" if transforms is not None else "its shards hold no odometry (a recording imported without it)"
    return Recording(frames, dataset_stamps(source), transforms, note=note)


def _shard_poses(folder: Path) -> np.ndarray:
    """The 4 x 4 sensor-to-world pose of every frame of a dataset folder, in `load_frames`' order
    (whose planar poses these are; read again for the height and tilt /tf carries)."""
    import h5py

    poses = []
    for path in shard_paths(folder):
        with h5py.File(path, "r") as f:
            poses.append(f["pose"][:].astype(np.float64))
    return np.concatenate(poses)
