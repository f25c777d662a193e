"""Dataset generation: a suite -> episodes -> shard tasks -> HDF5 shards, resumable and parallel.

`plan.plan` deals a suite's episodes (robot drives, each with its own scene and seed) to shards;
`run_tasks` simulates shards (`episode.simulate_episode` per episode) and writes them, preparing
the next episode and writing the last shard beside the device's work; `generate` runs the tasks
that are not finished yet (in this process, in local worker processes, or as Ray tasks), then
writes each dataset's manifest and card (`manifest`). Everything an episode draws comes from its
seed, so the same command on the same device gives identical arrays, and a rerun skips the shards
that are already complete.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import socket
import sys
import time
import warnings
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from ..devices import check_device_name, quiet_warp, resolve_device
from .episode import prepare_episode, simulate_episode
from .manifest import shard_entry, write_manifest
from .physics import Physics, rig
from .plan import ShardTask, plan
from .shards import FORMAT, FORMAT_VERSION, DatasetError, ShardFrames, read_attrs, verify_shard, write_shard
from .suites import Suite
from .workers import LocalWorkers

PLAN_FILE = "plan.json"
LOCK_FILE = ".generate.lock"  # "pid host" of the run writing the folder
# Where a run's time goes: a worker process's start (launch to Warp and its device ready; a spawned
# one also starts an interpreter and imports the package; 0 in this process), then run_tasks's parts.
PARTS = ("start-up", "prepare", "lidar", "sonar", "write", "waiting")


def run_tasks(
    tasks: Iterable[ShardTask], device=None, on_frames=None, *, overlap: bool = True
) -> tuple[list[dict], dict]:
    """Simulate and write shards, in order; returns (their manifest entries, seconds per part).

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
    rigs = {}  # task path -> (physics, the variant's rig before per-episode draws)
    jobs = ((task, episode) for task in tasks for episode in task.episodes)
    seconds = dict.fromkeys(PARTS, 0.0)

    def prepare(task: ShardTask, episode):
        t0 = time.perf_counter()
        ready = prepare_episode(episode, *rigs[task.path], task.suite)
        return ready, time.perf_counter() - t0

    def write(task: ShardTask, frames: ShardFrames, records: list) -> tuple[dict, float]:
        t0 = time.perf_counter()
        _write_shard(task, frames, records, rigs[task.path][1], device)
        return shard_entry(task), time.perf_counter() - t0

    def collect(future) -> tuple:
        t0 = time.perf_counter()
        value, took = future.result()
        seconds["waiting"] += time.perf_counter() - t0
        return value, took

    entries = []

    def wrote(entry: dict, took: float) -> None:
        entries.append(entry)
        seconds["write"] += took

    with ThreadPoolExecutor(1) as preparer, ThreadPoolExecutor(1) as writer:

        def take_next():
            """The next (task, episode) and its preparation, queued when overlapping; None at the end."""
            job = next(jobs, None)
            if job is None:
                return None
            task = job[0]
            if task.path not in rigs:  # built here, before the preparer thread reads it
                physics = Physics(**task.physics)
                rigs[task.path] = physics, rig(physics, tuple(task.suite.get("settings", ())))
            return job, preparer.submit(prepare, *job) if overlap else None

        def finish(task: ShardTask, frames: ShardFrames, records: list, writing):
            """Hand a finished shard to the writer (after the one in flight); returns the new write."""
            if writing is not None:  # one write in flight
                wrote(*collect(writing))
            if overlap:
                return writer.submit(write, task, frames, records)
            wrote(*write(task, frames, records))
            return None

        upcoming, writing = take_next(), None
        task = frames = records = None
        while upcoming is not None:
            (this, episode), ahead = upcoming
            if this is not task:
                if task is not None:
                    writing = finish(task, frames, records, writing)
                task, frames, records = this, ShardFrames(), []
            physics, nominal = rigs[task.path]
            ready = episode  # simulate_episode prepares it, unless the preparer has
            if overlap:
                ready, took = collect(ahead)
                seconds["prepare"] += took
            upcoming = take_next()  # the next preparation runs beside this rendering
            arrays, record = simulate_episode(
                ready,
                physics,
                nominal,
                task.suite,
                device=device,
                keep_signals=task.keep_signals,
                keep_arrivals=task.keep_arrivals,
                on_frames=on_frames,
                seconds=seconds,
            )
            _add_episode(frames, arrays, episode, task)
            records.append(record)
        if task is not None:
            writing = finish(task, frames, records, writing)
        if writing is not None:
            wrote(*collect(writing))
    return entries, seconds


def run_task(task: ShardTask, device=None, on_frames=None) -> dict:
    """Simulate and write one shard; returns its manifest entry. `on_frames(n)` reports progress."""
    return run_tasks([task], device, on_frames)[0][0]


