"""Dataset shards -> windows of K energyscapes and their LiDAR label (no warp: shards are HDF5).

The whole dataset is held in memory (float16 energyscapes, uint8 labels: ~1 GB per 12,500
frames of one elevation), so batches are gathered by indexing, on the GPU when training there. A window is K
consecutive frames of one episode; its label is the LiDAR image at the middle frame (as in the
paper) or the last one. Folds split by episode (every episode is its own random scene, so
validation scenes are never seen in training) or by scenario family.
"""

from __future__ import annotations

import dataclasses
import os
import typing
from dataclasses import dataclass
from numbers import Integral, Real
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from .devices import torch_device
from .elevations import elevation_rows, level_index, missing_elevations, rows_to_hold
from .inputs import check_fits, read_json
from .odometry import relative
from .shardfile import FORMAT as FORMAT  # re-exported: learn.data is where readers look for them
from .shardfile import FORMAT_VERSION as FORMAT_VERSION
from .shardfile import DataError as DataError
from .shardfile import ShardHeader, read_arrays, read_header

Label = Literal["middle", "last"]
MAX_FLOOR_DB = 300.0  # far below where 10^(-floor/20) underflows float32 (~760 dB)
LABELS: tuple[str, ...] = typing.get_args(Label)


@dataclass(frozen=True, kw_only=True)
class DataConfig:
    """How windows are cut and energyscapes normalised (stored with every checkpoint).

    Attributes:
        frames: Window length K.
        label: "middle" (the paper: label at the middle frame, adds K//2 frames of delay) or "last".
        floor_db: Input normalisation: each energyscape in dB below its own peak, floored at
            -floor_db and mapped to [0, 1]. Per-frame scaling makes the input independent of the
            absolute echo level (which differs between simulation and real sensors).
        history: Frames before the window that a model with memory also reads, every
            `history_stride` frames back from its first frame (0: the window alone). Near the
            start of a drive some are not there yet; they are given as absent, so a window is the
            same window with and without history.
        history_stride: Frames between two history frames (10 frames are 1 s of a drive).
    """

    frames: int = 5
    label: Label = "middle"
    floor_db: float = 40.0
    history: int = 0
    history_stride: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.frames, Integral) or isinstance(self.frames, bool):
            raise ValueError(f"frames must be an integer, got {self.frames!r}")
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if not isinstance(self.label, str) or self.label not in LABELS:
            raise ValueError(f"label must be one of {LABELS}, got {self.label!r}")
        if self.label == "middle" and self.frames % 2 == 0:
            raise ValueError(f"label 'middle' needs an odd window length K, got frames={self.frames} (or label 'last')")
        floor = self.floor_db
        if not isinstance(floor, Real) or isinstance(floor, bool) or not (0 < floor <= MAX_FLOOR_DB):
            # an infinite floor maps every cell to NaN (inf / inf), a NaN one every comparison to
            # False; one beyond float32's range (10^(-floor/20) underflows to 0) every cell to -inf
            raise ValueError(f"floor_db must be a finite number of dB in (0, {MAX_FLOOR_DB:g}], got {floor!r}")
        for name in ("history", "history_stride"):
            value = getattr(self, name)
            if not isinstance(value, Integral) or isinstance(value, bool) or value < (name == "history_stride"):
                raise ValueError(f"{name} must be an integer >= {int(name == 'history_stride')}, got {value!r}")

    @property
    def label_offset(self) -> int:
        """Frame of the label within a window."""
        return self.frames // 2 if self.label == "middle" else self.frames - 1

    @property
    def offsets(self) -> np.ndarray:
        """Every frame a window reads, relative to its first frame: the history, oldest first,
        then the window's K frames."""
        back = -self.history_stride * np.arange(self.history, 0, -1)
        return np.concatenate([back, np.arange(self.frames)]).astype(np.int64)

    @property
    def anchor(self) -> int:
        """Index of the label frame in `offsets`."""
        return self.history + self.label_offset


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
        energyscape: (T, E, R, A) float16, as stored (E elevation beams; 1: the level slice, which
            may also be given as (T, R, A)).
        label: (T, R, A) uint8 LiDAR image.
        episode: (T,) int64 episode index (unique across the dataset).
        scenario: (T,) int64 index into `scenarios`.
        scenarios: Scenario names.
        range_m, azimuth_rad: Axis coordinates (R,), (A,).
        elevation_deg: The beams' elevations (E,) [deg], increasing.
        info: Folder, manifest fields (suite, variant, plan_id) and the shards' configs.
        pose: (T, 3) float64 planar sensor poses (x, y [m], yaw [rad], `learn.odometry`) as
            odometry reports them; None where the data has none (a recording without odometry,
            a bare .npy).
    """

    energyscape: np.ndarray
    label: np.ndarray
    episode: np.ndarray
    scenario: np.ndarray
    scenarios: list[str]
    range_m: np.ndarray
    azimuth_rad: np.ndarray
    info: dict
    pose: np.ndarray | None = None
    elevation_deg: tuple[float, ...] = (0.0,)

    def __post_init__(self) -> None:
        self.elevation_deg = tuple(float(e) for e in self.elevation_deg)
        if self.energyscape.ndim == 3 and len(self.elevation_deg) == 1:  # (T, R, A): the one slice
            self.energyscape = self.energyscape[:, None]
        if self.energyscape.ndim != 4 or self.energyscape.shape[1] != len(self.elevation_deg):
            raise ValueError(
                f"energyscape must be (T, E, R, A) with E = {len(self.elevation_deg)} elevations "
                f"{list(self.elevation_deg)}, got shape {self.energyscape.shape}"
            )

    def __len__(self) -> int:
        return len(self.episode)

    @property
    def level(self) -> int:
        """Index of the elevation nearest 0 deg: the LiDAR's plane, which the echo peak reads."""
        return level_index(self.elevation_deg)


