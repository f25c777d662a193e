"""The table of issue 39's study from `benchmarks/memory_study.sh score`: scan F1 (0.10 m) and false
returns per arm and test set, mean ± std over seeds, and the differences that decide it, paired by
seed: memory minus K = 5, memory minus each occupancy grid, and each drift arm at its drift minus
memory at true odometry.

    python benchmarks/memory_study_summary.py WORKDIR --out benchmarks/results/memory_study/summary.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import provenance, write_json  # noqa: E402

TESTS = ("validation", "reality", "crossengine", "fresh")
GRIDS = ("occupancy grid (echo peak)", "occupancy grid (k5)")
# (row name, predictor in the report, drift it is read at)
ROWS = (
    ("K = 5 (no memory)", "k5", "0"),
    ("memory, true odometry", "memory", "0"),
    ("memory, 1 % drift (trained and tested)", "drift1", "0.01"),
    ("memory, 5 % drift (trained and tested)", "drift5", "0.05"),
    ("memory (true-odometry model), tested at 5 % drift", "memory", "0.05"),
    ("occupancy grid fed by echo peaks", GRIDS[0], "0"),
    ("occupancy grid fed by K = 5", GRIDS[1], "0"),
    ("occupancy grid fed by K = 5, 5 % drift", GRIDS[1], "0.05"),
    ("echo peak", "echo peak", "0"),
)
PAIRS = (  # (name, (predictor, drift), (predictor, drift)): first minus second
    ("memory minus K = 5", ("memory", "0"), ("k5", "0")),
    ("memory minus grid (echo peak)", ("memory", "0"), (GRIDS[0], "0")),
    ("memory minus grid (K = 5)", ("memory", "0"), (GRIDS[1], "0")),
    ("drift5 at 5 % minus memory at true odometry", ("drift5", "0.05"), ("memory", "0")),
    ("drift1 at 1 % minus memory at true odometry", ("drift1", "0.01"), ("memory", "0")),
)


def load(workdir: Path) -> dict:
    """{(seed, test, drift): metrics.json} of every evaluate report under WORKDIR/scores."""
    reports = {}
    for path in sorted(workdir.glob("scores/seed*/*/drift*/metrics.json")):
        drift, test, seed = path.parent.name.removeprefix("drift"), path.parents[1].name, path.parents[2].name
        reports[(int(seed.removeprefix("seed")), test, drift)] = json.loads(path.read_text())
    if not reports:
        raise SystemExit(f"no scores/seed*/TEST/driftD/metrics.json under {workdir}")
    return reports


def value(reports, seed, test, drift, name, metric="scan_f1") -> float:
    report = reports.get((seed, test, drift))
    if report is None or name not in report["results"]:
        return float("nan")
    return float(report["results"][name]["all"][metric]["mean"])


def add_training_validation(reports: dict, workdir: Path) -> None:
    """Where evaluate did not score the validation episodes, each run's own best validation score
    from training (the 2,000 validation windows early stopping read, at the threshold calibrated
    on them) stands in, at true odometry."""
    for path in sorted(workdir.glob("runs/seed*/*/summary.json")):
        seed, arm = int(path.parents[1].name.removeprefix("seed")), path.parent.name
        key = (seed, "validation", "0")
        if key in reports and arm in reports[key]["results"] and not reports[key].get("from_training"):
            continue
        best = json.loads(path.read_text())["best"]
        entry = {"all": {m: {"mean": best[f"val_{m}"]} for m in ("scan_f1", "false")}}
        reports.setdefault(key, {"results": {}, "from_training": True})["results"][arm] = entry


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("workdir", type=Path)
    p.add_argument("--out", type=Path, required=True, help="markdown file (a .json beside it)")
    args = p.parse_args()
    reports = load(args.workdir)
    add_training_validation(reports, args.workdir)
    seeds = sorted({k[0] for k in reports})
    table: dict = {"seeds": seeds, "rows": {}, "pairs": {}}
    lines = [
        "# Memory with odometry: scan F1 (0.10 m) and false returns, mean ± std over seeds "
        + ", ".join(map(str, seeds)),
        "",
        "| arm | " + " | ".join(f"{t}: scan F1" for t in TESTS) + " | crossengine: false returns |",
        "|---|" + "---|" * (len(TESTS) + 1),
    ]
    for row, name, drift in ROWS:
        cells, entry = [], {}
        for test in TESTS:
            values = np.array([value(reports, s, test, drift, name) for s in seeds])
            entry[test] = values.tolist()
            cells.append(f"{np.nanmean(values):.3f} ± {np.nanstd(values):.3f}" if np.isfinite(values).any() else "-")
        false = np.array([value(reports, s, "crossengine", drift, name, "false") for s in seeds])
        entry["crossengine_false"] = false.tolist()
        cells.append(f"{np.nanmean(false):.3f}" if np.isfinite(false).any() else "-")
        table["rows"][row] = entry
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    lines += ["", "Paired by seed (seed " + " / ".join(map(str, seeds)) + "):", ""]
    lines += ["| difference | " + " | ".join(TESTS) + " |", "|---|" + "---|" * len(TESTS)]
    for pair, (a, da), (b, db) in PAIRS:
        cells, entry = [], {}
        for test in TESTS:
            diff = [value(reports, s, test, da, a) - value(reports, s, test, db, b) for s in seeds]
            entry[test] = diff
            cells.append(" / ".join(f"{d:+.3f}" for d in diff))
        table["pairs"][pair] = entry
        lines.append(f"| {pair} | " + " | ".join(cells) + " |")
    if any(r.get("from_training") for r in reports.values()):
        lines += [
            "",
            "Validation: each run's best score in training (the 2,000 windows of held-out episodes early stopping "
            "read, at the threshold calibrated on them), for the models alone; the baselines were not scored there.",
        ]
    lines += ["", provenance_line(provenance("cpu"))]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    write_json(args.out.with_suffix(".json"), table, "cpu")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
