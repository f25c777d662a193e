"""Pictures of learning: loss/metric curves and sonar / LiDAR / prediction grids (Fig 4 style)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np


def plot_curves(history: list[dict], out: str | Path) -> Path:
    """Training loss and the validation metrics per epoch."""
    epochs = [r["epoch"] for r in history]
    panels = [("train_loss", "training loss"), ("val_ssim", "validation SSIM"), ("val_range_mae_m", "range MAE [m]")]
    panels.append(("val_iou", "occupancy IoU"))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.4))
    for ax, (key, title) in zip(axes, panels, strict=True):
        ax.plot(epochs, [r.get(key, np.nan) for r in history], "o-")
        ax.set_title(title)
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return Path(out)


def _polar(ax, image, range_m, azimuth_rad, title, cmap, vmax=None):
    az = np.rad2deg(azimuth_rad)
    extent = (az[-1], az[0], range_m[0], range_m[-1])
    ax.imshow(image[:, ::-1], origin="lower", aspect="auto", extent=extent, cmap=cmap, vmin=0, vmax=vmax)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("azimuth [deg]")
    ax.set_ylabel("range [m]")


def plot_examples(rows: list[dict], range_m, azimuth_rad, out: str | Path) -> Path:
    """One row per example: sonar input (label frame, normalised), LiDAR truth, prediction.

    Args:
        rows: dicts with "title", "sonar" (R, A) in [0, 1], "truth" (R, A), "pred" (R, A).
    """
    fig, axes = plt.subplots(len(rows), 3, figsize=(11, 3.2 * len(rows)), squeeze=False)
    for (a, b, c), row in zip(axes, rows, strict=True):
        _polar(a, row["sonar"], range_m, azimuth_rad, f"sonar: {row['title']}", "magma", 1.0)
        _polar(b, row["truth"], range_m, azimuth_rad, "LiDAR (truth)", "gray_r", 1.0)
        _polar(c, row["pred"], range_m, azimuth_rad, "prediction", "gray_r", 1.0)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return Path(out)
