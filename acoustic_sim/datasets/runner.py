"""Shard tasks -> shard files, in one process (this one or a worker), for any engine.

A `Renderer` is the seam between the machinery and an engine: it prepares an episode on the host,
renders it into arrays on the device, and says what its shards and datasets are made of.
`generate.SuiteRenderer` renders with our engine, `formats.crossengine` with pyroomacoustics.
Everything else is shared: the order of work, preparing the next episode and writing the last
shard beside the rendering, collecting episodes into shards, and the shard's attributes.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ..config import PolarGrid
from ..devices import quiet_warp
from .helper_processes import Helpers, helper_pool, helper_renderer
from .manifest import About, shard_entry
from .plan import Episode, ShardTask
from .shards import ShardFrames, write_shard
from .shared_frames import SharedFrames

# Where a run's time goes: a worker process's start (launch to Warp and its device ready; a spawned
# one also starts an interpreter and imports the package; 0 in this process), then run_tasks's parts.
# "assemble": the rendering thread's own host work between renderings (an episode's LiDAR image and
# record, adding it to its shard, handing full shards to their writer): on two H100s up to ~23-30 ms an
# episode of each rendering process lay outside every other part (benchmarks/results/multi_gpu/session33).
PARTS = ("start-up", "prepare", "lidar", "sonar", "assemble", "write", "waiting")
MAX_HELPERS = 4  # host processes beside one rendering process: enough to keep an H100's share fed
# Where a core is left, at least this many: 12 workers on two H100s of 32 cores (one core left each)
# rendered `randomised` at 11,408-11,486 frames/s with two helpers each, 11,763-12,082 with three and
# 12,166 with four, their rendering threads waiting 16-19 s (summed) for preparations and writes with
# two, 2-4 s with three (benchmarks/results/multi_gpu/session38).
MIN_HELPERS = 3
# Threads compressing a shard in a helper: one. Helpers write side by side, so the processes are the
# parallelism, and more threads only cost CPU: a `randomised` shard took 112-133 ms of CPU in one
# thread, 168-175 in two and ~203 in four (2-core CPU), and a worker of 12 on 32 cores gave its helpers two.
HELPER_WRITE_THREADS = 1


def host_helpers(workers: int, requested: int | None = None) -> int:
    """Helper processes each of `workers` rendering processes gets for its host work (`run_tasks`):
    `requested`, else the cores left per worker after its own, at least MIN_HELPERS and at most
    MAX_HELPERS; 0 (threads) only where no core is left, or fork is not available. A helper has its
    own interpreter lock (threads share the rendering's): on the H100 machine 4 workers made 1,574
    frames/s with one helper each, 2,007 with two, 2,122 with three (benchmarks/results/
    generate_cuda_same_job/run5_session26); 16 workers over two GPUs of 32 cores made 5,782
    `randomised` frames/s with threads (two H200s), 9,912 with one helper each (two H100s;
    multi_gpu/session36). Helpers mostly wait: their number sets how far ahead episodes are prepared
    and how many writes may be in flight, which absorbs a slow scene or shard (MIN_HELPERS)."""
    from ..devices import cpu_cores

    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if requested is not None:
        if requested < 0:
            raise ValueError(f"helpers must be >= 0, got {requested}")
        return requested
    if not sys.platform.startswith("linux"):
        return 0
    spare = cpu_cores() // workers - 1
    return 0 if spare < 1 else min(MAX_HELPERS, max(spare, MIN_HELPERS))


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
    tasks: Iterable[ShardTask],
    renderer: Renderer,
    device=None,
    on_frames=None,
    *,
    overlap: bool = True,
    helpers: int = 0,
) -> tuple[list[dict], dict]:
    """Render and write shards, in order; returns (their manifest entries, seconds per part).

    `tasks` is read lazily (a worker's may come from a shared queue): the next task is taken only
    when its first episode is due to be prepared, so a worker holds only the tasks of the episodes
    it prepares ahead (one; `helpers` with helpers). With `overlap` (the default) the device never
    waits for host work that can run beside it: the next episode is prepared (scene, drive, drawn
    physics; across shard boundaries too) while the device renders this one, and each finished shard
    is compressed and written while the next is rendered (the last one by this thread, after it).
    By default one thread does each (one preparation ahead, one write in flight); with `helpers` > 0
    (Linux) that many forked processes prepare and as many write, each with its own interpreter
    lock, `helpers` episodes ahead and up to `helpers` writes in flight. The arrays are the same
    either way. Seconds per part: "prepare", "lidar", "sonar", "write" (time each took, wherever it
    ran), "assemble" (the rendering thread's own host work between renderings) and "waiting" (the
    rendering thread blocked on a preparation or a write). `on_frames(n)`
    reports progress."""
    if not sys.platform.startswith("linux"):
        helpers = 0  # forked helpers and their death with the parent (prctl) are Linux's
    executors, run = [], None
    try:
        # the hand-over thread first: shut down first, before the helpers it hands shards to
        executors.append(ThreadPoolExecutor(1, thread_name_prefix="shard-handover"))
        for _ in range(2):  # the preparer, the writer
            if not overlap:
                executors.append(_AtOnce())
            elif helpers > 0:  # forked before Warp starts here where it has not yet (they never use it)
                executors.append(helper_pool(helpers, renderer))
            else:
                executors.append(ThreadPoolExecutor(1))
        import warp as wp

        quiet_warp()
        device = str(wp.get_device(device))
        run = _Run(renderer, device, on_frames, *executors, depth=max(1, helpers if overlap else 1))
        # The device this run renders on is the current one while it does: whatever Warp does
        # without naming a device (page-locked allocations, a mesh's tree) then stays on it. On
        # two GPUs every worker of cuda:1 had also opened a context on cuda:0 (~0.5 GB there
        # each), and its LiDAR took 26.5 s summed against 14.8 s with its own GPU current
        # (benchmarks/results/multi_gpu/session30). The driver makes contexts one process at a
        # time, machine-wide (one took 0.12 s alone, 1.2-1.5 s each for 12 workers at once on two
        # H100s), yet workers taking turns rendered no faster (multi_gpu/session39).
        with wp.ScopedDevice(device):
            run.render(tasks)
    finally:
        for executor in executors:
            executor.shutdown(wait=True, cancel_futures=True)
        if run is not None:
            run.release_shared()
    return run.entries, run.seconds


class _Run:
    """One process's pass over its tasks: it keeps `depth` episodes' preparations queued (taking
    the next episode when one starts rendering), renders each into the shard being filled, and
    hands each full shard to the writer once fewer than `depth` writes are in flight; it keeps the
    entries written (in shard order) and the seconds."""

    def __init__(self, renderer: Renderer, device: str, on_frames, handover, preparer, writer, *, depth: int = 1):
        self.renderer, self.device, self.on_frames = renderer, device, on_frames
        self.preparer, self.writer = preparer, writer  # executors: threads, processes, or _AtOnce
        self.handover = handover  # a thread: shards into shared memory and on to a helper
        self.depth = depth
        self.seconds = dict.fromkeys(PARTS, 0.0)
        self.entries: list[dict] = []
        # writes in flight, oldest first: each a future of (the write's future, its shared memory)
        self.writing: deque[Future] = deque()

    def render(self, tasks: Iterable[ShardTask]) -> None:
        jobs = ((task, episode) for task in tasks for episode in task.episodes)
        upcoming: deque = deque()
        self._take(jobs, upcoming)
        shard = None
        while upcoming:
            task, episode, preparation = upcoming.popleft()
            if shard is None or shard.task is not task:
                self._hand_to_writer(shard)
                shard = _Shard(task)
            ready = self._collect(preparation, "prepare")
            self._take(jobs, upcoming)  # the next preparations run beside this rendering
            arrays, record = self.renderer.render(
                task, ready, device=self.device, on_frames=self.on_frames, seconds=self.seconds
            )
            t0 = time.perf_counter()
            shard.add(episode, arrays, record)
            self.seconds["assemble"] += time.perf_counter() - t0
        last = self._write_here(shard) if shard is not None else None
        while self.writing:
            self._wait_for_write()
        if last is not None:
            self.entries.append(last)

    def _write_here(self, shard: _Shard) -> dict:
        """Write the last shard in this process: nothing is left to render beside it, and handing
        its ~30 MB to a helper (pickled through a pipe, queued behind the writes in flight) put
        0.1-0.2 s more at the end of every worker's run (a timeline of workers on the H100)."""
        entry, took = _write(self.renderer, shard, self.device)
        self.seconds["write"] += took
        return entry

    def _take(self, jobs, upcoming: deque) -> None:
        """Queue the preparation of the next episodes, up to `depth` of them."""
        while len(upcoming) < self.depth:
            job = next(jobs, None)
            if job is None:
                return
            upcoming.append((*job, self.preparer.submit(_prepare, self.renderer, *job)))

    def _hand_to_writer(self, shard: _Shard | None) -> None:
        """Send a full shard to the writer. To helper processes it goes through shared memory, from
        the hand-over thread: the copy (~33 MB a `paper` shard, by the system, without the GIL)
        took ~13 % of a rendering process's CPU on the H100 (py-spy, multi_gpu/session37)."""
        if shard is not None:
            if len(self.writing) >= self.depth:
                self._wait_for_write()
            t0 = time.perf_counter()
            if isinstance(self.writer, Helpers):
                handed = self.handover.submit(_hand_over, self.writer, shard, self.device)
            else:
                handed = Future()
                write = self.writer.submit(_write, self.renderer, shard, self.device)
                handed.set_result(((write, None), 0.0))
            took = time.perf_counter() - t0
            if isinstance(self.writer, _AtOnce):  # it wrote the shard right here: that is the write's
                took -= write.result()[1]
            self.seconds["assemble"] += took
            self.writing.append(handed)

    def _wait_for_write(self) -> None:
        write, shared = self._collect(self.writing.popleft(), "write")  # the hand-over's time is the write's
        try:
            self.entries.append(self._collect(write, "write"))
        finally:
            if shared is not None:
                shared.release()

    def release_shared(self) -> None:
        """Remove the shared memory of writes that never ran (a run stopped by an error); called
        once the hand-over thread has stopped."""
        for handed in self.writing:
            if handed.done() and not handed.cancelled() and handed.exception() is None:
                shared = handed.result()[0][1]
                if shared is not None:
                    shared.release()

    def _collect(self, future: Future, part: str):
        """A helper's result; the time its work took goes to `part`, the time blocked on it to "waiting"."""
        blocked = not future.done()
        t0 = time.perf_counter()
        value, took = future.result()
        if blocked:
            self.seconds["waiting"] += time.perf_counter() - t0
        self.seconds[part] += took
        return value


def _prepare(renderer: Renderer, task: ShardTask, episode: Episode) -> tuple[Any, float]:
    t0 = time.perf_counter()
    return helper_renderer(renderer).prepare(task, episode), time.perf_counter() - t0


def _hand_over(writer: Helpers, shard: _Shard, device: str) -> tuple[tuple[Future, SharedFrames | None], float]:
    """(The hand-over thread) a full shard copied into shared memory and submitted to a helper's
    write (pickled instead where there is no room in shared memory): (the write's future, the
    shared memory to release once it is done), and the time it took."""
    t0 = time.perf_counter()
    shared = SharedFrames.share(shard.frames)
    sent = shard if shared is None else _Shard(shard.task, shared, shard.records)
    try:
        write = writer.submit(_write, None, sent, device, HELPER_WRITE_THREADS)  # a helper holds the renderer
    except BaseException:
        if shared is not None:
            shared.release()
        raise
    return (write, shared), time.perf_counter() - t0


def _write(renderer: Renderer, shard: _Shard, device: str, threads: int | None = None) -> tuple[dict, float]:
    t0 = time.perf_counter()
    if isinstance(shard.frames, SharedFrames):
        shard = _Shard(shard.task, shard.frames.open(), shard.records)
    _write_shard(shard, helper_renderer(renderer).shard_header(shard.task), device, threads)
    return shard_entry(shard.task), time.perf_counter() - t0


class _AtOnce:
    """An executor that runs each call at once in the calling thread (no overlap): an error is
    raised by `submit` itself, as by a plain call."""

    def submit(self, fn, *args) -> Future:
        future = Future()
        future.set_result(fn(*args))
        return future

    def shutdown(self, **kwargs) -> None:
        pass


@dataclass
class _Shard:
    """A shard being filled: its task, the frames of its episodes so far and their records."""

    task: ShardTask
    frames: ShardFrames | SharedFrames = field(default_factory=ShardFrames)  # shared: on its way to a writer
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


def _write_shard(shard: _Shard, header: ShardHeader, device: str, threads: int | None) -> None:
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
        threads=threads,
    )
