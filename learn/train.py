"""Training: one readable loop (Adam, early stopping on validation scan F1), checkpoints with configs.

    python -m learn train --data data/paper --model paper --frames 5 --out runs/paper_k5
    torchrun --nproc_per_node 4 -m learn train --data data/paper --model polar_unet --out runs/unet

Single process on CPU or one GPU, or DDP under torchrun (one process per GPU; rank 0 validates
and writes). Mixed precision (bfloat16 autocast) on GPUs. `--folds k` trains k models, each
validated on a fold of whole episodes it never saw, and summarises them.

Every epoch the model's return threshold is calibrated on the validation windows (the one of
`learn.scan.CALIBRATION_THRESHOLDS` with the best mean scan F1 at 0.10 m); the metrics of
that epoch are read at it, and the checkpoint stores it for evaluate, predict and export.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from .augment import augmented_batch
from .config import MONITORS, LearnConfig, TrainConfig, to_record, with_grid
from .data import FORMAT_VERSION, Frames, Windows, load_frames, split_groups, validation_split
from .devices import torch_device
from .evaluate import calibrate_on_predictions, model_predictor, predict_batches, score_predictions
from .inputs import regular_file
from .models import build_model, parameter_count, run_model
from .progress import epoch_line, sizes_line, write_fold_summary
from .runs import (
    check_out_beside_data,
    run_folder,
    save_epoch,
    save_history,
    start_state,
    write_run_config,
    write_summary,
)
from .tensorboard import TensorBoardLog, summary_writer


def loss_fn(model, x, y: torch.Tensor, config: TrainConfig) -> torch.Tensor:
    out = run_model(model, x)
    kind = _unwrap(model).output
    if config.loss == "bce":
        if kind != "logits":
            raise ValueError("loss 'bce' needs a model that outputs logits (not the paper network)")
        weight = torch.full((), config.pos_weight, device=out.device)  # a fill, not a host upload
        return F.binary_cross_entropy_with_logits(out.float(), y, pos_weight=weight)
    image = torch.sigmoid(out) if kind == "logits" else out
    return F.mse_loss(image.float(), y)


# Validation keeps each window's prediction and label (float32) on the device for both the
# threshold sweep and the scores, up to this many bytes (2,000 paper-suite windows: 0.7 GB).
VALIDATION_KEEP_BYTES = 2 << 30
CHECK_EVERY = 50  # training steps between reads of the summed loss (each read waits for the GPU)


def _check_finite(total: torch.Tensor, epoch: int, step: int) -> None:
    if not torch.isfinite(total):
        raise FloatingPointError(
            f"the training loss became {float(total)} in epoch {epoch + 1} by step {step + 1}: "
            "lower --lr or check the data"
        )


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C during training; its message says what the run folder keeps and how to go on."""


def _unwrap(model):
    return model.module if hasattr(model, "module") else model


@dataclass
class _Dist:
    rank: int = 0
    world: int = 1
    local: int = 0
    joined: bool = False  # in a process group (launched by torchrun), even of one process

    @property
    def main(self) -> bool:
        return self.rank == 0


def _init_distributed(device: str) -> tuple[_Dist, torch.device]:
    """Under torchrun: join the process group and take this rank's GPU (or the CPU with gloo). A
    torchrun of one process joins too, so it runs the same path (NCCL, DDP) as a larger one."""
    if "LOCAL_RANK" not in os.environ:  # torchrun sets it for every process it starts
        return _Dist(), torch_device(device)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    import torch.distributed as dist

    local = int(os.environ["LOCAL_RANK"])
    cuda = device != "cpu" and torch.cuda.is_available()
    if not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo")
    if cuda:
        torch.cuda.set_device(local)
    return _Dist(dist.get_rank(), world, local, joined=True), torch.device(f"cuda:{local}" if cuda else "cpu")


def _process_group(dist_info: _Dist) -> dict | None:
    """The torchrun process group a run trained in (backend and size), None outside torchrun."""
    if not dist_info.joined:
        return None
    import torch.distributed as dist

    return {"backend": dist.get_backend(), "processes": dist_info.world}


