"""Dataset shards -> windows of K energyscapes and their LiDAR label (no warp: shards are HDF5).

The whole dataset is held in memory (float16 energyscapes, uint8 labels: ~1 GB per 12,500
frames), so batches are gathered by indexing, on the GPU when training there. A window is K
consecutive frames of one episode; its label is the LiDAR image at the middle frame (as in the
paper) or the last one. Folds split by episode (every episode is its own random scene, so
validation scenes are never seen in training) or by scenario family.
"""

from __future__ import annotations

import json
import os
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import h5py
import numpy as np
import torch

FORMAT = "sonar2lidar-dataset"  # written by acoustic_sim.datasets.shards; the file format is the interface
FORMAT_VERSION = 1
Label = Literal["middle", "last"]
LABELS: tuple[str, ...] = typing.get_args(Label)


class DataError(ValueError):
    """A dataset that cannot be read as asked (missing, foreign, other version, inconsistent)."""


@dataclass(frozen=True, kw_only=True)
class DataConfig:
    """How windows are cut and energyscapes normalised (stored with every checkpoint).

    Attributes:
        frames: Window length K.
        label: "middle" (the paper: label at the middle frame, adds K//2 frames of delay) or "last".
        floor_db: Input normalisation: each energyscape in dB below its own peak, floored at
            -floor_db and mapped to [0, 1]. Per-frame scaling makes the input independent of the
            absolute echo level (which differs between simulation and real sensors).
    """

    frames: int = 5
    label: Label = "middle"
    floor_db: float = 40.0

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.label not in LABELS:
            raise ValueError(f"label must be one of {LABELS}, got {self.label!r}")
        if self.label == "middle" and self.frames % 2 == 0:
            raise ValueError(f"label 'middle' needs an odd window length K, got frames={self.frames} (or label 'last')")
        if not self.floor_db > 0:
            raise ValueError(f"floor_db must be > 0, got {self.floor_db}")

    @property
    def label_offset(self) -> int:
        """Frame of the label within a window."""
        return self.frames // 2 if self.label == "middle" else self.frames - 1


def window_starts(episode: np.ndarray, frames: int) -> np.ndarray:
    """First frame of every window of `frames` consecutive frames that stays inside one episode.

    Args:
        episode: Episode index per frame, shape (T,); frames of one episode are contiguous.
        frames: Window length K >= 1.

    Returns:
        Start indices s, int64: frames s .. s + K - 1 all belong to episode[s].
    """
    episode = np.asarray(episode)
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    if episode.ndim != 1:
        raise ValueError(f"episode must be 1-D, got shape {episode.shape}")
    if len(episode) < frames:
        return np.zeros(0, dtype=np.int64)
    # A window is valid when no episode boundary lies between its first and last frame.
    boundary = np.concatenate([[0], np.cumsum(episode[1:] != episode[:-1])])
    starts = np.arange(len(episode) - frames + 1)
    return starts[boundary[starts] == boundary[starts + frames - 1]].astype(np.int64)


@dataclass
class Frames:
    """Every frame of a dataset folder, in memory.

    Attributes:
        energyscape: (T, R, A) float16, as stored.
        label: (T, R, A) uint8 LiDAR image.
        episode: (T,) int64 episode index (unique across the dataset).
        scenario: (T,) int64 index into `scenarios`.
        scenarios: Scenario names.
        range_m, azimuth_rad: Axis coordinates (R,), (A,).
        info: Folder, manifest fields (suite, variant, plan_id) and the shards' configs.
    """

    energyscape: np.ndarray
    label: np.ndarray
    episode: np.ndarray
    scenario: np.ndarray
    scenarios: list[str]
    range_m: np.ndarray
    azimuth_rad: np.ndarray
    info: dict

    def __len__(self) -> int:
        return len(self.episode)


def shard_paths(folder: str | Path) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder} is not a folder; give a dataset folder made by `python -m acoustic_sim generate`")
    paths = sorted(folder.glob("shard-*.h5"))
    if not paths:
        hint = [p.name for p in folder.iterdir() if p.is_dir() and any(p.glob("shard-*.h5"))]
        more = f" (it has datasets in {hint}: pick one)" if hint else ""
        raise DataError(f"{folder} holds no shard-*.h5 files{more}")
    return paths


def recorded_path(path: str | Path) -> str:
    """A path as checkpoints, configs and reports record it: relative to the working folder the
    command ran in (`../data/x` where it lies outside), never a machine's absolute path."""
    return os.path.relpath(Path(path).absolute())


