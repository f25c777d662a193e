"""Pictures of simulation output: scenes from above, trajectories, scans and polar images."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.backend_bases import FigureCanvasBase
from matplotlib.collections import LineCollection

from clitools import counted
from scenes import Scene

from .config import LidarConfig, PolarGrid
from .engine.lidar import ranges_to_points

_MATERIAL_COLORS = {
    "painted_wall": "0.25",
    "brick": "tab:brown",
    "floor": "0.6",
    "ceiling_tile": "0.7",
    "wood": "tab:orange",
    "metal": "tab:purple",
    "fabric": "tab:green",
    "glass": "tab:cyan",
    "mirror": "tab:pink",
}


def draw_scene_top(ax, scene: Scene, *, height: float) -> None:
    """Cross-section of the scene `height` [m] above the floor, coloured by material."""
    segments, faces = scene.section(height)
    material_ids = scene.face_material[faces]
    for k, mat in enumerate(scene.materials):
        sel = material_ids == k
        if sel.any():
            ax.add_collection(
                LineCollection(
                    segments[sel], colors=_MATERIAL_COLORS.get(mat.name, "k"), linewidths=1.6, label=mat.name
                )
            )
    lo, hi = scene.mesh.bounds[:, :2]
    pad = 0.05 * float(np.max(hi - lo))
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def check_picture_name(out: Path) -> None:
    """Refuse, before anything is drawn, an --out whose suffix names no format matplotlib writes
    (no suffix: PNG) or that names no file."""
    formats = FigureCanvasBase.get_supported_filetypes()
    if not out.name or out.name in (".", ".."):
        raise ValueError(f"--out {str(out)!r} names no file; give a picture file such as scene.png")
    if out.suffix and out.suffix[1:].lower() not in formats:
        raise ValueError(f"--out {out}: {out.suffix} is no picture format; give one of .{', .'.join(sorted(formats))}")


def draw_polar_image(
    ax, image: np.ndarray, grid: PolarGrid, *, title: str, cmap: str = "magma", label: str | None = None
) -> None:
    """A (range, azimuth) image with azimuth [deg] across (left = +90 deg, as seen from above)
    and range [m] upwards."""
    half = grid.azimuth_step_deg / 2
    extent = (grid.azimuth_max_deg + half, grid.azimuth_min_deg - half, grid.range_min_m, grid.range_max_m)
    im = ax.imshow(image[:, ::-1], origin="lower", aspect="auto", extent=extent, cmap=cmap, interpolation="nearest")
    ax.set_xlabel("azimuth [deg] (+ = left)")
    ax.set_ylabel("range [m]")
    ax.set_title(title)
    if label:
        plt.colorbar(im, ax=ax, label=label, fraction=0.046)


def draw_energyscape(
    ax,
    image: np.ndarray,
    lidar: np.ndarray | None,
    grid: PolarGrid,
    *,
    title: str,
    dynamic_range_db: float = 40.0,
    peak: float | None = None,
) -> None:
    """An energyscape (R, A) in dB below its peak (or `peak`, to compare images on one scale),
    with the LiDAR image's occupied cells on top."""
    peak = float(image.max()) if peak is None else peak
    db = 20 * np.log10(np.maximum(image / max(peak, 1e-30), 10 ** (-dynamic_range_db / 20)))
    draw_polar_image(ax, db, grid, title=title, label="dB")
    if lidar is not None:
        lidar_r, lidar_a = np.nonzero(lidar)
        az_deg = grid.azimuth_min_deg + lidar_a * grid.azimuth_step_deg
        ax.scatter(az_deg, grid.range_m[lidar_r], s=3, color="cyan", label="LiDAR", zorder=3)
        ax.legend(loc="upper right", fontsize=8)


