"""Where the array's elevation changes what a model reads: the windows of a dataset beamformed at several
elevations where the model that reads them all predicts the fewest false returns against the model that
reads the level slice alone (a ghost or a band it no longer takes for a wall), and, to be fair, the
windows where it predicts the most. Each row: the label frame at every elevation, and both models' scans
from above beside the LiDAR truth.

    python benchmarks/elevation_examples.py --checkpoint e1=RUN/best.pt --checkpoint e3=RUN2/best.pt \
        --data data/crossengine --out examples.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.drive_from_above import ranges_of  # noqa: E402
from benchmarks.provenance import provenance, relative  # noqa: E402
from learn.checkpoint import load_checkpoint  # noqa: E402
from learn.data import DataConfig, Windows, load_frames  # noqa: E402
from learn.evaluate import model_predictor, model_windows, plain_windows  # noqa: E402
from learn.scan import LABEL_THRESHOLD, first_return_ranges  # noqa: E402


def false_beams(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per window, the beams where the prediction returns and the truth has none (the metrics' "false")."""
    return (np.isfinite(pred) & ~np.isfinite(truth)).sum(axis=-1)


def read_scans(frames, checkpoints: list[str], device: str) -> tuple[Windows, np.ndarray, dict[str, np.ndarray]]:
    """Every window's LiDAR truth and each model's scan, (N, A) ranges [m] (inf = none), beside the windows of
    every elevation the frames hold (the first model's window layout), from NAME=PATH checkpoints."""
    named = (item.partition("=") for item in checkpoints)
    models = [(name, *load_checkpoint(path, device)) for name, _, path in named]
    windows = Windows(frames, plain_windows(DataConfig(**models[0][2]["data_config"])), device)
    chunks = np.array_split(np.arange(len(windows)), max(1, len(windows) // 64))
    range_m = torch.as_tensor(frames.range_m, device=windows.device)
    truth = np.concatenate(
        [
            first_return_ranges(windows.batch(chunk)[1][:, 0], range_m, threshold=LABEL_THRESHOLD).cpu().numpy()
            for chunk in chunks
        ]
    )
    scans = {}
    for name, model, ckpt in models:
        theirs, predict, threshold = model_windows(frames, ckpt, device), model_predictor(model), ckpt["threshold"]
        if not np.array_equal(theirs.starts + theirs.config.label_offset, windows.starts + windows.config.label_offset):
            raise SystemExit(f"{name} labels other frames than {models[0][0]} (another window length or history)")
        scans[name] = np.concatenate([ranges_of(predict, theirs, chunk, float(threshold)) for chunk in chunks])
    return windows, truth, scans


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", action="append", required=True, help="NAME=PATH: the level slice's model first")
    p.add_argument("--data", type=Path, required=True, help="dataset folder beamformed at several elevations")
    p.add_argument("--rows", type=int, default=3, help="windows of each kind (fewer and more false returns)")
    p.add_argument("--out", type=Path, required=True, help="PNG to write")
    p.add_argument("--device", default="cpu")
    args = p.parse_args()
    frames = load_frames(args.data)
    if frames.energyscape.shape[1] < 2:
        raise SystemExit(f"{args.data} holds one elevation: beamform it at several (processing.elevation_deg)")
    windows, truth, scans = read_scans(frames, args.checkpoint, args.device)
    (base, base_scan), (other, other_scan) = list(scans.items())[:2]
    change = false_beams(other_scan, truth) - false_beams(base_scan, truth)
    order = np.argsort(change, kind="stable")
    picked = [*order[: args.rows], *order[::-1][: args.rows]]
    rows = []
    for i in picked:
        x, _ = windows.batch(np.array([i]))
        scenario = frames.scenarios[int(windows.scenario[i])]
        verdict = f"{abs(int(change[i]))} {'fewer' if change[i] < 0 else 'more'}"
        rows.append(
            {
                "title": f"{scenario}, window {i}: {other} predicts {verdict} false beams than {base}",
                "sonar": x[0, :, windows.config.anchor].cpu().numpy(),
                "truth": truth[i],
                "scans": {name: scan[i] for name, scan in scans.items()},
            }
        )
    stamp = provenance(args.device)
    commit = stamp["commit"][:12] if stamp.get("commit") else "?"
    title = (
        f"{relative(args.data)}: the {args.rows} windows of {len(windows)} where {other} predicts the fewest false "
        f"returns against {base}, then the {args.rows} where it predicts the most (commit {commit}, "
        f"{stamp.get('device_name') or args.device}; {other} minus {base} over all windows: "
        f"{int(change.sum()):+d} false beams, mean {change.mean():+.2f} a window)"
    )
    from learn.plots import plot_elevation_examples

    plot_elevation_examples(rows, frames.range_m, frames.azimuth_rad, frames.elevation_deg, args.out, title=title)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
