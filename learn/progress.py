"""What a training run tells and leaves behind: one line per epoch, the warning for a model that
predicts no return, history.csv and curves.png, the k-fold summary."""

from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path

import numpy as np

NO_RETURN_ALARM = 0.9
"""Warn when the kept model predicts no return on at least this share of the validation beams."""


def epoch_line(row: dict, config, state: dict, improved: bool) -> str:
    """One line per epoch: what the validation windows say, and whether this epoch is kept."""
    kept = "kept" if improved else f"not better for {state['stale']} (best: epoch {state.get('best_epoch', '-')})"
    line = (
        f"epoch {row['epoch']}/{config.epochs}: train loss {row['train_loss']:.4g} | val scan F1 "
        f"{row['val_scan_f1']:.3f} (precision {row['val_return_precision']:.2f}, "
        f"recall {row['val_return_recall']:.2f}, missed {row['val_missed']:.2f}, false {row['val_false']:.2f}) "
        f"at threshold {row['val_threshold']:.2f}"
    )
    if config.monitor != "scan_f1":
        line += f", {config.monitor} {row[f'val_{config.monitor}']:.4g}"
    return f"{line} | {kept}"


def warn_if_silent(best: dict, out: Path, hint: str = "") -> None:
    """A model that predicts no return almost anywhere looks fine on MSE and SSIM: say so loudly."""
    share = best["val_no_return"]
    if share >= NO_RETURN_ALARM:
        warnings.warn(
            f"{out}: the kept model (epoch {best['epoch']}) predicts no return on {share:.0%} of the validation "
            f"beams even at its best threshold {best['val_threshold']:.2f} (scan F1 {best['val_scan_f1']:.3f}): it "
            f"has not learnt to place walls. Train longer or on more data{hint}.",
            stacklevel=3,
        )


def write_history(out: Path, history: list[dict], kept_epoch: int | None, monitor: str) -> None:
    with open(out / "history.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(history[0]))
        writer.writeheader()
        writer.writerows(history)
    from .plots import plot_curves

    plot_curves(history, out / "curves.png", kept_epoch=kept_epoch, monitor=monitor)


def write_fold_summary(out: Path, results: list[dict]) -> None:
    keys = list(results[0]["best"])
    table = {k: [r["best"][k] for r in results] for k in keys}
    summary = {k: {"mean": float(np.mean(v)), "std": float(np.std(v)), "folds": v} for k, v in table.items()}
    (out / "folds.json").write_text(json.dumps(summary, indent=1))
    lines = ["| metric | mean | std |", "|---|---|---|"]
    lines += [f"| {k} | {s['mean']:.4g} | {s['std']:.4g} |" for k, s in summary.items()]
    (out / "folds.md").write_text(f"# {len(results)}-fold cross-validation\n\n" + "\n".join(lines) + "\n")
