"""Where models put their false returns (a return in a beam whose LiDAR truth lies beyond the grid): how many
beams are empty at all, the share of them a model fills, at what range, and how close that range lies to the
nearest true return of the same scan (the echo of the nearest wall, spread over every azimuth by the array's
sidelobes, is a full-width band at that range).

    python benchmarks/false_returns_where.py --checkpoint e1=RUN/best.pt --checkpoint e3=RUN2/best.pt \
        --data crossengine=data/crossengine --data rough=data/crossengine_rough --out false_returns.md
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.elevation_examples import read_scans  # noqa: E402
from benchmarks.provenance import markdown, provenance, relative  # noqa: E402
from learn.data import load_frames  # noqa: E402

BAND_M = 0.15  # a false return this close to the scan's nearest true return sits on that wall's band


def where(pred: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """The false returns of scans `pred` against `truth`, (N, A) ranges [m], inf = none."""
    empty = ~np.isfinite(truth)
    false = np.isfinite(pred) & empty
    rows = np.nonzero(false)[0]
    nearest = np.where(np.isfinite(truth), truth, np.inf).min(axis=1)
    off = np.abs(pred[false] - nearest[rows])
    ranges = pred[false]
    quantile = (lambda v, q: float(np.quantile(v, q))) if len(ranges) else (lambda v, q: np.nan)
    return {
        "empty": float(empty.mean()),
        "false": float(false.sum() / max(empty.sum(), 1)),
        "windows": float(len(np.unique(rows)) / len(pred)),
        "range_median": quantile(ranges, 0.5),
        "range_p90": quantile(ranges, 0.9),
        "on_band": float((off <= BAND_M).mean()) if len(off) else np.nan,
        "off_median": quantile(off, 0.5),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", action="append", required=True, help="NAME=PATH, repeated")
    p.add_argument("--data", action="append", required=True, help="NAME=FOLDER, repeated")
    p.add_argument("--out", type=Path, required=True, help="markdown file to write")
    p.add_argument("--device", default="cpu")
    args = p.parse_args()
    lines = [
        "# Where the false returns lie",
        "",
        f"Models: {', '.join(f'`{c}`' for c in args.checkpoint)}. A false return: the model returns in a beam whose "
        "LiDAR truth lies beyond the grid (an empty beam). On band: within "
        f"{BAND_M:.2f} m of the nearest true return of the same scan.",
        "",
        "| data | model | empty beams | false (of empty) | windows with one | range median / 90 % [m] | on band | "
        "off the nearest wall, median [m] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for item in args.data:
        name, _, folder = item.partition("=")
        _, truth, scans = read_scans(load_frames(folder), args.checkpoint, args.device)
        for model, pred in scans.items():
            w = where(pred, truth)
            lines.append(
                f"| {name} (`{relative(folder)}`, {len(truth)} windows) | {model} | {w['empty']:.3f} "
                f"| {w['false']:.2f} | {w['windows']:.2f} | {w['range_median']:.2f} / {w['range_p90']:.2f} "
                f"| {w['on_band']:.2f} | {w['off_median']:.2f} |"
            )
    lines += ["", markdown(provenance(args.device)), ""]
    args.out.write_text("\n".join(lines))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
