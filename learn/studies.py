"""The experiments: the paper's Table 2 layout, and the multipath sim-to-real study.

    python -m learn table2 --train data/paper --test data/table2 --out runs/table2
    python -m learn sim2real --ablation data/ablation --reality data/reality --out runs/sim2real

Both train with `learn.train.train` and score with `learn.evaluate.evaluate`, so every number
in their tables comes from a real run whose checkpoint and report stay in the output folder.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from .data import DataConfig, load_frames, shard_paths
from .evaluate import evaluate
from .models import ModelConfig
from .train import TrainConfig, train

TABLE2_CASES = ("minimal", "many", "noisy")
FRAME_COUNTS = (1, 3, 5)


def _variant_folder(root: Path, name: str) -> Path:
    folder = root / name
    shard_paths(folder)  # clear error if missing
    return folder


def _cell(stats: dict, key: str) -> str:
    return f"{stats[key]['mean']:.4f} / {stats[key]['std']:.4f}"


def table2(
    train_data: str | Path,
    test_data: str | Path,
    out: str | Path,
    *,
    model: str = "polar_unet",
    train_config: TrainConfig,
    device: str = "cpu",
    progress: bool = True,
) -> dict:
    """Models with K = 1, 3, 5 trained on `train_data`; then the K = 5 model fine-tuned on each
    Table 2 case's training episodes (`test_data`/minimal, many, noisy) at a tenth of the learning
    rate. Every row is scored on the same held-out episodes of each case. Mean / std over windows."""
    out, test_root = Path(out), Path(test_data)
    frames = load_frames(train_data)
    cases = {c: load_frames(_variant_folder(test_root, c)) for c in TABLE2_CASES}
    runs = {}
    for k in FRAME_COUNTS:
        runs[f"K = {k}"] = run = out / f"k{k}"
        train(
            frames,
            run,
            model_config=ModelConfig(name=model, frames=k),
            data_config=DataConfig(frames=k),
            train_config=train_config,
            device=device,
            progress=progress,
            resume=True,
        )
    tuned = {c: out / f"k5_finetuned_{c}" for c in TABLE2_CASES}
    for c, run in tuned.items():
        train(
            cases[c],
            run,
            model_config=ModelConfig(name=model, frames=5),
            data_config=DataConfig(frames=5),
            train_config=dataclasses.replace(train_config, lr=train_config.lr / 10),
            device=device,
            progress=progress,
            resume=True,
            init_from=out / "k5" / "best.pt",
        )
    held = {c: torch.load(run / "best.pt", weights_only=False)["dataset"]["val_episodes"] for c, run in tuned.items()}
    rows = {}
    for name, run in runs.items():
        rows[name] = {
            c: evaluate(run / "best.pt", cases[c], run / c, device=device, episodes=held[c])["results"]["model"]["all"]
            for c in TABLE2_CASES
        }
    rows["K = 5 fine-tuned"] = {
        c: evaluate(run / "best.pt", cases[c], run / "eval", device=device, episodes=held[c])["results"]["model"]["all"]
        for c, run in tuned.items()
    }
    lines = [
        f"# Table 2 layout: {model}, trained on `{train_data}`, scored on `{test_data}`",
        "",
        "MSE mean / std over windows (as the paper); range MAE [m] mean / std in the second table. Rows K = 1, 3, 5 "
        "are trained on the first dataset only; the fine-tuned row is the K = 5 model trained further "
        "on each case's other episodes (lr / 10). "
        "Every row scores the same held-out episodes of each case.",
        "",
        "| input | " + " | ".join(f"{c} reflectors" if c != "noisy" else "noisy input" for c in TABLE2_CASES) + " |",
        "|---|---|---|---|",
    ]
    lines += [f"| {r} | " + " | ".join(_cell(v[c], "mse") for c in TABLE2_CASES) + " |" for r, v in rows.items()]
    lines += ["", "| input | " + " | ".join(TABLE2_CASES) + " |", "|---|---|---|---|"]
    lines += [
        f"| {r} | " + " | ".join(_cell(v[c], "range_mae_m") for c in TABLE2_CASES) + " |" for r, v in rows.items()
    ]
    (out / "table2.md").write_text("\n".join(lines) + "\n")
    (out / "table2.json").write_text(json.dumps(rows, indent=1))
    return rows


def sim2real(
    ablation: str | Path,
    reality: str | Path,
    out: str | Path,
    *,
    model: str = "polar_unet",
    frames: int = 5,
    train_config: TrainConfig,
    device: str = "cpu",
    progress: bool = True,
) -> dict:
    """One model per ablation variant (max_bounces 0, 1, 3), each scored on its own held-out
    episodes (in-domain) and on every window of the reality suite."""
    out, root = Path(out), Path(ablation)
    variants = sorted(p.name for p in root.iterdir() if p.is_dir() and any(p.glob("shard-*.h5")))
    if not variants:
        raise ValueError(f"{root} holds no variant folders with shards (expected bounces_0, bounces_1, ...)")
    real = load_frames(reality)
    table = {}
    for v in variants:
        run = out / v
        train(
            _variant_folder(root, v),
            run,
            model_config=ModelConfig(name=model, frames=frames),
            data_config=DataConfig(frames=frames),
            train_config=train_config,
            device=device,
            progress=progress,
            resume=True,
        )
        own = evaluate(run / "best.pt", _variant_folder(root, v), run / "in_domain", device=device, split="val")
        far = evaluate(run / "best.pt", real, run / "reality", device=device, split="all")
        table[v] = {
            "in_domain": own["results"]["model"]["all"],
            "reality": far["results"]["model"]["all"],
            "reality_echo_peak": far["results"]["echo peak"]["all"],
        }
    keys = (("range_mae_m", "range MAE [m]"), ("chamfer_m", "Chamfer [m]"), ("ssim", "SSIM"), ("iou", "IoU"))
    lines = [
        f"# Sim-to-real: {model} (K = {frames}) trained per multipath setting, scored on the reality suite",
        "",
        f"Training data `{ablation}`, held-out 'reality' data `{reality}`. Mean over windows (std in metrics.json).",
        "",
        "| trained on | " + " | ".join(f"{label} in-domain | {label} reality" for _, label in keys) + " |",
        "|---" * (1 + 2 * len(keys)) + "|",
    ]
    for v, r in table.items():
        cells = [f"{r['in_domain'][k]['mean']:.4f} | {r['reality'][k]['mean']:.4f}" for k, _ in keys]
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    base = next(iter(table.values()))["reality_echo_peak"]
    lines.append("| echo-peak baseline | " + " | ".join(f"- | {base[k]['mean']:.4f}" for k, _ in keys) + " |")
    (out / "sim2real.md").write_text("\n".join(lines) + "\n")
    (out / "sim2real.json").write_text(json.dumps(table, indent=1))
    _plot_sim2real(table, keys, out / "sim2real.png")
    return table


def _plot_sim2real(table: dict, keys, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(keys), figsize=(4 * len(keys), 3.4))
    names = list(table)
    x = np.arange(len(names))
    for ax, (k, label) in zip(axes, keys, strict=True):
        for shift, where in ((-0.2, "in_domain"), (0.2, "reality")):
            ax.bar(x + shift, [table[n][where][k]["mean"] for n in names], 0.4, label=where.replace("_", "-"))
        ax.set_xticks(x, names)
        ax.set_title(label)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