def render_examples(examples: list[tuple[str, np.ndarray, np.ndarray]], grid: PolarGrid, out: str | Path) -> Path:
    """A row of (title, energyscape (R, A), LiDAR image (R, A)) panels, e.g. for a dataset card."""
    out = Path(out)
    fig, axes = plt.subplots(1, len(examples), figsize=(5.5 * len(examples), 4.8), squeeze=False)
    for ax, (title, image, lidar) in zip(axes[0], examples, strict=True):
        draw_energyscape(ax, np.asarray(image, dtype=np.float32), lidar, grid, title=title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return out


def render_calibration(fit, energyscapes: list[tuple[str, np.ndarray]], grid: PolarGrid, out: str | Path) -> Path:
    """A calibration at a glance: the relative error at each step, each class's R (and where fitted
    its s) before and after, each microphone's fitted gain and delay, the emitter's directivity
    where it was fitted, the echo energy per bin where s was fitted to it, and one ping's
    energyscapes (recorded, simulated with the nominal and the fitted values), in dB below the
    first one's peak."""
    out = Path(out)
    n = len(energyscapes)
    optional = ((_directivity_panel, len(fit.directivity) > 0), (_energy_panel, fit.energy is not None))
    extra = [panel for panel, drawn in optional if drawn]
    top = 3 + len(extra)
    fig = plt.figure(figsize=(5.5 * max(n, top), 8.6))  # a top panel as wide as an energyscape: labels clear
    grid_spec = fig.add_gridspec(2, top * n)  # the top row's panels over the bottom row's n
    loss = fig.add_subplot(grid_spec[0, :n])
    loss.semilogy(np.arange(1, len(fit.loss) + 1), fit.loss, marker=".")
    loss.set(xlabel="evaluation", ylabel="error energy / recording's", title="fit")
    bars = fig.add_subplot(grid_spec[0, n : 2 * n])
    where = np.arange(len(fit.classes))
    shown = [("R", fit.nominal, fit.reflection, None)]
    if fit.scattering_fitted.any():  # s beside R, hatched, where it was fitted
        shown.append(("s", fit.scattering_nominal, np.where(fit.scattering_fitted, fit.scattering, np.nan), "//"))
    width = 0.8 / (2 * len(shown))
    for j, (name, start, fitted, hatch) in enumerate(shown):
        left = where - 0.4 + 2 * j * width + width / 2
        bars.bar(left, start, width, color="tab:blue", hatch=hatch, label=f"{name}: scene (start)")
        bars.bar(left + width, fitted, width, color="tab:orange", hatch=hatch, label=f"{name}: fitted")
    bars.set_xticks(where, fit.classes, rotation=20)
    ylabel = "energy reflection R" + (", scattering s (hatched)" if len(shown) > 1 else "")
    bars.set(ylabel=ylabel, ylim=(0, 1.05), title="surface classes")
    bars.legend(loc="upper right", fontsize=8)
    mics = fig.add_subplot(grid_spec[0, 2 * n : 3 * n])
    index = np.arange(len(fit.mic_gain_db))
    mics.bar(index, fit.mic_gain_db, 0.8, color="tab:blue")
    mics.set(xlabel="microphone", title="microphones (fitted)")
    mics.set_ylabel("gain [dB]", color="tab:blue")
    lags = mics.twinx()
    lags.plot(index, fit.mic_delay_s * 1e6, "o", color="tab:red", markersize=4)
    lags.set_ylabel("delay [us]", color="tab:red")
    for k, panel in enumerate(extra, start=3):
        panel(fig.add_subplot(grid_spec[0, k * n : (k + 1) * n]), fit)
    peak = float(np.max(energyscapes[0][1]))  # one dB scale: the first image's peak
    for k, (title, image) in enumerate(energyscapes):
        ax = fig.add_subplot(grid_spec[1, top * k : top * k + top])
        draw_energyscape(ax, np.asarray(image, dtype=np.float32), None, grid, title=title, peak=peak)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80, bbox_inches="tight")
    plt.close(fig)
    return out


def _directivity_panel(beam, fit) -> None:
    beam.plot(fit.directivity_deg, fit.directivity_nominal, "o-", label="nominal piston (start)")
    beam.plot(fit.directivity_deg, fit.directivity, "o-", label="fitted")
    beam.axhline(0.0, color="0.6", linewidth=0.8)
    beam.set(xlabel="angle from the emitter's axis [deg]", ylabel="pressure (1 on axis)", title="emitter")
    beam.legend(loc="upper right", fontsize=8)


def _energy_panel(ax, fit) -> None:
    """The energy stage: the recordings' echo energy per bin beside the simulation's (plus the
    fitted noise) at the waveform fit's s and at the fitted s."""
    energy = fit.energy
    start_ms = energy.bin_start_s * 1e3
    ax.semilogy(start_ms, energy.recorded, "k.-", label="recorded")
    ax.semilogy(start_ms, energy.before, "-", label=f"simulated, waveform's s ({energy.loss_before:.2g})")
    ax.semilogy(start_ms, energy.after, "-", label=f"simulated, fitted s ({energy.loss_after:.2g})")
    ax.axhline(energy.noise, color="0.6", linestyle="--", linewidth=0.8, label="fitted noise")
    ax.set(xlabel="bin start [ms]", ylabel="energy per bin (all mics and pings)", title="echo energy (s by energy)")
    ax.legend(loc="best", fontsize=7)


def render_elevations(
    what: str, energy: np.ndarray, lidar: np.ndarray, elevation_deg, grid: PolarGrid, out: str | Path
) -> Path:
    """One frame (E, R, A) at each of its increasing elevations, highest first, each titled
    "`what` at E deg", with its LiDAR image (R, A) on top; e.g. a dataset card's stack."""
    rows = [(f"{what} at {e:g} deg", energy[j], lidar) for j, e in enumerate(elevation_deg)]
    return render_examples(rows[::-1], grid, out)