def validate(model, windows: Windows, indices: np.ndarray, *, amp: bool = True) -> dict[str, float]:
    """Mean metrics of the model on the given windows (see learn.evaluate.score), read at the
    return threshold calibrated on them ("threshold")."""
    predict = model_predictor(_unwrap(model), amp=amp)
    cells = len(windows.frames.range_m) * len(windows.frames.azimuth_rad)
    kept = None  # else the windows are predicted twice, for the sweep and for the scores
    if len(indices) * cells * 8 <= VALIDATION_KEEP_BYTES:
        kept = list(predict_batches(predict, windows, indices))
    threshold, _ = calibrate_on_predictions(kept or predict_batches(predict, windows, indices), windows)
    per = score_predictions(kept or predict_batches(predict, windows, indices), windows, threshold)
    means = {k: float(np.nanmean(v)) if np.isfinite(v).any() else float("nan") for k, v in per.items()}
    return means | {"threshold": threshold}


def train(
    data: str | Path | Frames,
    out: str | Path,
    config: LearnConfig,
    *,
    device: str = "cpu",
    resume: bool = False,
    folds: int = 1,
    progress: bool = True,
    init_from: str | Path | None = None,
    overwrite: bool = False,
    tensorboard: bool = False,
    inputs: tuple = (),
) -> dict:
    """Train a model (or `folds` models) on a dataset folder; returns the summary of the run.

    Writes into `out`: config.json (every setting and the dataset's identity, from the start),
    last.pt and best.pt (weights, optimizer, epoch, all configs, dataset identity), history.csv
    and curves.png, summary.json. With folds > 1: out/fold_i/ each,
    and folds.json/folds.md with mean and std over the folds. A folder that already holds
    checkpoints is continued (`resume`, exactly as if never stopped: every random draw of an
    epoch comes from (seed, epoch)) or replaced (`overwrite`), never silently overwritten; one
    run at a time writes it (`learn.runs`). Ctrl-C raises RunInterrupted, whose message says
    what the folder keeps.
    `tensorboard` also logs every epoch under out/tensorboard (`learn.tensorboard`). `inputs`:
    other files the run read (a --config file), which `overwrite` refuses to delete with the old run.
    """
    if tensorboard:
        summary_writer()  # a missing extra is refused before anything is written
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 1:
        raise ValueError(f"--folds must be an integer >= 1 (1: no cross-validation), got {folds!r}")
    if init_from is not None:
        regular_file(init_from, "--init-from checkpoint")  # not a folder or a FIFO (torch.load would block)
    if not isinstance(data, Frames):
        check_out_beside_data(Path(out), Path(data))
    protected = (init_from, *inputs)  # what --overwrite must not delete with the old run
    with run_folder(Path(out), resume=resume, overwrite=overwrite, inputs=protected):  # one run at a time
        each = {"resume": resume, "progress": progress, "init_from": init_from, "tensorboard": tensorboard}
        return _train_in(data, Path(out), config, device=device, folds=folds, **each)


def _train_in(data, out: Path, config: LearnConfig, *, device: str, folds: int, **each) -> dict:
    """`train` once its run folder is held."""
    dist_info, dev = _init_distributed(device)
    if dev.type == "cpu":
        torch.set_flush_denormal(True)  # denormal gradients make CPU steps many times slower
    # only the elevations the model reads: a level-slice model of five-elevation data holds a fifth
    frames = data if isinstance(data, Frames) else load_frames(data, elevation_deg=config.model.elevation_deg)
    if (suite := frames.info.get("suite")) in ("crossengine", "crossengine_rough"):
        raise ValueError(f"{frames.info['folder']} is the {suite} test set: score models on it, never train on it")
    config = with_grid(config, frames)
    windows = Windows(
        frames, config.data, dev, odometry=config.model.uses_odometry, elevation_deg=config.model.elevation_deg
    )
    groups = windows.episode if config.train.split_by == "episode" else windows.scenario
    _check_enough_groups(groups, folds, config.train.split_by, frames.info["folder"])
    each |= {"config": config, "dist_info": dist_info}
    if folds > 1:
        fold_of = split_groups(groups, folds, seed=config.train.split_seed_or_seed)
        results = [
            _train_one(windows, fold_of != k, fold_of == k, out / f"fold_{k}", fold=k, **each) for k in range(folds)
        ]
        if dist_info.main:
            write_fold_summary(out, results)
        result = {"folds": results}
    else:
        held = validation_split(groups, config.train.val_fraction, seed=config.train.split_seed_or_seed)
        result = _train_one(windows, ~held, held, out, **each)
    if dist_info.joined:
        import torch.distributed as dist

        dist.barrier()  # rank 0 writes the summaries last; leaving without this aborts gloo ranks at exit
        dist.destroy_process_group()
    return result