def level_slice(frames: Frames) -> Frames:
    """The frames' elevation nearest 0 deg alone (E = 1, no copy): what a planar sonar image
    holds, and what the classical readouts (echo peak, occupancy grids) read."""
    if len(frames.elevation_deg) == 1:
        return frames
    k = frames.level
    return dataclasses.replace(
        frames, energyscape=frames.energyscape[:, k : k + 1], elevation_deg=frames.elevation_deg[k : k + 1]
    )


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


def load_frames(folder: str | Path, *, elevation_deg=None) -> Frames:
    """Read every shard of a dataset folder: each checked as `learn.shardfile` says, all of one run
    (one plan id and variant, no shard twice: episode ids restart at 0 in every run, so shards of
    two runs would join unrelated drives into windows), on one grid, and within the memory
    available before anything is allocated. `elevation_deg` [deg] keeps only those beams (a level-slice
    model of five-elevation data holds a fifth); data lacking one keeps all, for the reader to refuse."""
    folder = Path(folder)
    info = {"folder": recorded_path(folder)}
    manifest = _manifest(folder)
    headers = [read_header(path) for path in shard_paths(folder)]
    _check_one_run(headers, manifest)
    first = headers[0]
    for header in headers[1:]:
        if (header.range_count, header.azimuth_count) != (first.range_count, first.azimuth_count):
            raise DataError(f"{header.path} uses another range/azimuth grid than {first.path}")
        if header.elevation_deg != first.elevation_deg:
            raise DataError(
                f"{header.path} holds elevations {list(header.elevation_deg)} deg, {first.path} "
                f"{list(first.elevation_deg)}: one dataset is beamformed at one set of elevations"
            )
    total, shape = sum(h.frames for h in headers), (first.range_count, first.azimuth_count)
    keep = rows_to_hold(first.elevation_deg, elevation_deg)
    elevations = len(keep)
    held = total * (shape[0] * shape[1] * (2 * elevations + 1) + 16)  # float16 energyscape, uint8 label, two int64
    check_fits(
        held + 2 * max(h.read_bytes for h in headers),  # and one shard's arrays as read, then converted
        f"{folder} ({len(headers)} shards, {total:,} frames of {f'{elevations} x ' if elevations > 1 else ''}"
        f"{shape[0]} x {shape[1]})",
        "read fewer shards (a folder holding some of them) or use a machine with more memory",
    )
    energyscape = np.empty((total, elevations, *shape), np.float16)
    label = np.empty((total, *shape), np.uint8)
    episode, scenario = np.empty(total, np.int64), np.empty(total, np.int64)
    pose: np.ndarray | None = np.empty((total, 3))
    names, seen, grid, start = [], {}, None, 0
    for header in headers:
        arrays = read_arrays(header, seen)
        if grid is None:
            grid = (arrays.range_m, arrays.azimuth_rad)
        elif not (np.array_equal(grid[0], arrays.range_m) and np.array_equal(grid[1], arrays.azimuth_rad)):
            raise DataError(f"{header.path} uses another range/azimuth grid than {first.path}")
        names += [n for n in header.scenarios if n not in names]
        remap = np.array([names.index(n) for n in header.scenarios], dtype=np.int64)
        rows = slice(start, start + header.frames)
        energyscape[rows], label[rows], episode[rows] = arrays.energyscape[:, keep], arrays.label, arrays.episode
        scenario[rows] = remap[arrays.scenario]
        if pose is not None and arrays.pose is not None:
            pose[rows] = arrays.pose
        else:  # poses of some frames only are no poses
            pose = None
        start += header.frames
    info |= {k: manifest.get(k) for k in ("suite", "variant", "physics")}
    info |= {"plan_id": first.plan_id, "config": first.config}
    kept = tuple(first.elevation_deg[i] for i in keep)
    return Frames(energyscape, label, episode, scenario, names, grid[0], grid[1], info, pose, kept)


