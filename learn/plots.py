"""Pictures of learning: loss/metric curves, sonar / LiDAR / prediction grids (Fig 4 style), drives from above."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from clitools import counted

_FONT = {"font.size": 10, "axes.titlesize": 11, "axes.labelsize": 10, "legend.fontsize": 9}
_NEAR_M = 0.10  # a predicted return this close to the true one (same column) is drawn as a hit
_ALONE = "tab:purple"  # a predicted scan without truth: neither the hits' green nor the misses' red
_NO_TRUTH = "no LiDAR truth in this data: the predicted scan alone"


def plot_curves(
    history: list[dict], out: str | Path, *, kept_epoch: int | None = None, monitor: str | None = None
) -> Path:
    """Training loss and the validation metrics per epoch; a panel whose keys are all absent is left out.

    Args:
        history: One dict per epoch: "epoch", "train_loss" and "val_*" metrics (any may be missing).
        out: PNG path.
        kept_epoch: Epoch of the kept checkpoint, marked by a dashed line on every panel.
        monitor: Validation metric that picked `kept_epoch` (e.g. "scan_f1"), named in the title.
    """
    epochs = [r["epoch"] for r in history]
    panels = [  # title, y label, ((key, label), ...)
        ("loss", "loss", (("train_loss", "train"), ("val_loss", "validation"))),
        (
            "scan F1",
            "share",
            (
                ("val_scan_f1", "validation F1"),
                ("val_return_precision", "validation precision"),
                ("val_return_recall", "validation recall"),
            ),
        ),
        ("missed and false returns", "share", (("val_missed", "validation missed"), ("val_false", "validation false"))),
        (
            "range error",
            "distance [m]",
            (("val_range_mae_tp_m", "validation range MAE, true positives"), ("val_chamfer_m", "validation Chamfer")),
        ),
        ("return threshold", "threshold", (("val_threshold", "calibrated threshold"),)),
    ]
    # The loss panel always stays: train_loss is logged every epoch.
    panels = [p for p in panels if p[0] == "loss" or any(key in r for key, _ in p[2] for r in history)]
    pad = max(0.5, 0.02 * (max(epochs) - min(epochs)))  # one x range for all panels, even a panel with one point
    with plt.rc_context(_FONT):
        cols = min(3, len(panels))
        rows = -(-len(panels) // cols)
        fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 4 * rows), squeeze=False, layout="constrained")
        for ax in axes.flat[len(panels) :]:
            ax.set_visible(False)
        marker = "o" if len(epochs) <= 40 else None  # markers clutter long runs
        for ax, (title, ylabel, keys) in zip(axes.flat, panels, strict=False):
            for key, label in keys:
                values = np.array([r.get(key, np.nan) for r in history], dtype=float)
                if np.isfinite(values).any():
                    ax.plot(epochs, values, marker=marker, markersize=3, label=label)
                if key == "train_loss":
                    finite = values[np.isfinite(values)]
                    # The first epochs' loss dwarfs the rest on a linear axis.
                    if len(finite) and finite.min() > 0 and finite.max() > 20 * finite.min():
                        ax.set_yscale("log")
            if kept_epoch is not None:
                ax.axvline(kept_epoch, color="0.3", linestyle="--", linewidth=1, label=f"kept epoch {kept_epoch}")
            ax.set(title=title, xlabel="epoch", ylabel=ylabel, xlim=(min(epochs) - pad, max(epochs) + pad))
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.grid(alpha=0.3)
            ax.legend()
        if kept_epoch is not None:
            why = f" (best validation {monitor.removeprefix('val_')})" if monitor else ""
            fig.suptitle(f"kept epoch {kept_epoch}{why}", fontsize=12)
        fig.savefig(out, dpi=90)
    plt.close(fig)
    return Path(out)


def _first_return(image: np.ndarray, range_m: np.ndarray, threshold: float) -> np.ndarray:
    """The scan the metrics read (`learn.scan.first_return_ranges`) of one (R, A) image: (A,) [m], inf = none."""
    import torch

    from .scan import first_return_ranges

    return first_return_ranges(torch.as_tensor(np.asarray(image))[None], range_m, threshold=threshold)[0].numpy()


def _edges(centres: np.ndarray) -> tuple[float, float]:
    """Outer cell edges of a uniform grid of bin centres."""
    half = 0.5 * (centres[-1] - centres[0]) / max(len(centres) - 1, 1)
    return centres[0] - half, centres[-1] + half


def _polar(fig, ax, image, range_m, azimuth_rad, title, cmap, label):
    """(R, A) image with +azimuth (left) on the left, as in the top-down view; returns the colour bar."""
    az0, az1 = np.rad2deg(_edges(azimuth_rad))
    r0, r1 = _edges(range_m)
    im = ax.imshow(
        image, origin="lower", aspect="auto", extent=(az0, az1, r0, r1), cmap=cmap, vmin=0, vmax=1, interpolation="none"
    )
    ax.set_xlim(az1, az0)
    ax.set_xticks([t for t in (90, 45, 0, -45, -90) if az0 <= t <= az1])
    ax.set(title=title, xlabel="azimuth [deg] (+ = left)", ylabel="range [m]")
    return fig.colorbar(im, ax=ax, label=label, fraction=0.08, pad=0.02)


def _top_down(ax, truth_r, pred_r, range_m, azimuth_rad):
    """Sensor-frame map seen from above, x forward up the page, y left to the left. `truth_r` None:
    data without LiDAR truth, so the predicted scan is drawn alone, neither hit nor false."""
    rmax = float(range_m[-1])
    # Horizontal axis is y, inverted so that left (+y) is on the left; vertical is x.
    arc = np.linspace(azimuth_rad[0], azimuth_rad[-1], 200)
    for ring in np.arange(1.0, rmax + 1e-9, 1.0):  # 1 m rings; they cross the y axis at its 1 m ticks
        ax.plot(ring * np.sin(arc), ring * np.cos(arc), color="0.8", linewidth=0.8, zorder=0)
    for a in (azimuth_rad[0], azimuth_rad[-1]):
        ax.plot([0, rmax * np.sin(a)], [0, rmax * np.cos(a)], "--", color="0.5", linewidth=1, zorder=0)
    ax.plot([], [], "--", color="0.5", linewidth=1, label="field of view")
    ax.plot(0, 0, marker="^", markersize=12, color="tab:blue", linestyle="none", zorder=4, label="robot, heading +x")

    def xy(r):
        keep = np.isfinite(r)
        return r[keep] * np.sin(azimuth_rad[keep]), r[keep] * np.cos(azimuth_rad[keep])

    title = "top view (robot heading up)"
    if truth_r is None:  # nothing to compare with: no colour may say right or wrong
        count = counted(int(np.isfinite(pred_r).sum()), "return")
        ax.scatter(*xy(pred_r), s=9, color=_ALONE, label=f"predicted scan ({count})", zorder=3)
        title = "top view (robot heading up), no truth to compare"
    else:
        with np.errstate(invalid="ignore"):  # inf - inf is nan: a column with no return on either side is no hit
            near = np.abs(pred_r - truth_r) <= _NEAR_M
        off = np.where(near, np.inf, pred_r)
        hits = np.where(near, pred_r, np.inf)
        ax.scatter(*xy(truth_r), s=14, color="black", label="LiDAR truth", zorder=2)
        within = f"predicted scan, within {_NEAR_M:.2f} m ({near.sum()})"
        ax.scatter(*xy(hits), s=9, color="tab:green", label=within, zorder=3)
        off_count = np.isfinite(off).sum()
        ax.scatter(*xy(off), s=9, color="tab:red", label=f"predicted scan, off / false ({off_count})", zorder=3)
    side = rmax * max(np.sin(np.abs(azimuth_rad)).max(), 0.2) * 1.05
    ax.set_xlim(side, -side)
    ax.set_ylim(min(rmax * np.cos(np.abs(azimuth_rad)).min(), 0) - 0.3, rmax * 1.05)
    ax.set_aspect("equal")
    ax.set_xticks(np.arange(-np.floor(side), np.floor(side) + 1))
    ax.set(title=title, xlabel="y [m] (left +)", ylabel="x [m] (forward)")
    # Outside, to the right: the half disc fills the axes and a legend inside would hide returns.
    ax.legend(loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=9)


def plot_examples(rows: list[dict], range_m, azimuth_rad, out: str | Path, *, threshold: float = 0.5) -> Path:
    """`examples_figure` saved as `out` (PNG, or any format matplotlib writes by its suffix)."""
    with plt.rc_context(_FONT):
        fig = examples_figure(rows, range_m, azimuth_rad, threshold=threshold)
        fig.savefig(out, dpi=90)
    plt.close(fig)
    return Path(out)


def examples_figure(rows: list[dict], range_m, azimuth_rad, *, threshold: float = 0.5) -> Figure:
    """One row per example: sonar input, LiDAR truth, prediction (polar images) and a top view of both
    scans; a row without truth (recorded data) shows sonar, prediction and the predicted scan alone,
    and its title says that the data holds no truth. The figure is left open: close it.

    Args:
        rows: Dicts with "title", "sonar" (R, A) normalised echo level in [0, 1] of the label frame,
            "truth" (R, A) 0/1 LiDAR image or None where the data holds none, "pred" (R, A) return
            probability, optional "caption" (metrics text) and "threshold" (this row's, instead of
            `threshold`).
        range_m: Range bin centres [m], ascending, shape (R,).
        azimuth_rad: Azimuth bin centres [rad], ascending, positive left, shape (A,).
        threshold: Probability at which a predicted cell counts as a return.
    """
    range_m, azimuth_rad = np.asarray(range_m, dtype=float), np.asarray(azimuth_rad, dtype=float)
    width = 18 if any(row["truth"] is not None for row in rows) else 14  # a panel fewer without truth
    with plt.rc_context(_FONT):
        fig = plt.figure(figsize=(width, 4.2 * len(rows)), layout="constrained")
        subfigs = np.atleast_1d(fig.subfigures(len(rows), 1))
        for sub, row in zip(subfigs, rows, strict=True):
            truth = row["truth"]
            notes = [row.get("caption")] + ([_NO_TRUTH] if truth is None else [])
            sub.suptitle("  |  ".join([row["title"], *filter(None, notes)]), fontsize=12, fontweight="bold")
            if truth is None:
                sonar_ax, pred_ax, top_ax = sub.subplots(1, 3, width_ratios=(1, 1, 2.1))
            else:
                sonar_ax, truth_ax, pred_ax, top_ax = sub.subplots(1, 4, width_ratios=(1, 1, 1, 2.1))
            echo = "echo level (0 = -40 dB, 1 = peak)"
            _polar(sub, sonar_ax, row["sonar"], range_m, azimuth_rad, "sonar input", "magma", echo)
            if truth is not None:
                cbar = _polar(sub, truth_ax, truth, range_m, azimuth_rad, "LiDAR truth", "gray_r", "LiDAR return")
                cbar.set_ticks([0, 1])
            level = row.get("threshold", threshold)
            label = f"return probability (red: threshold {level:.2f})"
            cbar = _polar(sub, pred_ax, row["pred"], range_m, azimuth_rad, "prediction", "gray_r", label)
            cbar.ax.axhline(level, color="tab:red", linewidth=2)
            truth_r = None if truth is None else _first_return(truth, range_m, 0.5)
            pred_r = _first_return(row["pred"], range_m, level)
            _top_down(top_ax, truth_r, pred_r, range_m, azimuth_rad)
    return fig


def world_points(ranges, poses, azimuth_rad) -> np.ndarray:
    """The world-frame points of a drive's returns, frame by frame, each frame's beams in order.

    Args:
        ranges: Range [m] per frame and beam, shape (T, A); inf or NaN = no return (left out).
        poses: Planar sensor poses x [m], y [m], yaw [rad] in the world, shape (T, 3).
        azimuth_rad: Beam directions [rad], 0 = sensor x axis (ahead), positive left, shape (A,).

    Returns:
        x, y [m] of each return, float64, shape (N, 2).
    """
    ranges, poses = np.asarray(ranges, dtype=np.float64), np.asarray(poses, dtype=np.float64)
    heading = poses[:, 2:3] + np.asarray(azimuth_rad, dtype=np.float64)[None, :]
    keep = np.isfinite(ranges)
    r = np.where(keep, ranges, 0.0)
    x, y = poses[:, :1] + r * np.cos(heading), poses[:, 1:2] + r * np.sin(heading)
    return np.stack([x[keep], y[keep]], axis=1)


def plot_drive_from_above(scans: dict[str, np.ndarray], poses, azimuth_rad, out: str | Path, *, title=None) -> Path:
    """A whole drive seen from above: one panel per named scan set, each its returns in the world and the path.

    Every panel has the same limits (all sets' returns and the path) and equal aspect, so a wall
    that stays put, a ghost that smears along the path or a wall that only memory keeps show as
    such side by side.

    Args:
        scans: Name (e.g. "truth", "K = 5", "memory", "occupancy grid") -> ranges [m] per frame and
            beam, shape (T, A), inf or NaN = no return.
        poses: Planar sensor poses x [m], y [m], yaw [rad] in the world, shape (T, 3).
        azimuth_rad: Beam directions [rad], 0 = ahead, positive left, shape (A,).
        out: PNG path.
        title: Figure title.
    """
    poses = np.asarray(poses, dtype=np.float64)
    points = {name: world_points(ranges, poses, azimuth_rad) for name, ranges in scans.items()}
    everything = np.concatenate([poses[:, :2], *points.values()])
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    pad = 0.03 * float((hi - lo).max()) + 0.2
    lo, hi = lo - pad, hi + pad
    cols = min(len(points), 4)
    rows = -(-len(points) // cols)
    tall = float(np.clip((hi[1] - lo[1]) / (hi[0] - lo[0]), 0.3, 3.0))  # panel height per width
    with plt.rc_context(_FONT):
        fig, axes = plt.subplots(
            rows, cols, figsize=(4.5 * cols, 4.5 * rows * tall + 0.8), squeeze=False, layout="constrained"
        )
        for ax in axes.flat[len(points) :]:
            ax.set_visible(False)
        for ax, (name, xy) in zip(axes.flat, points.items(), strict=False):
            ax.scatter(xy[:, 0], xy[:, 1], s=1.5, color="black", linewidths=0, rasterized=True, label="returns")
            ax.plot(poses[:, 0], poses[:, 1], color="tab:blue", linewidth=1.2, label="sensor path")
            ax.plot(*poses[0, :2], marker="o", color="tab:blue", linestyle="none", label="start")
            ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), title=f"{name} ({len(xy):,} returns)")
            ax.set(xlabel="x [m]", ylabel="y [m]")
            ax.set_aspect("equal")
            ax.grid(alpha=0.3)
        handles, labels = axes.flat[0].get_legend_handles_labels()
        # A dot as small as the panels' would not show in the legend.
        handles[0] = Line2D([], [], marker="o", markersize=3, color="black", linestyle="none")
        fig.legend(handles, labels, loc="outside lower center", ncols=3)
        if title:
            fig.suptitle(title, fontsize=12)
        fig.savefig(out, dpi=90)
    plt.close(fig)
    return Path(out)


def plot_elevation_examples(
    rows: list[dict], range_m, azimuth_rad, elevation_deg, out: str | Path, *, title: str | None = None
) -> Path:
    """One row per window: the label frame's sonar input at each elevation, then a top view of each model's scan
    beside the LiDAR truth, so a ghost or a band that one model reads as a wall and another does not shows as such.

    Args:
        rows: Dicts with "title", "sonar" (E, R, A) normalised echo level in [0, 1] of the label frame,
            "truth" (A,) true range per beam [m] (inf = none) and "scans" {model name: (A,) range per beam [m]}.
        range_m: Range bin centres [m], ascending, shape (R,).
        azimuth_rad: Azimuth bin centres [rad], ascending, positive left, shape (A,).
        elevation_deg: Elevation of each sonar slice [deg], shape (E,).
        out: PNG path.
        title: Figure title.
    """
    range_m, azimuth_rad = np.asarray(range_m, dtype=float), np.asarray(azimuth_rad, dtype=float)
    elevations = np.atleast_1d(np.asarray(elevation_deg, dtype=float))
    models = len(rows[0]["scans"])
    with plt.rc_context(_FONT):
        fig = plt.figure(figsize=(4.6 * len(elevations) + 6.5 * models, 4.2 * len(rows) + 0.5), layout="constrained")
        subfigs = np.atleast_1d(fig.subfigures(len(rows), 1))
        for sub, row in zip(subfigs, rows, strict=True):
            sub.suptitle(row["title"], fontsize=12, fontweight="bold")
            axes = sub.subplots(1, len(elevations) + models, width_ratios=(1,) * len(elevations) + (1.45,) * models)
            for ax, image, elevation in zip(axes[: len(elevations)], row["sonar"], elevations, strict=True):
                _polar(sub, ax, image, range_m, azimuth_rad, f"sonar input at {elevation:+.0f} deg", "magma", "echo")
            for ax, (name, scan) in zip(axes[len(elevations) :], row["scans"].items(), strict=True):
                _top_down(ax, row["truth"], scan, range_m, azimuth_rad)
                ax.set_title(name)
        if title:
            fig.suptitle(title, fontsize=12)
        fig.savefig(out, dpi=80)
    plt.close(fig)
    return Path(out)
