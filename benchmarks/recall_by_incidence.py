"""Which true returns does a model find, by the angle at which its beam meets the wall? For each
true LiDAR return of a test set, the incidence angle (between the beam and the wall's normal, from
the true scan's neighbouring beams), and whether each predictor returns within 0.10 m there (at
its own threshold); recall per angle band, over every window and per scenario family, beside
the echo peak. A specular echo off a wall met at grazing incidence goes away from the sensor, so
an engine without edge or rough-surface scattering leaves such walls silent.

    python benchmarks/recall_by_incidence.py RUN... --test crossengine=data/crossengine --out recall.md
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import provenance, relative  # noqa: E402
from learn.checkpoint import load_checkpoint  # noqa: E402
from learn.cli import named_folder  # noqa: E402
from learn.data import DataConfig, Windows, level_slice, load_frames  # noqa: E402
from learn.evaluate import (  # noqa: E402
    BASELINE_THRESHOLD,
    echo_peak_predictor,
    model_predictor,
    model_windows,
    plain_windows,
    predict_batches,
    with_noisy_odometry,
)
from learn.odometry import OdometryNoise  # noqa: E402
from learn.scan import LABEL_THRESHOLD, SCAN_TOLERANCE_M, first_return_ranges  # noqa: E402

BANDS_DEG = (0, 30, 50, 70, 90)  # incidence bands [deg]
NEIGHBOURS = 2  # beams either side that fit the wall's direction
CONTINUITY_M = 0.3  # a neighbour farther than this in range from the beam's own return is another surface


def incidence_deg(ranges: np.ndarray, azimuth_rad: np.ndarray) -> np.ndarray:
    """Angle [deg] between each beam and the normal of the surface it returns from, (..., A).

    The surface's direction at beam a is the chord between the returns of beams a - NEIGHBOURS
    and a + NEIGHBOURS; nan where the beam has no return, a neighbour is missing or off the grid,
    or a neighbour lies more than CONTINUITY_M in range from it (a corner or another surface).
    """
    n, a = NEIGHBOURS, ranges.shape[-1]
    out = np.full(ranges.shape, np.nan)
    mid, lo, hi = slice(n, a - n), slice(0, a - 2 * n), slice(2 * n, a)
    with np.errstate(invalid="ignore", divide="ignore"):  # beams without a return (inf) end up nan, as they should
        x, y = ranges * np.cos(azimuth_rad), ranges * np.sin(azimuth_rad)
        tx, ty = x[..., hi] - x[..., lo], y[..., hi] - y[..., lo]
        ok = np.isfinite(ranges[..., mid]) & np.isfinite(tx) & np.isfinite(ty)
        ok &= np.abs(ranges[..., lo] - ranges[..., mid]) <= CONTINUITY_M
        ok &= np.abs(ranges[..., hi] - ranges[..., mid]) <= CONTINUITY_M
        # the beam meets the surface at angle phi to its tangent; the incidence angle is 90 - phi
        sin_phi = np.abs(np.cos(azimuth_rad[mid]) * ty - np.sin(azimuth_rad[mid]) * tx) / np.hypot(tx, ty)
        out[..., mid] = np.where(ok, 90.0 - np.degrees(np.arcsin(np.clip(sin_phi, 0.0, 1.0))), np.nan)
    return out


def found(predict, windows: Windows, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """(true ranges, whether the predictor returns within SCAN_TOLERANCE_M), each (windows, A)."""
    range_m = torch.as_tensor(windows.frames.range_m, device=windows.device)
    true, hit = [], []
    for pred, y in predict_batches(predict, windows, np.arange(len(windows)), 32):
        t = first_return_ranges(y, range_m, threshold=LABEL_THRESHOLD)
        p = first_return_ranges(pred, range_m, threshold=threshold)
        true.append(t.cpu().numpy())
        hit.append(((p - t).abs() <= SCAN_TOLERANCE_M + 1e-9).cpu().numpy())
    return np.concatenate(true), np.concatenate(hit)


def banded(angle: np.ndarray, hit: np.ndarray, mask: np.ndarray) -> list[tuple[int, float]]:
    """(true returns, recall) per incidence band of BANDS_DEG, then for the returns without an angle."""
    rows = []
    for lo, hi in itertools.pairwise(BANDS_DEG):
        sel = mask & (angle >= lo) & (angle < hi if hi < 90 else angle <= hi)
        rows.append((int(sel.sum()), float(hit[sel].mean()) if sel.any() else float("nan")))
    sel = mask & np.isnan(angle)
    rows.append((int(sel.sum()), float(hit[sel].mean()) if sel.any() else float("nan")))
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="run folders with best.pt (their recall is averaged)")
    p.add_argument("--test", type=named_folder, required=True, help="NAME=FOLDER of the test set")
    p.add_argument("--out", type=Path, required=True, help="markdown file to write")
    p.add_argument("--device", default="cpu")
    p.add_argument("--odometry-drift", type=float, default=0.0, help="models with memory read drifting odometry")
    args = p.parse_args()
    name, folder = args.test
    frames = load_frames(folder)
    noise = OdometryNoise.from_drift(args.odometry_drift)
    if noise.active:
        frames = with_noisy_odometry(frames, noise, seed=0)
    hits, config = [], None
    for run in args.runs:
        model, ckpt = load_checkpoint(run / "best.pt", args.device)
        config = DataConfig(**ckpt["data_config"])
        true, hit = found(model_predictor(model), model_windows(frames, ckpt, args.device), float(ckpt["threshold"]))
        hits.append(hit)
        print(f"{run}: recall {hit[np.isfinite(true)].mean():.3f}", flush=True)
    windows = Windows(level_slice(frames), plain_windows(config), args.device)  # the echo peak's: the level slice
    _, peak = found(echo_peak_predictor(windows.config.label_offset), windows, BASELINE_THRESHOLD)
    angle = incidence_deg(true, np.asarray(frames.azimuth_rad))
    has = np.isfinite(true)
    family_of = np.asarray(frames.scenarios)[windows.scenario]  # per window
    families = ["all", *sorted(set(family_of))]
    heads = [f"{lo}-{hi} deg" for lo, hi in itertools.pairwise(BANDS_DEG)] + ["no angle"]
    lines = [
        f"# Recall by incidence angle on `{name}`",
        "",
        f"Runs: {', '.join(f'`{relative(r)}`' for r in args.runs)} (recall averaged over them, each at its own "
        "threshold), "
        f"and the echo peak; a true return counts as found when the prediction's nearest return in its beam lies "
        f"within {SCAN_TOLERANCE_M} m. Incidence: between the beam and the wall's normal, from the true scan "
        f"({NEIGHBOURS} beams either side; 'no angle' = corners, surface ends and lone returns).",
        "",
        "Each cell: model recall / echo-peak recall (share of the family's true returns in that band).",
        "",
        "| family | " + " | ".join(heads) + " |",
        "|---|" + "---|" * len(heads),
    ]
    for family in families:
        mask = has if family == "all" else has & (family_of == family)[:, None]
        model_rows = [banded(angle, h, mask) for h in hits]
        peak_rows = banded(angle, peak, mask)
        cells = []
        for i, (count, peak_recall) in enumerate(peak_rows):
            recall = np.mean([rows[i][1] for rows in model_rows])
            cells.append(f"{recall:.2f} / {peak_recall:.2f} ({100 * count / max(mask.sum(), 1):.0f} %)")
        lines.append(f"| {family} | " + " | ".join(cells) + " |")
    lines += ["", provenance_line(provenance(args.device))]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
