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

import dataclasses
import json
import math
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from .augment import AugmentConfig, augmented_batch
from .checkpoint import check_compatible, save_checkpoint
from .data import FORMAT_VERSION, DataConfig, Frames, Windows, load_frames, split_groups, torch_device, validation_split
from .evaluate import calibrate_on_predictions, model_predictor, predict_batches, score_predictions
from .models import ModelConfig, build_model, parameter_count
from .progress import epoch_line, warn_if_silent, write_fold_summary, write_history
from .tensorboard import TensorBoardLog, summary_writer

LOSSES = ("mse", "bce")
SPLITS = ("episode", "scenario")
MONITORS = {"scan_f1": 1.0, "beam_accuracy": 1.0, "chamfer_m": -1.0, "ssim": 1.0}  # sign: larger is better


@dataclass(frozen=True, kw_only=True)
class TrainConfig:
    """Optimisation settings (the paper's Adam 1e-4, batch 12 and MSE; early stopping on scan F1).

    Attributes:
        loss: "mse" on the predicted image (the paper) or "bce" (logit models; positives weighted
            by `pos_weight`, since returns cover ~0.5 % of the cells).
        patience: Epochs without a better validation `monitor` before stopping.
        monitor: The validation metric that picks best.pt and stops early: "scan_f1" (at 0.10 m,
            the default), "beam_accuracy", "chamfer_m" (lower is better) or "ssim" (the paper's;
            it rewards near-empty images on sparse labels).
        val_fraction: Share of episodes (or scenarios, `split_by`) held out when not folding.
        seed: Initialisation, batch order and augmentation draws; also the validation split (or
            folds) unless `split_seed` is set.
        split_seed: Seed of the validation split (or folds) alone: fix it to vary `seed` over one
            validation set, as a seed-to-seed spread that is training noise alone needs.
        max_train_windows: Training windows per epoch at most (a random subset each epoch).
        max_val_windows: Validation windows evaluated per epoch at most (a fixed subset).
        amp: bfloat16 autocast on GPUs.
        max_minutes: Time budget: no new epoch starts once this many minutes have passed since
            the run (or its resumption) began.
        augment: Training-time augmentation (`learn.augment`; on by default, as the sim-to-real
            study kept it).
        cuda_graphs: Run the training steps' forward and backward as CUDA graphs
            (`torch.compile(mode="reduce-overhead")`; GPUs only, ~25 s of compiling first): a
            small network spends most of an eager step launching kernels.
    """

    epochs: int = 15
    batch_size: int = 12
    lr: float = 1e-4
    loss: str = "mse"
    pos_weight: float = 10.0
    patience: int = 4
    monitor: str = "scan_f1"
    val_fraction: float = 0.1
    split_by: str = "episode"
    seed: int = 0
    split_seed: int | None = None
    max_train_windows: int | None = None
    max_val_windows: int | None = 2000
    amp: bool = True
    max_minutes: float | None = None
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    cuda_graphs: bool = False

    @property
    def split_seed_or_seed(self) -> int:
        return self.seed if self.split_seed is None else self.split_seed

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {self.loss!r}")
        if self.monitor not in MONITORS:
            raise ValueError(f"monitor must be one of {tuple(MONITORS)}, got {self.monitor!r}")
        if self.split_by not in SPLITS:
            raise ValueError(f"split_by must be one of {SPLITS}, got {self.split_by!r}")
        if self.epochs < 1 or self.batch_size < 1 or not self.lr > 0 or self.patience < 1:
            raise ValueError("epochs, batch_size, patience must be >= 1 and lr > 0")
        if not (0 < self.val_fraction < 1):
            raise ValueError(f"val_fraction must lie in (0, 1), got {self.val_fraction}")
        if not (self.pos_weight > 0) or not math.isfinite(self.pos_weight) or not math.isfinite(self.lr):
            raise ValueError(f"lr and pos_weight must be finite and > 0, got {self.lr} and {self.pos_weight}")
        if self.max_minutes is not None and not (0 < self.max_minutes < math.inf):
            raise ValueError(f"max_minutes must be a finite number of minutes > 0, got {self.max_minutes}")


