"""What an evaluation writes: the metric columns of every table, report.md and the per-window and
per-scenario CSV files (`learn.evaluate` scores; this module only lays the numbers out)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from .data import Windows
from .scan import EXTRA_TOLERANCES_M, tolerance_suffix


def example_file(name: str, *, first: bool) -> str:
    """examples.png for the first model of an evaluation, examples_<name>.png for the others."""
    return "examples.png" if first else "examples_" + "".join(c if c.isalnum() else "_" for c in name) + ".png"


METRICS = (
    ("scan_f1", "scan F1 @0.10 m", "{:.3f}"),
    ("beam_accuracy", "beam acc.", "{:.3f}"),
    ("return_precision", "precision", "{:.3f}"),
    ("return_recall", "recall", "{:.3f}"),
    ("range_mae_tp_m", "range MAE of TP [m]", "{:.3f}"),
    ("missed", "missed", "{:.2f}"),
    ("wrong_range", "wrong range", "{:.2f}"),
    ("false", "false", "{:.2f}"),
    ("chamfer_m", "Chamfer [m]", "{:.3f}"),
    ("iou", "IoU", "{:.3f}"),
)
OTHER_METRICS = (
    *(
        (f"{k}{tolerance_suffix(t)}", f"{label} @{t:.2f} m", "{:.3f}")
        for t in EXTRA_TOLERANCES_M
        for k, label in (("scan_f1", "scan F1"), ("beam_accuracy", "beam acc."))
    ),
    ("mse", "MSE", "{:.5f}"),
    ("ssim", "SSIM", "{:.4f}"),
    ("peak_range_mae_m", "peak range MAE [m] (ignores confidence)", "{:.3f}"),
)


def _cell(stat, fmt):
    if not np.isfinite(stat["mean"]):
        return "-"
    return fmt.format(stat["mean"]) + " ± " + fmt.format(stat["std"])


def _table(rows: dict, columns, first: str) -> list[str]:
    lines = [f"| {first} | " + " | ".join(label for _, label, _ in columns) + " |", "|---" * (len(columns) + 1) + "|"]
    lines += [f"| {name} | " + " | ".join(_cell(r[k], f) for k, _, f in columns) + " |" for name, r in rows.items()]
    return lines


def report_markdown(report: dict) -> str:
    res = report["results"]
    checkpoints = report.get("checkpoints", {"model": report["checkpoint"]})
    thresholds = report.get("thresholds", {})
    skipped = f", from frame {report['from_frame']} of each episode" if report.get("from_frame") else ""
    lines = [
        f"# Evaluation: {report['model']['name']} (K = {report['data_config']['frames']}) on {_scored_on(report)}",
        "",
        f"{report['windows']:,} windows ({report['split']} split{skipped}) of `{report['data']}`. Mean ± std over "
        "windows; "
        "a prediction is read as a LiDAR scan: per beam the nearest cell at or above the return threshold.",
        "",
        "| predictor | checkpoint | return threshold |",
        "|---|---|---|",
    ]
    for name in res:
        source = f"`{checkpoints[name]}`" if name in checkpoints else "baseline"
        lines.append(f"| {name} | {source} | {thresholds.get(name, float('nan')):.2f} |")
    lines += ["", *_table({n: r["all"] for n, r in res.items()}, METRICS, "predictor")]
    lines += ["", "Other tolerances and the image metrics (MSE and SSIM reward empty images on sparse labels):", ""]
    lines += _table({n: r["all"] for n, r in res.items()}, OTHER_METRICS, "predictor")
    first = report.get("examples_from", "model")
    lines += ["", f"{first} per scenario (windows):", ""]
    per = {f"{s} ({r['windows']})": r for s, r in res[first].items() if s != "all"}
    lines += _table(per, METRICS, "scenario")
    if "inference" in report:
        t = report["inference"]
        lines += [
            "",
            f"Inference of {first} on {t['device']}: {t['ms_per_frame_batch1']:.2f} ms per frame (batch 1), "
            f"{t['frames_per_s_batched']:,.0f} frames/s batched (medians of "
            f"{' and '.join(map(str, t['timed_calls']))} timed calls).",
        ]
    lines += [
        "",
        f"Examples: windows at evenly spaced quantiles of {first}'s scan F1, its poorest at the top and its best "
        "at the bottom (not picked by hand); each row shows the sonar input, the LiDAR truth, the prediction and "
        "the scan read from it, from above.",
    ]
    for name in checkpoints:
        path = example_file(name, first=name == first)
        lines += ["", f"`{path}`: predictions of {name} (`{checkpoints[name]}`).", "", f"![{name}]({path})"]
    if any(" - |" in line for line in lines):
        lines += ["", "`-`: no window defines it (the range MAE of true positives needs at least one true positive)."]
    lines.append("")
    return "\n".join(lines)


def _scored_on(report: dict) -> str:
    """What the evaluation scored: the suite's name read as a suite (`paper` is a suite, not the
    paper), with its variant; the folder where the data names no suite (a recording)."""
    if not report.get("suite"):
        return f"`{report['data']}`"
    variant = f", variant `{report['variant']}`" if report.get("variant") else ""
    return f"the `{report['suite']}` suite{variant}"


def write_per_window(path: Path, per_window: dict, indices: np.ndarray, windows: Windows) -> None:
    """One row per predictor and window: its index, episode, scenario and every metric."""
    keys = list(next(iter(per_window.values())))
    names = windows.frames.scenarios
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["predictor", "window", "episode", "scenario", *keys])
        for name, per in per_window.items():
            for i, w in enumerate(indices):
                row = [name, int(w), int(windows.episode[w]), names[windows.scenario[w]]]
                writer.writerow(row + [f"{per[k][i]:.6g}" for k in keys])


def write_per_scenario(path: Path, results: dict) -> None:
    keys = [k for k, _, _ in METRICS + OTHER_METRICS]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["predictor", "scenario", "windows", *[f"{k}_{s}" for k in keys for s in ("mean", "std")]])
        for name, r in results.items():
            for scen, stats in r.items():
                writer.writerow([name, scen, stats["windows"], *[stats[k][s] for k in keys for s in ("mean", "std")]])
