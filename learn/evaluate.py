"""Evaluation: the scan metric and the other metrics per scenario, baselines beside the models, a report.

    python -m learn evaluate --checkpoint runs/unet/best.pt --data data/reality --out runs/unet/reality
    python -m learn evaluate --checkpoint pretrained=learn/pretrained/polar_unet_k5.pt \\
        --checkpoint "smoke run=out/run/best.pt" --data out/drive --out out/report

Metrics per window (learn.metrics), primary first: `scan_f1` at 0.10 m (the prediction read as a
LiDAR scan at the model's calibrated return threshold), beam accuracy, return precision and
recall, the range error of the true positives, missed and false returns, Chamfer distance and
occupancy IoU; then the scan metrics at 0.05 and 0.25 m, MSE, SSIM and the column-peak range
error (which ignores confidence). Two baselines are scored the same way: "empty" (no return
anywhere: what SSIM and MSE give for free on sparse labels) and "echo peak" (the strongest echo
of each beam of the label frame's energyscape, within 10 dB of the frame's peak).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from .checkpoint import check_grid, load_checkpoint, return_threshold
from .data import DataConfig, Frames, Windows, level_slice, load_frames, recorded_path
from .grid_baselines import grid_predictors
from .metrics import image_metrics
from .models import ModelConfig, predict_image, trained_elevations
from .odometry import OdometryNoise, noisy_drive
from .report import example_file, report_markdown, write_per_scenario, write_per_window
from .scan import CALIBRATION_THRESHOLDS, echo_peak_image, scan_f1_sweep

ECHO_PEAK_LEVEL = 0.75  # normalised input (40 dB floor): within 10 dB of the frame's peak
BASELINE_THRESHOLD = 0.5  # baselines predict 0/1 images: any threshold in (0, 1] reads them alike


def predict_batches(predict: Callable, windows: Windows, indices: np.ndarray, batch_size: int = 32):
    """(prediction (B, R, A) float32 in [0, 1], label (B, R, A)) per batch of windows."""
    with torch.no_grad():
        for start in range(0, len(indices), batch_size):
            chunk = indices[start : start + batch_size]
            x, y = windows.batch(chunk)
            pred = predict.by_window(chunk) if hasattr(predict, "by_window") else predict(x)  # see grid_baselines
            yield pred.float().clamp(0, 1)[:, 0], y[:, 0]


def _axes(windows: Windows) -> tuple[torch.Tensor, torch.Tensor]:
    return (
        torch.as_tensor(windows.frames.range_m, device=windows.device),
        torch.as_tensor(windows.frames.azimuth_rad, device=windows.device),
    )


def score(
    predict: Callable,
    windows: Windows,
    indices: np.ndarray,
    *,
    threshold: float,
    batch_size: int = 32,
    progress: str | None = None,
) -> dict[str, np.ndarray]:
    """Per-window metrics (`learn.metrics.image_metrics`) of a predictor x (B, E, K, R, A) -> image
    (B, 1, R, A) in [0, 1], whose cells >= threshold are returns. `progress` names a progress bar."""
    bar = tqdm(total=len(indices), desc=progress, unit="win", disable=progress is None, leave=False)
    per = score_predictions(predict_batches(predict, windows, indices, batch_size), windows, threshold, bar.update)
    bar.refresh()  # the final count, even when every window came within tqdm's first 0.1 s (one batch)
    bar.close()
    return per


def score_predictions(
    predictions: Iterable, windows: Windows, threshold: float, done: Callable[[int], object] | None = None
) -> dict[str, np.ndarray]:
    """`score` of (prediction, label) batches made already (see `predict_batches`); `done` is told
    how many windows each batch held."""
    if not 0 < threshold <= 1:
        raise ValueError(f"the return threshold must lie in (0, 1], got {threshold}")
    range_m, azimuth_rad = _axes(windows)
    per: dict[str, list] = {}
    for pred, y in predictions:
        for k, v in image_metrics(pred, y, range_m, azimuth_rad, threshold=threshold).items():
            per.setdefault(k, []).append(v)
        if done:
            done(len(y))
    return {k: torch.cat(v).cpu().numpy() for k, v in per.items()}  # one copy per metric, not per batch


def calibrate_threshold(
    predict: Callable, windows: Windows, indices: np.ndarray, *, batch_size: int = 32, thresholds=CALIBRATION_THRESHOLDS
) -> tuple[float, np.ndarray]:
    """The return threshold with the highest mean `scan_f1` (0.10 m) over the given windows.

    Returns:
        (threshold, mean scan_f1 per threshold of `thresholds`); ties go to the lower threshold.
    """
    return calibrate_on_predictions(predict_batches(predict, windows, indices, batch_size), windows, thresholds)


def calibrate_on_predictions(
    predictions: Iterable, windows: Windows, thresholds=CALIBRATION_THRESHOLDS
) -> tuple[float, np.ndarray]:
    """`calibrate_threshold` on (prediction, label) batches made already (see `predict_batches`)."""
    range_m, _ = _axes(windows)
    total = torch.zeros(len(thresholds), dtype=torch.float64, device=windows.device)
    count = 0
    for pred, y in predictions:
        total += scan_f1_sweep(pred, y, range_m, thresholds).sum(dim=1)
        count += len(y)
    mean = (total / max(count, 1)).cpu().numpy()
    return float(thresholds[int(np.argmax(mean))]), mean


def model_predictor(model, *, amp: bool = True) -> Callable:
    def predict(x):
        device = (x[0] if isinstance(x, tuple) else x).device
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp and device.type == "cuda"):
            return predict_image(model, x)

    model.eval()
    return predict


def echo_peak_predictor(label_offset: int) -> Callable:
    """The classic sonar readout: one return per beam at its strongest echo, if strong enough."""

    def predict(x):
        return echo_peak_image(x[:, :, label_offset].float(), ECHO_PEAK_LEVEL)  # (B, 1, R, A)

    return predict


def empty_predictor(x):
    return torch.zeros_like(x[:, :, 0])


def summarise(per: dict[str, np.ndarray], scenario: np.ndarray, names: list[str]) -> dict:
    """Mean and std over all windows and per scenario (nan-aware: range errors are nan without a true positive)."""

    def stats(mask):
        return {k: {"mean": _nanmean(v[mask]), "std": _nanstd(v[mask])} for k, v in per.items()} | {
            "windows": int(mask.sum())
        }

    out = {"all": stats(np.ones(len(scenario), bool))}
    for i, name in enumerate(names):
        if (scenario == i).any():
            out[name] = stats(scenario == i)
    return out


def _nanmean(v):
    return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")


def _nanstd(v):
    return float(np.nanstd(v)) if np.isfinite(v).any() else float("nan")


def inference_timing(
    model, windows: Windows, *, repeats: int = 20, batch_size: int = 32, budget_s: float = 2.0
) -> dict:
    """Per-frame latency (batch 1, median) and batched throughput of the model on its device:
    up to `repeats` timed calls after two warm-ups, fewer (at least one) once `budget_s` is spent,
    so a slow CPU does not spend minutes on it."""
    sync = torch.cuda.synchronize if windows.device.type == "cuda" else (lambda: None)
    predict = model_predictor(model)
    x1, _ = windows.batch([0])
    xb, _ = windows.batch(np.arange(min(batch_size, len(windows))))

    def timed(x):
        times = []
        with torch.no_grad():
            while len(times) < repeats + 2 and (len(times) < 3 or sum(times) < budget_s):
                t0 = time.perf_counter()
                predict(x)
                sync()
                times.append(time.perf_counter() - t0)
        return float(np.median(times[2:])), len(times) - 2

    (single, n1), (batch, nb) = timed(x1), timed(xb)
    return {
        "device": str(windows.device),
        "ms_per_frame_batch1": 1e3 * single,
        "frames_per_s_batched": len(xb) / batch,
        "timed_calls": [n1, nb],
    }


def _named_checkpoints(checkpoint) -> dict[str, Path]:
    """{name: path} from one path, a list of paths or "name=path" strings, or a dict."""
    if isinstance(checkpoint, dict):
        return {str(k): Path(v) for k, v in checkpoint.items()}
    items = [checkpoint] if isinstance(checkpoint, str | Path) else list(checkpoint)
    if len(items) == 1 and "=" not in str(items[0]):
        return {"model": Path(items[0])}
    named = {}
    for item in items:
        name, sep, path = str(item).partition("=")
        name, path = (name, path) if sep else (Path(name).parent.name or Path(name).stem, name)
        if not name:
            raise ValueError(f"--checkpoint {item!r} has an empty name: give name=path, or the path alone")
        if name in named or name in ("echo peak", "empty"):
            raise ValueError(f"checkpoint name {name!r} is used twice or names a baseline; give name=path")
        named[name] = Path(path)
    return named


def evaluate(
    checkpoint,
    data: str | Path | Frames,
    out: str | Path,
    *,
    device: str = "cpu",
    split: str = "auto",
    episodes=None,
    from_frame: int = 0,
    batch_size: int = 32,
    examples: int = 4,
    timing: bool = True,
    threshold: float | None = None,
    progress: bool = False,
    odometry_noise: OdometryNoise | None = None,
    odometry_seed: int = 0,
    grids: bool = True,
) -> dict:
    """Score one or more checkpoints on a dataset (with baselines) and write metrics.json (means
    and std overall and per scenario), per_scenario.csv, per_window.csv (every metric of every
    window), examples.png and report.md into `out`.

    Args:
        checkpoint: A checkpoint path (reported as "model"), or several as a list of paths or
            "name=path" strings, or a {name: path} dict. All must share the window settings
            and grid; the first one picks the split and draws examples.png.
        split: "all" windows, "val" (the episodes the first checkpoint held out, on its own
            training data), or "auto" (val on the training data, else all).
        episodes: Episode ids to score instead of a split.
        from_frame: Score only the windows that start at least this many frames into their
            episode (e.g. past the pings a calibration was fitted to).
        threshold: Return threshold for every model instead of each checkpoint's calibrated one.
        progress: A progress bar per model and baseline while it is scored.
        odometry_noise: Models with memory (and the occupancy grids) read the drive's poses as
            odometry with this drift reports them (`learn.odometry`), drawn per episode from
            `odometry_seed`; None or all zero: the true poses.
        grids: Score the occupancy-grid baselines too (`learn.grid_baselines`; data with poses),
            fed by echo peaks and by the first model without memory.
    """
    from .plots import plot_examples

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a folder for the report")
    named = _named_checkpoints(checkpoint)
    models = {name: load_checkpoint(path, device) for name, path in named.items()}
    first_name = next(iter(models))
    ckpt = models[first_name][1]
    frames = data if isinstance(data, Frames) else load_frames(data)
    if odometry_noise is not None and odometry_noise.active:
        frames = with_noisy_odometry(frames, odometry_noise, seed=odometry_seed)
    data_config = DataConfig(**ckpt["data_config"])
    # the baselines' windows (and every model's on one elevation): the level slice, as a planar sonar has it
    windows = Windows(level_slice(frames), plain_windows(data_config), device)
    for name, (_, c) in models.items():
        check_grid(frames, c, name)
        theirs = DataConfig(**c["data_config"])
        if (theirs.frames, theirs.label) != (data_config.frames, data_config.label):
            raise ValueError(
                f"{name!r} reads other windows (K = {theirs.frames}, label {theirs.label}) than {first_name!r} "
                f"(K = {data_config.frames}, label {data_config.label}); compare alike"
            )
    indices, split = _pick_windows(windows, ckpt, frames, split, episodes)
    if from_frame < 0:
        raise ValueError(f"from_frame must be >= 0, got {from_frame}")
    if from_frame:
        indices = indices[windows.position[indices] >= from_frame]
        if len(indices) == 0:
            where = frames.info.get("folder")
            raise ValueError(f"no window of {where} starts {from_frame} or more frames into its episode")
    out.mkdir(parents=True, exist_ok=True)
    scenario = windows.scenario[indices]
    predictors = {}
    held = windows if windows.frames is frames else None  # one copy of the frames on the device
    for name, (m, c) in models.items():
        their_windows = model_windows(frames, c, device, share=held)
        held = their_windows if held is None else held
        predictors[name] = (model_predictor(m), return_threshold(c, threshold, str(named[name])), their_windows)
    predictors["echo peak"] = (echo_peak_predictor(data_config.label_offset), BASELINE_THRESHOLD, windows)
    predictors["empty"] = (empty_predictor, BASELINE_THRESHOLD, windows)
    if grids and frames.pose is not None:
        plain = [name for name, (_, c) in models.items() if not ModelConfig(**c["model_config"]).uses_odometry]
        feeders = {name: predictors[name] for name in plain[:1]}  # the first model without memory
        for name, images in grid_predictors(windows, indices, feeders, ECHO_PEAK_LEVEL).items():
            predictors[name] = (images, BASELINE_THRESHOLD, windows)
    results, per_window = {}, {}
    for name, (predict, t, their_windows) in predictors.items():
        bar = f"scoring {name}" if progress else None
        per_window[name] = score(predict, their_windows, indices, threshold=t, batch_size=batch_size, progress=bar)
        results[name] = summarise(per_window[name], scenario, frames.scenarios)
    report = {
        "checkpoints": {name: recorded_path(path) for name, path in named.items()},
        "checkpoint": recorded_path(named[first_name]),
        "data": frames.info.get("folder"),
        "suite": frames.info.get("suite"),
        "variant": frames.info.get("variant"),
        "split": split,
        "from_frame": from_frame,
        "windows": len(indices),
        "model": ckpt["model_config"],
        "parameters": ckpt["parameters"],
        "data_config": ckpt["data_config"],
        "thresholds": {name: t for name, (_, t, _) in predictors.items()},
        "odometry_noise": dataclasses.asdict(odometry_noise) if odometry_noise else None,
        "odometry_seed": odometry_seed if odometry_noise else None,
        "examples_from": first_name,
        "results": results,
    }
    if timing:
        report["inference"] = inference_timing(models[first_name][0], predictors[first_name][2])
    (out / "metrics.json").write_text(json.dumps(report, indent=1))
    write_per_scenario(out / "per_scenario.csv", results)
    write_per_window(out / "per_window.csv", per_window, indices, windows)
    for name in models:  # the same windows for every model, picked by the first one's scores
        rows = _example_rows(predictors, name, first_name, per_window, windows, indices, frames, examples)
        path = out / example_file(name, first=name == first_name)
        plot_examples(rows, frames.range_m, frames.azimuth_rad, path, threshold=predictors[name][1])
    (out / "report.md").write_text(report_markdown(report))
    return report


def plain_windows(config: DataConfig) -> DataConfig:
    """The windows without history: what a model without memory and the baselines read."""
    return dataclasses.replace(config, history=0, history_stride=1)


def model_windows(frames: Frames, ckpt: dict, device, share: Windows | None = None) -> Windows:
    """The windows a checkpoint's model reads (its history and motion for a model with memory),
    holding the frames on the device once with `share`'s."""
    model = ModelConfig(**ckpt["model_config"])
    data = DataConfig(**ckpt["data_config"])
    elevations = trained_elevations(model.elevation_deg)
    return Windows(frames, data, device, odometry=model.uses_odometry, share=share, elevation_deg=elevations)