def _train_one(
    windows: Windows,
    train_mask: np.ndarray,
    val_mask: np.ndarray,
    out: Path,
    *,
    config: LearnConfig,
    dist_info: _Dist,
    resume: bool,
    progress: bool,
    init_from: str | Path | None,
    fold: int | None = None,
    tensorboard: bool = False,
) -> dict:
    """One model trained on the windows of `train_mask`, validated on those of `val_mask`, into
    `out`; returns its summary (empty on ranks other than 0)."""
    recipe, dev = config.train, windows.device
    torch.manual_seed(recipe.seed)
    model = build_model(config.model).to(dev)
    optimizer = torch.optim.Adam(model.parameters(), lr=recipe.lr)
    train_idx, val_idx = np.flatnonzero(train_mask), _validation_windows(val_mask, recipe)
    out.mkdir(parents=True, exist_ok=True)
    last = out / "last.pt"
    resumed = bool(resume and last.exists())
    state = start_state(model, optimizer, config, windows, last if resumed else None, init_from)
    model, stepper = _for_device(model, recipe, dist_info, dev)
    meta = _run_record(config, windows, val_mask, fold, parameter_count(_unwrap(model)))
    if dist_info.main:  # the run explains itself from its first epoch on, also if it is stopped
        write_run_config(out, meta, dev, resumed, init_from, _process_group(dist_info))
        sizes = sizes_line(
            train_windows=len(train_idx),
            train_episodes=len(np.unique(windows.episode[train_idx])),
            per_epoch=min(len(train_idx), recipe.max_train_windows or len(train_idx)),
            val_windows=len(val_idx),
            val_of=int(val_mask.sum()),
            val_episodes=len(np.unique(windows.episode[val_idx])),
        )
        tqdm.write(sizes if fold is None else f"fold {fold}: {sizes}")
    board = TensorBoardLog(out, val_idx) if tensorboard and dist_info.main else None
    run = _Run(model, stepper, optimizer, windows, train_idx, val_idx, out, config, dist_info, meta, board, progress)
    run.saved = state["epoch"]
    try:
        while state["epoch"] < recipe.epochs and state["stale"] < recipe.patience:
            if _epoch(run, state):
                break
    except KeyboardInterrupt:
        raise RunInterrupted(_interrupted_text(out, run.saved, recipe.epochs)) from None
    finally:
        if board:
            board.close()
    return write_summary(out, state, recipe, meta, len(train_idx), len(val_idx)) if dist_info.main else {}


def _check_enough_groups(groups: np.ndarray, folds: int, split_by: str, folder: str) -> None:
    """Refuse a dataset with too few episodes (or scenarios) to hold some out, naming the count."""
    count, needed = len(np.unique(groups)), max(folds, 2)
    if count < needed:
        what = "--folds " + str(folds) if folds > 1 else "a validation split"
        raise ValueError(
            f"{folder} holds {count} {split_by}{'s' if count != 1 else ''} with whole windows; {what} needs at "
            f"least {needed} (validation holds whole {split_by}s out): generate more episodes, or fewer --folds"
        )


@dataclass
class _Run:
    """What every epoch of one model's training works with (its progress is the `state` dict)."""

    model: torch.nn.Module
    stepper: object  # the model, or its compiled CUDA graphs
    optimizer: torch.optim.Optimizer
    windows: Windows
    train_idx: np.ndarray
    val_idx: np.ndarray
    out: Path
    config: LearnConfig
    dist_info: _Dist
    meta: dict
    board: TensorBoardLog | None
    progress: bool
    started: float = field(default_factory=time.perf_counter)
    saved: int = 0  # the epoch last.pt holds


