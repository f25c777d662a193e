"""Shard tasks -> shard files, in one process (this one or a worker), for any engine.

A `Renderer` is the seam between the machinery and an engine: it prepares an episode on the host,
renders it into arrays on the device, and says what its shards and datasets are made of.
`generate.SuiteRenderer` renders with our engine, `formats.crossengine` with pyroomacoustics.
Everything else is shared: the order of work, preparing the next episode and writing the last
shard beside the rendering, collecting episodes into shards, and the shard's attributes.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ..config import PolarGrid
from ..devices import quiet_warp
from .manifest import About, shard_entry
from .plan import Episode, ShardTask
from .shards import ShardFrames, write_shard

# Where a run's time goes: a worker process's start (launch to Warp and its device ready; a spawned
# one also starts an interpreter and imports the package; 0 in this process), then run_tasks's parts.
PARTS = ("start-up", "prepare", "lidar", "sonar", "write", "waiting")


@dataclass(frozen=True)
class ShardHeader:
    """What a shard says about how it was made.

    Attributes:
        config: The settings its arrays come from (JSON-able), its `config` attribute.
        scenarios: Scenario names, indexed by its `scenario` array.
        grid: The energyscape's polar grid (its `range_m` and `azimuth_rad` axes).
        elevation_deg: The beams' elevations [deg] (its `elevation_deg` axis).
    """

    config: dict
    scenarios: list[str]
    grid: PolarGrid
    elevation_deg: tuple[float, ...] = (0.0,)


class Renderer(Protocol):
    """What an engine gives the machinery (`run_tasks`, `generate.make_dataset`). It is pickled to
    each worker process, so it holds settings, not devices; a cache it fills while rendering stays
    in the process that filled it."""

    def prepare(self, task: ShardTask, episode: Episode) -> Any:
        """The host half of `episode` (scene, drive, draws; no device), handed to `render`. Runs on
        another thread, beside the rendering of the episode before."""

    def render(
        self, task: ShardTask, prepared: Any, *, device: str, on_frames: Callable[[int], None] | None, seconds: dict
    ) -> tuple[dict, dict]:
        """One prepared episode on `device` -> (arrays, record). Arrays, frame first: "energyscape"
        (frame, range, azimuth) or (frame, elevation, range, azimuth), "lidar_ranges" (frame, beam)
        [m], "lidar_image" (frame, range, azimuth), "pose" (frame, 4, 4), "time" (frame,) [s], and
        "signals" and "arrivals" where the task keeps them; record: the episode's JSON record for
        its shard. Calls `on_frames(n)` as frames are done and adds the seconds of its parts
        ("prepare", "lidar", "sonar") to `seconds`."""

    def shard_header(self, task: ShardTask) -> ShardHeader:
        """The task's shard's settings, scenario names and grid."""

    def describe(self, tasks: list[ShardTask]) -> About:
        """The manifest fields and card tables of one variant's dataset (all its tasks)."""


def run_tasks(
    tasks: Iterable[ShardTask], renderer: Renderer, device=None, on_frames=None, *, overlap: bool = True
) -> tuple[list[dict], dict]:
    """Render and write shards, in order; returns (their manifest entries, seconds per part).

    `tasks` is read lazily (a worker's may come from a shared queue): the next task is taken only
    when its first episode is due to be prepared, during the last episode of the one before, so
    a worker holds at most one task it has not started. With `overlap` (the default) the device
    never waits for host work that can run beside it: one thread prepares the next episode (scene,
    drive, drawn physics; across shard boundaries too) while the device renders this one, and
    another compresses and writes each finished shard while the next is rendered (one write in
    flight: at most two shards in memory). The arrays are the same either way. Seconds per part:
    "prepare", "lidar", "sonar", "write" (time each took, wherever it ran) and "waiting" (the
    rendering thread blocked on a preparation or a write). `on_frames(n)` reports progress."""
    import warp as wp

    quiet_warp()
    device = str(wp.get_device(device))
    with ThreadPoolExecutor(1) as preparer, ThreadPoolExecutor(1) as writer:
        helpers = (preparer, writer) if overlap else (_AtOnce(), _AtOnce())
        run = _Run(renderer, device, on_frames, *helpers)
        run.render(tasks)
    return run.entries, run.seconds


def run_task(task: ShardTask, renderer: Renderer, device=None, on_frames=None) -> dict:
    """Render and write one shard; returns its manifest entry. `on_frames(n)` reports progress."""
    return run_tasks([task], renderer, device, on_frames)[0][0]


