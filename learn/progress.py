"""What a training run tells and leaves behind: the validation set's size, one line per epoch, the
warning for a model that predicts no return, history.csv and curves.png, the k-fold summary.

The epoch line accounts for every true return (found, at the wrong range, missed: they add up
to 1, so a low precision beside few false returns is explained) and says why an epoch is kept
or not, with the patience left.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import warnings
from pathlib import Path

import numpy as np

NO_RETURN_ALARM = 0.9
"""Warn when the kept model predicts no return on at least this share of the validation beams."""

MONITOR_NAMES = {"scan_f1": "scan F1", "beam_accuracy": "beam accuracy", "chamfer_m": "Chamfer [m]", "ssim": "SSIM"}


def sizes_line(
    *, train_windows: int, train_episodes: int, per_epoch: int, val_windows: int, val_of: int, val_episodes: int
) -> str:
    """What the run trains and validates on, said once before its first epoch line. Validation on a
    single episode is named as such: its scores are one scene's and swing from scene to scene."""
    each = "" if per_epoch >= train_windows else f" ({per_epoch:,} per epoch, drawn anew each epoch)"
    drawn = "" if val_windows >= val_of else f" (a fixed draw of {val_windows:,} of {val_of:,})"
    line = (
        f"training on {train_windows:,} windows of {_count(train_episodes, 'episode')}{each}; validating on "
        f"{val_windows:,} windows{drawn} of {_count(val_episodes, 'episode')}"
    )
    if val_episodes == 1:
        line += " only: the scores are one scene's (more episodes: raise --val-fraction or generate more)"
    return line


def epoch_line(row: dict, config, state: dict, improved: bool, previous: int | None = None) -> str:
    """One line per epoch: the validation scores at the calibrated threshold, and whether (and why)
    this epoch is kept. `previous` is the epoch kept before this one (None: none was)."""
    line = (
        f"epoch {row['epoch']}/{config.epochs}: train loss {row['train_loss']:.4g} | val scan F1 "
        f"{row['val_scan_f1']:.3f} at threshold {row['val_threshold']:.2f} ({returns_text(row)})"
    )
    if config.monitor != "scan_f1":
        line += f", {MONITOR_NAMES[config.monitor]} {row[f'val_{config.monitor}']:.4g}"
    return f"{line} | {keep_text(row, config, state, improved, previous)}"


def returns_text(row: dict, prefix: str = "val_") -> str:
    """The shares of the returns, as "precision 0.25; true returns 0.15 found, 0.42 at the wrong range,
    0.43 missed; false 0.00" (found + wrong range + missed = 1; false: of the empty beams)."""
    keys = ("return_precision", "return_recall", "wrong_range", "missed", "false")
    v = {k: row.get(f"{prefix}{k}", math.nan) for k in keys}  # a row from before wrong_range: nan
    return (
        f"precision {v['return_precision']:.2f}; true returns {v['return_recall']:.2f} found, "
        f"{v['wrong_range']:.2f} at the wrong range, {v['missed']:.2f} missed; false {v['false']:.2f}"
    )


def keep_text(row: dict, config, state: dict, improved: bool, previous: int | None) -> str:
    """Why the epoch is kept ("kept: first epoch", "kept: best scan F1 so far (0.388 in epoch 2)")
    or not ("not kept: epoch 2 stays best (scan F1 0.388); 1 of 4 epochs without a better one")."""
    name = MONITOR_NAMES[config.monitor]
    earlier = next((r for r in state["history"] if r["epoch"] == previous), None)
    if improved:
        if earlier is None:
            return "kept: first epoch" if row["epoch"] == 1 else f"kept: first epoch with a {name}"
        return f"kept: best {name} so far ({earlier[f'val_{config.monitor}']:.3f} in epoch {previous})"
    why = f"{name} is nan" if math.isnan(row[f"val_{config.monitor}"]) else "no better"
    if earlier is not None:
        why = f"epoch {previous} stays best ({name} {earlier[f'val_{config.monitor}']:.3f})"
    stop = "; stopping" if state["stale"] >= config.patience else ""
    return f"not kept: {why}; {state['stale']} of {config.patience} epochs without a better one{stop}"


def summary_line(summary: dict) -> str:
    """The line `learn train` ends with, per run (or fold): the kept epoch and its validation scores."""
    best = summary["best"]
    return (
        f"{summary['out']}: kept epoch {summary['best_epoch']} of {summary['epochs']}: validation scan F1 "
        f"{best['val_scan_f1']:.3f} at threshold {best['val_threshold']:.2f} (beam accuracy "
        f"{best['val_beam_accuracy']:.3f}, {returns_text(best)}); {summary['samples_per_s']:,.0f} training "
        f"windows/s; {summary['parameters']:,} parameters"
    )


def _count(n: int, noun: str) -> str:
    return f"{n:,} {noun}" + ("" if n == 1 else "s")


def write_whole(path: Path, text: str) -> None:
    """Write `text` to `path` through a temporary file: `path` is whole or as it was, and a failed
    write (a full disk, Ctrl-C) leaves no temporary one; an OSError names the file."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        tmp.replace(path)
    except BaseException as err:  # also Ctrl-C: no temporary file is left behind
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        if not isinstance(err, OSError):
            raise
        raise OSError(
            f"could not write {path} ({err.strerror or err}); free space, then continue with --resume"
        ) from None


def warn_if_silent(best: dict, out: Path, hint: str = "") -> None:
    """A model that predicts no return almost anywhere looks fine on MSE and SSIM: say so loudly."""
    share = best["val_no_return"]
    if share >= NO_RETURN_ALARM:
        warnings.warn(
            f"{out}: the kept model (epoch {best['epoch']}) predicts no return on {share:.0%} of the validation "
            f"beams even at its best threshold {best['val_threshold']:.2f} (scan F1 {best['val_scan_f1']:.3f}): it "
            f"has not learnt to place walls. Train longer or on more data{hint}.",
            stacklevel=3,
        )


def write_history(out: Path, history: list[dict], kept_epoch: int | None, monitor: str) -> None:
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=_columns(history))
    writer.writeheader()
    writer.writerows(history)
    write_whole(out / "history.csv", text.getvalue())
    from .plots import plot_curves

    plot_curves(history, out / "curves.png", kept_epoch=kept_epoch, monitor=monitor)


def _columns(history: list[dict]) -> list[str]:
    """Every key of the rows in first-seen order (a resumed run's older rows may lack a newer one)."""
    return list(dict.fromkeys(k for row in history for k in row))


def write_fold_summary(out: Path, results: list[dict]) -> None:
    keys = list(results[0]["best"])
    table = {k: [r["best"].get(k, math.nan) for r in results] for k in keys}
    summary = {k: {"mean": float(np.mean(v)), "std": float(np.std(v)), "folds": v} for k, v in table.items()}
    write_whole(out / "folds.json", json.dumps(summary, indent=1))
    lines = ["| metric | mean | std |", "|---|---|---|"]
    lines += [f"| {k} | {s['mean']:.4g} | {s['std']:.4g} |" for k, s in summary.items()]
    write_whole(out / "folds.md", f"# {len(results)}-fold cross-validation\n\n" + "\n".join(lines) + "\n")