def _add_episode(frames: ShardFrames, arrays: dict, episode, task: ShardTask) -> None:
    """Append one simulated episode's arrays to the shard's frames."""
    for key in ("energyscape", "lidar_ranges", "lidar_image", "pose", "time"):
        getattr(frames, key).append(arrays[key])
    frames.episode.append(np.full(episode.frames, episode.index))
    frames.scenario.append(np.full(episode.frames, episode.scenario))
    if task.keep_signals:
        frames.signals.append(arrays["signals"])
    if task.keep_arrivals:
        offset = sum(len(e) for e in frames.episode[:-1])
        frames.arrivals.append(arrays["arrivals"] | {"frame": arrays["arrivals"]["frame"] + offset})


def _write_shard(task: ShardTask, frames: ShardFrames, records: list, nominal, device: str) -> None:
    from .. import __version__

    grid = nominal.processing.grid
    config = {"suite": task.suite, "variant": task.variant, "physics": task.physics, "sim": nominal.to_dict()}
    attrs = {
        "suite": task.suite["name"],
        "variant": task.variant,
        "shard": task.shard,
        "plan_id": task.plan_id,
        "seed": task.seed,
        "device": device,
        "package_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "config": config,
        "episodes": records,
        "scenarios": [s["name"] for s in task.suite["scenarios"]],
    }
    Path(task.path).parent.mkdir(parents=True, exist_ok=True)
    write_shard(Path(task.path), frames, attrs=attrs, range_m=grid.range_m, azimuth_rad=grid.azimuth_rad)


def is_complete(task: ShardTask) -> bool:
    """Whether the task's shard exists, belongs to this plan and passes its checksums. A shard of
    this plan that fails them is moved aside (`.damaged`) and counted as not done."""
    path = Path(task.path)
    if not path.exists():
        return False
    attrs = read_attrs(path)  # raises DatasetError for foreign, truncated or other-version files
    if attrs.get("plan_id") != task.plan_id or int(attrs["frame_count"]) != task.frame_count:
        raise DatasetError(
            f"{path} belongs to another run (plan {attrs.get('plan_id')}, not {task.plan_id}); "
            "use another --out or remove that folder"
        )
    try:
        verify_shard(path)
    except DatasetError as err:
        damaged = path.with_name(path.name + ".damaged")
        os.replace(path, damaged)
        warnings.warn(f"{err}; moved it to {damaged.name} and writing the shard again", stacklevel=2)
        return False
    return True


@contextlib.contextmanager
def output_lock(out: Path):
    """Hold `out`/.generate.lock while writing, so two runs never write the same shards. A lock
    left by a run that died on this host is taken over; a live one is refused."""
    path = out / LOCK_FILE
    me = f"{os.getpid()} {socket.gethostname()}"
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            break
        except FileExistsError:
            pid, _, host = path.read_text(errors="replace").strip().partition(" ")
            if host != socket.gethostname() or _alive(pid):
                raise DatasetError(
                    f"another generate (pid {pid} on {host or '?'}) is writing {out}; wait for it, or delete "
                    f"{path} if it is no longer running"
                ) from None
            path.unlink(missing_ok=True)  # its writer is gone
    else:
        raise DatasetError(f"could not take the lock {path}")
    with os.fdopen(fd, "w") as f:
        f.write(me)
    try:
        yield
    finally:
        path.unlink(missing_ok=True)


