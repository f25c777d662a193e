"""Planning a dataset: a suite's episodes (robot drives, each with its own scene and seed) dealt
to shard tasks. Pure bookkeeping: nothing here simulates or writes, so a plan is cheap to redo and
its id tells whether a folder on disk belongs to the same run."""

from __future__ import annotations

import hashlib
import json
import math
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import scenes
from clitools.limits import check_fits, check_memory, free_disk_bytes

from ..config import SimConfig
from .mesh_scenarios import content_key
from .physics import Physics, rig
from .shards import FORMAT_VERSION
from .suites import Suite

FRAMES_PER_SHARD = 250  # default shard size: ~20 MB; enough shards to keep several workers busy
DISK_SHARE = 0.5
"""Least share of its arrays' bytes a frame takes on disk: gzip keeps 0.67 of the tiny suite's
energyscapes and 0.70 of its LiDAR ranges (the labels, almost all zeros, shrink to nothing), so
a run whose arrays need more than twice the free space can never fit."""
BYTES_PER_EPISODE = 4096  # an Episode, its scene's arguments and its share of the shard tasks and plan.json
MAX_SCAN_ELEMENTS = 2**31 - 1  # ranges of one episode's LiDAR scan (frames x beams): Warp indexes with int32
SHARDS_IN_MEMORY = 3
"""Copies of a shard's frames a process holds at once at most: the shard being filled, the
arrays concatenated for writing, and the shard before it still being written."""


def shards_in_memory(helpers: int) -> int:
    """Copies of a shard a rendering process and its `helpers` writing processes hold at most:
    SHARDS_IN_MEMORY with threads; with helpers, the shard being filled, and per write in flight
    (one per helper) the rendering process's and the helper's, plus the helper's concatenation."""
    return SHARDS_IN_MEMORY if helpers == 0 else 1 + 3 * helpers


@dataclass(frozen=True)
class Episode:
    """One robot drive: its scene, length and seed (the same in every variant)."""

    index: int
    scenario: int
    scenario_name: str
    builder: str
    scene_params: dict
    frames: int
    seed: int


@dataclass(frozen=True)
class ShardTask:
    """Everything a worker needs to write one shard with its run's renderer (picklable,
    JSON-able). `suite` is the suite's JSON (its `name` at least; another engine keeps its own
    settings here), `physics` the variant's (empty where there is none)."""

    path: str
    variant: str
    shard: int
    plan_id: str
    seed: int
    suite: dict
    physics: dict
    episodes: tuple[Episode, ...]
    keep_signals: bool = False
    keep_arrivals: bool = False

    @property
    def frame_count(self) -> int:
        return sum(e.frames for e in self.episodes)


def plan_id(key: dict) -> str:
    """The id of a run: a hash of everything that decides its arrays (`key`, JSON-able)."""
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:16]


def episode_seed(seed: int, suite_name: str, index: int) -> int:
    """Seed of episode `index`: independent streams per (seed, suite, episode)."""
    entropy = [int(seed), zlib.crc32(suite_name.encode()), int(index)]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0] & 0x7FFFFFFF)


def plan_episodes(suite: Suite, frames: int, seed: int) -> list[Episode]:
    """Episodes of `suite.episode_frames` frames (the last one shorter) dealt to the scenarios by
    weight, interleaved so every stretch of episodes mixes scenarios."""
    count = math.ceil(frames / suite.episode_frames)
    weights = np.array([s.weight for s in suite.scenarios], dtype=np.float64)
    # Largest-remainder dealing in order: episode e goes to the scenario furthest behind its share.
    dealt = np.zeros(len(weights))
    episodes = []
    for e in range(count):
        k = int(np.argmax(weights / weights.sum() * (e + 1) - dealt))
        dealt[k] += 1
        scenario = suite.scenarios[k]
        ep_seed = episode_seed(seed, suite.name, e)
        params = scenario.scene_params(np.random.default_rng([ep_seed, 1]), ep_seed)
        length = min(suite.episode_frames, frames - e * suite.episode_frames)
        episodes.append(Episode(e, k, scenario.name, scenario.builder, params, length, ep_seed))
    return episodes


def frame_bytes(sim: SimConfig, *, keep_signals: bool) -> tuple[float, float]:
    """Bytes of one frame of a dataset made with the rig `sim`: (on disk at the least, in memory
    while its shard is filled), from the grid, the LiDAR's beams and, if kept, the signals."""
    cells = sim.processing.grid.range_count * sim.processing.grid.azimuth_count * np.size(sim.processing.elevation_deg)
    samples = sim.sonar.microphone_count * sim.sonar.record_samples if keep_signals else 0
    fixed = 16 * 8 + 8 + 4 + 2  # pose, time, episode, scenario
    disk = DISK_SHARE * (2 * cells + 4 * sim.lidar.beam_count + 2 * samples) + fixed  # float16, float32, float16
    memory = 5 * cells + 4 * sim.lidar.beam_count + 4 * samples + fixed  # float32 energyscape, uint8 label, float32
    return disk, memory