def loss_fn(model, x: torch.Tensor, y: torch.Tensor, config: TrainConfig) -> torch.Tensor:
    out = model(x)
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
    *,
    model_config: ModelConfig,
    data_config: DataConfig,
    train_config: TrainConfig,
    device: str = "cpu",
    resume: bool = False,
    folds: int = 1,
    progress: bool = True,
    init_from: str | Path | None = None,
    overwrite: bool = False,
    tensorboard: bool = False,
) -> dict:
    """Train a model (or `folds` models) on a dataset folder; returns the summary of the run.

    Writes into `out`: config.json (every setting and the dataset's identity, from the start),
    last.pt and best.pt (weights, optimizer, epoch, all configs, dataset identity), history.csv
    and curves.png, summary.json. With folds > 1: out/fold_i/ each,
    and folds.json/folds.md with mean and std over the folds. A folder that already holds
    checkpoints is continued (`resume`) or replaced (`overwrite`), never silently overwritten.
    `tensorboard` also logs every epoch under out/tensorboard (`learn.tensorboard`).
    """
    _check_out(Path(out), resume=resume, overwrite=overwrite)
    if tensorboard:
        summary_writer()  # a missing extra is refused before anything is written
    if init_from is not None and not Path(init_from).is_file():
        raise FileNotFoundError(f"--init-from checkpoint {init_from} does not exist")
    dist_info, dev = _init_distributed(device)
    if dev.type == "cpu":
        torch.set_flush_denormal(True)  # denormal gradients make CPU steps many times slower
    frames = data if isinstance(data, Frames) else load_frames(data)
    if frames.info.get("suite") == "crossengine":
        raise ValueError(f"{frames.info['folder']} is the crossengine test set: score models on it, never train on it")
    windows = Windows(frames, data_config, dev)
    groups = windows.episode if train_config.split_by == "episode" else windows.scenario
    out = Path(out)
    common = (model_config, data_config, train_config, dist_info, resume, progress, init_from)
    if folds > 1:
        fold_of = split_groups(groups, folds, seed=train_config.split_seed_or_seed)
        results = [
            _train_one(windows, fold_of != k, fold_of == k, out / f"fold_{k}", *common, fold=k, tensorboard=tensorboard)
            for k in range(folds)
        ]
        if dist_info.main:
            write_fold_summary(out, results)
        result = {"folds": results}
    else:
        held = validation_split(groups, train_config.val_fraction, seed=train_config.split_seed_or_seed)
        result = _train_one(windows, ~held, held, out, *common, tensorboard=tensorboard)
    if dist_info.joined:
        import torch.distributed as dist

        dist.barrier()  # rank 0 writes the summaries last; leaving without this aborts gloo ranks at exit
        dist.destroy_process_group()
    return result