def _epoch(run: _Run, state: dict) -> bool:
    """Train one epoch, then (rank 0) validate it, keep it or not, save it and say so; True when
    the run stops after it (patience or time spent; every rank learns it from rank 0)."""
    recipe, dev, epoch, dist_info = run.config.train, run.windows.device, state["epoch"], run.dist_info
    model, optimizer, windows, out = run.model, run.optimizer, run.windows, run.out
    order_rng, draws = _epoch_streams(recipe.seed, epoch, dist_info.rank, dev)
    order = _epoch_order(order_rng, run.train_idx, recipe, dist_info)
    shown = run.progress and dist_info.main
    train_loss, train_s = _train_epoch(model, run.stepper, optimizer, windows, order, run.config, draws, state, shown)
    stop = torch.zeros(1, device=dev)
    if dist_info.main:
        metrics = validate(model, windows, run.val_idx, amp=recipe.amp)
        row = {"epoch": epoch + 1, "step": state["step"], "train_loss": train_loss}
        row |= {f"val_{k}": v for k, v in metrics.items()}
        row |= {"train_seconds": train_s, "samples_per_s": len(order) * dist_info.world / train_s}
        previous = state.get("best_epoch")
        improved = _keep(state, row, recipe.monitor)
        tqdm.write(epoch_line(row, recipe, state, improved, previous))  # also with --quiet: logs need it
        save_epoch(out, _unwrap(model), optimizer, state, metrics["threshold"], run.meta, improved)
        run.saved = state["epoch"]
        save_history(out, state, recipe.monitor)
        if run.board:
            run.board.epoch(row, model_predictor(_unwrap(model), amp=recipe.amp), windows)
        spent = time.perf_counter() - run.started
        out_of_time = recipe.max_minutes is not None and spent > 60 * recipe.max_minutes
        stop[0] = float(state["stale"] >= recipe.patience or out_of_time)
    else:
        state["epoch"] = epoch + 1
    if dist_info.joined:
        import torch.distributed as dist

        dist.broadcast(stop, 0)
    return bool(stop.item())


def _epoch_streams(seed: int, epoch: int, rank: int, device) -> tuple[np.random.Generator, torch.Generator]:
    """The random streams of one epoch, drawn from (seed, epoch) alone so that a resumed run draws
    what an uninterrupted one would: the window order (the same on every rank), this rank's
    augmentation draws, and torch's global generator (dropout, should a model ever have it)."""
    torch.manual_seed(int(np.random.SeedSequence([seed, epoch, rank]).generate_state(1)[0]))
    draws = torch.Generator(device=device)
    draws.manual_seed(seed + 1000 * epoch + rank)
    return np.random.default_rng(seed + 1000 * epoch), draws


def _interrupted_text(out: Path, saved: int, epochs: int) -> str:
    """What a Ctrl-C leaves: the epoch last.pt holds and how to go on."""
    if saved == 0:
        return f"no epoch had ended, so {out} holds no checkpoint: the same command starts the run again"
    return f"{out / 'last.pt'} keeps epoch {saved} of {epochs}: the same command with --resume continues the run"


def _validation_windows(val_mask: np.ndarray, recipe: TrainConfig) -> np.ndarray:
    """The validation windows scored every epoch: all, or a fixed draw of `max_val_windows`."""
    val_idx = np.flatnonzero(val_mask)
    if recipe.max_val_windows and len(val_idx) > recipe.max_val_windows:
        draw = np.random.default_rng(recipe.split_seed_or_seed).choice(val_idx, recipe.max_val_windows, replace=False)
        val_idx = np.sort(draw)
    return val_idx


