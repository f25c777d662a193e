"""The `crossengine` test set: drives through empty polygon rooms whose echoes come from another
engine, pyroomacoustics' image-source method (order 4; an optional extra, `pip install -e
".[test]"`, never needed to simulate with ours), recorded by the eRTIS array and processed by our
`energyscape` as a user's recordings would be, with exact LiDAR truth cut from the floor plan.

Nothing of our tracer or recorder is used, so a model scored here meets echoes it has never seen
the like of: for scoring only, never for training, early stopping or choosing a threshold.
Floor plans (L, T, U, corridor junctions, irregular halls) are the families of our `randomised`
suite's empty rooms: what differs is the engine that makes their echoes.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from scenes import FLOOR_PLANS, floor_plan, polygon_room, trajectory

from ..config import LidarConfig, ProcessingConfig, SonarConfig
from ..datasets.suites import DRIVE
from ..extras import MissingExtra

IMAGE_ORDER = 4  # reflections per path: walls, floor and ceiling alike
SAMPLE_RATE_HZ = 450_000  # pyroomacoustics wants an integer rate
SPEED_M_S = DRIVE["speed_m_s"]  # our robot's speed, as in every suite with one speed
DT_S = 0.1
EPISODE_FRAMES = 100
ENGINE = "pyroomacoustics image sources"


def _need_pyroomacoustics():
    try:
        import pyroomacoustics
    except ImportError:
        raise MissingExtra(
            "the crossengine test set needs pyroomacoustics (an optional extra): pip install -e '.[test]'"
        ) from None
    return pyroomacoustics


@dataclass(frozen=True, kw_only=True)
class Room:
    """One episode's room: an extruded floor plan and what its surfaces reflect.

    Attributes:
        plan: Floor-plan family (FLOOR_PLANS).
        corners: Floor plan, counter-clockwise, (N, 2) [m].
        height_m: Ceiling height [m].
        wall_reflection, floor_reflection: Pressure reflection coefficients, 0..1.
        ceiling_reflection: 0 for an open room (no ceiling echo).
        sensor_height_m: Height of the sensor above the floor [m].
        snr_db: Gaussian noise below the recording's RMS [dB].
    """

    plan: str
    corners: tuple[tuple[float, float], ...]
    height_m: float
    wall_reflection: float
    floor_reflection: float
    ceiling_reflection: float
    sensor_height_m: float
    snr_db: float


def draw_room(plan: str, rng: np.random.Generator) -> Room:
    """Everything random about one episode's room, from `rng`."""
    corners = floor_plan(plan, rng)
    open_top = rng.uniform() < 0.2
    return Room(
        plan=plan,
        corners=tuple(map(tuple, corners.round(4).tolist())),
        height_m=float(rng.uniform(2.4, 4.0)),
        wall_reflection=float(rng.uniform(0.5, 0.99)),
        floor_reflection=float(rng.uniform(0.5, 0.95)),
        ceiling_reflection=0.0 if open_top else float(rng.uniform(0.5, 0.95)),
        sensor_height_m=float(rng.uniform(0.2, 0.5)),
        snr_db=float(rng.uniform(20.0, 35.0)),
    )


def scan_floor_plan(corners: np.ndarray, poses: np.ndarray, lidar: LidarConfig) -> np.ndarray:
    """Exact planar LiDAR ranges (N, beams) [m] against the walls of a floor plan (walls span the
    room's height, so a level scan sees only them); inf where no wall lies within range."""
    corners = np.asarray(corners, dtype=np.float64)
    a, b = corners, np.roll(corners, -1, axis=0)
    edge = b - a
    directions = lidar.beam_directions()
    out = np.full((len(poses), len(directions)), np.inf)
    for i, pose in enumerate(poses):
        d = (pose[:3, :3] @ directions.T).T[:, :2]  # (B, 2): a level scan stays level
        o = pose[:2, 3]
        # origin + t d = a + s edge: solve for t (along the beam) and s (along the wall)
        denom = d[:, None, 0] * edge[None, :, 1] - d[:, None, 1] * edge[None, :, 0]
        rel = a[None, :, :] - o
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (rel[..., 0] * edge[None, :, 1] - rel[..., 1] * edge[None, :, 0]) / denom
            s = (rel[..., 0] * d[:, None, 1] - rel[..., 1] * d[:, None, 0]) / denom
        hit = (np.abs(denom) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1)
        ranges = np.where(hit, t, np.inf).min(axis=1)
        out[i] = np.where((ranges >= lidar.range_min_m) & (ranges <= lidar.range_max_m), ranges, np.inf)
    return out


