"""Is a model's return threshold what limits it on another test set? For each trained run, the mean
scan F1 (0.10 m) over every window of two test sets at every calibration threshold, and the score
on the report set at: the run's own threshold (calibrated on its validation windows), the one
best on the choice set, and the one best on the report set itself (an oracle, never a result).

    python benchmarks/threshold_transfer.py RUN... --choose reality=data/reality \
        --report crossengine=data/crossengine --out threshold_transfer.md
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import provenance, relative  # noqa: E402
from learn.checkpoint import load_checkpoint  # noqa: E402
from learn.cli import named_folder  # noqa: E402
from learn.data import DataConfig, Windows, load_frames  # noqa: E402
from learn.evaluate import CALIBRATION_THRESHOLDS, calibrate_on_predictions, model_predictor, predict_batches  # noqa: E402


def sweep(run: Path, frames, device: str) -> tuple[float, np.ndarray]:
    """(the run's own threshold, mean scan F1 per CALIBRATION_THRESHOLDS) over every window of `frames`."""
    model, ckpt = load_checkpoint(run / "best.pt", device)
    windows = Windows(frames, DataConfig(**ckpt["data_config"]), device)
    batches = predict_batches(model_predictor(model), windows, np.arange(len(windows)), 32)
    return float(ckpt["threshold"]), calibrate_on_predictions(batches, windows)[1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="run folders with best.pt")
    p.add_argument("--choose", type=named_folder, required=True, help="NAME=FOLDER: the set a threshold is chosen on")
    p.add_argument("--report", type=named_folder, required=True, help="NAME=FOLDER: the set reported")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", type=Path, help="also write the table here (markdown)")
    args = p.parse_args()
    (choose, choose_dir), (report, report_dir) = args.choose, args.report
    sets = {choose: load_frames(choose_dir), report: load_frames(report_dir)}
    t = np.asarray(CALIBRATION_THRESHOLDS)
    lines = [
        f"scan F1 at 0.10 m on `{report}` ({relative(report_dir)}) at three thresholds; "
        f"`{choose}`: {relative(choose_dir)}",
        "",
        f"| run | own threshold | {report} at it | best on {choose} | {report} at it | best on {report} (oracle) "
        f"| {report} at it |",
        "|---|---|---|---|---|---|---|",
    ]
    for run in args.runs:
        own, on_choice = sweep(run, sets[choose], args.device)
        _, on_report = sweep(run, sets[report], args.device)
        i_own, i_choice, i_report = int(np.argmin(abs(t - own))), int(np.argmax(on_choice)), int(np.argmax(on_report))
        lines.append(
            f"| {relative(run)} | {own:.2f} | {on_report[i_own]:.3f} | {t[i_choice]:.2f} | {on_report[i_choice]:.3f} "
            f"| {t[i_report]:.2f} | {on_report[i_report]:.3f} |"
        )
        print(lines[-1], flush=True)
    lines += ["", provenance_line(provenance(args.device))]
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
