"""The folder of a training run (`learn train --out`): one run at a time writes it; what a run
finds there before it starts and what it leaves. A folder that holds a run is continued
(`--resume`, from its last.pt, refused by name when that file does not fit the run) or replaced
(`--overwrite`: the old run's files go first, so the folder never holds the config of one run
beside the checkpoints of another), never written over by surprise. config.json, the
checkpoints, history.csv and summary.json are written whole or not at all.

The lock is `clitools.locks.folder_lock` (an flock on OUT/.train.lock, freed by the kernel when its
process ends, so a killed run's lock file is taken over); the dataset folders of `generate` keep
their own "pid host" lock file.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from clitools.locks import folder_lock

from .checkpoint import check_compatible, check_grid, config_changes, load_weights, read_checkpoint, save_checkpoint
from .config import MONITORS, LearnConfig, TrainConfig
from .data import Windows
from .models import ModelConfig
from .progress import warn_if_silent, write_history, write_whole

LOCK_FILE = ".train.lock"
RUN_FILES = ("config.json", "last.pt", "best.pt", "history.csv", "curves.png", "summary.json", "folds.json", "folds.md")
"""What a run writes into its folder (and into each fold_k/ of a k-fold run)."""


@contextlib.contextmanager
def run_folder(out: Path, *, resume: bool, overwrite: bool, inputs=()) -> Iterator[Path]:
    """Hold the run folder `out` for one run: create it, lock it (rank 0 of a torchrun; the other
    ranks only check), refuse what the run must not touch, clear a run that `overwrite` replaces
    (never one of the run's `inputs`: an --init-from checkpoint or a --config file in it).
    A folder this call created and the run left empty (a refused run) is removed again."""
    out = Path(out)
    if resume and overwrite:
        raise ValueError("--resume continues the run in --out and --overwrite deletes it: give one of them")
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a folder for the run")
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:  # a dangling link, a read-only or virtual file system
        reason = err.strerror or str(err)
        raise OSError(f"cannot make the run folder --out {out} ({reason}): choose another folder") from None
    main = os.environ.get("RANK", "0") == "0"  # set by torchrun, before the process group exists
    try:
        with folder_lock(out, LOCK_FILE, command="learn train") if main else contextlib.nullcontext():
            check_run_folder(out, resume=resume, overwrite=overwrite)
            if overwrite:
                check_inputs_survive(out, inputs)
            if main:
                clear_run(out, keep_run=not overwrite)
            yield out
    finally:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()


def check_out_beside_data(out: Path, data: Path) -> None:
    """Refuse a run folder that is, or lies inside, the dataset folder it trains on: a dataset
    folder holds one run of the simulator, and --overwrite would clear run files among its shards."""
    target = Path(os.path.realpath(out))
    if target.is_relative_to(os.path.realpath(data)):
        raise ValueError(
            f"--out {out} is or lies inside the dataset folder --data {data}: give the run a folder of its own"
        )


def check_run_folder(out: Path, *, resume: bool, overwrite: bool) -> None:
    """Refuse a folder that holds a run unless it is continued or replaced, and a run to continue
    whose last.pt is missing (best.pt alone would restart from scratch and overwrite it)."""
    found = sorted(p.relative_to(out).as_posix() for p in out.glob("**/*.pt"))
    if found and not (resume or overwrite):
        raise ValueError(
            f"--out {out} already holds a run ({', '.join(found[:3])}); continue it with --resume, "
            "replace it with --overwrite, or choose another folder"
        )
    if resume and not overwrite:
        for best in sorted(out.glob("**/best.pt")):
            if not (best.parent / "last.pt").exists():
                raise ValueError(
                    f"--resume: {best.parent} has best.pt but no last.pt, the checkpoint a run continues from; "
                    f"fine-tune the kept model into a new folder with --init-from {best}, or replace the run "
                    "with --overwrite"
                )


def check_inputs_survive(out: Path, inputs) -> None:
    """Refuse to replace the run in `out` when one of this run's input files lies in it: clearing
    the old run would delete the checkpoint it starts from or the config it was read from."""
    inside = out.resolve()
    for given in inputs:
        if given is not None and Path(given).resolve().is_relative_to(inside):
            raise ValueError(
                f"--overwrite would delete {given}, an input of this run, with the run in --out {out}: "
                "copy it out of that folder first, or train into another --out"
            )


def clear_run(out: Path, *, keep_run: bool = False) -> None:
    """Remove the files of the run in `out` (and in its fold_k/ folders): the checkpoints,
    history, summaries and TensorBoard events that `learn train` writes, nothing else. With
    `keep_run`, only the temporary files a killed run left (the lock is held: no live run
    writes them)."""
    for folder in [out, *sorted(out.glob("fold_*"))]:
        if not folder.is_dir():
            continue
        doomed = [folder / f"{name}.tmp" for name in RUN_FILES]
        if not keep_run:
            doomed += [folder / name for name in RUN_FILES]
            doomed += list((folder / "tensorboard").glob("events.out.tfevents.*"))
        for path in doomed:
            path.unlink(missing_ok=True)
        for empty in (folder / "tensorboard", folder):
            if not keep_run and empty != out and empty.is_dir() and not any(empty.iterdir()):
                empty.rmdir()


def start_state(model, optimizer, config: LearnConfig, windows: Windows, last: Path | None, init_from) -> dict:
    """The run's progress so far (epoch, step, best, stale, history): restored with the weights
    and optimizer from `last` when resuming, else new (weights from `init_from` when fine-tuning).
    A file that does not fit this run is refused naming the file and what differs."""
    if last is not None:
        ckpt = read_checkpoint(last, windows.device, role="--resume")
        check_compatible(ckpt, config, windows, path=last)
        check_same_grid(windows, ckpt, f"--resume {last}")
        load_weights(model, ckpt, last, role="--resume")
        if "optimizer" in ckpt:
            try:
                optimizer.load_state_dict(ckpt["optimizer"])
            except (ValueError, KeyError, TypeError, RuntimeError) as err:
                raise ValueError(f"--resume {last}: its optimizer state does not fit this model ({err})") from None
        else:  # packed to travel between machines (benchmarks/learner_converged.sh pack)
            warnings.warn(f"{last} has no optimizer state: Adam restarts its moment estimates", stacklevel=3)
        state = ckpt.get("state")
        if not isinstance(state, dict) or not {"epoch", "step", "stale", "history"} <= set(state):
            raise ValueError(f"--resume {last} holds no training progress (a stripped or exported checkpoint?)")
        state.setdefault("best", state.pop("best_ssim", -math.inf))  # checkpoints from before `monitor`
        check_progress(state, config.train.monitor, last)
        check_optimizer_state(optimizer, last)
        kept = last.with_name("best.pt")
        if state.get("best_epoch") is not None and not kept.exists():
            raise ValueError(
                f"--resume: {kept} is missing (the run kept epoch {state['best_epoch']} there); put it back, "
                "or start a new run"
            )
        return state
    if init_from is not None:  # fine-tuning: weights only
        ckpt = read_checkpoint(init_from, windows.device, role="--init-from")
        changed = config_changes(ModelConfig(**ckpt["model_config"]), config.model, "model")
        if changed:
            raise ValueError(
                f"--init-from {init_from} holds another model than this run builds ({'; '.join(changed)}): give "
                "the same --model, --frames and --width (or --set model.FIELD)"
            )
        check_same_grid(windows, ckpt, f"--init-from {init_from}")
        load_weights(model, ckpt, init_from, role="--init-from")
    return {"epoch": 0, "step": 0, "best": -math.inf, "stale": 0, "history": []}


def check_progress(state: dict, monitor: str, path: Path) -> None:
    """Refuse a last.pt whose training progress is not what `learn train` writes: counts that are
    not integers >= 0, a history that does not hold one row per epoch done (with the monitored
    score), a best score that is NaN or a kept epoch outside them. Resumed, such a state trains
    the wrong number of epochs, keeps no epoch, or fails in the summary."""
    bad = f"--resume {path}: its training progress is damaged"
    redo = "resume from a last.pt written by `learn train`, or start a new run"
    for key in ("epoch", "step", "stale"):
        value = state[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{bad} (state.{key} is {value!r}, not a count >= 0): {redo}")
    history, score = state["history"], f"val_{monitor}"
    rows_fit = isinstance(history, list) and all(
        isinstance(r, dict) and isinstance(r.get("epoch"), int) and isinstance(r.get(score), float | int)
        for r in history
    )
    # the length first: a damaged epoch count of 10^9 would otherwise build a list of 10^9
    if not rows_fit or len(history) != state["epoch"] or any(r["epoch"] != k for k, r in enumerate(history, 1)):
        raise ValueError(
            f"{bad} (state.history is not one row with {score} per epoch of the {state['epoch']} done): {redo}"
        )
    best, kept = state["best"], state.get("best_epoch")
    if isinstance(best, bool) or not isinstance(best, float | int) or math.isnan(best):
        raise ValueError(f"{bad} (state.best is {best!r}, not a score): {redo}")
    if kept is not None and not (isinstance(kept, int) and 1 <= kept <= state["epoch"]):
        raise ValueError(f"{bad} (state.best_epoch is {kept!r}, not one of the epochs done): {redo}")


def check_optimizer_state(optimizer, path: Path) -> None:
    """Refuse optimizer moments that do not match the weights they belong to, or hold NaN or inf,
    and settings (learning rate, betas) that are not finite: Adam would fail at its first step
    with a shape error, or turn the weights to NaN (which reads as a learning-rate problem)."""
    import torch

    where = f"--resume {path}: its optimizer state"
    for group in optimizer.param_groups:
        for key, value in group.items():
            numbers = value if isinstance(value, tuple | list) and key != "params" else (value,)
            if key != "params" and any(isinstance(v, float) and not math.isfinite(v) for v in numbers):
                raise ValueError(f"{where} has {key} {value!r}, not finite: resume from another last.pt")
        for param in group["params"]:
            for key, moment in optimizer.state.get(param, {}).items():
                if not isinstance(moment, torch.Tensor):
                    raise ValueError(f"{where} holds {key} {moment!r}, not a tensor: resume from another last.pt")
                if moment.ndim and moment.shape != param.shape:
                    raise ValueError(
                        f"{where} does not fit this model ({key} is {list(moment.shape)} for weights of "
                        f"{list(param.shape)}): resume from another last.pt"
                    )
                if moment.is_floating_point() and not bool(torch.isfinite(moment).all()):
                    raise ValueError(f"{where} holds NaN or inf in {key}: resume from an earlier last.pt")


def check_same_grid(windows: Windows, ckpt: dict, name: str) -> None:
    """Refuse a checkpoint trained on another range/azimuth grid than the run's data (old ones
    without the grid pass: their dataset identity was checked)."""
    if "range_m" in ckpt and "azimuth_rad" in ckpt:
        check_grid(windows.frames, ckpt, name)


def write_run_config(out: Path, meta: dict, dev, resumed: bool, init_from, process_group: dict | None) -> None:
    """config.json: the whole config (`learn train --config` reads it back), the dataset, where it ran."""
    run = {k: meta[k] for k in ("model_config", "data_config", "train_config", "dataset", "parameters")}
    init = None if init_from is None else os.path.relpath(Path(init_from).absolute())  # as data.recorded_path
    run |= {"device": str(dev), "resumed": resumed, "init_from": init}
    run["process_group"] = process_group
    write_whole(out / "config.json", json.dumps(run, indent=1))


RESUME_HINT = "continue the run with --resume"


def save_epoch(out: Path, model, optimizer, state: dict, threshold: float, meta: dict, improved: bool) -> None:
    """best.pt when kept, then last.pt (each with the threshold calibrated this epoch). best.pt
    goes first: a run stopped between the two resumes from the last.pt before, redoes this epoch
    exactly and keeps it again."""
    ckpt = {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "state": state}
    ckpt |= {"threshold": threshold} | meta
    if improved:
        save_checkpoint(ckpt, out / "best.pt", then=RESUME_HINT)
    save_checkpoint(ckpt, out / "last.pt", then=RESUME_HINT)


def save_history(out: Path, state: dict, monitor: str) -> None:
    """history.csv and curves.png (the kept epoch marked); a full disk is one line naming the folder."""
    try:
        write_history(out, state["history"], state.get("best_epoch"), monitor)
    except OSError as err:  # curves.png from matplotlib
        raise OSError(f"could not write the history of {out} ({err.strerror or err}); {RESUME_HINT}") from None


def write_summary(out: Path, state: dict, recipe: TrainConfig, meta: dict, train_count: int, val_count: int) -> dict:
    """summary.json: the kept epoch's validation metrics and threshold, speed, sizes and configs."""
    sign = MONITORS[recipe.monitor]
    best = max(state["history"], key=lambda r: _nan_low(sign * r[f"val_{recipe.monitor}"]))
    summary = {
        "out": os.path.relpath(Path(out).absolute()),  # no machine's absolute path in the summary
        "epochs": state["epoch"],
        "best_epoch": best["epoch"],
        "best": {k: v for k, v in best.items() if k.startswith("val_")},
        "samples_per_s": float(np.median([r["samples_per_s"] for r in state["history"]])),
        "train_windows": train_count,
        "val_windows": val_count,
    } | {k: meta[k] for k in ("model_config", "data_config", "train_config", "parameters", "dataset")}
    summary["threshold"] = best["val_threshold"]
    write_whole(out / "summary.json", json.dumps(summary, indent=1))
    warn_if_silent(best, out, hint="" if recipe.loss == "bce" else ", or with --loss bce")
    return summary


def _nan_low(x: float) -> float:
    return -math.inf if math.isnan(x) else x