def _alive(pid: str) -> bool:
    try:
        os.kill(int(pid), 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:
        return True
    return True


def _check_plan_file(out: Path, tasks: list[ShardTask], meta: dict) -> None:
    """Write out/plan.json, or check that an existing one describes the same run."""
    path = out / PLAN_FILE
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except json.JSONDecodeError:
            raise DatasetError(f"{path} is not valid JSON; is {out} a sonar2lidar dataset folder?") from None
        if old.get("format") != FORMAT:
            raise DatasetError(f"{path} is not a {FORMAT} plan; choose another --out")
        if old.get("plan_id") != tasks[0].plan_id:
            raise DatasetError(
                f"{out} holds a run with other settings (plan {old.get('plan_id')}, suite {old.get('suite')!r}, "
                f"frames {old.get('frames')}, shards {old.get('shards')}, seed {old.get('seed')}); "
                "rerun with those settings to resume it, or use another --out"
            )
        return
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {out} is a file; give a folder for the dataset")
    if out.is_dir() and any(out.iterdir()):
        raise DatasetError(
            f"--out {out} holds other files and no {PLAN_FILE}: it is not a dataset folder, and nothing in it "
            "will be overwritten; choose an empty or new folder"
        )
    out.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(PLAN_FILE + ".tmp")
    tmp.write_text(
        json.dumps({"format": FORMAT, "format_version": FORMAT_VERSION, "plan_id": tasks[0].plan_id} | meta, indent=1)
    )
    tmp.replace(path)


def _worker_share(tasks: Iterable[ShardTask], device: str, on_frames, overlap: bool) -> dict:
    """A worker process's share of a run (shards from the queue all workers share); its seconds by part."""
    return run_tasks(tasks, device, on_frames, overlap=overlap)[1]


def generate(
    suite: Suite,
    out: str | Path,
    *,
    frames: int | None = None,
    shards: int | None = None,
    seed: int = 0,
    device: str = "auto",
    workers: int = 1,
    ray_address: str | None = None,
    keep_signals: bool = False,
    keep_arrivals: bool = False,
    progress: bool = True,
    overlap: bool = True,
) -> dict:
    """Generate (or finish) a dataset; returns a summary (frames, shards, seconds, frames/s, and
    `seconds_by_part`: the time spent preparing episodes, in LiDAR, in the sonar, writing and
    waiting, summed over workers; see `run_tasks`). `overlap=False` runs each worker's parts one
    after another (for measuring what the overlap gains; the shards are the same).

    With `workers` > 1, up to that many processes (one per shard at most) are forked from this one
    if CUDA has not been started in it, else spawned (`worker_start` in the summary; see
    `workers`): call `generate` before using the GPU in the same process for the faster start."""
    t0 = time.perf_counter()
    out = Path(out)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    check_device_name(device, allow_auto=True)  # a typo fails here, before any process or Warp starts
    tasks = plan(
        suite,
        out,
        frames=frames,
        shards=shards,
        seed=seed,
        keep_signals=keep_signals,
        keep_arrivals=keep_arrivals,
    )
    frames = sum(t.frame_count for t in tasks) // len(suite.variants)
    meta = {"suite": suite.name, "frames": frames, "shards": len(tasks) // len(suite.variants), "seed": seed}
    processes = 1 if ray_address else min(workers, len(tasks))
    pool = None
    try:
        if processes > 1:  # workers check the device themselves: this process must not start CUDA to fork them
            pool = LocalWorkers(device, processes, functools.partial(_worker_share, overlap=overlap))
            devices = pool.wait_ready()  # all up, each on a device it checked, before any file is written
        else:
            devices = [resolve_device(device)]
        _check_plan_file(out, tasks, meta | {"variants": list(suite.variants), "suite_config": suite.to_json()})
        with output_lock(out):  # one writer per folder
            todo = [t for t in tasks if not is_complete(t)]
            done_frames = sum(t.frame_count for t in tasks) - sum(t.frame_count for t in todo)
            bar = tqdm(total=sum(t.frame_count for t in tasks), initial=done_frames, unit="frame", disable=not progress)
            bar.set_description(f"{suite.name}")
            try:
                if ray_address:
                    _run_on_ray(todo, ray_address, devices[0].startswith("cuda"), bar)
                    parts = {}  # not reported back by Ray tasks
                elif pool:
                    parts = dict.fromkeys(PARTS, 0.0) | pool.run(todo, bar)
                else:
                    parts = run_tasks(todo, devices[0], on_frames=bar.update, overlap=overlap)[1]
            finally:
                if pool:  # inside the lock: no worker is writing once it is released
                    pool.close(abort=sys.exc_info()[0] is not None)
            bar.close()
            seconds = time.perf_counter() - t0
            for variant in suite.variants:
                write_manifest(out / variant, [t for t in tasks if t.variant == variant], suite, meta)
    finally:
        if pool:
            pool.close(abort=True)  # a failure before the run (foreign folder, lock refused); else closed already
    made = sum(t.frame_count for t in todo)
    return {
        "suite": suite.name,
        "out": str(out),
        "frames": sum(t.frame_count for t in tasks),
        "shards": len(tasks),
        "shards_written": len(todo),
        "shards_skipped": len(tasks) - len(todo),
        "seconds": seconds,
        "frames_per_s": made / seconds if made else 0.0,
        "devices": sorted(set(devices)),
        "seconds_by_part": parts,
        "workers": processes,
        "worker_start": pool.start_method if pool else None,
    }


def _run_on_ray(tasks: list[ShardTask], address: str, gpu: bool, bar) -> None:
    try:
        import ray
    except ImportError:
        raise RuntimeError("--ray-address needs Ray: pip install 'sonar2lidar[ray]'") from None
    try:
        ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
    except ConnectionError as error:
        if os.environ.get("RAY_AUTH_MODE") == "token":
            raise
        # Ray turns token authentication on by default for local clusters since 2.59 (for all
        # since 2.61); a caller without the mode is refused with nothing but "failed to connect".
        raise ConnectionError(
            f"{error}. If the cluster was started with token authentication (the default of local "
            "clusters since Ray 2.59), set RAY_AUTH_MODE=token here too (the token is read from "
            "~/.ray/auth_token or RAY_AUTH_TOKEN)"
        ) from error
    remote = ray.remote(num_gpus=1 if gpu else 0, max_retries=2)(run_task)
    pending = {remote.remote(t, "cuda:0" if gpu else "cpu"): t for t in tasks}
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            ray.get(ref)
            bar.update(pending.pop(ref).frame_count)
