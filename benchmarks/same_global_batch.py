"""Does DDP train as one GPU does? `learn train` runs at the same global batch, one process against
a torchrun of N, compared on validation: each run's best validation scan F1 (and the Chamfer
distance of that epoch), the N-process minus one-process difference paired by seed beside the
seed-to-seed spread (the noise), and the validation curves in one figure.

    python benchmarks/same_global_batch.py RUN [RUN ...] --out DIR

Each RUN is a `learn train` folder (config.json and history.csv); its seed, batch per process and
process count are read from config.json. All runs must share everything else (recipe, model, data,
dataset) and their validation windows (`learn train --split-seed`): the seed also draws the split
otherwise, and the spread would not be training noise. Pairing by seed pairs the initial weights
and the epochs' window order, not the batches: DDP's ranks take halves of that order, so a
paired difference is no less noisy than an unpaired one. With two seeds the noise is one
difference. The train loss of a DDP run is rank 0's share.
Writes same_global_batch.md, .json and .png to DIR.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import relative, write_json  # noqa: E402

METRIC = "val_scan_f1"


def load_run(folder: Path) -> dict:
    config = json.loads((folder / "config.json").read_text())
    with open(folder / "history.csv", newline="") as f:
        history = [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]
    if not history:
        raise ValueError(f"{folder}/history.csv has no epochs")
    group = config.get("process_group") or {"processes": 1}
    processes = int(group["processes"])
    best = max(history, key=lambda r: -math.inf if math.isnan(r[METRIC]) else r[METRIC])
    rates = [r["samples_per_s"] for r in history[1:]] or [history[0]["samples_per_s"]]  # epoch 1 warms up
    return {
        "folder": relative(folder),
        "seed": int(config["train_config"]["seed"]),
        "processes": processes,
        "backend": group.get("backend"),
        "batch_per_process": int(config["train_config"]["batch_size"]),
        "global_batch": processes * int(config["train_config"]["batch_size"]),
        "val_episodes": config["dataset"]["val_episodes"],
        "split_seed": config["dataset"].get("split_seed"),  # None: a run from before it was recorded
        # what must match across the runs: all but the seed, the batch per process and the split's seed
        "recipe": {
            "train": {k: v for k, v in config["train_config"].items() if k not in ("seed", "batch_size", "split_seed")},
            "model": config.get("model_config"),
            "data": config.get("data_config"),
            "plan_id": config["dataset"].get("plan_id"),
        },
        "epochs": len(history),
        "best_epoch": int(best["epoch"]),
        "best_scan_f1": best[METRIC],
        "chamfer_m_at_best": best["val_chamfer_m"],
        "final_train_loss": history[-1]["train_loss"],
        "windows_per_s": float(np.median(rates)),
        "curve": [r[METRIC] for r in history],
    }


def compare(runs: list[dict]) -> dict:
    """Per seed, the many-process run's best scan F1 minus the one-process run's, beside the noise:
    the largest spread over seeds within either process count. Within noise when every paired
    difference is no larger than that spread."""
    if len({r["global_batch"] for r in runs}) != 1:
        raise ValueError(f"runs differ in global batch: {sorted({r['global_batch'] for r in runs})}")
    if len({(tuple(r["val_episodes"]), r["split_seed"]) for r in runs}) != 1 or runs[0]["split_seed"] is None:
        raise ValueError(
            "runs were not validated on the same windows (episodes and split seed, as config.json records "
            "them), so the seed-to-seed spread would mix in the split: train them with one --split-seed"
        )
    if any(r["recipe"] != runs[0]["recipe"] for r in runs):
        raise ValueError("runs differ in more than seed and batch per process (train, model or data config, dataset)")
    by = {(r["processes"], r["seed"]): r for r in runs}
    if len(by) != len(runs):
        raise ValueError("two runs have the same process count and seed")
    counts = sorted({r["processes"] for r in runs})
    if len(counts) != 2 or counts[0] != 1:
        raise ValueError(f"need one-process runs and runs of one other process count, got {counts}")
    many = counts[1]
    seeds = sorted(s for p, s in by if p == 1 and (many, s) in by)
    if not seeds:
        raise ValueError("no seed has both a one-process and a many-process run")
    paired = {s: by[many, s]["best_scan_f1"] - by[1, s]["best_scan_f1"] for s in seeds}
    best = {p: [r["best_scan_f1"] for r in runs if r["processes"] == p] for p in counts}
    spreads = {p: float(np.ptp(scores)) for p, scores in best.items() if len(scores) > 1}
    noise = max(spreads.values()) if spreads else None
    within = None if noise is None else all(abs(d) <= noise for d in paired.values())
    return {"processes": many, "paired_difference": paired, "seed_spread": spreads, "noise": noise, "within": within}


def markdown(runs: list[dict], result: dict) -> str:
    many = result["processes"]
    lines = [
        f"# One GPU against {many} at the same global batch ({runs[0]['global_batch']} windows)",
        "",
        "`learn train` runs, one process at the full batch against a torchrun of "
        f"{many} processes at 1/{many} of it each. Best validation scan F1 (0.10 m) over the run's epochs; "
        "Chamfer distance at that epoch; training windows/s is the median over epochs after the first.",
        "",
        "| processes | backend | seed | batch per process | epochs | best scan F1 | at epoch | Chamfer (m) "
        "| final train loss | training windows/s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(runs, key=lambda r: (r["processes"], r["seed"])):
        lines.append(
            f"| {r['processes']} | {r['backend'] or '-'} | {r['seed']} | {r['batch_per_process']} | {r['epochs']} "
            f"| {r['best_scan_f1']:.4f} | {r['best_epoch']} | {r['chamfer_m_at_best']:.3f} "
            f"| {r['final_train_loss']:.4f} | {r['windows_per_s']:,.0f} |"
        )
    paired = ", ".join(f"seed {s}: {d:+.4f}" for s, d in result["paired_difference"].items())
    spread = ", ".join(f"{p} process(es): {v:.4f}" for p, v in result["seed_spread"].items())
    lines += ["", f"{many} processes minus one, paired by seed: {paired}."]
    if result["noise"] is None:
        lines.append("No process count has two seeds: there is no noise estimate to compare with.")
    else:
        lines.append(
            f"Spread of the best scan F1 over seeds (the noise): {spread}. "
            + ("Every paired difference is within" if result["within"] else "A paired difference is **outside**")
            + f" the larger spread ({result['noise']:.4f})."
        )
    return "\n".join(lines) + "\n"


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    seeds = sorted({r["seed"] for r in runs})
    for r in sorted(runs, key=lambda r: (r["processes"], r["seed"])):
        colour = f"C{seeds.index(r['seed'])}"
        style = "-" if r["processes"] == 1 else "--"
        label = f"{r['processes']} GPU{'s' if r['processes'] > 1 else ''}, seed {r['seed']}"
        ax.plot(range(1, r["epochs"] + 1), r["curve"], style, color=colour, marker="o", ms=3, label=label)
    ax.set_xlabel("epoch")
    ax.set_ylabel("validation scan F1 (0.10 m)")
    ax.set_title(f"Same global batch ({runs[0]['global_batch']}): one process vs DDP")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    runs = [load_run(folder) for folder in args.runs]
    result = compare(runs)
    args.out.mkdir(parents=True, exist_ok=True)
    stamped = write_json(args.out / "same_global_batch.json", {"runs": runs} | result)
    (args.out / "same_global_batch.md").write_text(
        markdown(runs, result) + "\n" + provenance_line(stamped["provenance"]) + "\n"
    )
    plot(runs, args.out / "same_global_batch.png")
    print((args.out / "same_global_batch.md").read_text())
    return result


if __name__ == "__main__":
    main()
