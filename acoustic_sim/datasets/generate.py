"""Dataset generation: shard tasks -> a dataset folder, resumable and parallel, for any engine.

`make_dataset` is the machinery every dataset shares: it checks the folder against the plan
(`folder`: plan.json, the lock, complete shards kept, damaged ones written again), renders the
shards still to do with the renderer it is given (`runner.run_tasks`: in this process, in local
worker processes, or as Ray tasks), then writes each variant's manifest and card (`manifest`).
`generate` makes a suite's dataset with our engine: `plan.plan` deals the suite's episodes to
shards and `SuiteRenderer` simulates them (`episode`); `formats.crossengine` brings its own plan
and renderer. Everything an episode draws comes from its seed, so the same command on the same
device gives identical arrays, and a rerun skips the shards that are already complete.
"""

from __future__ import annotations

import functools
import importlib
import json
import os
import sys
import threading
import time
import warnings
from collections import deque
from collections.abc import Iterable
from pathlib import Path

from tqdm.auto import tqdm

from ..config import SimConfig
from ..devices import check_device_name, resolve_device
from ..extras import MissingExtra
from .episode import build_scene, prepare_episode, simulate_episode
from .folder import (
    PLAN_FILE,
    check_no_strangers,
    check_plan_file,
    forget_plan,
    is_complete,
    output_lock,
    remove_temporaries,
)
from .manifest import About, FactTable, rig_facts, write_manifest
from .mesh_scenarios import MeshFile, mesh_material_map
from .physics import Physics, rig
from .plan import Episode, ShardTask, check_shard_memory, plan
from .runner import PARTS, Renderer, ShardHeader, host_helpers, run_tasks
from .suites import Suite, mesh_files
from .workers import LocalWorkers


class SuiteRenderer:
    """Our engine (`episode`): a task's physics variant and its suite's settings make the rig, each
    episode is prepared (`prepare_episode`: scene, drive, draws) and simulated (`simulate_episode`:
    LiDAR and sonar). `meshes`: where the suite's mesh files lie on this machine, by scenario name
    (`suites.mesh_files`); the tasks name them only by file name and hash."""

    def __init__(self, meshes: dict[str, MeshFile] | None = None) -> None:
        self._rigs: dict[str, tuple[Physics, SimConfig]] = {}  # by physics and settings: not per shard (~7 ms)
        self.meshes = dict(meshes or {})

    def rig(self, task: ShardTask) -> tuple[Physics, SimConfig]:
        """The task's physics and its variant's rig before per-episode draws (made once per process
        for each physics and settings: by its first preparation, before anything else asks)."""
        settings = tuple(task.suite.get("settings", ()))
        key = json.dumps([task.physics, settings], sort_keys=True)
        if key not in self._rigs:
            physics = Physics(**task.physics)
            self._rigs[key] = physics, rig(physics, settings)
        return self._rigs[key]

    def prepare(self, task: ShardTask, episode: Episode):
        return prepare_episode(episode, *self.rig(task), task.suite, self.meshes)

    def render(self, task: ShardTask, prepared, *, device: str, on_frames, seconds: dict) -> tuple[dict, dict]:
        physics, nominal = self.rig(task)
        return simulate_episode(
            prepared,
            physics,
            nominal,
            task.suite,
            device=device,
            keep_signals=task.keep_signals,
            keep_arrivals=task.keep_arrivals,
            on_frames=on_frames,
            seconds=seconds,
        )

    def shard_header(self, task: ShardTask) -> ShardHeader:
        nominal = self.rig(task)[1]
        config = {"suite": task.suite, "variant": task.variant, "physics": task.physics, "sim": nominal.to_dict()}
        processing = nominal.processing
        return ShardHeader(
            config, [s["name"] for s in task.suite["scenarios"]], processing.grid, processing.elevations_deg
        )

    def describe(self, tasks: list[ShardTask]) -> About:
        suite, physics = tasks[0].suite, tasks[0].physics
        settings = list(suite.get("settings", ()))
        sim = self.rig(tasks[0])[1].to_dict()  # the rig before per-episode draws
        fields = {"description": suite["description"], "physics": physics, "sim": sim, "settings": settings}
        meshes = {s["name"]: s["mesh"] for s in suite["scenarios"] if s.get("mesh")}
        mapped = {name: mesh_material_map(self.meshes[name]) for name in meshes if name in self.meshes}
        meshes = {
            name: mesh | ({"material_map": mapped[name]} if name in mapped else {}) for name, mesh in meshes.items()
        }
        if meshes:
            fields["meshes"] = meshes
        tables = (
            FactTable(
                "The rig as simulated (after every setting; per-episode draws below come on top):",
                rig_facts(sim, settings),
            ),
            FactTable(
                "Sensor physics of this variant (per-episode ranges are drawn per drive; `manifest.json` has the "
                "whole rig):",
                tuple((name, str(value)) for name, value in physics.items()),
                columns=("setting", "value"),
            ),
        )
        if meshes:
            tables += (
                FactTable(
                    "The mesh files its scenes are, by name and SHA-256 of their bytes (`manifest.json`: `meshes`):",
                    tuple((name, _mesh_fact(mesh)) for name, mesh in meshes.items()),
                    columns=("scenario", "mesh file"),
                ),
                FactTable(
                    "What the material names of each mesh became (`manifest.json`: `meshes.<scenario>.material_map`; "
                    "map a name otherwise with the scenario's material table):",
                    tuple(
                        _mapped_fact(scenario, entry)
                        for scenario, entries in mapped.items()
                        for entry in entries[:MAPPED_NAMES_ON_CARD]
                    )
                    + tuple(
                        (scenario, f"... and {len(entries) - MAPPED_NAMES_ON_CARD} more names in `manifest.json`")
                        for scenario, entries in mapped.items()
                        if len(entries) > MAPPED_NAMES_ON_CARD
                    ),
                    columns=("scenario: name in the file", "our material"),
                ),
            )
        return About(fields, tables)


