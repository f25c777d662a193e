"""Summaries over repeated runs (`seeds-summary`, `table2-summary`; `sim2real-summary` is in
`learn.studies`) and the files they read:
JSON that studies and evaluations wrote, and a user may hand over damaged, empty, foreign or
twice. Each is read through `learn.inputs.read_json` (a regular file that parses) and each
number taken from it is refused by file and field when it is missing or not a number, rather
than as a bare KeyError, a numpy type error, a traceback or a hang on a FIFO."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from clitools.outputs import atomic_folder

from .inputs import read_json
from .report import METRICS

TABLE2_CASES = ("minimal", "many", "noisy")


def read_record(folder: str | Path, name: str, made_by: str) -> tuple[dict, Path]:
    """(the JSON object, its path) of the file `name` in a folder a study wrote: a regular file
    that parses, refused naming it (and the command that writes such folders) otherwise."""
    path = Path(folder) / name
    advice = f"give folders written by `{made_by}`"
    if not os.path.lexists(path):
        raise FileNotFoundError(f"{path} does not exist: {advice}")
    return read_json(path, "summary input", advice), path


def number_at(record, path: Path, *keys) -> float:
    """The number at `keys` in a study's JSON `record` (read from `path`), refused naming the
    file and the field where it is missing or not a number."""
    value = record
    for key in keys:
        if not isinstance(value, dict) or key not in value:
            raise ValueError(f"{path} has no {'.'.join(keys)}: it is not a complete study output")
        value = value[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{path}: {'.'.join(keys)} is {value!r}, not a number")
    return float(value)


def study_table(record, path: Path, what: str) -> dict:
    """A study's table (rows of columns, as sim2real.json and table2.json hold it), refused naming
    the file when it is empty or not rows of objects."""
    if not record or not all(isinstance(row, dict) and row for row in record.values()):
        raise ValueError(f"{path} holds no {what} (an empty or foreign file): give a finished study's folder")
    return record


def distinct_folders(folders: list, what: str) -> None:
    """Refuse fewer than two folders, or one folder twice (it would count as two runs that agree)."""
    if len(folders) < 2:
        raise ValueError(f"give at least two {what} folders to summarise")
    seen: dict[str, str | Path] = {}
    for folder in folders:
        key = os.path.realpath(folder)
        if key in seen:
            raise ValueError(f"{folder} is given twice (also as {seen[key]}): each run counts once; give it once")
        seen[key] = folder


def spread(values: list[float]) -> dict:
    """Mean, std and the values themselves, of one number over repeated runs."""
    return {"mean": float(np.mean(values)), "std": float(np.std(values)), "runs": values}


def seeds_summary(reports: list[str | Path], out: str | Path, *, overwrite: bool = False) -> dict:
    """Mean and std across repeated evaluations (e.g. one per training seed) of every predictor:
    reads each folder's metrics.json (written by `evaluate`), writes summary.md and summary.json.
    Each cell is the spread of the runs' window means, so it shows how much a result depends on
    the seed rather than on the windows. Files already in `out` are replaced only with
    `overwrite`, files of `reports` never (`clitools.outputs`)."""
    names = ("summary.md", "summary.json")
    with atomic_folder(out, overwrite=overwrite, inputs=[Path(r) for r in reports], expected=names) as stage:
        return _seeds_summary(reports, stage)


def _seeds_summary(reports: list[str | Path], out: Path) -> dict:
    read = [read_record(r, "metrics.json", "learn evaluate") for r in reports]
    distinct_folders(reports, "evaluation")
    for record, path in read:
        if not isinstance(record.get("results"), dict) or not record["results"]:
            raise ValueError(f"{path} has no results: give folders written by `learn evaluate`")
    runs = [record for record, _ in read]
    names = list(runs[0]["results"])
    if any(list(r["results"]) != names for r in runs):
        raise ValueError(f"the evaluations scored different predictors: {[list(r['results']) for r in runs]}")
    summary = {}
    for name in names:
        summary[name] = {}
        for key, _, _ in METRICS:
            summary[name][key] = spread([number_at(r, path, "results", name, "all", key, "mean") for r, path in read])
    windows = int(number_at(runs[0], read[0][1], "windows"))
    lines = [
        f"# {len(runs)} runs on `{runs[0].get('data')}` ({runs[0].get('split')} split, {windows:,} windows each)",
        "",
        "Mean ± std over the runs of each run's mean over windows: " + ", ".join(f"`{Path(r)}`" for r in reports) + ".",
        "",
        "| predictor | " + " | ".join(label for _, label, _ in METRICS) + " |",
        "|---" * (len(METRICS) + 1) + "|",
    ]
    for name, stats in summary.items():
        cells = [
            "-" if not np.isfinite(stats[k]["mean"]) else f"{f.format(stats[k]['mean'])} ± {f.format(stats[k]['std'])}"
            for k, _, f in METRICS
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def table2_summary(runs: list[str | Path], out: str | Path, *, overwrite: bool = False) -> dict:
    """Table 2 over repeated runs (e.g. seeds), from their table2.json and the K = 5 row's reports:
    scan F1 mean ± std of the runs' window means per row and case, the echo-peak baseline on the
    same windows, and per-run paired differences (each run scores all its rows on the same validation
    episodes, so the episodes' difficulty cancels out of a difference). Files already in `out`
    are replaced only with `overwrite`, files of `runs` never (`clitools.outputs`)."""
    names = ("table2.md", "table2.json")
    with atomic_folder(out, overwrite=overwrite, inputs=[Path(r) for r in runs], expected=names) as stage:
        return _table2_summary(runs, stage)


def _table2_summary(runs: list[str | Path], out: Path) -> dict:
    read = [read_record(r, "table2.json", "learn table2") for r in runs]
    distinct_folders(runs, "table2")
    tables = [study_table(t, path, "Table 2 rows") for t, path in read]
    rows = list(tables[0])
    if len(rows) < 2 or any(list(t) != rows for t in tables):
        raise ValueError(f"the runs hold different rows, or fewer than two: {[list(t) for t in tables]}")

    def scores(r: str, c: str) -> np.ndarray:
        return np.array([number_at(t, path, r, c, "scan_f1", "mean") for t, path in read])

    f1 = {r: {c: scores(r, c) for c in TABLE2_CASES} for r in rows}
    peak = {}
    for c in TABLE2_CASES:
        reports = [read_record(Path(r) / "k5" / c, "metrics.json", "learn table2") for r in runs]
        peak[c] = np.array([number_at(rep, p, "results", "echo peak", "all", "scan_f1", "mean") for rep, p in reports])

    def cell(values: np.ndarray) -> str:
        return f"{values.mean():.3f} ± {values.std():.3f}"

    names = ", ".join(f"`{Path(r).name}`" for r in runs)
    lines = [
        f"# Table 2 layout over {len(runs)} runs ({names})",
        "",
        "scan F1 at 0.10 m: mean ± std over the runs of each run's mean over its validation windows "
        "(the episodes its early stopping read).",
        "",
        "| input | " + " | ".join(TABLE2_CASES) + " |",
        "|---|---|---|---|",
    ]
    lines += [f"| {r} | " + " | ".join(cell(f1[r][c]) for c in TABLE2_CASES) + " |" for r in rows]
    lines += ["| echo-peak baseline | " + " | ".join(cell(peak[c]) for c in TABLE2_CASES) + " |", ""]
    pairs = [(r, rows[0]) for r in rows[1:-1]] + [(rows[-1], rows[-2])]  # longer windows; fine-tuning
    lines += [
        "Paired differences per run (same windows):",
        "",
        "| | case | " + " | ".join(Path(r).name for r in runs) + " |",
    ]
    lines += ["|---" * (2 + len(runs)) + "|"]
    for b, a in pairs:
        for c in TABLE2_CASES:
            lines.append(f"| {b} minus {a} | {c} | " + " | ".join(f"{d:+.3f}" for d in f1[b][c] - f1[a][c]) + " |")
    (out / "table2.md").write_text("\n".join(lines) + "\n")
    summary = {r: {c: spread(v.tolist()) for c, v in f1[r].items()} for r in rows}
    summary["echo peak"] = {c: spread(v.tolist()) for c, v in peak.items()}
    (out / "table2.json").write_text(json.dumps(summary, indent=1))
    return summary
