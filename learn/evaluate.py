"""Evaluation: image and physical metrics per scenario, baselines beside the model, a report.

    python -m learn evaluate --checkpoint runs/unet/best.pt --data data/reality --out runs/unet/reality

Metrics per window (learn.metrics): MSE and SSIM of the image, per-beam range MAE [m] with the
shares of missed and false returns, Chamfer distance [m] between predicted and true points, and
occupancy IoU. Two baselines are scored the same way: "empty" (predicts no return anywhere:
what SSIM and MSE give for free on sparse labels) and "echo peak" (the strongest echo of each
beam of the label frame's energyscape, within 10 dB of the frame's peak).
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from .data import DataConfig, Frames, Windows, load_frames
from .metrics import image_metrics
from .models import predict_image

ECHO_PEAK_LEVEL = 0.75  # normalised input (40 dB floor): within 10 dB of the frame's peak


def score(predict: Callable, windows: Windows, indices: np.ndarray, *, batch_size: int = 32) -> dict[str, np.ndarray]:
    """Per-window metrics of a predictor x (B, 1, K, R, A) -> image (B, 1, R, A) in [0, 1]."""
    per: dict[str, list] = {}
    range_m = torch.as_tensor(windows.frames.range_m, device=windows.device)
    azimuth_rad = torch.as_tensor(windows.frames.azimuth_rad, device=windows.device)
    with torch.no_grad():
        for start in range(0, len(indices), batch_size):
            x, y = windows.batch(indices[start : start + batch_size])
            pred = predict(x).float().clamp(0, 1)
            for k, v in image_metrics(pred[:, 0], y[:, 0], range_m, azimuth_rad).items():
                per.setdefault(k, []).append(v.detach().double().cpu().numpy())
    return {k: np.concatenate(v) for k, v in per.items()}


def model_predictor(model, *, amp: bool = True) -> Callable:
    def predict(x):
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp and x.device.type == "cuda"):
            return predict_image(model, x)

    model.eval()
    return predict


def echo_peak_predictor(label_offset: int) -> Callable:
    """The classic sonar readout: one return per beam at its strongest echo, if strong enough."""

    def predict(x):
        frame = x[:, :, label_offset]  # (B, 1, R, A)
        peak, where = frame.max(dim=2, keepdim=True)
        image = torch.zeros_like(frame)
        image.scatter_(2, where, (peak >= ECHO_PEAK_LEVEL).float())
        return image

    return predict


def empty_predictor(x):
    return torch.zeros_like(x[:, :, 0])


def summarise(per: dict[str, np.ndarray], scenario: np.ndarray, names: list[str]) -> dict:
    """Mean and std over all windows and per scenario (nan-aware)."""

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
    model, windows: Windows, *, repeats: int = 20, batch_size: int = 32, budget_s: float = 5.0
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


def evaluate(
    checkpoint: str | Path,
    data: str | Path | Frames,
    out: str | Path,
    *,
    device: str = "cpu",
    split: str = "auto",
    episodes=None,
    batch_size: int = 32,
    examples: int = 4,
    timing: bool = True,
) -> dict:
    """Score a checkpoint on a dataset (with baselines) and write metrics.json, per_scenario.csv,
    examples.png and report.md into `out`. split: "all" windows, "val" (the episodes the
    checkpoint held out, on its own training data), or "auto" (val on the training data, else all).
    `episodes` (ids) scores those episodes only, whatever the split."""
    from .plots import plot_examples
    from .train import load_checkpoint

    model, ckpt = load_checkpoint(checkpoint, device)
    frames = data if isinstance(data, Frames) else load_frames(data)
    if not (np.allclose(frames.range_m, ckpt["range_m"]) and np.allclose(frames.azimuth_rad, ckpt["azimuth_rad"])):
        raise ValueError("the dataset's range/azimuth grid differs from the one the model was trained on")
    data_config = DataConfig(**ckpt["data_config"])
    windows = Windows(frames, data_config, device)
    same = frames.info.get("plan_id") is not None and frames.info.get("plan_id") == ckpt["dataset"]["plan_id"]
    if split == "auto":
        split = "val" if same else "all"
    if episodes is not None:
        split = "episodes"
        indices = np.flatnonzero(np.isin(windows.episode, np.asarray(episodes)))
        if len(indices) == 0:
            raise ValueError(f"none of the episodes {list(episodes)[:5]}... is in {frames.info.get('folder')}")
    elif split == "val":
        if not same:
            raise ValueError("--split val needs the dataset the checkpoint was trained on")
        indices = np.flatnonzero(np.isin(windows.episode, ckpt["dataset"]["val_episodes"]))
    elif split == "all":
        indices = np.arange(len(windows))
    else:
        raise ValueError(f"split must be auto, val or all, got {split!r}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = windows.scenario[indices]
    predictors = {
        "model": model_predictor(model),
        "echo peak": echo_peak_predictor(data_config.label_offset),
        "empty": empty_predictor,
    }
    results = {}
    for name, predict in predictors.items():
        per = score(predict, windows, indices, batch_size=batch_size)
        results[name] = summarise(per, scenario, frames.scenarios)
        if name == "model":
            model_per = per
    report = {
        "checkpoint": str(checkpoint),
        "data": frames.info.get("folder"),
        "suite": frames.info.get("suite"),
        "variant": frames.info.get("variant"),
        "split": split,
        "windows": len(indices),
        "model": ckpt["model_config"],
        "parameters": ckpt["parameters"],
        "data_config": ckpt["data_config"],
        "results": results,
    }
    if timing:
        report["inference"] = inference_timing(model, windows)
    (out / "metrics.json").write_text(json.dumps(report, indent=1))
    _write_per_scenario(out / "per_scenario.csv", results)
    # Examples: the median-SSIM window of a few scenarios, so the picture is typical, not cherry-picked.
    rows, predict = [], predictors["model"]
    for i in np.unique(scenario)[:examples]:
        local = np.flatnonzero(scenario == i)
        pick = indices[local[np.argsort(model_per["ssim"][local])[len(local) // 2]]]
        x, y = windows.batch([pick])
        with torch.no_grad():
            pred = predict(x).float().clamp(0, 1)
        rows.append(
            {
                "title": frames.scenarios[i],
                "sonar": x[0, 0, data_config.label_offset].cpu().numpy(),
                "truth": y[0, 0].cpu().numpy(),
                "pred": pred[0, 0].cpu().numpy(),
            }
        )
    plot_examples(rows, frames.range_m, frames.azimuth_rad, out / "examples.png")
    (out / "report.md").write_text(report_markdown(report))
    return report


METRICS = (("mse", "MSE", "{:.5f}"), ("ssim", "SSIM", "{:.4f}"), ("range_mae_m", "range MAE [m]", "{:.3f}"))
METRICS += (("missed", "missed", "{:.2f}"), ("false", "false", "{:.2f}"), ("chamfer_m", "Chamfer [m]", "{:.3f}"))
METRICS += (("iou", "IoU", "{:.3f}"),)


def _cell(stat, fmt):
    return fmt.format(stat["mean"]) + " ± " + fmt.format(stat["std"])


def report_markdown(report: dict) -> str:
    res = report["results"]
    head = "| predictor | " + " | ".join(label for _, label, _ in METRICS) + " |"
    rule = "|---" * (len(METRICS) + 1) + "|"
    lines = [
        f"# Evaluation: {report['model']['name']} (K = {report['data_config']['frames']}) on "
        f"{report['suite']}{' / ' + report['variant'] if report['variant'] else ''}",
        "",
        f"{report['windows']:,} windows ({report['split']} split) of `{report['data']}`; checkpoint "
        f"`{report['checkpoint']}` ({report['parameters']:,} parameters). Mean ± std over windows.",
        "",
        head,
        rule,
    ]
    for name, r in res.items():
        lines.append(f"| {name} | " + " | ".join(_cell(r["all"][k], f) for k, _, f in METRICS) + " |")
    lines += ["", "Model per scenario:", "", head.replace("predictor", "scenario"), rule]
    for scen, r in res["model"].items():
        if scen != "all":
            lines.append(f"| {scen} ({r['windows']}) | " + " | ".join(_cell(r[k], f) for k, _, f in METRICS) + " |")
    if "inference" in report:
        t = report["inference"]
        lines += [
            "",
            f"Inference on {t['device']}: {t['ms_per_frame_batch1']:.2f} ms per frame (batch 1), "
            f"{t['frames_per_s_batched']:,.0f} frames/s batched (medians of "
            f"{' and '.join(map(str, t['timed_calls']))} timed calls).",
        ]
    lines += ["", "![sonar, LiDAR truth and prediction](examples.png)", ""]
    return "\n".join(lines)


def _write_per_scenario(path: Path, results: dict) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["predictor", "scenario", "windows", *[f"{k}_{s}" for k, _, _ in METRICS for s in ("mean", "std")]]
        )
        for name, r in results.items():
            for scen, stats in r.items():
                row = [name, scen, stats["windows"]]
                row += [stats[k][s] for k, _, _ in METRICS for s in ("mean", "std")]
                writer.writerow(row)