def load_frames(folder: str | Path) -> Frames:
    """Read every shard of a dataset folder, checking format, version and grids."""
    parts, names, info = [], [], {"folder": recorded_path(folder)}
    grid = None
    manifest = Path(folder) / "manifest.json"
    if manifest.exists():
        meta = json.loads(manifest.read_text())
        info |= {k: meta.get(k) for k in ("suite", "variant", "plan_id", "physics")}
    for path in shard_paths(folder):
        try:
            f = h5py.File(path, "r")
        except OSError as err:
            raise DataError(f"{path} is not a readable HDF5 file ({err})") from None
        with f:
            if f.attrs.get("format") != FORMAT:
                raise DataError(f"{path} is not a {FORMAT} shard")
            version = int(f.attrs.get("format_version", -1))
            if version != FORMAT_VERSION:
                raise DataError(f"{path} has format_version {version}; this learner reads {FORMAT_VERSION}")
            axes = (f["range_m"][:], f["azimuth_rad"][:])
            if grid is None:
                grid = axes
            elif not (np.array_equal(grid[0], axes[0]) and np.array_equal(grid[1], axes[1])):
                raise DataError(f"{path} uses another range/azimuth grid than the first shard")
            local = json.loads(f.attrs["scenarios"])
            for name in local:
                if name not in names:
                    names.append(name)
            remap = np.array([names.index(n) for n in local], dtype=np.int64)
            try:
                arrays = [f[k][:] for k in ("energyscape", "lidar/image", "episode", "scenario")]
            except (OSError, KeyError) as err:  # a checksum or decompression failure, a missing dataset
                first = str(err).strip().splitlines()[0]
                raise DataError(f"{path} is damaged or incomplete ({first}); regenerate it") from None
            energyscape, label, episode, scenario = arrays
            if not np.isfinite(energyscape).all():
                raise DataError(f"{path}: energyscape holds NaN or inf values; regenerate this shard")
            parts.append((energyscape, label, episode.astype(np.int64), remap[scenario.astype(np.int64)]))
            info.setdefault("config", json.loads(f.attrs["config"]))
    energyscape, label, episode, scenario = (np.concatenate(p) for p in zip(*parts, strict=True))
    return Frames(energyscape, label, episode, scenario, names, grid[0], grid[1], info)


def normalise(energyscape: torch.Tensor, floor_db: float | torch.Tensor) -> torch.Tensor:
    """Energyscapes (..., R, A) -> dB below each image's peak, floored at -floor_db, in [0, 1]
    (`floor_db` may be a tensor that broadcasts: one floor per window)."""
    e = energyscape.float().clamp_min(0.0)
    peak = e.amax(dim=(-2, -1), keepdim=True).clamp_min(1e-12)
    db = 20.0 * torch.log10((e / peak).clamp_min(10.0 ** (-floor_db / 20.0)))
    return 1.0 + db / floor_db


def torch_device(name: str | torch.device) -> torch.device:
    """The torch device `name` ("cpu", "cuda", "cuda:1", ...), refused with a clear message when this
    machine cannot provide it (torch's own errors name a deserialiser or a driver call instead)."""
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"device {name!r} is not a torch device: use cpu, cuda or cuda:i") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            built = f"CUDA {torch.version.cuda}" if torch.version.cuda else "no CUDA"
            raise ValueError(
                f"device {name!r}: no CUDA GPU is usable here (torch {torch.__version__}, {built}); use cpu"
            )
        if device.index is not None and device.index >= count:
            raise ValueError(f"device {name!r}: this machine has {count} CUDA GPU(s), cuda:0..cuda:{count - 1}")
    elif device.type != "cpu":
        raise ValueError(f"device {name!r} is not supported: use cpu, cuda or cuda:i")
    return device


class Windows:
    """Windows of a dataset on a device: `batch(indices)` -> (x (B, 1, K, R, A), y (B, 1, R, A)).

    Args:
        frames: The dataset (see `load_frames`).
        config: Window length, label position and normalisation.
        device: Where the frames are kept and batches are made.
    """

    def __init__(self, frames: Frames, config: DataConfig, device: str | torch.device = "cpu"):
        self.frames, self.config = frames, config
        self.device = torch_device(device)
        self.starts = window_starts(frames.episode, config.frames)
        if len(self.starts) == 0:
            raise DataError(f"no window of {config.frames} frames fits in any episode of {frames.info['folder']}")
        label_frame = self.starts + config.label_offset
        self.episode = frames.episode[label_frame]
        self.scenario = frames.scenario[label_frame]
        self._energyscape = torch.from_numpy(frames.energyscape).to(self.device)
        self._label = torch.from_numpy(frames.label).to(self.device)
        self._starts = torch.from_numpy(self.starts).to(self.device)
        self._offsets = torch.arange(config.frames, device=self.device)

    def __len__(self) -> int:
        return len(self.starts)

    def batch(self, indices) -> tuple[torch.Tensor, torch.Tensor]:
        energy, y = self.raw(indices)
        return normalise(energy, self.config.floor_db)[:, None], y[:, None]

    def raw(self, indices) -> tuple[torch.Tensor, torch.Tensor]:
        """Energyscapes as stored (B, K, R, A) and labels (B, R, A), before normalisation."""
        index = torch.as_tensor(indices, device=self.device, dtype=torch.int64)
        start = self._starts[index]
        return self._energyscape[start[:, None] + self._offsets], self._label[start + self.config.label_offset].float()


def split_groups(groups: np.ndarray, folds: int, *, seed: int = 0) -> np.ndarray:
    """Fold (0..folds-1) of every item, with whole groups (episodes or scenarios) per fold:
    groups are shuffled with `seed` and dealt round robin."""
    unique = np.unique(groups)
    if folds < 2 or folds > len(unique):
        raise ValueError(f"folds must lie in 2..{len(unique)} (the number of groups), got {folds}")
    order = np.random.default_rng(seed).permutation(unique)
    fold_of = {g: i % folds for i, g in enumerate(order)}
    return np.array([fold_of[g] for g in groups], dtype=np.int64)


def validation_split(groups: np.ndarray, fraction: float, *, seed: int = 0) -> np.ndarray:
    """Boolean mask of validation items: whole groups, about `fraction` of them (at least one)."""
    unique = np.unique(groups)
    if not 0 < fraction < 1 or len(unique) < 2:
        raise ValueError(f"need 0 < fraction < 1 and >= 2 groups, got {fraction} and {len(unique)}")
    count = min(max(1, round(fraction * len(unique))), len(unique) - 1)
    held = np.random.default_rng(seed).permutation(unique)[:count]
    return np.isin(groups, held)