def record_ping(room: Room, pose: np.ndarray, sonar: SonarConfig, rng: np.random.Generator) -> np.ndarray:
    """The eRTIS recording of one ping at `pose` in `room` by pyroomacoustics: (mics, samples)
    float32, sample 0 at the start of the call, with Gaussian noise at the room's SNR."""
    pra = _need_pyroomacoustics()

    def material(reflection: float):  # energy absorbed: 1 - R^2, the same in every band
        return pra.Material(1.0 - reflection**2)

    shell = pra.Room.from_corners(
        np.asarray(room.corners).T,
        fs=SAMPLE_RATE_HZ,
        max_order=IMAGE_ORDER,
        materials=material(room.wall_reflection),
        air_absorption=False,
        ray_tracing=False,
    )
    shell.extrude(
        room.height_m,
        materials={"floor": material(room.floor_reflection), "ceiling": material(room.ceiling_reflection)},
    )
    rotation, position = pose[:3, :3], pose[:3, 3]
    shell.add_source(rotation @ np.asarray(sonar.emitter_m) + position, signal=sonar.chirp.samples())
    shell.add_microphone_array((np.asarray(sonar.microphones_m) @ rotation.T + position).T)
    shell.simulate()
    start = pra.constants.get("frac_delay_length") // 2  # its delay filters shift every path by this
    signals = shell.mic_array.signals[:, start : start + sonar.record_samples]
    signals = np.pad(signals, ((0, 0), (0, sonar.record_samples - signals.shape[1])))
    noise = rng.normal(0.0, 1.0, signals.shape) * np.sqrt(np.mean(signals**2)) * 10.0 ** (-room.snr_db / 20.0)
    return (signals + noise).astype(np.float32)


def planner_scene(room: Room):
    """Our scene of the room, for the drive planner alone (the echoes never see it)."""
    return polygon_room(room.plan, corners=np.asarray(room.corners), height=room.height_m)


def simulate_episode(index: int, frames: int, seed: int, device: str) -> tuple[dict, dict]:
    """Episode `index` of the test set: its room, drive, recordings, energyscapes and LiDAR truth."""
    from ..devices import quiet_warp
    from ..engine.beamform import energyscape
    from ..engine.lidar import lidar_image

    quiet_warp()  # a spawned worker starts its own Warp
    episode_seed = int(np.random.default_rng([seed, index]).integers(2**31 - 1))
    rng = np.random.default_rng(episode_seed)
    room = draw_room(FLOOR_PLANS[index % len(FLOOR_PLANS)], rng)
    poses = trajectory(
        planner_scene(room),
        frames=frames,
        dt=DT_S,
        speed=SPEED_M_S,
        sensor_height=room.sensor_height_m,
        seed=episode_seed,
    )
    sonar, lidar, processing = SonarConfig.ertis(), LidarConfig.hokuyo_ust20lx(), ProcessingConfig()
    signals = np.stack([record_ping(room, pose, sonar, rng) for pose in poses])
    ranges = scan_floor_plan(np.asarray(room.corners), poses, lidar)
    arrays = {
        "energyscape": energyscape(signals, sonar, processing, device=device),
        "lidar_ranges": ranges,
        "lidar_image": lidar_image(ranges, lidar, processing.grid),
        "pose": poses,
        "time": np.arange(frames) * DT_S,
    }
    record = {"index": index, "seed": episode_seed, "frames": frames, "scenario": room.plan} | asdict(room)
    return arrays, record