def _manifest(folder: Path) -> dict:
    """manifest.json's fields ({} where the folder has none)."""
    path = folder / "manifest.json"
    if not os.path.lexists(path):
        return {}
    manifest = read_json(path, "manifest", "regenerate the dataset, or remove manifest.json (its shards say the rest)")
    if not isinstance(manifest.get("plan_id"), str | None):
        raise DataError(f"manifest {path}: plan_id is {manifest['plan_id']!r}, not a plan id (text)")
    return manifest | {"path": path}


def _check_one_run(headers: list[ShardHeader], manifest: dict) -> None:
    """Refuse shards of more than one run (plan id) or variant, and a shard read twice (one file
    under two names, or one shard index twice), naming both files."""
    first, by_file, by_index = headers[0], {}, {}
    planned = manifest.get("plan_id")
    if planned is not None and planned != first.plan_id:
        raise DataError(
            f"{manifest['path']} is of run (plan) {planned}, but {first.path} of plan {first.plan_id}: the folder "
            "mixes two runs; keep one run's files per folder (or remove the stale manifest.json)"
        )
    for header in headers:
        if header.plan_id != first.plan_id or header.variant != first.variant:
            raise DataError(
                f"{header.path} belongs to run (plan) {_run(header)}, {first.path} to plan {_run(first)}: the "
                "folder mixes shards of two runs, whose episodes would be joined into windows; keep one run's shards "
                "per folder"
            )
        twin = by_file.setdefault(header.file_id, header.path)
        if twin != header.path:
            raise DataError(f"{header.path} is the same file as {twin} (a link): remove it, or it counts twice")
        twin = by_index.setdefault(header.index, header.path)
        if twin != header.path:
            raise DataError(f"{header.path} repeats shard {header.index} of its run ({twin}): remove the copy")


def _run(header: ShardHeader) -> str:
    return header.plan_id + (f" (variant {header.variant!r})" if header.variant else "")


def normalise(energyscape: torch.Tensor, floor_db: float | torch.Tensor) -> torch.Tensor:
    """Energyscapes (..., E, R, A) -> dB below each frame's peak over all its elevations (a floor
    echo below stays that much stronger than a wall at the level), floored at -floor_db, in
    [0, 1] (`floor_db` may be a tensor that broadcasts: one floor per window)."""
    e = energyscape.float().clamp_min(0.0)
    peak = e.amax(dim=(-3, -2, -1), keepdim=True).clamp_min(1e-12)
    db = 20.0 * torch.log10((e / peak).clamp_min(10.0 ** (-floor_db / 20.0)))
    return 1.0 + db / floor_db


