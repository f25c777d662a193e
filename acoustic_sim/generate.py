"""Dataset generation: a suite -> episodes -> shard tasks -> HDF5 shards, resumable and parallel.

`plan` deals a suite's episodes (robot drives, each with its own scene and seed) to shards;
`run_task` simulates one shard and writes it; `generate` runs the tasks that are not finished
yet (in this process, in local worker processes, or as Ray tasks), then writes each dataset's
manifest and card. Everything an episode draws comes from its seed, so the same command on the
same device gives identical arrays, and a rerun skips the shards that are already complete.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import multiprocessing
import os
import socket
import threading
import time
import warnings
import zlib
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from .dataset import FORMAT, FORMAT_VERSION, DatasetError, ShardFrames, read_attrs, verify_shard, write_shard
from .devices import check_device
from .suites import Physics, Suite

FRAMES_PER_SHARD = 250  # default shard size: ~20 MB; enough shards to keep several workers busy
PLAN_FILE = "plan.json"
LOCK_FILE = ".generate.lock"  # "pid host" of the run writing the folder


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
    """Everything a worker needs to write one shard (picklable, JSON-able)."""

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
    key |= {"keep_signals": keep_signals, "keep_arrivals": keep_arrivals}
    plan_id = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:16]
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
                    plan_id=plan_id,
                    seed=seed,
                    suite=suite_json,
                    physics=dataclasses.asdict(physics),
                    episodes=tuple(episodes[bounds[s] : bounds[s + 1]]),
                    keep_signals=keep_signals,
                    keep_arrivals=keep_arrivals,
                )
            )
    return tasks


def episode_sonar_config(physics: Physics, rng: np.random.Generator):
    """The simulated sensor of one episode: air temperature and channel mismatch drawn from `rng`
    (always in the same order, so variants that differ elsewhere draw the same values)."""
    from .config import AtmosphereConfig, SonarConfig

    nominal = SonarConfig.ertis()
    mics = nominal.microphone_count
    snr_db = float(rng.uniform(*physics.snr_db))
    temperature = float(rng.uniform(*physics.temperature_c))
    position = rng.normal(0.0, 1.0, (mics, 3)) * physics.mic_position_sigma_m
    gain = 10.0 ** (rng.normal(0.0, 1.0, mics) * physics.mic_gain_sigma_db / 20.0)
    delay = np.abs(rng.normal(0.0, 1.0, mics)) * physics.mic_delay_sigma_s
    mismatch = {}
    if physics.mic_position_sigma_m > 0:
        mismatch["microphones_m"] = tuple(map(tuple, np.asarray(nominal.microphones_m) + position))
    if physics.mic_gain_sigma_db > 0:
        mismatch["microphone_gain"] = tuple(gain)
    if physics.mic_delay_sigma_s > 0:
        mismatch["microphone_delay_s"] = tuple(delay)
    config = dataclasses.replace(nominal, atmosphere=AtmosphereConfig(temperature_c=temperature), **mismatch)
    return config, snr_db


def simulate_episode(
    episode: Episode, physics: Physics, suite: dict, *, device, keep_signals=False, keep_arrivals=False
):
    """Scene, drive, LiDAR and sonar of one episode -> (arrays, episode record for the shard)."""
    import scenes

    from .config import LidarConfig, PolarGrid, SonarConfig
    from .lidar import Lidar, lidar_image
    from .paths import Sonar

    scene = scenes.BUILDERS[episode.builder](**episode.scene_params)
    poses = scenes.trajectory(
        scene, frames=episode.frames, dt=suite["dt_s"], speed=suite["speed_m_s"], seed=episode.seed
    )
    lidar_config = LidarConfig.hokuyo_ust20lx(
        noise=physics.lidar_noise,
        noise_m=physics.lidar_noise_m if physics.lidar_noise != "none" else 0.0,
        dropout_probability=physics.lidar_dropout_probability,
    )
    ranges = Lidar(lidar_config, device=device).scan(scene, poses, seed=episode.seed)
    sonar_config, snr_db = episode_sonar_config(physics, np.random.default_rng([episode.seed, 2]))
    sonar = Sonar(
        sonar_config,
        max_bounces=physics.max_bounces,
        ray_count=physics.ray_count,
        scattering=physics.scattering,
        edge_width_m=physics.edge_width_m,
        device=device,
    )
    result = sonar.simulate(
        scene,
        poses,
        noise=physics.sonar_noise,
        snr_db=snr_db,
        seed=episode.seed,
        keep_signals=keep_signals,
        processing_config=SonarConfig.ertis(),
    )
    arrays = {
        "energyscape": result.energyscape,
        "lidar_ranges": ranges,
        "lidar_image": lidar_image(ranges, lidar_config, PolarGrid()),
        "pose": poses,
        "time": np.arange(episode.frames) * suite["dt_s"],
        "signals": result.signals,
    }
    if keep_arrivals:
        arrivals = sonar.trace(scene, poses)
        arrays["arrivals"] = {
            "frame": arrivals.pose_index,
            "delay_s": arrivals.delay_s,
            "direction": arrivals.direction,
            "amplitude": arrivals.amplitude,
            "order": arrivals.order,
            "kind": arrivals.kind,
            "point_m": arrivals.point_m,
        }
    record = dataclasses.asdict(episode) | {
        "scene": scene.describe(),
        "snr_db": snr_db,
        "temperature_c": sonar_config.atmosphere.temperature_c,
        "sonar_config": dataclasses.asdict(sonar_config) if sonar_config != SonarConfig.ertis() else None,
        "lidar_config": dataclasses.asdict(lidar_config),
    }
    return arrays, record


def run_task(task: ShardTask, device=None, on_frames=None) -> dict:
    """Simulate and write one shard; returns its manifest entry. `on_frames(n)` reports progress."""
    import warp as wp

    from . import __version__
    from .config import PolarGrid, SonarConfig

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    device = str(wp.get_device(device))
    physics = Physics(**task.physics)
    frames, records = ShardFrames(), []
    offset = 0
    for episode in task.episodes:
        arrays, record = simulate_episode(
            episode,
            physics,
            task.suite,
            device=device,
            keep_signals=task.keep_signals,
            keep_arrivals=task.keep_arrivals,
        )
        for key in ("energyscape", "lidar_ranges", "lidar_image", "pose", "time"):
            getattr(frames, key).append(arrays[key])
        frames.episode.append(np.full(episode.frames, episode.index))
        frames.scenario.append(np.full(episode.frames, episode.scenario))
        if task.keep_signals:
            frames.signals.append(arrays["signals"])
        if task.keep_arrivals:
            frames.arrivals.append(arrays["arrivals"] | {"frame": arrays["arrivals"]["frame"] + offset})
        offset += episode.frames
        records.append(record)
        if on_frames:
            on_frames(episode.frames)
    grid = PolarGrid()
    config = {
        "suite": task.suite,
        "variant": task.variant,
        "physics": task.physics,
        "sonar": dataclasses.asdict(SonarConfig.ertis()),
        "processing": {"speed_of_sound": 343.0, "lowpass_hz": 1e3, "grid": dataclasses.asdict(grid)},
    }
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
    return shard_entry(task)


def shard_entry(task: ShardTask) -> dict:
    path = Path(task.path)
    scenarios = Counter()
    for e in task.episodes:
        scenarios[e.scenario_name] += e.frames
    return {
        "file": path.name,
        "frames": task.frame_count,
        "episodes": [e.index for e in task.episodes],
        "seeds": [e.seed for e in task.episodes],
        "scenarios": dict(scenarios),
        "bytes": path.stat().st_size,
    }


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


_WORKER_DEVICE = None


def _init_worker(devices, parent: int) -> None:
    global _WORKER_DEVICE
    _WORKER_DEVICE = devices.get()
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()


def _exit_with_parent(parent: int) -> None:
    """A worker whose parent died (even by SIGKILL) exits too, instead of simulating on for nobody."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _run_in_worker(task: ShardTask) -> dict:
    return run_task(task, _WORKER_DEVICE)