def render_lidar(
    scene: Scene,
    poses: np.ndarray,
    ranges: np.ndarray,
    config: LidarConfig,
    image: np.ndarray,
    grid: PolarGrid,
    out: str | Path,
    *,
    frame: int = 0,
) -> Path:
    """Top view (scene section, trajectory, one scan) beside that scan's LiDAR image; writes a PNG."""
    out = Path(out)
    sensor_height = float(poses[frame, 2, 3] - scene.floor_z)
    fig, (top, polar) = plt.subplots(1, 2, figsize=(14, 6), gridspec_kw={"width_ratios": [1.25, 1]})
    draw_scene_top(top, scene, height=sensor_height)
    xy = poses[:, :2, 3]
    top.plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=1.2, label="trajectory")
    top.plot(*xy[0], "o", color="tab:blue", ms=6, label="start")
    points = ranges_to_points(ranges[frame : frame + 1], config, poses[frame : frame + 1])[0]
    top.scatter(points[:, 0], points[:, 1], s=2, color="tab:red", label=f"LiDAR scan (frame {frame})", zorder=3)
    heading = poses[frame, :2, 0]
    top.annotate(
        "",
        xy=xy[frame] + 0.6 * heading,
        xytext=xy[frame],
        arrowprops={"arrowstyle": "->", "color": "k", "lw": 1.5},
        zorder=4,
    )
    # Outline of the polar image's field of view.
    az = np.linspace(grid.azimuth_min_deg, grid.azimuth_max_deg, 91)
    yaw = np.arctan2(heading[1], heading[0])
    ring = np.deg2rad(az) + yaw
    fov = np.concatenate([[xy[frame]], xy[frame] + grid.range_max_m * np.c_[np.cos(ring), np.sin(ring)], [xy[frame]]])
    top.plot(fov[:, 0], fov[:, 1], "--", color="0.5", lw=0.8, label=f"image field ({grid.range_max_m:g} m)")
    top.set_title(f"{scene.name}: section at {sensor_height:.2f} m, {len(poses)} poses")
    handles, labels = top.get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 8), fontsize=8)
    draw_polar_image(polar, image[frame], grid, title=f"LiDAR image (frame {frame})", cmap="Greys", label="return")
    fig.tight_layout(rect=(0, 0.07, 1, 1))  # room for the legend below both panels
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out


MAX_ECHO_POINTS = 4000
"""The strongest echoes drawn in a sonar picture's top view: more hide the scene."""


def reflection_points_title(label: str, echo_count: int) -> str:
    """The top view's title, saying how many of the ping's echoes it draws when not all."""
    if echo_count > MAX_ECHO_POINTS:
        return f"{label}: last reflection points of the {MAX_ECHO_POINTS:,} strongest of {echo_count:,} echoes"
    return f"{label}: last reflection points of {counted(echo_count, 'echo', 'echoes')}"


def render_sonar(
    scene: Scene,
    pose: np.ndarray,
    results: list[tuple[str, object, np.ndarray]],
    lidar: np.ndarray,
    grid: PolarGrid,
    out: str | Path,
    *,
    dynamic_range_db: float = 40.0,
) -> Path:
    """One row per simulation setting: the scene from above with the echoes' last reflection points
    coloured by bounce order, beside the energyscape (dB) with the LiDAR image on top.

    Args:
        results: (label, Arrivals of this single pose, energyscape (R, A)) per row.
        lidar: LiDAR image (R, A) of the same pose on `grid`.
    """
    out = Path(out)
    rows = len(results)
    fig, axes = plt.subplots(rows, 2, figsize=(14, 6 * rows), squeeze=False, gridspec_kw={"width_ratios": [1.1, 1]})
    height = float(pose[2, 3] - scene.floor_z)
    cmap = plt.get_cmap("viridis")
    max_order = max(int(a.order.max()) if len(a) else 1 for _, a, _ in results)
    for (label, arrivals, image), (top, polar) in zip(results, axes, strict=True):
        draw_scene_top(top, scene, height=height)
        world = arrivals.point_m @ pose[:3, :3].T + pose[:3, 3]
        strongest = np.argsort(arrivals.amplitude)[::-1][:MAX_ECHO_POINTS]
        for order in range(1, max_order + 1):
            sel = strongest[arrivals.order[strongest] == order]
            if len(sel):
                top.scatter(
                    world[sel, 0],
                    world[sel, 1],
                    s=6,
                    color=cmap((order - 1) / max(max_order - 1, 1)),
                    label=f"order {order} ({len(sel)})",
                    zorder=3,
                    alpha=0.8,
                )
        top.plot(*pose[:2, 3], "k^", ms=9, label="sonar", zorder=4)
        heading = pose[:2, 0]
        top.annotate(
            "",
            xy=pose[:2, 3] + 0.6 * heading,
            xytext=pose[:2, 3],
            arrowprops={"arrowstyle": "->", "color": "k", "lw": 1.5},
            zorder=4,
        )
        top.set_title(reflection_points_title(label, len(arrivals)))
        top.legend(loc="upper right", fontsize=7, framealpha=0.9)
        title = f"{label}: energyscape with the LiDAR image"
        draw_energyscape(polar, image, lidar, grid, title=title, dynamic_range_db=dynamic_range_db)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return out
