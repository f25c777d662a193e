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
import math
import typing
from dataclasses import dataclass, field
from numbers import Integral, Real
from pathlib import Path
from typing import Literal

import numpy as np

from .augment import AugmentConfig
from .data import DataConfig, Frames
from .elevations import missing_elevations
from .models import LEVEL_SLICE, ModelConfig

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
        # Each field by name, its type first: a hand-edited config.json (`--config`) may hold any
        # JSON value, and a wrong type would otherwise fail deep inside training, or not at all.
        for name in ("epochs", "batch_size", "patience"):
            _check_count(self, name, 1)
        for name in ("max_train_windows", "max_val_windows"):
            if getattr(self, name) is not None:
                _check_count(self, name, 1, unset=" (or none for all)")
        _check_count(self, "seed", 0, MAX_SEED)
        if self.split_seed is not None:
            _check_count(self, "split_seed", 0, MAX_SEED, unset=" (or none: the seed's)")
        for name in ("lr", "pos_weight"):
            if not (_is_number(getattr(self, name)) and 0 < getattr(self, name) < math.inf):
                raise ValueError(f"train.{name} must be a finite number > 0, got {getattr(self, name)!r}")
        if not (_is_number(self.val_fraction) and 0 < self.val_fraction < 1):
            raise ValueError(f"train.val_fraction (--val-fraction) must lie in (0, 1), got {self.val_fraction!r}")
        if self.max_minutes is not None and not (_is_number(self.max_minutes) and 0 < self.max_minutes < math.inf):
            raise ValueError(f"train.max_minutes must be a finite number of minutes > 0, got {self.max_minutes!r}")
        for name in ("amp", "cuda_graphs"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"train.{name} must be true or false, got {getattr(self, name)!r}")
        for name, choices in (("loss", LOSSES), ("monitor", tuple(MONITORS)), ("split_by", SPLITS)):
            if getattr(self, name) not in choices:
                raise ValueError(f"train.{name} must be one of {choices}, got {getattr(self, name)!r}")


MAX_SEED = 2**63 - 1  # numpy's SeedSequence takes integers >= 0, torch's manual_seed 64-bit ones


def _is_number(value) -> bool:
    return isinstance(value, Real) and not isinstance(value, bool)


def _check_count(config, name: str, low: int, high: int | None = None, unset: str = "") -> None:
    """Refuse a field that is not an integer in low..high, naming it and its option."""
    value = getattr(config, name)
    fits = isinstance(value, Integral) and not isinstance(value, bool) and value >= low
    if not fits or (high is not None and value > high):
        span = f">= {low}" if high is None else f"in {low}..{high:,}"
        option = "--" + name.replace("_", "-")
        raise ValueError(f"train.{name} ({option}) must be an integer {span}{unset}, got {value!r}")


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
    its default; augmentation absent from it counts as none and elevations as the level slice,
    which is what such a run trained with.

    Raises:
        ValueError: a section is missing, or holds a field this version does not know.
    """
    for section in ("model_config", "data_config", "train_config"):
        if not isinstance(record.get(section), dict):
            found = type(record.get(section)).__name__ if section in record else "missing"
            raise ValueError(f"the recorded configs are not this version's: its {section} is {found}, not settings")
    if not isinstance(record["train_config"].get("augment", {}), dict):
        raise ValueError("the recorded configs are not this version's: its train_config.augment is not settings")
    try:
        recipe = dict(record["train_config"])
        augment = AugmentConfig(**{**dataclasses.asdict(AugmentConfig.none()), **recipe.pop("augment", {})})
        model = {"elevation_deg": LEVEL_SLICE, **record["model_config"]}  # a run of before elevations read that
        return LearnConfig(
            model=ModelConfig(**model),
            data=DataConfig(**record["data_config"]),
            augment=augment,
            train=TrainConfig(**recipe),
        )
    except TypeError as err:  # a field this version does not know
        raise ValueError(f"the recorded configs are not this version's: {err}") from None


def read_run_config(path: str | Path) -> LearnConfig:
    """The config a run wrote to its config.json (`learn train --config RUN/config.json`)."""
    from .inputs import read_json

    record = read_json(path, "--config", "give the config.json a run wrote (or fix the file)")
    try:
        return from_record(record)
    except ValueError as err:
        raise ValueError(f"--config {path}: {err}") from None


def with_grid(config: LearnConfig, frames: Frames) -> LearnConfig:
    """`config` with the model told the elevations it reads (the data's) and, for a model with
    memory, the polar grid it resamples on; refused where it was given others."""
    folder = frames.info["folder"]
    given = config.model.elevation_deg
    missing = missing_elevations(frames.elevation_deg, given or ())
    if missing:
        raise ValueError(
            f"model.elevation_deg {list(given)}: {folder} holds no energyscapes at {missing} deg (its elevations: "
            f"{list(frames.elevation_deg)})"
        )
    model = dataclasses.replace(config.model, elevation_deg=given or frames.elevation_deg)
    if not config.model.uses_odometry:
        return dataclasses.replace(config, model=model)
    r, a = frames.range_m, frames.azimuth_rad
    even = np.allclose(np.diff(r), r[1] - r[0], rtol=1e-3) and np.allclose(np.diff(a), a[1] - a[0], rtol=1e-3)
    if len(r) < 2 or len(a) < 2 or not even:
        raise ValueError(f"{folder}: polar_memory needs evenly spaced range and azimuth bins")
    extent = (float(r[0]), float(r[-1]), float(a[0]), float(a[-1]))
    if config.model.extent is not None and not np.allclose(config.model.extent, extent, atol=1e-6):
        raise ValueError(f"model.extent {config.model.extent} is not the grid of {folder} ({extent})")
    return dataclasses.replace(config, model=dataclasses.replace(model, extent=extent))
