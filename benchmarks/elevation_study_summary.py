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
ARMS = {"e1": "level slice (E = 1)", "e3": "three elevations (E = 3)", "e5": "five elevations (E = 5)"}
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
    arms = [a for a in ARMS if any(a in r["results"] for r in reports.values())]
    rows = [(ARMS[a], a) for a in arms] + [("echo peak", "echo peak")]
    table: dict = {"seeds": seeds, "scan_f1": {}, "false": {}, "pairs": {}, "targets": {}}
    lines = [f"# Elevation: mean ± std over seeds {', '.join(map(str, seeds))}", ""]
    header = ["| predictor | " + " | ".join(TESTS) + " |", "|---|" + "---|" * len(TESTS)]
    for metric, title in (
        ("scan_f1", "Scan F1 (0.10 m):"),
        ("false", "False returns (share of the beams without a true return where the predictor returns):"),
    ):
        lines += [title, "", *header]
        for row, name in rows:
            table[metric][name] = {t: values(reports, seeds, t, name, metric).tolist() for t in TESTS}
            lines.append(f"| {row} | " + " | ".join(spread(np.array(table[metric][name][t])) for t in TESTS) + " |")
        lines.append("")
    pairs = [(a, "e1") for a in arms if a != "e1"] + ([("e5", "e3")] if {"e3", "e5"} <= set(arms) else [])
    for arm, base in pairs:
        lines += [f"Paired by seed (seed {' / '.join(map(str, seeds))}), {ARMS[arm]} minus {ARMS[base]}:", ""]
        lines += ["| difference | " + " | ".join(TESTS) + " |", "|---|" + "---|" * len(TESTS)]
        for metric in ("scan_f1", "false"):
            diffs = {t: (np.array(table[metric][arm][t]) - np.array(table[metric][base][t])).tolist() for t in TESTS}
            table["pairs"][f"{arm} - {base} {metric}"] = diffs
            cells = [" / ".join(f"{d:+.3f}" for d in diffs[t]) for t in TESTS]
            lines.append(f"| {metric.replace('_', ' ')} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["The issue's targets (each arm with E > 1 against the level slice):", ""]
    for arm in (a for a in arms if a != "e1"):
        lines += _targets(table, arm)
    lines += ["", provenance_line(provenance("cpu"))]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    write_json(args.out.with_suffix(".json"), table, "cpu")
    print("\n".join(lines))


def _targets(table: dict, arm: str) -> list[str]:
    """The issue's targets for `arm` against e1, recorded in table["targets"]; their lines."""
    e = arm.removeprefix("e")
    ratio = np.array(table["false"][arm]["crossengine"]) / np.array(table["false"]["e1"]["crossengine"])
    met = bool(np.all(ratio <= 0.5))
    table["targets"][f"crossengine false returns, E = {e} over E = 1, at most 0.5"] = {
        "per_seed": ratio.tolist(),
        "met": met,
    }
    lines = [
        f"- false returns on crossengine, E = {e} over E = 1: {' / '.join(f'{r:.2f}' for r in ratio)} "
        f"(at most 0.50: {'met' if met else 'not met'})"
    ]
    for test, floor in TARGETS:
        f1 = np.array(table["scan_f1"][arm][test])
        ahead = np.array(table["pairs"][f"{arm} - e1 scan_f1"][test]) > 0
        met = bool(np.nanmean(f1) >= floor and ahead.all())
        table["targets"][f"E = {e}: {test} scan F1 >= {floor}, ahead of E = 1 in every seed"] = {
            "mean": float(np.nanmean(f1)),
            "ahead": ahead.tolist(),
            "met": met,
        }
        lines.append(
            f"- E = {e}: scan F1 on {test}: {np.nanmean(f1):.3f} (at least {floor}), ahead of E = 1 in "
            f"{int(ahead.sum())} of {len(ahead)} seeds: {'met' if met else 'not met'}"
        )
    return lines


if __name__ == "__main__":
    main()