def _check_out(out: Path, *, resume: bool, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a folder for the run")
    found = sorted(p.relative_to(out).as_posix() for p in out.glob("**/*.pt")) if out.is_dir() else []
    if found and not (resume or overwrite):
        raise ValueError(
            f"--out {out} already holds a run ({', '.join(found[:3])}); continue it with --resume, "
            "replace it with --overwrite, or choose another folder"
        )


def _nan_low(x: float) -> float:
    return -math.inf if math.isnan(x) else x


def _train_one(
    windows,
    train_mask,
    val_mask,
    out,
    model_config,
    data_config,
    config,
    dist_info,
    resume,
    progress,
    init_from,
    fold=None,
    tensorboard=False,
) -> dict:
    dev = windows.device
    torch.manual_seed(config.seed)
    model = build_model(model_config).to(dev)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    train_idx, val_idx = np.flatnonzero(train_mask), np.flatnonzero(val_mask)
    if config.max_val_windows and len(val_idx) > config.max_val_windows:
        val_idx = np.sort(
            np.random.default_rng(config.split_seed_or_seed).choice(val_idx, config.max_val_windows, replace=False)
        )
    out.mkdir(parents=True, exist_ok=True)
    state = {"epoch": 0, "step": 0, "best": -math.inf, "stale": 0, "history": []}
    sign = MONITORS[config.monitor]
    last = out / "last.pt"
    if resume and last.exists():
        ckpt = torch.load(last, map_location=dev, weights_only=True)
        check_compatible(ckpt, model_config, data_config, config, windows)
        model.load_state_dict(ckpt["model"])
        if "optimizer" in ckpt:
            optimizer.load_state_dict(ckpt["optimizer"])
        else:  # packed to travel between machines (benchmarks/learner_converged.sh pack)
            warnings.warn(f"{last} has no optimizer state: Adam restarts its moment estimates", stacklevel=2)
        state = ckpt["state"]
        state.setdefault("best", state.pop("best_ssim", -math.inf))  # checkpoints from before `monitor`
    elif init_from is not None:  # fine-tuning: weights only
        ckpt = torch.load(init_from, map_location=dev, weights_only=True)
        model.load_state_dict(ckpt["model"])
    if dist_info.joined:
        from torch.nn.parallel import DistributedDataParallel

        model = DistributedDataParallel(model, device_ids=[dist_info.local] if dev.type == "cuda" else None)
    use_amp = config.amp and dev.type == "cuda"
    if config.cuda_graphs and dev.type != "cuda":
        raise ValueError(f"train.cuda_graphs needs a CUDA device, got {dev}")
    # Validation runs the eager model: evaluation mode would capture graphs of its own.
    stepper = torch.compile(model, mode="reduce-overhead") if config.cuda_graphs else model
    if dev.type == "cuda":
        torch.backends.cudnn.benchmark = True  # fixed input sizes: let cuDNN pick its fastest kernels
    started = time.perf_counter()
    identity = {
        "folder": windows.frames.info["folder"],
        "plan_id": windows.frames.info.get("plan_id"),
        "format_version": FORMAT_VERSION,
        "val_episodes": sorted(int(e) for e in np.unique(windows.episode[val_mask])),
        "fold": fold,
        "split_seed": config.split_seed_or_seed,  # drew val_episodes and the validated windows
    }
    meta = {
        "model_config": dataclasses.asdict(model_config),
        "data_config": dataclasses.asdict(data_config),
        "train_config": dataclasses.asdict(config),
        "dataset": identity,
        "parameters": parameter_count(_unwrap(model)),
        "scenarios": windows.frames.scenarios,
        "range_m": windows.frames.range_m.tolist(),
        "azimuth_rad": windows.frames.azimuth_rad.tolist(),
    }
    if dist_info.main:  # the run explains itself from its first epoch on, also if it is stopped
        run = {k: meta[k] for k in ("model_config", "data_config", "train_config", "dataset", "parameters")}
        resumed = bool(resume and last.exists())
        init = None if init_from is None else os.path.relpath(Path(init_from).absolute())  # as data.recorded_path
        run |= {"device": str(dev), "resumed": resumed, "init_from": init}
        run["process_group"] = _process_group(dist_info)
        (out / "config.json").write_text(json.dumps(run, indent=1))
    board = TensorBoardLog(out, val_idx) if tensorboard and dist_info.main else None
    rng = np.random.default_rng(config.seed + 1000 * state["epoch"])
    draws = torch.Generator(device=dev)  # augmentation draws, reseeded every epoch like the order
    while state["epoch"] < config.epochs and state["stale"] < config.patience:
        epoch = state["epoch"]
        model.train()
        order = rng.permutation(train_idx)
        if config.max_train_windows:
            order = order[: config.max_train_windows]
        per_rank = len(order) // dist_info.world
        order = order[dist_info.rank * per_rank : (dist_info.rank + 1) * per_rank]
        steps = math.ceil(len(order) / config.batch_size)
        # Indices go to the device once per epoch and the loss is summed there: a host read per step
        # (a print, a NaN check, an upload) would make the CPU wait for the GPU before every launch.
        order_on_device = torch.as_tensor(order, device=dev)
        bar = tqdm(total=len(order), desc=f"epoch {epoch + 1}", unit="win", disable=not (progress and dist_info.main))
        t0, total = time.perf_counter(), torch.zeros((), device=dev)
        draws.manual_seed(config.seed + 1000 * epoch + dist_info.rank)
        for s in range(steps):
            chunk = order_on_device[s * config.batch_size : (s + 1) * config.batch_size]
            if config.augment.active:
                x, y = augmented_batch(windows, chunk, config.augment, draws)
            else:
                x, y = windows.batch(chunk)
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=use_amp):
                loss = loss_fn(stepper, x, y, config)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += loss.detach() * len(chunk)
            state["step"] += 1
            bar.update(len(chunk))
            if (s + 1) % CHECK_EVERY == 0 or s + 1 == steps:
                _check_finite(total, epoch, s)  # NaN would silently end with no best.pt
                bar.set_postfix(loss=f"{float(total) / min((s + 1) * config.batch_size, len(order)):.4g}")
        train_s = time.perf_counter() - t0  # _check_finite has waited for the last step
        total = float(total)
        bar.close()
        stop = torch.zeros(1, device=dev)
        if dist_info.main:
            metrics = validate(model, windows, val_idx, amp=config.amp)
            row = {
                "epoch": epoch + 1,
                "step": state["step"],
                "train_loss": total / max(len(order), 1),
                **{f"val_{k}": v for k, v in metrics.items()},
                "train_seconds": train_s,
                "samples_per_s": len(order) * dist_info.world / train_s,
            }
            state["history"].append(row)
            value = sign * metrics[config.monitor]
            improved = value > state["best"]  # False for nan
            if improved:
                state["best"] = value
                state["best_epoch"] = epoch + 1
            state["stale"] = 0 if improved else state["stale"] + 1
            state["epoch"] = epoch + 1
            tqdm.write(epoch_line(row, config, state, improved))  # also with --quiet: logs need it
            ckpt = {
                "model": _unwrap(model).state_dict(),
                "optimizer": optimizer.state_dict(),
                "state": state,
                "threshold": metrics["threshold"],
            } | meta
            save_checkpoint(ckpt, last)
            if improved:
                save_checkpoint(ckpt, out / "best.pt")
            write_history(out, state["history"], state.get("best_epoch"), config.monitor)
            if board:
                board.epoch(row, model_predictor(_unwrap(model), amp=config.amp), windows)
            out_of_time = config.max_minutes is not None and time.perf_counter() - started > 60 * config.max_minutes
            stop[0] = float(state["stale"] >= config.patience or out_of_time)
        else:
            state["epoch"] = epoch + 1
        if dist_info.joined:
            import torch.distributed as dist

            dist.broadcast(stop, 0)
        if stop.item():
            break
    if board:
        board.close()
    summary = {}
    if dist_info.main:
        best = max(state["history"], key=lambda r: _nan_low(sign * r[f"val_{config.monitor}"]))
        summary = {
            "out": os.path.relpath(Path(out).absolute()),  # no machine's absolute path in the summary
            "epochs": state["epoch"],
            "best_epoch": best["epoch"],
            "best": {k: v for k, v in best.items() if k.startswith("val_")},
            "samples_per_s": float(np.median([r["samples_per_s"] for r in state["history"]])),
            "train_windows": len(train_idx),
            "val_windows": len(val_idx),
        } | {k: meta[k] for k in ("model_config", "data_config", "train_config", "parameters", "dataset")}
        summary["threshold"] = best["val_threshold"]
        (out / "summary.json").write_text(json.dumps(summary, indent=1))
        warn_if_silent(best, out, hint="" if config.loss == "bce" else ", or with --loss bce")
    return summary