class Windows:
    """Windows of a dataset on a device: `batch(indices)` -> (x, y (B, 1, R, A)).

    x is the frames (B, E, N, R, A) normalised (E elevations, `elevation_deg`, the models'
    channels, `level` the one nearest 0 deg; N = history + K, oldest first; absent history
    frames are 0), or with `odometry` the pair (frames, motion): motion (B, N, 4) holds each
    frame's pose in the label frame's sensor frame (x, y [m], yaw [rad]) and 1 where the frame
    is there (0 for history before the drive began).

    Args:
        frames: The dataset (see `load_frames`).
        config: Window length, history, label position and normalisation.
        device: Where the frames are kept and batches are made.
        odometry: Give each frame's motion (a model with memory reads it); needs the data's poses.
        share: Windows of the same frames on the same device whose copies of them to use.
        elevation_deg: The elevations [deg] the windows hold, some of the frames' (a model
            trained on fewer reads those); None: all of them.
    """

    def __init__(
        self,
        frames: Frames,
        config: DataConfig,
        device: str | torch.device = "cpu",
        *,
        odometry=False,
        share=None,
        elevation_deg=None,
    ):
        self.frames, self.config, self.odometry = frames, config, bool(odometry)
        self.device = torch_device(device)
        if config.history and not self.odometry:
            raise ValueError(f"history frames ({config.history}) are read by a model with memory, which needs odometry")
        if self.odometry and frames.pose is None:
            raise DataError(
                f"{frames.info['folder']} holds no poses (a recording without odometry, or a bare .npy), and a "
                "model with memory needs them: use a model without memory (polar_unet), or data with odometry"
            )
        self._pick = None  # rows of the frames' elevations to read; None: all of them, in order
        if elevation_deg is not None:
            missing = missing_elevations(frames.elevation_deg, elevation_deg)
            if missing:
                raise DataError(
                    f"{frames.info.get('folder')} holds no energyscapes at {missing} deg (its elevations: "
                    f"{list(frames.elevation_deg)}): beamform the data at the model's elevations"
                )
            rows = elevation_rows(frames.elevation_deg, elevation_deg)
            if rows != list(range(len(frames.elevation_deg))):
                self._pick = torch.as_tensor(rows, device=self.device)
        self.elevation_deg = (
            frames.elevation_deg if self._pick is None else tuple(frames.elevation_deg[r] for r in rows)
        )
        self.level = level_index(self.elevation_deg)  # the channel of the LiDAR's plane in x
        self.starts = window_starts(frames.episode, config.frames)
        if len(self.starts) == 0:
            longest = int(np.unique(frames.episode, return_counts=True)[1].max()) if len(frames.episode) else 0
            raise DataError(
                f"no window of {config.frames} frames fits in any episode of {frames.info['folder']} (the longest "
                f"has {longest}): give more frames, or use a model of a shorter window (--frames)"
            )
        label_frame = self.starts + config.label_offset
        self.episode = frames.episode[label_frame]
        self.scenario = frames.scenario[label_frame]
        first_of_episode = np.flatnonzero(np.r_[True, frames.episode[1:] != frames.episode[:-1]])
        first = first_of_episode[np.searchsorted(first_of_episode, self.starts, side="right") - 1]
        self.position = self.starts - first  # how many frames into its episode each window starts
        held = share if share is not None and share.frames is frames and share.device == self.device else None
        # windows of other models on the same frames share one copy on the device (a 50,000-frame
        # dataset is 6.5 GB: one per model would not fit a GPU beside the others)
        self._energyscape = held._energyscape if held else torch.from_numpy(frames.energyscape).to(self.device)
        self._label = held._label if held else torch.from_numpy(frames.label).to(self.device)
        self._starts = torch.from_numpy(self.starts).to(self.device)
        self._first = torch.from_numpy(first).to(self.device)  # each window's episode's first frame
        self._offsets = torch.from_numpy(config.offsets).to(self.device)
        self._pose = None
        if self.odometry:
            self._pose = held._pose if held and held._pose is not None else torch.from_numpy(frames.pose).float()
            self._pose = self._pose.to(self.device)

    def __len__(self) -> int:
        return len(self.starts)

    def batch(self, indices):
        energy, y, motion = self.raw(indices)
        x = normalise(energy, self.config.floor_db).transpose(1, 2)
        return ((x, motion) if self.odometry else x), y[:, None]

    def raw(self, indices) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Energyscapes as stored (B, N, E, R, A) (0 where absent), labels (B, R, A), and motion
        (B, N, 4) or None (see the class docstring), before normalisation."""
        index = torch.as_tensor(indices, device=self.device, dtype=torch.int64)
        start = self._starts[index]
        frame = start[:, None] + self._offsets  # (B, N)
        present = frame >= self._first[index][:, None]
        frame = torch.maximum(frame, self._first[index][:, None])
        if self._pick is None:
            stored = self._energyscape[frame]
        else:  # only the rows read: (B, N, P, R, A)
            stored = self._energyscape[frame[:, :, None], self._pick]
        energy = stored * present[:, :, None, None, None]
        label = self._label[start + self.config.label_offset].float()
        if not self.odometry:
            return energy, label, None
        pose = self._pose[frame]  # (B, N, 3)
        motion = relative(pose, pose[:, self.config.anchor, None])
        return energy, label, torch.cat([motion, present[:, :, None].float()], -1)


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
