"""How far back does a model with memory look? Scores a polar_memory run with only its newest h
history frames given (the older ones absent, as before a drive began) for h = 0 .. its history:
the scan F1 gained per step back is the horizon that helps. No retraining: the same weights read
less of the past.

    python benchmarks/memory_horizon.py RUN... --test reality=data/reality --out horizon.md
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import provenance, relative, write_json  # noqa: E402
from learn.checkpoint import load_checkpoint  # noqa: E402
from learn.cli import named_folder  # noqa: E402
from learn.data import DataConfig, load_frames  # noqa: E402
from learn.evaluate import model_predictor, model_windows, score  # noqa: E402

FRAME_S = 0.1  # the simulated drives' frame period [s]


def forgetting(predict, history: int, kept: int):
    """`predict` with all but the newest `kept` of `history` frames made absent."""
    gone = history - kept

    def forgetful(x):
        frames, motion = x
        frames, motion = frames.clone(), motion.clone()
        frames[:, :, :gone] = 0.0
        motion[:, :gone, 3] = 0.0
        return predict((frames, motion))

    return forgetful


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="polar_memory run folders with best.pt (averaged)")
    p.add_argument("--test", type=named_folder, required=True, help="NAME=FOLDER of the test set")
    p.add_argument("--out", type=Path, required=True, help="markdown file (a .json beside it)")
    p.add_argument("--device", default="cpu")
    args = p.parse_args()
    name, folder = args.test
    frames = load_frames(folder)
    curves = []
    for run in args.runs:
        model, ckpt = load_checkpoint(run / "best.pt", args.device)
        config = DataConfig(**ckpt["data_config"])
        if not config.history:
            raise SystemExit(f"{run} reads no history: give polar_memory runs")
        windows = model_windows(frames, ckpt, args.device)
        indices = np.arange(len(windows))
        predict, threshold = model_predictor(model), float(ckpt["threshold"])
        curve = []
        for kept in range(config.history + 1):
            per = score(forgetting(predict, config.history, kept), windows, indices, threshold=threshold)
            curve.append(float(np.mean(per["scan_f1"])))
            print(f"{run}: {kept} history frames: scan F1 {curve[-1]:.3f}", flush=True)
        curves.append(curve)
    mean = np.mean(curves, axis=0)
    stride = config.history_stride
    lines = [
        f"# How far back memory helps, on `{name}`",
        "",
        f"Runs {', '.join(f'`{relative(r)}`' for r in args.runs)} (scan F1 at 0.10 m, mean over runs, each at its own "
        f"threshold), given only the newest h of their {config.history} history frames ({stride} frames apart) "
        f"besides the window of {config.frames}.",
        "",
        "| history frames given | reaching back | scan F1 | gain over none |",
        "|---|---|---|---|",
    ]
    for kept, f1 in enumerate(mean):
        back = kept * stride + config.label_offset
        lines.append(f"| {kept} | {back} frames ({back * FRAME_S:.1f} s) | {f1:.3f} | {f1 - mean[0]:+.3f} |")
    lines += ["", provenance_line(provenance(args.device))]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    record = {"test": name, "runs": [relative(r) for r in args.runs], "curves": curves, "stride": stride}
    write_json(args.out.with_suffix(".json"), record, args.device)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