def worker_devices(device: str, workers: int) -> list[str]:
    """One device per worker: 'auto' spreads workers over the GPUs (or uses the CPU)."""
    import warp as wp

    if device != "auto":
        return [device] * workers
    gpus = wp.get_cuda_device_count()
    return [f"cuda:{i % gpus}" for i in range(workers)] if gpus else ["cpu"] * workers


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
) -> dict:
    """Generate (or finish) a dataset; returns a summary (frames, shards, seconds, frames/s)."""
    t0 = time.perf_counter()
    out = Path(out)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    check_device(device, allow_auto=True)
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
    _check_plan_file(out, tasks, meta | {"variants": list(suite.variants), "suite_config": suite.to_json()})
    with output_lock(out):  # one writer per folder
        todo = [t for t in tasks if not is_complete(t)]
        done_frames = sum(t.frame_count for t in tasks) - sum(t.frame_count for t in todo)
        bar = tqdm(total=sum(t.frame_count for t in tasks), initial=done_frames, unit="frame", disable=not progress)
        bar.set_description(f"{suite.name}")
        devices = worker_devices(device, workers)
        if ray_address:
            _run_on_ray(todo, ray_address, devices[0].startswith("cuda"), bar)
        elif workers == 1 or len(todo) <= 1:
            for task in todo:
                run_task(task, devices[0], on_frames=bar.update)
        else:
            context = multiprocessing.get_context("spawn")
            queue = context.Queue()  # handed to each worker at its start; no manager process to outlive us
            for d in devices:
                queue.put(d)
            init = (queue, os.getpid())
            with ProcessPoolExecutor(workers, mp_context=context, initializer=_init_worker, initargs=init) as pool:
                futures = {pool.submit(_run_in_worker, t): t for t in todo}
                for future in as_completed(futures):
                    future.result()
                    bar.update(futures[future].frame_count)
        bar.close()
        seconds = time.perf_counter() - t0
        for variant in suite.variants:
            write_manifest(out / variant, [t for t in tasks if t.variant == variant], suite, meta)
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
    }