class _Run:
    """One process's pass over its tasks: it takes each episode (and queues its preparation) when
    the one before starts rendering, renders it into the shard being filled, and hands each full
    shard to the writer after the write in flight; it keeps the entries written and the seconds."""

    def __init__(self, renderer: Renderer, device: str, on_frames, preparer, writer):
        self.renderer, self.device, self.on_frames = renderer, device, on_frames
        self.preparer, self.writer = preparer, writer  # executors: threads, or _AtOnce without overlap
        self.seconds = dict.fromkeys(PARTS, 0.0)
        self.entries: list[dict] = []
        self.writing: Future | None = None  # the one write in flight

    def render(self, tasks: Iterable[ShardTask]) -> None:
        jobs = ((task, episode) for task in tasks for episode in task.episodes)
        upcoming, shard = self._take(jobs), None
        while upcoming is not None:
            task, episode, preparation = upcoming
            if shard is None or shard.task is not task:
                self._hand_to_writer(shard)
                shard = _Shard(task)
            ready = self._collect(preparation, "prepare")
            upcoming = self._take(jobs)  # the next preparation runs beside this rendering
            arrays, record = self.renderer.render(
                task, ready, device=self.device, on_frames=self.on_frames, seconds=self.seconds
            )
            shard.add(episode, arrays, record)
        self._hand_to_writer(shard)
        self._wait_for_write()

    def _take(self, jobs) -> tuple[ShardTask, Episode, Future] | None:
        """The next task and episode, with its preparation queued; None at the end."""
        job = next(jobs, None)
        return None if job is None else (*job, self.preparer.submit(self._prepare, *job))

    def _prepare(self, task: ShardTask, episode: Episode) -> tuple[Any, float]:
        t0 = time.perf_counter()
        return self.renderer.prepare(task, episode), time.perf_counter() - t0

    def _hand_to_writer(self, shard: _Shard | None) -> None:
        if shard is not None:
            self._wait_for_write()  # one write in flight
            self.writing = self.writer.submit(self._write, shard)

    def _write(self, shard: _Shard) -> tuple[dict, float]:
        t0 = time.perf_counter()
        _write_shard(shard, self.renderer.shard_header(shard.task), self.device)
        return shard_entry(shard.task), time.perf_counter() - t0

    def _wait_for_write(self) -> None:
        if self.writing is not None:
            self.entries.append(self._collect(self.writing, "write"))
            self.writing = None

    def _collect(self, future: Future, part: str):
        """A helper's result; the time its work took goes to `part`, the time blocked on it to "waiting"."""
        blocked = not future.done()
        t0 = time.perf_counter()
        value, took = future.result()
        if blocked:
            self.seconds["waiting"] += time.perf_counter() - t0
        self.seconds[part] += took
        return value


class _AtOnce:
    """An executor that runs each call at once in the calling thread (no overlap): an error is
    raised by `submit` itself, as by a plain call."""

    def submit(self, fn, *args) -> Future:
        future = Future()
        future.set_result(fn(*args))
        return future


@dataclass
class _Shard:
    """A shard being filled: its task, the frames of its episodes so far and their records."""

    task: ShardTask
    frames: ShardFrames = field(default_factory=ShardFrames)
    records: list[dict] = field(default_factory=list)

    def add(self, episode: Episode, arrays: dict, record: dict) -> None:
        """Append one rendered episode (see `Renderer.render`)."""
        frames = self.frames
        for key in ("energyscape", "lidar_ranges", "lidar_image", "pose", "time"):
            getattr(frames, key).append(arrays[key])
        frames.episode.append(np.full(episode.frames, episode.index))
        frames.scenario.append(np.full(episode.frames, episode.scenario))
        if self.task.keep_signals:
            frames.signals.append(arrays["signals"])
        if self.task.keep_arrivals:
            offset = sum(len(e) for e in frames.episode[:-1])
            frames.arrivals.append(arrays["arrivals"] | {"frame": arrays["arrivals"]["frame"] + offset})
        self.records.append(record)


def _write_shard(shard: _Shard, header: ShardHeader, device: str) -> None:
    from .. import __version__

    task = shard.task
    attrs = {
        "suite": task.suite["name"],
        "variant": task.variant,
        "shard": task.shard,
        "plan_id": task.plan_id,
        "seed": task.seed,
        "device": device,
        "package_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "config": header.config,
        "episodes": shard.records,
        "scenarios": header.scenarios,
    }
    Path(task.path).parent.mkdir(parents=True, exist_ok=True)
    grid = header.grid
    write_shard(
        Path(task.path),
        shard.frames,
        attrs=attrs,
        range_m=grid.range_m,
        azimuth_rad=grid.azimuth_rad,
        elevation_deg=header.elevation_deg,
    )
