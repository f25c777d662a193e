"""Which training change helps off our own simulator? Compares arms of a study (each trained with one
change, same seeds) against a reference arm, from their `learn sim2real` folders: mean ± std
over seeds per test set, each arm's difference to the reference paired by seed, and the arm a
rule picks: the highest mean on the CHOOSE set (never on the report set). Says per run whether it
stopped by early stopping or by its time budget.

    python benchmarks/compare_arms.py plain=study/randomised mirror=part4/mirror aug=part4/aug \
        --variant bounces_3 --choose reality --report crossengine --out part4/
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import provenance  # noqa: E402
from learn.cli import named_folder  # noqa: E402

METRIC = "scan_f1"


def load_arm(folder: Path, variant: str) -> dict[int, dict]:
    """{seed: that run's sim2real scores for `variant`} from folder/seed*/sim2real.json."""
    runs = {}
    for path in sorted(folder.glob("seed*/sim2real.json")):
        scores = json.loads(path.read_text())
        if variant not in scores:
            raise ValueError(f"{path} has no variant {variant!r} (it has {sorted(scores)})")
        runs[int(path.parent.name.removeprefix("seed"))] = scores[variant]
    if not runs:
        raise ValueError(f"no seed*/sim2real.json under {folder}")
    return runs


def stop_reason(run: Path) -> str:
    """'early stop' when the run ended `patience` sub-epochs after its best, 'time budget' when it ended
    sooner, 'cut off' when its history outran its summary (a process killed mid-run: the summary is an
    earlier call's, and the checkpoint scored may be a later epoch's)."""
    patience = json.loads((run / "config.json").read_text())["train_config"]["patience"]
    with open(run / "history.csv") as f:
        epochs = [int(row["epoch"]) for row in csv.DictReader(f)]
    summary = json.loads((run / "summary.json").read_text())
    if summary["epochs"] != len(epochs):
        return f"cut off, {len(epochs)} (summary of {summary['epochs']})"
    stopped = len(epochs) - summary["best_epoch"] >= patience
    return f"{'early stop' if stopped else 'time budget'}, {len(epochs)} ({summary['best_epoch']})"


def compare(arms: dict[str, dict[int, dict]], reference: str, sets: list[str]) -> dict:
    """Per arm and test set: per-seed scores, mean, std (ddof 0, as `learn sim2real-summary`) and the
    paired differences to `reference`."""
    seeds = sorted(arms[reference])
    for name, runs in arms.items():
        if sorted(runs) != seeds:
            raise ValueError(f"arm {name!r} has seeds {sorted(runs)}, the reference {reference!r} has {seeds}")
    scores = {
        name: {s: np.array([runs[seed][s][METRIC]["mean"] for seed in seeds]) for s in sets}
        for name, runs in arms.items()
    }
    return {
        name: {
            s: {"seeds": v, "mean": v.mean(), "std": v.std(), "paired": v - scores[reference][s]}
            for s, v in by_set.items()
        }
        for name, by_set in scores.items()
    }


def choose(table: dict, choose_set: str) -> str:
    return max(table, key=lambda name: table[name][choose_set]["mean"])


def markdown(
    table: dict, reference: str, sets: list[str], choose_set: str, report: str, echo: dict, stops: dict
) -> str:
    seeds = len(next(iter(table.values()))[sets[0]]["seeds"])
    picked = choose(table, choose_set)
    head = " | ".join(f"{s}: mean ± std" for s in sets)
    lines = [
        f"Scan F1 (0.10 m), {seeds} seeds per arm; paired differences are arm minus `{reference}`, seed by seed.",
        "",
        f"| arm | {head} | {choose_set} minus {reference} | {report} minus {reference} "
        "| stopped by, sub-epochs (kept) |",
        "|---|" + "---|" * (len(sets) + 3),
    ]
    for name, row in table.items():
        cells = " | ".join(f"{row[s]['mean']:.3f} ± {row[s]['std']:.3f}" for s in sets)
        paired = [
            " / ".join(f"{d:+.3f}" for d in row[s]["paired"]) if name != reference else "-"
            for s in (choose_set, report)
        ]
        bold = "**" if name == picked else ""
        lines.append(f"| {bold}{name}{bold} | {cells} | {paired[0]} | {paired[1]} | {'; '.join(stops[name])} |")
    cells = " | ".join(f"{echo[s]:.3f}" if s in echo else "-" for s in sets)
    lines.append(f"| echo peak | {cells} | - | - | - |")
    lines += [
        "",
        f"Chosen by the highest mean on `{choose_set}`: **{picked}**, {report} "
        f"{table[picked][report]['mean']:.3f} ± {table[picked][report]['std']:.3f} "
        f"({table[picked][report]['mean'] / echo[report]:.1f}x the echo peak).",
    ]
    return "\n".join(lines) + "\n"


def plot(table: dict, reference: str, panels: list[str], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in table if n != reference]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 0.5 * len(names) + 1.8), sharey=True)
    for ax, s in zip(np.atleast_1d(axes), panels, strict=True):
        for i, name in enumerate(names):
            d = table[name][s]["paired"]
            ax.plot(d, np.full(len(d), i), "o", color="tab:blue", alpha=0.7)
            ax.plot([d.mean()], [i], "|", color="k", markersize=16)
        ax.axvline(0, color="0.4", linewidth=1)
        ax.set_yticks(range(len(names)), names)
        ax.set_title(f"{s}: scan F1 minus {reference}\n(dots: seeds, bar: mean)")
        ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "arms", nargs="+", type=named_folder, help="NAME=FOLDER of seed*/sim2real.json; the first is the reference"
    )
    p.add_argument("--variant", default="bounces_3", help="the trained variant compared")
    p.add_argument("--choose", default="reality", help="the test set an arm is chosen on")
    p.add_argument("--report", default="crossengine", help="the test set reported, never chosen on")
    p.add_argument("--out", type=Path, required=True, help="folder for compare_arms.md and compare_arms.png")
    args = p.parse_args()
    folders = {name: Path(folder) for name, folder in args.arms}
    if len(folders) != len(args.arms):
        p.error("each arm needs its own name")
    if len(folders) < 2:
        p.error("give a reference and at least one arm")
    reference = args.arms[0][0]
    arms = {name: load_arm(folder, args.variant) for name, folder in folders.items()}
    sets = ["in_domain", args.choose, args.report]
    table = compare(arms, reference, sets)
    first = next(iter(arms[reference].values()))
    echo = {s: first[f"{s}_echo_peak"][METRIC]["mean"] for s in sets if f"{s}_echo_peak" in first}
    stops = {
        name: [stop_reason(folder / f"seed{seed}" / args.variant) for seed in sorted(arms[name])]
        for name, folder in folders.items()
    }
    args.out.mkdir(parents=True, exist_ok=True)
    text = markdown(table, reference, sets, args.choose, args.report, echo, stops)
    text += "\n" + provenance_line(provenance()) + "\n"
    (args.out / "compare_arms.md").write_text(text)
    plot(table, reference, [args.choose, args.report], args.out / "compare_arms.png")
    print(text, end="")
    print(f"wrote {args.out / 'compare_arms.md'} and {args.out / 'compare_arms.png'}")


if __name__ == "__main__":
    main()