def _run_on_ray(tasks: list[ShardTask], address: str, gpu: bool, bar) -> None:
    try:
        import ray
    except ImportError:
        raise RuntimeError("--ray-address needs Ray: pip install 'sonar2lidar[ray]'") from None
    ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
    remote = ray.remote(num_gpus=1 if gpu else 0, max_retries=2)(run_task)
    pending = {remote.remote(t, "cuda:0" if gpu else "cpu"): t for t in tasks}
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            ray.get(ref)
            bar.update(pending.pop(ref).frame_count)


def write_manifest(folder: Path, tasks: list[ShardTask], suite: Suite, meta: dict) -> Path:
    """manifest.json (shards, scenarios, seeds, counts) and the dataset card of one variant."""
    entries = [shard_entry(t) for t in tasks]
    scenarios = Counter()
    for e in entries:
        scenarios.update(e["scenarios"])
    variant = tasks[0].variant
    manifest = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "plan_id": tasks[0].plan_id,
        "suite": suite.name,
        "variant": variant,
        "description": suite.description,
        "seed": meta["seed"],
        "frames": sum(e["frames"] for e in entries),
        "episodes": sum(len(e["episodes"]) for e in entries),
        "scenarios": dict(scenarios),
        "physics": tasks[0].physics,
        "shards": entries,
    }
    path = folder / "manifest.json"
    tmp = path.with_name("manifest.json.tmp")
    tmp.write_text(json.dumps(manifest, indent=1))
    tmp.replace(path)
    write_card(folder, manifest)
    return path


def write_card(folder: Path, manifest: dict) -> None:
    """README.md and card.png: what the dataset holds, how to read it, example frames."""
    import h5py

    from .config import PolarGrid
    from .render import render_examples

    examples, seen = [], set()
    for entry in manifest["shards"]:
        with h5py.File(folder / entry["file"], "r") as f:
            names = json.loads(f.attrs["scenarios"])
            scenario, episode = f["scenario"][:], f["episode"][:]
            for i in np.unique(episode, return_index=True)[1]:
                name = names[scenario[i]]
                if name in seen or len(examples) == 4:
                    continue
                seen.add(name)
                k = min(i + 5, len(episode) - 1) if episode[min(i + 5, len(episode) - 1)] == episode[i] else i
                examples.append((f"{name}, frame {k}", f["energyscape"][k], f["lidar/image"][k]))
    render_examples(examples, PolarGrid(), folder / "card.png")
    title = manifest["suite"] + (f" / {manifest['variant']}" if manifest["variant"] else "")
    rows = "\n".join(f"| {name} | {count:,} |" for name, count in manifest["scenarios"].items())
    physics = "\n".join(f"| {k} | {v} |" for k, v in manifest["physics"].items())
    text = f"""# Dataset: {title}

{manifest["description"]}

{manifest["frames"]:,} frames in {manifest["episodes"]} episodes (robot drives), {len(manifest["shards"])} shards,
seed {manifest["seed"]}, {FORMAT} format version {FORMAT_VERSION}. Made by `python -m acoustic_sim generate`;
rerunning the same command resumes or verifies it.

![example frames: energyscape (dB) with the LiDAR label on top](card.png)

| scenario | frames |
|---|---|
{rows}

Sensor physics:

| setting | value |
|---|---|
{physics}

Each `shard-*.h5` holds `energyscape` (frame, range, azimuth) float16, `lidar/ranges`,
`lidar/image` (the label), `pose`, `time`, `episode`, `scenario`, and the axes `range_m`,
`azimuth_rad`; its attributes hold every config as JSON and one record per episode (scene,
seed, SNR, temperature). Read it with h5py:

```python
import h5py
with h5py.File("{manifest["shards"][0]["file"]}") as f:
    energyscape, label = f["energyscape"][:10], f["lidar/image"][:10]
```
"""
    (folder / "README.md").write_text(text)