MAPPED_NAMES_ON_CARD = 30  # a card lists this many names of a mesh; the manifest lists all


def _mapped_fact(scenario: str, entry: dict) -> tuple[str, str]:
    """One material name of a mesh on a dataset card: what it became, for how many faces, and why."""
    name = "(no name)" if entry["name"] is None else f"`{entry['name']}`"
    faces = f"{entry['faces']:,} face" + ("" if entry["faces"] == 1 else "s")
    return f"{scenario}: {name}", f"{entry['material']} ({faces}; {entry['rule']})"


def _mesh_fact(mesh: dict) -> str:
    """A mesh file on a dataset card: name, hash, frame and unit as given, its material table."""
    text = f"`{mesh['file']}` (sha256 {mesh['sha256'][:16]}...), up {mesh['up']}, units {mesh['units']}"
    if "materials" in mesh:
        text += f"; materials `{mesh['materials']}` (sha256 {mesh['materials_sha256'][:16]}...)"
    return text


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
    ray_tasks_per_gpu: int = 1,
    keep_signals: bool = False,
    keep_arrivals: bool = False,
    progress: bool = True,
    overlap: bool = True,
    helpers: int | None = None,
) -> dict:
    """Generate (or finish) a suite's dataset with our engine; returns `make_dataset`'s summary.
    `overlap=False` runs each worker's parts one after another (for measuring what the overlap
    gains; the shards are the same); `helpers`: host processes per worker (`runner.host_helpers`)."""
    engine = None if ray_address else _import_beside(ENGINE_MODULES)
    keep = {"keep_signals": keep_signals, "keep_arrivals": keep_arrivals}
    tasks = plan(suite, out, frames=frames, shards=shards, seed=seed, **keep)
    processes = 1 if ray_address else min(workers, len(tasks))
    check_shard_memory(tasks, processes, 0 if ray_address or not overlap else host_helpers(processes, helpers))
    first: dict[int, Episode] = {}
    for episode in (e for t in tasks for e in t.episodes):
        first.setdefault(episode.scenario, episode)
    with warnings.catch_warnings():  # the run itself says what its scenes leave out
        warnings.simplefilter("ignore")
        for episode in first.values():  # a builder's refusal comes now, before any file is written
            build_scene(episode, suite.name, mesh_files(suite))
    frames = sum(t.frame_count for t in tasks) // len(suite.variants)
    meta = {"suite": suite.name, "frames": frames, "shards": len(tasks) // len(suite.variants), "seed": seed}
    meta |= {"variants": list(suite.variants), "suite_config": suite.to_json()}
    if engine is not None:
        engine.join()  # before any fork: a child forked amid an import could deadlock on its lock
    return make_dataset(
        tasks,
        SuiteRenderer(mesh_files(suite)),
        out,
        plan_meta=meta,
        device=device,
        workers=workers,
        ray_address=ray_address,
        ray_tasks_per_gpu=ray_tasks_per_gpu,
        progress=progress,
        overlap=overlap,
        helpers=helpers,
    )


# Our engine's modules: Warp's Python side (imported, not started) and scipy.signal (the beamformer's
# filters) took ~2 s to import in each worker process on the H100 machine, before its first frame.
ENGINE_MODULES = ("acoustic_sim.engine.sonar", "acoustic_sim.engine.lidar")


def _import_beside(modules: tuple[str, ...]) -> threading.Thread:
    """Import `modules` on a thread while this one plans the run, so that worker processes forked
    afterwards start with them (and this process, rendering alone, has them). Errors are left to
    the import where the module is used."""

    def load() -> None:
        for name in modules:
            try:
                importlib.import_module(name)
            except Exception:  # the renderer's own import reports it
                return

    thread = threading.Thread(target=load, daemon=True, name="engine-import")
    thread.start()
    return thread


def make_dataset(
    tasks: list[ShardTask],
    renderer: Renderer,
    out: str | Path,
    *,
    plan_meta: dict,
    device: str = "auto",
    workers: int = 1,
    ray_address: str | None = None,
    ray_tasks_per_gpu: int = 1,
    progress: bool = True,
    overlap: bool = True,
    helpers: int | None = None,
) -> dict:
    """Write (or finish) the dataset of `tasks` into `out`, each shard rendered by `renderer`;
    returns a summary (frames, shards, seconds, frames/s, and `seconds_by_part`: the time spent
    preparing episodes, in LiDAR, in the sonar, writing and waiting, summed over workers; see
    `runner.run_tasks`). `plan_meta` goes into plan.json beside the plan id (suite, frames, shards
    and seed at least: a rerun with other settings is refused naming them).

    With `workers` > 1, up to that many processes (one per shard at most) are forked from this one
    if CUDA has not been started in it, else spawned (`worker_start` in the summary; see
    `workers`): call this before using the GPU in the same process for the faster start."""
    t0 = time.perf_counter()
    out = Path(out)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if ray_tasks_per_gpu < 1 or (ray_tasks_per_gpu != 1 and not ray_address):
        raise ValueError(f"ray_tasks_per_gpu must be >= 1 and needs a Ray address, got {ray_tasks_per_gpu}")
    processes = 1 if ray_address else min(workers, len(tasks))
    helpers = host_helpers(processes, helpers)  # a negative count is refused before any process starts
    check_device_name(device, allow_auto=True)  # a typo fails here, before any process or Warp starts
    name = tasks[0].suite["name"]
    if ray_address:
        _ray()  # a missing extra is refused before any process starts or any file is written
    pool, fresh, planned = None, not (out / PLAN_FILE).exists(), False
    made_folder = not out.exists()
    try:
        if processes > 1:  # workers check the device themselves: this process must not start CUDA to fork them
            work = functools.partial(_worker_share, renderer=renderer, overlap=overlap, helpers=helpers)
            pool = LocalWorkers(device, processes, work)
            devices = pool.wait_ready()  # all up, each on a device it checked, before any file is written
        else:
            devices = [resolve_device(device)]
        check_plan_file(out, tasks, plan_meta)
        planned = fresh  # this run wrote plan.json
        with output_lock(out):  # one writer per folder
            check_no_strangers(tasks)
            todo = [t for t in tasks if not is_complete(t)]
            done_frames = sum(t.frame_count for t in tasks) - sum(t.frame_count for t in todo)
            bar = tqdm(total=sum(t.frame_count for t in tasks), initial=done_frames, unit="frame", disable=not progress)
            bar.set_description(name)
            try:
                if ray_address:
                    gpu_share = 1 / ray_tasks_per_gpu if devices[0].startswith("cuda") else 0
                    devices = _run_on_ray(todo, renderer, ray_address, gpu_share, bar) or devices
                    parts = {}  # not reported back by Ray tasks
                elif pool:
                    # the card's plotting imports (~0.5 s) while the workers render, not after them
                    threading.Thread(target=importlib.import_module, args=("acoustic_sim.render",), daemon=True).start()
                    # longest shards first: the last ones taken, and the workers' ends, differ less
                    longest_first = sorted(todo, key=lambda t: -t.frame_count)
                    parts = dict.fromkeys(PARTS, 0.0) | pool.run(longest_first, bar)
                else:
                    parts = run_tasks(
                        todo, renderer, devices[0], on_frames=bar.update, overlap=overlap, helpers=helpers
                    )[1]
            finally:
                if pool:  # inside the lock: no worker is writing once it is released
                    failed = sys.exc_info()[0]
                    interrupted = failed is not None and issubclass(failed, KeyboardInterrupt)
                    # Ctrl-C stops them at once; after a run that returned, all is written: they exit
                    # while the manifest and card are written
                    pool.close(abort=failed is not None, now=interrupted, wait=failed is not None)
                    if interrupted:
                        remove_temporaries(todo)  # the shards the stopped workers were writing
            bar.close()
            seconds = time.perf_counter() - t0
            for variant in dict.fromkeys(t.variant for t in tasks):
                mine = [t for t in tasks if t.variant == variant]
                write_manifest(out / variant, mine, renderer.describe(mine))
    except BaseException as error:
        if pool:
            pool.close(abort=True, now=isinstance(error, KeyboardInterrupt))
        if planned:
            forget_plan(out, tasks, made_folder=made_folder)  # unless a shard was finished under it
        raise
    finally:
        if pool:
            pool.close(abort=True)  # a failure before the run (foreign folder, lock refused); else joins them
    made = sum(t.frame_count for t in todo)
    return {
        "suite": name,
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
        "helpers": helpers if overlap and not ray_address else 0,
        "ray_tasks_per_gpu": ray_tasks_per_gpu if ray_address else None,
    }


def _worker_share(
    tasks: Iterable[ShardTask], device: str, on_frames, *, renderer: Renderer, overlap: bool, helpers: int = 0
) -> dict:
    """A worker process's share of a run (shards from the queue all workers share); its seconds by part."""
    return run_tasks(tasks, renderer, device, on_frames, overlap=overlap, helpers=helpers)[1]


def _ray():
    try:
        import ray
    except ImportError:
        raise MissingExtra("--ray-address needs Ray (the `ray` extra): pip install -e '.[ray]'") from None
    return ray


class ShardRenderer:
    """A Ray actor: one process holding its share of one GPU (or one CPU) for the whole run, warm
    between the runs of shards it is handed (a Ray task per shard started a fresh process each, ~5 s
    on an H100 host). A run's next episodes are prepared and last shard written beside the
    rendering by threads (helper processes are not forked from a Ray worker: gRPC forks badly)."""

    def __init__(self, renderer: Renderer, device: str):
        import socket

        import ray

        self.renderer, self.device = renderer, device
        gpus = ray.get_gpu_ids() if device.startswith("cuda") else []  # as its host numbers them
        host = socket.gethostname()
        self.where = f"{host} GPU {','.join(map(str, gpus))}" if gpus else f"{host} CPU"

    def render(self, tasks: list[ShardTask]) -> tuple[int, str]:
        """Render and write `tasks` in order; returns their frames and where they were rendered
        (the host and its GPU: each actor's own device is its cuda:0)."""
        run_tasks(tasks, self.renderer, self.device)
        return sum(task.frame_count for task in tasks), self.where


MAX_RUN = 8  # shards handed to a Ray actor at once: its bar moves at least every 8 shards


def ray_run_length(remaining: int, actors: int) -> int:
    """Shards to hand the next free actor: about half of an even share of what is left, so that
    its rendering overlaps its writing over several shards while the last ones still spread over
    every actor (runs shrink as the work runs out); at least 1, at most MAX_RUN."""
    return max(1, min(MAX_RUN, remaining // (2 * actors)))


def ray_slots(ray, gpu_share: float, tasks: int) -> int:
    """How many ShardRenderer actors the cluster holds at once: its GPUs over each actor's share
    (its CPUs when rendering on CPUs), never more than there are tasks."""
    resources = ray.cluster_resources()
    slots = resources.get("GPU", 0) / gpu_share if gpu_share else resources.get("CPU", 1)
    return max(1, min(tasks, int(slots + 1e-9)))


def _run_on_ray(tasks: list[ShardTask], renderer: Renderer, address: str, gpu_share: float, bar) -> list[str]:
    """The shard tasks rendered by ShardRenderer actors, each holding `gpu_share` of a GPU (1/n: n
    share one; 0: one CPU each), the next run of tasks (`ray_run_length`) handed to whichever actor
    finishes first. One shard a call made 1,110 frames/s on two H100s against 2,513 for local
    workers (benchmarks/results/multi_gpu/session30): each call's write waited for its rendering.
    Returns where the shards were rendered (host and GPU of each actor that rendered some)."""
    ray = _ray()
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
    if not tasks:
        return []
    hold = {"num_gpus": gpu_share} if gpu_share else {"num_cpus": 1}
    actor = ray.remote(**hold, max_restarts=2, max_task_retries=2)(ShardRenderer)
    device = "cuda:0" if gpu_share else "cpu"  # Ray shows an actor only the GPU it holds: its cuda:0
    actors = [actor.remote(renderer, device) for _ in range(ray_slots(ray, gpu_share, len(tasks)))]
    todo, pending, places = deque(tasks), {}, set()

    def hand(to) -> None:
        run = [todo.popleft() for _ in range(ray_run_length(len(todo), len(actors)))]
        pending[to.render.remote(run)] = to

    for to in actors:
        if todo:
            hand(to)
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            frames, where = ray.get(ref)  # a shard's error, raised here
            to = pending.pop(ref)
            bar.update(frames)
            places.add(where)
            if todo:
                hand(to)
    return sorted(places)
