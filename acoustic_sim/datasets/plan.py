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

from .shards import FORMAT_VERSION
from .suites import Suite

FRAMES_PER_SHARD = 250  # default shard size: ~20 MB; enough shards to keep several workers busy


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
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    episodes = plan_episodes(suite, frames, seed)
    shards = min(math.ceil(frames / FRAMES_PER_SHARD), len(episodes)) if shards is None else shards
    if not 1 <= shards <= len(episodes):
        raise ValueError(f"shards must lie in 1..{len(episodes)} (one episode at least per shard), got {shards}")
    suite_json = suite.to_json()
    key = {"suite": suite_json, "frames": frames, "shards": shards, "seed": seed, "format_version": FORMAT_VERSION}
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