def check_size(suite: Suite, out: str | Path, frames: int, *, keep_signals: bool) -> None:
    """Refuse a run whose shards cannot fit on the disk of `out` (at their least compressed
    size; the shards already there count as room), before its episodes are planned: `--frames
    1e9` is refused in a moment, with both figures, instead of planning ten million episodes for
    a disk that holds a thousandth."""
    rigs = [rig(p, suite.settings) for p in suite.variants.values()]
    per_frame = sum(frame_bytes(sim, keep_signals=keep_signals)[0] for sim in rigs)
    for sim in rigs:
        check_scan(min(frames, suite.episode_frames), sim, f"suite {suite.name!r}: an episode (episode_frames)")
    written = sum(p.stat().st_size for p in Path(out).rglob("shard-*.h5")) if Path(out).is_dir() else 0
    check_fits(
        frames * per_frame,
        available=free_disk_bytes(out) + written,  # a resumed run has its finished shards on disk already
        what=f"{frames:,} frames ({_count(len(suite.variants), 'variant')}, {per_frame / 1e3:,.0f} KB a frame or more)",
        room=f"free on the disk of {out}",
        advice="give fewer --frames (or a suite with fewer), or another --out",
    )
    episodes = math.ceil(frames / suite.episode_frames)
    check_memory(
        episodes * BYTES_PER_EPISODE,
        what=f"planning {episodes:,} episodes ({frames:,} frames of {suite.episode_frames:,})",
        advice="give fewer --frames or longer episode_frames",
    )


MOST_INT64 = 2**63 - 1
"""Counts and seeds are stored as int64 in every shard and plan."""


def short_number(value: int) -> str:
    """An integer as a user reads it: 12,345, or 1.000e+30 when it has more than 15 digits."""
    digits = str(abs(value))
    if len(digits) <= 15:
        return f"{value:,}"
    return f"{'-' if value < 0 else ''}{digits[0]}.{digits[1:4]}e+{len(digits) - 1}"


def check_seed(seed: int, what: str) -> None:
    """Refuse a seed numpy cannot take (negative) or the shards cannot store (beyond int64)."""
    if not 0 <= seed <= MOST_INT64:
        raise ValueError(f"{what} must lie in 0..2**63-1, got {short_number(seed)}")


def check_scan(frames: int, sim: SimConfig, what: str) -> None:
    """Refuse a drive of `frames` poses whose LiDAR scan (one array of frames x beams ranges) and
    labels Warp cannot index (int32) or this machine's memory cannot hold; `what` names it."""
    beams = sim.lidar.beam_count
    if frames * beams > MAX_SCAN_ELEMENTS:
        raise ValueError(
            f"{what} of {frames:,} frames x {beams:,} LiDAR beams exceeds the {MAX_SCAN_ELEMENTS:,} ranges a scan "
            "array may hold (Warp indexes with int32); give fewer frames"
        )
    cells = sim.processing.grid.range_count * sim.processing.grid.azimuth_count
    check_memory(
        frames * (8 * beams + cells + 16 * 8),  # ranges (float32, twice), labels (uint8), poses (float64)
        what=f"{what} of {frames:,} frames x {beams:,} LiDAR beams",
        advice="give fewer frames",
    )


def check_shard_memory(tasks: list[ShardTask], processes: int, helpers: int = 0) -> None:
    """Refuse shards too large for this machine's memory: each of `processes` (with its `helpers`)
    holds up to `shards_in_memory` copies of its largest shard's frames while it is filled and written."""
    largest = max(tasks, key=lambda t: t.frame_count)
    physics = Physics(**largest.physics)
    per_frame = frame_bytes(rig(physics, tuple(largest.suite.get("settings", ()))), keep_signals=largest.keep_signals)
    check_memory(
        largest.frame_count * per_frame[1] * shards_in_memory(helpers) * processes,
        what=f"{_count(processes, 'process', 'processes')} filling shards of up to {largest.frame_count:,} frames "
        f"({per_frame[1] / 1e6:,.2f} MB a frame in memory)",
        advice="give more --shards (smaller ones) or fewer --workers",
    )


def _count(n: int, one: str, many: str = "") -> str:
    return f"{n:,} {one if n == 1 else many or one + 's'}"


def plan(
    suite: Suite,
    out: str | Path,
    *,
    frames: int | None = None,
    shards: int | None = None,
    seed: int = 0,
    keep_signals: bool = False,
    keep_arrivals: bool = False,
) -> list[ShardTask]:
    """The shard tasks of a run: per variant, the episodes split into `shards` contiguous groups
    (default: one per FRAMES_PER_SHARD frames; it does not depend on the worker count, so a run
    can be resumed with other --workers)."""
    frames = suite.frames if frames is None else int(frames)
    if not 1 <= frames <= MOST_INT64:
        raise ValueError(f"frames must lie in 1..2**63-1, got {short_number(frames)}")
    check_seed(seed, "seed")
    check_size(suite, out, frames, keep_signals=keep_signals)
    episodes = plan_episodes(suite, frames, seed)
    shards = min(math.ceil(frames / FRAMES_PER_SHARD), len(episodes)) if shards is None else shards
    if not 1 <= shards <= len(episodes):
        raise ValueError(f"shards must lie in 1..{len(episodes)} (one episode at least per shard), got {shards}")
    suite_json = suite.to_json()
    # a mesh counts by its content (the hash of its bytes), not by its file's name or place
    key = {"suite": content_key(suite_json), "frames": frames, "shards": shards, "seed": seed}
    key["format_version"] = FORMAT_VERSION
    key["scenes_revision"] = scenes.REVISION
    key |= {"keep_signals": keep_signals, "keep_arrivals": keep_arrivals}
    run_id = plan_id(key)
    bounds = np.linspace(0, len(episodes), shards + 1).round().astype(int)
    tasks = []
    for variant, physics in suite.variants.items():
        folder = Path(out) / variant
        for s in range(shards):
            tasks.append(
                ShardTask(
                    path=str(folder / f"shard-{s:05d}.h5"),
                    variant=variant,
                    shard=s,
                    plan_id=run_id,
                    seed=seed,
                    suite=suite_json,
                    physics=physics.to_json(),
                    episodes=tuple(episodes[bounds[s] : bounds[s + 1]]),
                    keep_signals=keep_signals,
                    keep_arrivals=keep_arrivals,
                )
            )
    return tasks