def with_noisy_odometry(frames: Frames, noise: OdometryNoise, *, seed: int) -> Frames:
    """`frames` with its poses as odometry with `noise` reports them, one draw per episode (from
    `seed` and the episode id, so the same episode drifts alike in every run)."""
    if frames.pose is None:
        raise ValueError(f"{frames.info['folder']} holds no poses to add odometry noise to")
    pose = frames.pose.copy()
    for episode in np.unique(frames.episode):
        rows = np.flatnonzero(frames.episode == episode)
        rng = np.random.default_rng([seed, int(episode)])
        pose[rows] = noisy_drive(frames.pose[rows], noise, rng)
    return dataclasses.replace(frames, pose=pose)


def _pick_windows(windows: Windows, ckpt: dict, frames: Frames, split: str, episodes) -> tuple[np.ndarray, str]:
    same = frames.info.get("plan_id") is not None and frames.info.get("plan_id") == ckpt["dataset"]["plan_id"]
    if split == "auto":
        split = "val" if same else "all"
    if episodes is not None:
        indices = np.flatnonzero(np.isin(windows.episode, np.asarray(episodes)))
        if len(indices) == 0:
            raise ValueError(f"none of the episodes {list(episodes)[:5]}... is in {frames.info.get('folder')}")
        return indices, "episodes"
    if split == "val":
        if not same:
            raise ValueError("--split val needs the dataset the checkpoint was trained on")
        indices = np.flatnonzero(np.isin(windows.episode, ckpt["dataset"]["val_episodes"]))
        if len(indices) == 0:
            held = ckpt["dataset"]["val_episodes"]
            raise ValueError(
                f"{frames.info.get('folder')} holds no whole window of the episodes the checkpoint validated on "
                f"({held[:5]}{'...' if len(held) > 5 else ''}): score every window with --split all"
            )
        return indices, split
    if split == "all":
        return np.arange(len(windows)), split
    raise ValueError(f"split must be auto, val or all, got {split!r}")


