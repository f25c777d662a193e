"""The experiments: the paper's Table 2 layout, and the multipath sim-to-real study.

    python -m learn table2 --train data/paper --test data/table2 --out runs/table2
    python -m learn sim2real --ablation data/ablation --reality data/reality --out runs/sim2real

Both train with `learn.train.train` and score with `learn.evaluate.evaluate`, so every number
in their tables comes from a real run whose checkpoint and report stay in the output folder.
(Their reports leave out inference timing: `benchmarks/bench_learn.py` measures speed.)
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import warnings
from pathlib import Path

import numpy as np
import torch

from clitools.outputs import atomic_folder, atomic_output, check_name

from .checkpoint import load_checkpoint, read_checkpoint, return_threshold
from .config import LearnConfig, from_record
from .data import load_frames, recorded_path, shard_paths
from .evaluate import evaluate, model_predictor, model_windows
from .models import ModelConfig
from .summaries import TABLE2_CASES, distinct_folders, number_at, read_record, spread, study_table
from .summaries import seeds_summary as seeds_summary  # re-exported: the studies' summaries
from .summaries import table2_summary as table2_summary
from .train import train

FRAME_COUNTS = (1, 3, 5)
SIM2REAL_KEYS = (("scan_f1", "scan F1"), ("beam_accuracy", "beam acc."), ("chamfer_m", "Chamfer [m]"), ("iou", "IoU"))

ECHO_PEAK = "_echo_peak"  # a sim2real table's key for the baseline on a test set: "reality_echo_peak"


def _variant_folder(root: Path, name: str) -> Path:
    folder = root / name
    shard_paths(folder)  # clear error if missing
    return folder


def _paths(*items) -> list[Path]:
    """The items that name files or folders (the inputs an output must never replace)."""
    return [Path(p) for p in items if isinstance(p, str | Path)]


def _check_study_out(out: Path, inputs: list[Path]) -> None:
    """A study trains and scores into `out`: never an input folder, nor a folder inside one."""
    target = Path(os.path.realpath(out))
    for folder in inputs:
        if target.is_relative_to(os.path.realpath(folder)):
            raise ValueError(f"--out {out} is or lies inside the input folder {folder}: choose a folder of its own")


def _cell(stats: dict, key: str) -> str:
    return f"{stats[key]['mean']:.4f} / {stats[key]['std']:.4f}"


def table2(
    train_data: str | Path,
    test_data: str | Path,
    out: str | Path,
    *,
    config: LearnConfig,
    device: str = "cpu",
    progress: bool = True,
) -> dict:
    """Models with K = 1, 3, 5 trained on `train_data`; then the K = 5 model fine-tuned on each
    Table 2 case's training episodes (`test_data`/minimal, many, noisy) at a tenth of the learning
    rate. Every row is scored on the same validation episodes of each case (those early stopping
    read). Mean / std over windows.
    `config` gives the settings other than K (network and width, label frame, input floor, recipe)."""
    out, test_root = Path(out), Path(test_data)
    _check_study_out(out, _paths(train_data, test_data))
    frames = load_frames(train_data)
    cases = {c: load_frames(_variant_folder(test_root, c)) for c in TABLE2_CASES}
    runs = {}
    for k in FRAME_COUNTS:
        runs[f"K = {k}"] = run = out / f"k{k}"
        train(frames, run, config.with_frames(k), device=device, progress=progress, resume=True)
    tuned = {c: out / f"k5_finetuned_{c}" for c in TABLE2_CASES}
    slower = dataclasses.replace(config.train, lr=config.train.lr / 10)
    for c, run in tuned.items():
        train(
            cases[c],
            run,
            dataclasses.replace(config.with_frames(5), train=slower),
            device=device,
            progress=progress,
            resume=True,
            init_from=out / "k5" / "best.pt",
        )
    held = {c: torch.load(run / "best.pt", weights_only=True)["dataset"]["val_episodes"] for c, run in tuned.items()}

    def scored(run: Path, case: str, folder: str) -> dict:
        report = evaluate(run / "best.pt", cases[case], run / folder, device=device, episodes=held[case], timing=False)
        return report["results"]["model"]["all"]

    rows = {name: {c: scored(run, c, c) for c in TABLE2_CASES} for name, run in runs.items()}
    rows["K = 5 fine-tuned"] = {c: scored(run, c, "eval") for c, run in tuned.items()}
    lines = [
        f"# Table 2 layout: {config.model.name}, trained on `{train_data}`, scored on `{test_data}`",
        "",
        "scan F1 at 0.10 m mean / std over windows; the paper's MSE in the second table. Rows K = 1, 3, 5 "
        "are trained on the first dataset only; the fine-tuned row is the K = 5 model trained further "
        "on each case's other episodes (lr / 10). "
        "Every row scores the same validation episodes of each case (the ones early stopping read: "
        "not a test set).",
        "",
        "| input | " + " | ".join(f"{c} reflectors" if c != "noisy" else "noisy input" for c in TABLE2_CASES) + " |",
        "|---|---|---|---|",
    ]
    lines += [f"| {r} | " + " | ".join(_cell(v[c], "scan_f1") for c in TABLE2_CASES) + " |" for r, v in rows.items()]
    lines += ["", "MSE (the paper's metric):", "", "| input | " + " | ".join(TABLE2_CASES) + " |", "|---|---|---|---|"]
    lines += [f"| {r} | " + " | ".join(_cell(v[c], "mse") for c in TABLE2_CASES) + " |" for r, v in rows.items()]
    with atomic_folder(out, overwrite=True, inputs=_paths(train_data, test_data)) as stage:  # a rerun resumes
        (stage / "table2.md").write_text("\n".join(lines) + "\n")
        (stage / "table2.json").write_text(json.dumps(rows, indent=1))
    return rows


def sim2real(
    ablation: str | Path,
    reality: str | Path,
    out: str | Path,
    *,
    config: LearnConfig,
    device: str = "cpu",
    progress: bool = True,
    score_only: bool = False,
    variants: list[str] | None = None,
) -> dict:
    """One model per variant of a training suite with bounce variants (`ablation`, `randomised`:
    max_bounces 0, 1, 3, ...), each scored on its own validation episodes (in-domain) and on every
    window of each test set, beside the echo-peak baseline there. `reality` is one folder (named
    "reality") or {name: folder}, e.g. {"reality": ..., "crossengine": ...}. `config` is what to
    train (its model's K included).

    `score_only`: train nothing; score the runs already in `out/VARIANT` (e.g. trained side by side
    by `learn train` on a GPU, as benchmarks/sim2real_study.sh does), whose checkpoints name their
    own model and settings. `variants` limits it to those named (all of `ablation`'s by default)."""
    out, root = Path(out), Path(ablation)
    _check_study_out(out, _paths(ablation, *([reality] if isinstance(reality, str | Path) else reality.values())))
    if not root.is_dir():
        what = "does not exist" if not os.path.lexists(root) else "is not a folder"
        raise ValueError(f"--ablation {root} {what}: give a suite folder of variants (bounces_0/, bounces_1/, ...)")
    present = sorted(p.name for p in root.iterdir() if p.is_dir() and any(p.glob("shard-*.h5")))
    if not present:
        raise ValueError(f"{root} holds no variant folders with shards (expected bounces_0, bounces_1, ...)")
    if variants is not None and (not variants or set(variants) - set(present)):
        raise ValueError(f"variants {variants} are not all in {root}, which holds {present}")
    variants = present if variants is None else list(variants)
    tests = {"reality": reality} if isinstance(reality, str | Path) else dict(reality)
    if not tests or "in_domain" in tests or any(name.endswith(ECHO_PEAK) for name in tests):
        raise ValueError(f"name the test sets (not in_domain or ...{ECHO_PEAK}), got {list(tests)}")
    for name in tests:  # each names a folder and a picture under `out`
        check_name(name, "test set name")
    test_frames = {name: load_frames(folder) for name, folder in tests.items()}
    table, model_config = {}, config.model
    for v in variants:
        run = out / v
        if score_only:
            model_config = _trained_model(run)
        else:
            train(_variant_folder(root, v), run, config, device=device, progress=progress, resume=True)
        own = evaluate(
            run / "best.pt", _variant_folder(root, v), run / "in_domain", device=device, split="val", timing=False
        )
        table[v] = {"in_domain": own["results"]["model"]["all"]}
        for name, test in test_frames.items():
            far = evaluate(run / "best.pt", test, run / name, device=device, split="all", timing=False)
            table[v] |= {name: far["results"]["model"]["all"], name + ECHO_PEAK: far["results"]["echo peak"]["all"]}
    sets = ", ".join(f"{name} `{recorded_path(folder)}`" for name, folder in tests.items())
    header = f"Training data `{recorded_path(ablation)}`; test sets: {sets}. Mean over windows (std in metrics.json)."
    title = (
        f"Sim-to-real: {model_config.name} (K = {model_config.frames}) trained per multipath setting, "
        f"scored on {', '.join(tests)}"
    )
    with atomic_folder(out, overwrite=True, inputs=_paths(ablation, *tests.values())) as stage:  # a rerun resumes
        for name, test in test_frames.items():
            typical_windows({v: out / v for v in variants}, name, test, stage / f"examples_{name}.png", device=device)
        _write_sim2real(table, stage, title, header)
    return table


def typical_windows(runs: dict[str, Path], test: str, frames, out: Path, *, device: str = "cpu") -> Path:
    """A picture of test set `test`: one row per trained run, its window of median scan F1 there
    (from the run's evaluation `RUN/TEST/per_window.csv`: what it typically does, not its best)
    as sonar input, LiDAR truth, prediction and both scans from above."""
    from .plots import plot_examples

    rows = []
    for name, run in runs.items():
        with open(run / test / "per_window.csv", newline="") as f:
            scores = sorted(
                (float(r["scan_f1"]), int(r["window"])) for r in csv.DictReader(f) if r["predictor"] == "model"
            )
        f1, window = scores[(len(scores) - 1) // 2]
        model, ckpt = load_checkpoint(run / "best.pt", device)
        windows = model_windows(frames, ckpt, device)
        x, y = windows.batch([window])
        with torch.no_grad():
            pred = model_predictor(model)(x).float().clamp(0, 1)
        rows.append(
            {
                "title": f"trained on {name}: {frames.scenarios[windows.scenario[window]]}, window {window}",
                "caption": f"its median scan F1 on {test}: {f1:.2f} (of {len(scores)} windows)",
                "sonar": (x[0] if isinstance(x, tuple) else x)[0, windows.level, windows.config.anchor].cpu().numpy(),
                "truth": y[0, 0].cpu().numpy(),
                "pred": pred[0, 0].cpu().numpy(),
                "threshold": return_threshold(ckpt),
            }
        )
    with atomic_output(out, overwrite=True, inputs=list(runs.values())) as tmp:
        plot_examples(rows, frames.range_m, frames.azimuth_rad, tmp)
    return Path(out)


def _trained_model(run: Path) -> ModelConfig:
    """The network of a run to score, refused when it has no best.pt; a run whose training has
    not stopped (neither early stopping nor its epoch limit), or that cannot tell (no last.pt), is
    scored with a warning. Both files are read through `learn.checkpoint`'s checks."""
    if not (run / "best.pt").is_file():
        raise ValueError(f"{run} has no best.pt to score: train it first (learn train --out {run} ...)")
    best = read_checkpoint(run / "best.pt", role="--score-only")
    if not os.path.lexists(run / "last.pt"):
        warnings.warn(f"{run} has no last.pt: scoring its best.pt, not knowing if training stopped", stacklevel=3)
        return ModelConfig(**best["model_config"])
    last = read_checkpoint(run / "last.pt", role="--score-only")
    state, recipe = last.get("state"), from_record(last).train
    counts = isinstance(state, dict) and all(isinstance(state.get(k), int) for k in ("epoch", "stale"))
    if not counts:
        raise ValueError(f"--score-only {run / 'last.pt'} holds no training progress: train the run with learn train")
    if state["stale"] < recipe.patience and state["epoch"] < recipe.epochs:
        warnings.warn(
            f"{run}: training has not stopped (epoch {state['epoch']}, {state['stale']} without gain of "
            f"{recipe.patience}); scoring its best.pt so far",
            stacklevel=3,
        )
    return ModelConfig(**best["model_config"])


def _test_sets(table: dict) -> list[str]:
    first = next(iter(table.values()))
    return [k for k in first if k != "in_domain" and not k.endswith(ECHO_PEAK)]


SIM2REAL_FILES = ("sim2real.md", "sim2real.json", "sim2real.png")


def sim2real_summary(runs: list[str | Path], out: str | Path, *, overwrite: bool = False) -> dict:
    """Mean and std across repeated sim2real runs (e.g. seeds), from their sim2real.json files:
    each cell is the spread of the runs' window means, so it shows how much a conclusion
    depends on the draw of scenes and the training seed. Files already in `out` are replaced
    only with `overwrite`, files of `runs` never (`clitools.outputs`)."""
    with atomic_folder(out, overwrite=overwrite, inputs=_paths(*runs), expected=SIM2REAL_FILES) as stage:
        return _sim2real_summary(runs, stage)


def _sim2real_summary(runs: list[str | Path], out: Path) -> dict:
    read = [read_record(r, "sim2real.json", "learn sim2real") for r in runs]
    distinct_folders(runs, "sim2real")
    tables = [study_table(t, path, "rows of trained variants") for t, path in read]
    variants = list(tables[0])
    if any(list(t) != variants for t in tables):
        raise ValueError(f"the runs trained different variants: {[list(t) for t in tables]}")

    def across(v: str, where: str, key: str) -> dict:
        return spread([number_at(t, path, v, where, key, "mean") for t, path in read])

    tests = _test_sets(tables[0])
    wheres = ("in_domain", *tests, *(t + ECHO_PEAK for t in tests))
    summary = {v: {w: {k: across(v, w, k) for k, _ in SIM2REAL_KEYS} for w in wheres} for v in variants}
    names = ", ".join(f"`{Path(r).name}`" for r in runs)
    header = f"Mean and std over {len(runs)} runs ({names}); each run's value is its mean over windows."
    run_names = " | ".join(Path(r).name for r in runs)
    per_run = []
    for test in tests:
        scores = {v: np.array(summary[v][test]["scan_f1"]["runs"]) for v in variants}
        per_run += ["", f"{test} scan F1 of each run:", "", f"| trained on | {run_names} |"]
        per_run += ["|---" * (1 + len(runs)) + "|"]
        per_run += [f"| {v} | " + " | ".join(f"{x:.4f}" for x in scores[v]) + " |" for v in variants]
        # Paired per run (same scenes and seed), so scene difficulty cancels out of the difference.
        first = variants[0]
        per_run += [
            f"| {v} minus {first} | " + " | ".join(f"{x:+.4f}" for x in scores[v] - scores[first]) + " |"
            for v in variants[1:]
        ]
    _write_sim2real(summary, out, f"Sim-to-real over {len(runs)} runs", header, errorbars=True, more=per_run)
    return summary


def _write_sim2real(
    table: dict, out: Path, title: str, header: str, errorbars: bool = False, more: list[str] = ()
) -> None:
    """sim2real.md (the table, then the lines `more`), sim2real.json and sim2real.png into `out`."""

    def cell(stats: dict) -> str:
        return f"{stats['mean']:.3f} ± {stats['std']:.3f}" if errorbars else f"{stats['mean']:.4f}"

    wheres = ["in_domain", *_test_sets(table)]
    columns = [(k, w) for k, _ in SIM2REAL_KEYS for w in wheres]
    lines = [
        f"# {title}",
        "",
        header,
        "",
        "| trained on | " + " | ".join(f"{label} {w.replace('_', '-')}" for _, label in SIM2REAL_KEYS for w in wheres),
        "|---" * (1 + len(columns)) + "|",
    ]
    lines[-2] += " |"
    for v, r in table.items():
        lines.append(f"| {v} | " + " | ".join(cell(r[w][k]) for k, w in columns) + " |")
    first = next(iter(table.values()))
    baseline = [("-" if w == "in_domain" else cell(first[w + ECHO_PEAK][k])) for k, w in columns]
    lines.append("| echo-peak baseline | " + " | ".join(baseline) + " |")
    (out / "sim2real.md").write_text("\n".join([*lines, *more]) + "\n")
    (out / "sim2real.json").write_text(json.dumps(table, indent=1))
    _plot_sim2real(table, out / "sim2real.png", errorbars)


def _plot_sim2real(table: dict, path: Path, errorbars: bool) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(SIM2REAL_KEYS), figsize=(4 * len(SIM2REAL_KEYS), 3.4))
    names = list(table)
    x = np.arange(len(names))
    wheres = ["in_domain", *_test_sets(table)]
    width = 0.8 / len(wheres)
    for ax, (k, label) in zip(axes, SIM2REAL_KEYS, strict=True):
        for i, where in enumerate(wheres):
            stats = [table[n][where][k] for n in names]
            spread = [s["std"] for s in stats] if errorbars else None
            shift = (i - (len(wheres) - 1) / 2) * width
            ax.bar(x + shift, [s["mean"] for s in stats], width, yerr=spread, capsize=3, label=where.replace("_", "-"))
        ax.set_xticks(x, names)
        ax.set_title(label)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