def _for_device(model, recipe: TrainConfig, dist_info: _Dist, dev: torch.device):
    """(model, stepper): the model in DDP under torchrun, and what the training steps call (the
    model itself, or its CUDA graphs)."""
    if dist_info.joined:
        from torch.nn.parallel import DistributedDataParallel

        model = DistributedDataParallel(model, device_ids=[dist_info.local] if dev.type == "cuda" else None)
    if recipe.cuda_graphs and dev.type != "cuda":
        raise ValueError(f"train.cuda_graphs needs a CUDA device, got {dev}")
    # Validation runs the eager model: evaluation mode would capture graphs of its own.
    stepper = torch.compile(model, mode="reduce-overhead") if recipe.cuda_graphs else model
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True  # fixed input sizes: let cuDNN pick its fastest kernels
    return model, stepper


def _run_record(config: LearnConfig, windows: Windows, val_mask: np.ndarray, fold: int | None, parameters: int):
    """What every checkpoint of the run carries besides weights and progress: the configs, the
    dataset's identity and the validation episodes, the grid."""
    identity = {
        "folder": windows.frames.info["folder"],
        "plan_id": windows.frames.info.get("plan_id"),
        "format_version": FORMAT_VERSION,
        "val_episodes": sorted(int(e) for e in np.unique(windows.episode[val_mask])),
        "fold": fold,
        "split_seed": config.train.split_seed_or_seed,  # drew val_episodes and the validated windows
    }
    return to_record(config) | {
        "dataset": identity,
        "parameters": parameters,
        "scenarios": windows.frames.scenarios,
        "range_m": windows.frames.range_m.tolist(),
        "azimuth_rad": windows.frames.azimuth_rad.tolist(),
    }


def _epoch_order(rng: np.random.Generator, train_idx: np.ndarray, recipe: TrainConfig, dist_info: _Dist):
    """This rank's training windows of the next epoch, in the order they are stepped through."""
    order = rng.permutation(train_idx)
    if recipe.max_train_windows:
        order = order[: recipe.max_train_windows]
    per_rank = len(order) // dist_info.world
    return order[dist_info.rank * per_rank : (dist_info.rank + 1) * per_rank]


def _train_epoch(model, stepper, optimizer, windows, order, config: LearnConfig, draws, state, progress: bool):
    """One pass of optimisation steps over `order`; (mean training loss, seconds it took)."""
    recipe, dev = config.train, windows.device
    model.train()
    use_amp = recipe.amp and dev.type == "cuda"
    steps = math.ceil(len(order) / recipe.batch_size)
    # Indices go to the device once per epoch and the loss is summed there: a host read per step
    # (a print, a NaN check, an upload) would make the CPU wait for the GPU before every launch.
    order_on_device = torch.as_tensor(order, device=dev)
    bar = tqdm(total=len(order), desc=f"epoch {state['epoch'] + 1}", unit="win", disable=not progress)
    t0, total = time.perf_counter(), torch.zeros((), device=dev)
    for s in range(steps):
        chunk = order_on_device[s * recipe.batch_size : (s + 1) * recipe.batch_size]
        if config.augment.active:
            x, y = augmented_batch(windows, chunk, config.augment, draws)
        else:
            x, y = windows.batch(chunk)
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=use_amp):
            loss = loss_fn(stepper, x, y, recipe)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        total += loss.detach() * len(chunk)
        state["step"] += 1
        bar.update(len(chunk))
        if (s + 1) % CHECK_EVERY == 0 or s + 1 == steps:
            _check_finite(total, state["epoch"], s)  # NaN would silently end with no best.pt
            bar.set_postfix(loss=f"{float(total) / min((s + 1) * recipe.batch_size, len(order)):.4g}")
    train_s = time.perf_counter() - t0  # _check_finite has waited for the last step
    bar.close()
    return float(total) / max(len(order), 1), train_s


def _keep(state: dict, row: dict, monitor: str) -> bool:
    """Add the epoch's history row to `state` and decide: is this epoch's model the best so far
    on the validation `monitor`? (Never for nan.) Counts the epochs without a better one."""
    state["history"].append(row)
    value = MONITORS[monitor] * row[f"val_{monitor}"]
    improved = value > state["best"]  # False for nan
    if improved:
        state["best"] = value
        state["best_epoch"] = row["epoch"]
    state["stale"] = 0 if improved else state["stale"] + 1
    state["epoch"] = row["epoch"]
    return improved