def _example_rows(predictors, name, picker, per_window, windows, indices, frames, count) -> list[dict]:
    """Windows at evenly spaced quantiles of `picker`'s scan_f1, in that order (poor to good, none
    cherry-picked)."""
    f1 = per_window[name]["scan_f1"]
    rank = np.empty(len(f1), dtype=int)
    rank[np.argsort(f1, kind="stable")] = np.arange(len(f1))  # this model's rank of each window
    order = np.argsort(per_window[picker]["scan_f1"], kind="stable")
    picks = list(dict.fromkeys(int(order[round(q * (len(order) - 1))]) for q in np.linspace(0.1, 0.9, count)))
    predict, _, their_windows = predictors[name]
    offset = windows.config.label_offset
    rows = []
    for local in picks:
        x, y = windows.batch([indices[local]])
        with torch.no_grad():
            pred = predict(their_windows.batch([indices[local]])[0]).float().clamp(0, 1)
        peak = per_window["echo peak"]["scan_f1"][local]
        rows.append(
            {
                "title": f"{frames.scenarios[windows.scenario[indices[local]]]}, window {int(indices[local])}",
                "caption": f"{name}: scan_f1 {f1[local]:.2f}, beam accuracy "
                f"{per_window[name]['beam_accuracy'][local]:.2f} (rank {rank[local] + 1} of {len(f1)}); "
                f"echo peak scan_f1 {peak:.2f}",
                "sonar": x[0, windows.level, offset].cpu().numpy(),
                "truth": y[0, 0].cpu().numpy(),
                "pred": pred[0, 0].cpu().numpy(),
            }
        )
    return rows


# (key, column title, format): the primary metric first. Tables read their columns from here.