def _settings(frames: int, seed: int) -> dict:
    pra = _need_pyroomacoustics()
    rig = {"lidar": asdict(LidarConfig.hokuyo_ust20lx()), "sonar": asdict(SonarConfig.ertis())}
    rig["processing"] = asdict(ProcessingConfig())
    engine = {"name": ENGINE, "version": pra.__version__, "order": IMAGE_ORDER, "sample_rate_hz": SAMPLE_RATE_HZ}
    engine |= {"speed_m_s": SPEED_M_S, "dt_s": DT_S, "episode_frames": EPISODE_FRAMES, "plans": FLOOR_PLANS}
    return {"frames": frames, "seed": seed, "engine": engine, "sim": rig}


def generate_crossengine(
    out: str | Path,
    *,
    frames: int = 1000,
    seed: int = 0,
    device: str = "cpu",
    workers: int = 1,
    progress: bool = True,
) -> dict:
    """Write the crossengine test set into `out` (one shard per 100-frame episode, our shard
    format, `manifest.json`); finished shards of the same settings are kept, so a killed run
    resumes. Returns a summary like `generate`'s."""
    from tqdm.auto import tqdm

    from .. import __version__
    from ..datasets.generate import output_lock
    from ..datasets.shards import FORMAT, FORMAT_VERSION, ShardFrames, read_attrs, verify_shard, write_shard
    from ..devices import resolve_device

    if frames < 1 or workers < 1:
        raise ValueError(f"frames and workers must be >= 1, got {frames} and {workers}")
    t0, out = time.perf_counter(), Path(out)
    settings = _settings(frames, seed)
    plan_id = hashlib.sha256(json.dumps(settings | {"format_version": FORMAT_VERSION}).encode()).hexdigest()[:16]
    lengths = [min(EPISODE_FRAMES, frames - start) for start in range(0, frames, EPISODE_FRAMES)]
    paths = [out / f"shard-{i:05d}.h5" for i in range(len(lengths))]
    grid = ProcessingConfig().grid
    device = resolve_device(device)
    out.mkdir(parents=True, exist_ok=True)
    with output_lock(out):
        todo = []
        for i, path in enumerate(paths):
            if path.exists():
                if read_attrs(path).get("plan_id") != plan_id:
                    raise ValueError(f"{path} belongs to another run; use another --out or remove that folder")
                verify_shard(path)
                continue
            todo.append(i)
        bar = tqdm(total=frames, initial=frames - sum(lengths[i] for i in todo), unit="frame", disable=not progress)
        bar.set_description("crossengine")
        context = multiprocessing.get_context("spawn")  # the parent has started Warp (and CUDA): never fork it
        with ProcessPoolExecutor(workers, mp_context=context) as pool:
            jobs = {i: pool.submit(simulate_episode, i, lengths[i], seed, device) for i in todo}
            for i, job in jobs.items():
                arrays, record = job.result()
                shard = ShardFrames()
                for key in ("energyscape", "lidar_ranges", "lidar_image", "pose", "time"):
                    getattr(shard, key).append(arrays[key])
                shard.episode.append(np.full(lengths[i], i))
                shard.scenario.append(np.full(lengths[i], FLOOR_PLANS.index(record["scenario"])))
                attrs = {"suite": "crossengine", "variant": "", "shard": i, "plan_id": plan_id, "seed": seed}
                attrs |= {"device": device, "package_version": __version__, "created": time.strftime("%FT%T%z")}
                attrs |= {"config": settings, "episodes": [record], "scenarios": list(FLOOR_PLANS)}
                write_shard(paths[i], shard, attrs=attrs, range_m=grid.range_m, azimuth_rad=grid.azimuth_rad)
                bar.update(lengths[i])
        bar.close()
    manifest = {"format": FORMAT, "suite": "crossengine", "variant": "", "plan_id": plan_id, "seed": seed}
    manifest |= {"frames": frames, "shards": [p.name for p in paths], "engine": settings["engine"]}
    manifest["use"] = "scoring only: never train, stop early or choose a threshold on this set"
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    seconds = time.perf_counter() - t0
    made = sum(lengths[i] for i in todo)
    return {
        "suite": "crossengine",
        "out": str(out),
        "frames": frames,
        "shards": len(paths),
        "shards_written": len(todo),
        "shards_skipped": len(paths) - len(todo),
        "seconds": seconds,
        "frames_per_s": made / seconds if made else 0.0,
        "devices": [device],
    }
