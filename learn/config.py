"""The learner's configuration tree: one root, `LearnConfig`, that `--set` addresses and a run records.

    LearnConfig
    ├── model: ModelConfig      which network and its size (learn.models)
    ├── data: DataConfig        how windows are cut and normalised (learn.data)
    ├── augment: AugmentConfig  training-time changes to windows (learn.augment)
    └── train: TrainConfig      the optimisation recipe (below)

Runs store it as the record every checkpoint and config.json has held since the first:
"model_config", "data_config" and "train_config" with the augmentation inside it (`to_record`);
`from_record` reads any of them back, older ones included.
"""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from .augment import AugmentConfig
from .data import DataConfig
from .models import ModelConfig

Loss = Literal["mse", "bce"]
Split = Literal["episode", "scenario"]
Monitor = Literal["scan_f1", "beam_accuracy", "chamfer_m", "ssim"]
LOSSES: tuple[str, ...] = typing.get_args(Loss)
SPLITS: tuple[str, ...] = typing.get_args(Split)
MONITORS = {"scan_f1": 1.0, "beam_accuracy": 1.0, "chamfer_m": -1.0, "ssim": 1.0}  # sign: larger is better
assert tuple(MONITORS) == typing.get_args(Monitor)


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
        val_fraction: Share of episodes (or scenarios, `split_by`) held out for validation when not folding.
        seed: Initialisation, batch order and augmentation draws; also the validation split (or
            folds) unless `split_seed` is set.
        split_seed: Seed of the validation split (or folds) alone: fix it to vary `seed` over one
            validation set, as a seed-to-seed spread that is training noise alone needs.
        max_train_windows: Training windows per epoch at most (a random subset each epoch).
        max_val_windows: Validation windows evaluated per epoch at most (a fixed subset).
        amp: bfloat16 autocast on GPUs.
        max_minutes: Time budget: no new epoch starts once this many minutes have passed since
            the run (or its resumption) began.
        cuda_graphs: Run the training steps' forward and backward as CUDA graphs
            (`torch.compile(mode="reduce-overhead")`; GPUs only, ~25 s of compiling first): a
            small network spends most of an eager step launching kernels.
    """

    epochs: int = 15
    batch_size: int = 12
    lr: float = 1e-4
    loss: Loss = "mse"
    pos_weight: float = 10.0
    patience: int = 4
    monitor: Monitor = "scan_f1"
    val_fraction: float = 0.1
    split_by: Split = "episode"
    seed: int = 0
    split_seed: int | None = None
    max_train_windows: int | None = None
    max_val_windows: int | None = 2000
    amp: bool = True
    max_minutes: float | None = None
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


@dataclass(frozen=True, kw_only=True)
class LearnConfig:
    """Everything a training run is given, in four sections (the defaults: polar UNet, K = 5, the
    augmentation the sim-to-real study kept, Adam 1e-4). `--set train.lr=3e-4`, `augment=none`.

    The network and the windows read the same number of frames: `model.frames == data.frames`
    and `model.history == data.history` (`with_frames` changes both; `learn train --frames` and
    `--history` set both).
    """

    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        if self.model.frames != self.data.frames:
            raise ValueError(
                f"model.frames and data.frames must agree: set the window length with --frames "
                f"(got {self.model.frames} and {self.data.frames})"
            )
        if self.model.history != self.data.history:
            raise ValueError(
                f"model.history and data.history must agree: set them with --history "
                f"(got {self.model.history} and {self.data.history})"
            )
        if self.data.history and not self.model.uses_odometry:
            raise ValueError(f"history frames ({self.data.history}) are read by --model polar_memory only")

    def with_frames(self, frames: int) -> LearnConfig:
        """This config with windows (and the network's input) of `frames` energyscapes."""
        return dataclasses.replace(
            self,
            model=dataclasses.replace(self.model, frames=frames),
            data=dataclasses.replace(self.data, frames=frames),
        )


def to_record(config: LearnConfig) -> dict:
    """The config as checkpoints and config.json store it: {"model_config", "data_config",
    "train_config"}, the augmentation inside "train_config" (where it was before it had a section)."""
    return {
        "model_config": dataclasses.asdict(config.model),
        "data_config": dataclasses.asdict(config.data),
        "train_config": dataclasses.asdict(config.train) | {"augment": dataclasses.asdict(config.augment)},
    }


def from_record(record: dict) -> LearnConfig:
    """The config a checkpoint or config.json records. A field added since it was written counts at
    its default; augmentation absent from it counts as none, which is what such a run trained with.

    Raises:
        ValueError: a section is missing, or holds a field this version does not know.
    """
    try:
        recipe = dict(record["train_config"])
        augment = AugmentConfig(**{**dataclasses.asdict(AugmentConfig.none()), **recipe.pop("augment", {})})
        return LearnConfig(
            model=ModelConfig(**record["model_config"]),
            data=DataConfig(**record["data_config"]),
            augment=augment,
            train=TrainConfig(**recipe),
        )
    except (KeyError, TypeError) as err:
        raise ValueError(f"the recorded configs are not this version's: {type(err).__name__} {err}") from None


def read_run_config(path: str | Path) -> LearnConfig:
    """The config a run wrote to its config.json (`learn train --config RUN/config.json`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--config {path} does not exist")
    try:
        record = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"--config {path} is not JSON: {err}") from None
    if not isinstance(record, dict):
        raise ValueError(f"--config {path} is not a run's config.json")
    try:
        return from_record(record)
    except ValueError as err:
        raise ValueError(f"--config {path}: {err}") from None
