"""The tables of issue 40's study from `benchmarks/elevation_study.sh score`: scan F1 (0.10 m) and
false returns of each arm and baseline on each test set, mean ± std over seeds; the differences
that decide it, paired by seed (three elevations minus the level slice); and the issue's targets.

    python benchmarks/elevation_study_summary.py WORKDIR --out benchmarks/results/elevation_study/elevation_study.md
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

TESTS = ("validation", "reality", "crossengine", "crossengine_rough", "fresh")
ROWS = (("level slice (E = 1)", "e1"), ("three elevations (E = 3)", "e3"), ("echo peak", "echo peak"))
TARGETS = (  # (test, the E = 3 model's scan F1 at least)
    ("crossengine", 0.55),
    ("crossengine_rough", 0.65),
)


def load(workdir: Path) -> dict:
    """{(seed, test): metrics.json} of every evaluate report under WORKDIR/scores."""
    reports = {}
    for path in sorted(workdir.glob("scores/seed*/*/metrics.json")):
        test, seed = path.parent.name, int(path.parents[1].name.removeprefix("seed"))
        reports[(seed, test)] = json.loads(path.read_text())
    if not reports:
        raise SystemExit(f"no scores/seed*/TEST/metrics.json under {workdir}")
    return reports


def values(reports: dict, seeds: list[int], test: str, name: str, metric: str) -> np.ndarray:
    out = []
    for seed in seeds:
        report = reports.get((seed, test))
        has = report is not None and name in report["results"]
        out.append(float(report["results"][name]["all"][metric]["mean"]) if has else np.nan)
    return np.array(out)


def spread(v: np.ndarray) -> str:
    return f"{np.nanmean(v):.3f} ± {np.nanstd(v):.3f}" if np.isfinite(v).any() else "-"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("workdir", type=Path)
    p.add_argument("--out", type=Path, required=True, help="markdown file (a .json beside it)")
    args = p.parse_args()
    reports = load(args.workdir)
    seeds = sorted({seed for seed, _ in reports})
    table: dict = {"seeds": seeds, "scan_f1": {}, "false": {}, "pairs": {}, "targets": {}}
    lines = [f"# Elevation: mean ± std over seeds {', '.join(map(str, seeds))}", "", "Scan F1 (0.10 m):", ""]
    lines += ["| predictor | " + " | ".join(TESTS) + " |", "|---|" + "---|" * len(TESTS)]
    for row, name in ROWS:
        table["scan_f1"][name] = {t: values(reports, seeds, t, name, "scan_f1").tolist() for t in TESTS}
        lines.append(f"| {row} | " + " | ".join(spread(np.array(table["scan_f1"][name][t])) for t in TESTS) + " |")
    lines += ["", "False returns (share of the beams without a true return where the predictor returns):", ""]
    lines += ["| predictor | " + " | ".join(TESTS) + " |", "|---|" + "---|" * len(TESTS)]
    for row, name in ROWS:
        table["false"][name] = {t: values(reports, seeds, t, name, "false").tolist() for t in TESTS}
        lines.append(f"| {row} | " + " | ".join(spread(np.array(table["false"][name][t])) for t in TESTS) + " |")
    lines += ["", f"Paired by seed (seed {' / '.join(map(str, seeds))}), E = 3 minus E = 1:", ""]
    lines += ["| difference | " + " | ".join(TESTS) + " |", "|---|" + "---|" * len(TESTS)]
    for metric in ("scan_f1", "false"):
        diffs = {t: (np.array(table[metric]["e3"][t]) - np.array(table[metric]["e1"][t])).tolist() for t in TESTS}
        table["pairs"][metric] = diffs
        cells = [" / ".join(f"{d:+.3f}" for d in diffs[t]) for t in TESTS]
        lines.append(f"| {metric.replace('_', ' ')} | " + " | ".join(cells) + " |")
    lines += ["", "The issue's targets:", ""]
    ratio = np.array(table["false"]["e3"]["crossengine"]) / np.array(table["false"]["e1"]["crossengine"])
    met = bool(np.all(ratio <= 0.5))
    table["targets"]["crossengine false returns, E = 3 over E = 1, at most 0.5"] = {
        "per_seed": ratio.tolist(),
        "met": met,
    }
    lines.append(
        f"- false returns on crossengine, E = 3 over E = 1: {' / '.join(f'{r:.2f}' for r in ratio)} "
        f"(at most 0.50: {'met' if met else 'not met'})"
    )
    for test, floor in TARGETS:
        f1 = np.array(table["scan_f1"]["e3"][test])
        ahead = np.array(table["pairs"]["scan_f1"][test]) > 0
        met = bool(np.nanmean(f1) >= floor and ahead.all())
        table["targets"][f"{test} scan F1 >= {floor}, ahead of E = 1 in every seed"] = {
            "mean": float(np.nanmean(f1)),
            "ahead": ahead.tolist(),
            "met": met,
        }
        lines.append(
            f"- scan F1 on {test}: {np.nanmean(f1):.3f} (at least {floor}), ahead of E = 1 in "
            f"{int(ahead.sum())} of {len(ahead)} seeds: {'met' if met else 'not met'}"
        )
    lines += ["", provenance_line(provenance("cpu"))]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    write_json(args.out.with_suffix(".json"), table, "cpu")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
