"""The `crossengine` test set: drives through empty polygon rooms whose echoes come from another
engine, pyroomacoustics' image-source method (order 4; an optional extra, `pip install
".[crossengine]"`, never needed to simulate with ours), recorded by the eRTIS array and processed by our
`energyscape` as a user's recordings would be, with exact LiDAR truth cut from the floor plan.

Nothing of our tracer or recorder is used, so a model scored here meets echoes it has never seen
the like of: for scoring only, never for training, early stopping or choosing a threshold.
Floor plans (L, T, U, corridor junctions, irregular halls) are the families of our `randomised`
suite's empty rooms: what differs is the engine that makes their echoes.

Two variants: `crossengine` is image sources alone, so its walls are mirrors (a wall seen
obliquely sends nothing back); `crossengine_rough` adds the diffuse backscatter of rough walls
(`rough_walls`: random point scatterers with Lambert amplitudes, scattering coefficient drawn per
room, the specular echoes keeping the rest of the energy). Both draw the same rooms, drives and
noise for the same seed (the rough walls come from a child generator).

The set is written by `generate`'s machinery (`datasets.generate.make_dataset`): plan.json, the
output lock, resuming, rewriting a damaged shard, the manifest and the dataset card are every
dataset's. What is this module's own: the plan's episodes (`plan_crossengine`: one shard per
drive) and the renderer that turns a drive into arrays (`CrossEngineRenderer`).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

import scenes
from scenes import FLOOR_PLANS, floor_plan, polygon_room, trajectory

from ..config import LidarConfig, ProcessingConfig, SonarConfig
from ..datasets.generate import make_dataset
from ..datasets.manifest import About, FactTable, sensor_facts
from ..datasets.plan import Episode, ShardTask, check_seed, plan_id
from ..datasets.runner import ShardHeader
from ..datasets.shards import FORMAT_VERSION
from ..datasets.suites import DRIVE
from ..extras import MissingExtra
from .rough_walls import DENSITY_PER_M2, SCATTERING_RANGE, RoughWalls, draw_rough_walls, scattered_echoes

IMAGE_ORDER = 4  # reflections per path: walls, floor and ceiling alike
SAMPLE_RATE_HZ = 450_000  # pyroomacoustics wants an integer rate
SPEED_M_S = DRIVE["speed_m_s"]  # our robot's speed, as in every suite with one speed
DT_S = 0.1
EPISODE_FRAMES = 100
ENGINE = "pyroomacoustics image sources"
SUITE = "crossengine"
SUITE_ROUGH = "crossengine_rough"
USE = "scoring only: never train, stop early or choose a threshold on this set"
DESCRIPTION = (
    "A test set from another engine: pyroomacoustics' image sources (order 4) in empty L, T, U, junction and "
    "hall rooms, recorded by the eRTIS array and processed by our energyscape, with exact LiDAR truth from the "
    "floor plan. For scoring only: never train, stop early or choose a threshold on it."
)
DESCRIPTION_ROUGH = (
    "A test set from another engine with rough walls: pyroomacoustics' image sources (order 4) plus the diffuse "
    f"backscatter of random point scatterers on the walls ({DENSITY_PER_M2:g} per m^2, Gaussian amplitudes, "
    f"Lambert's law; scattering coefficient drawn per room, uniform in [{SCATTERING_RANGE[0]:g}, "
    f"{SCATTERING_RANGE[1]:g}], the image sources keeping the rest of the walls' echo) in empty L, T, U, junction "
    "and hall rooms, recorded by the eRTIS array and processed by our energyscape, with exact LiDAR truth from the "
    "floor plan. For scoring only: never train, stop early or choose a threshold on it."
)


def _need_pyroomacoustics():
    try:
        import pyroomacoustics
    except ImportError:
        raise MissingExtra(
            "the crossengine test set needs pyroomacoustics (an optional extra): pip install '.[crossengine]'"
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


def record_ping(
    room: Room, pose: np.ndarray, sonar: SonarConfig, rng: np.random.Generator, rough: RoughWalls | None = None
) -> np.ndarray:
    """The eRTIS recording of one ping at `pose` in `room` by pyroomacoustics: (mics, samples)
    float32, sample 0 at the start of the call, with Gaussian noise at the room's SNR. With `rough`
    walls their diffuse echoes are added and the walls' image sources keep 1 - s of the energy."""
    pra = _need_pyroomacoustics()
    wall_reflection = room.wall_reflection * (1.0 if rough is None else np.sqrt(1.0 - rough.scattering))

    def material(reflection: float):  # energy absorbed: 1 - R^2, the same in every band
        return pra.Material(1.0 - reflection**2)

    shell = pra.Room.from_corners(
        np.asarray(room.corners).T,
        fs=SAMPLE_RATE_HZ,
        max_order=IMAGE_ORDER,
        materials=material(wall_reflection),
        air_absorption=False,
        ray_tracing=False,
    )
    shell.extrude(
        room.height_m,
        materials={"floor": material(room.floor_reflection), "ceiling": material(room.ceiling_reflection)},
    )
    rotation, position = pose[:3, :3], pose[:3, 3]
    emitter, call = rotation @ np.asarray(sonar.emitter_m) + position, sonar.chirp.samples()
    microphones = np.asarray(sonar.microphones_m) @ rotation.T + position
    shell.add_source(emitter, signal=call)
    shell.add_microphone_array(microphones.T)
    shell.simulate()
    start = pra.constants.get("frac_delay_length") // 2  # its delay filters shift every path by this
    signals = shell.mic_array.signals[:, start : start + sonar.record_samples]
    signals = np.pad(signals, ((0, 0), (0, sonar.record_samples - signals.shape[1])))
    if rough is not None:
        each = {"sample_rate_hz": SAMPLE_RATE_HZ, "speed_of_sound": shell.c, "samples": sonar.record_samples}
        signals = signals + scattered_echoes(rough, emitter, microphones, call, **each)
    noise = rng.normal(0.0, 1.0, signals.shape) * np.sqrt(np.mean(signals**2)) * 10.0 ** (-room.snr_db / 20.0)
    return (signals + noise).astype(np.float32)


def planner_scene(room: Room):
    """Our scene of the room, for the drive planner alone (the echoes never see it)."""
    return polygon_room(room.plan, corners=np.asarray(room.corners), height=room.height_m)


@dataclass(frozen=True)
class Drive:
    """One episode's host half: its room, the robot's poses (N, 4, 4), the generator its pings'
    noise is drawn from (it goes on from where the room's draws stopped) and, in the rough
    variant, the walls' scatterers."""

    episode: Episode
    room: Room
    poses: np.ndarray
    rng: np.random.Generator
    rough: RoughWalls | None = None


class CrossEngineRenderer:
    """Drives through `draw_room`'s rooms: pyroomacoustics records each ping (in place of our tracer
    and recorder), our `energyscape` processes the recordings, the LiDAR truth is cut from the floor
    plan (`scan_floor_plan`). A `datasets.runner.Renderer`."""

    def prepare(self, task: ShardTask, episode: Episode) -> Drive:
        rng = np.random.default_rng(episode.seed)
        room = draw_room(episode.scenario_name, rng)
        rough = None
        if settings := task.suite["config"]["engine"].get("rough_walls"):
            # the drive's first child generator (as rng.spawn(1)): rng's own draws stay the specular set's
            child = np.random.default_rng(np.random.SeedSequence(episode.seed).spawn(1)[0])
            draws = {"density_per_m2": settings["density_per_m2"], "scattering_range": settings["scattering_range"]}
            rough = draw_rough_walls(np.asarray(room.corners), room.height_m, room.wall_reflection, child, **draws)
        poses = trajectory(
            planner_scene(room),
            frames=episode.frames,
            dt=DT_S,
            speed=SPEED_M_S,
            sensor_height=room.sensor_height_m,
            seed=episode.seed,
        )
        return Drive(episode, room, poses, rng, rough)

    def render(self, task: ShardTask, drive: Drive, *, device: str, on_frames, seconds: dict) -> tuple[dict, dict]:
        from ..engine.beamform import energyscape
        from ..engine.lidar import lidar_image

        sonar, lidar = SonarConfig.ertis(), LidarConfig.hokuyo_ust20lx()
        processing = ProcessingConfig(**task.suite["config"]["sim"]["processing"])  # its elevations too
        t0 = time.perf_counter()
        signals = []
        for pose in drive.poses:
            signals.append(record_ping(drive.room, pose, sonar, drive.rng, drive.rough))
            if on_frames:
                on_frames(1)
        image = energyscape(np.stack(signals), sonar, processing, device=device)
        t1 = time.perf_counter()
        ranges = scan_floor_plan(np.asarray(drive.room.corners), drive.poses, lidar)
        seconds["sonar"] = seconds.get("sonar", 0.0) + t1 - t0
        seconds["lidar"] = seconds.get("lidar", 0.0) + time.perf_counter() - t1
        episode = drive.episode
        arrays = {
            "energyscape": image,
            "lidar_ranges": ranges,
            "lidar_image": lidar_image(ranges, lidar, processing.grid, np.uint8),
            "pose": drive.poses,
            "time": np.arange(episode.frames) * DT_S,
        }
        if task.keep_signals:  # the recordings themselves, e.g. to calibrate our simulator to these rooms
            arrays["signals"] = np.stack(signals)
        record = {"index": episode.index, "seed": episode.seed, "frames": episode.frames, "scenario": drive.room.plan}
        return arrays, record | asdict(drive.room) | (drive.rough.record() if drive.rough else {})

    def shard_header(self, task: ShardTask) -> ShardHeader:
        processing = ProcessingConfig(**task.suite["config"]["sim"]["processing"])
        return ShardHeader(task.suite["config"], list(FLOOR_PLANS), processing.grid, processing.elevations_deg)

    def describe(self, tasks: list[ShardTask]) -> About:
        config = tasks[0].suite["config"]
        engine = config["engine"]
        echoes = (
            f"{engine['name']} (version {engine['version']}) to order {engine['order']}, "
            f"sampled at {engine['sample_rate_hz'] / 1e3:g} kHz"
        )
        rooms = "one per drive, drawn by `draw_room` (its episode record holds it: corners, reflections, SNR)"
        rows = (("echoes", echoes), ("room", rooms))
        description = DESCRIPTION
        if rough := engine.get("rough_walls"):
            description, (low, high) = DESCRIPTION_ROUGH, rough["scattering_range"]
            walls = (
                f"rough: {rough['density_per_m2']:g} random point scatterers per m^2 of wall (Gaussian amplitudes, "
                f"Lambert's law), scattering coefficient uniform in [{low:g}, {high:g}] per room (in its record)"
            )
            rows += (("walls", walls),)
        rows += tuple(sensor_facts(config["sim"]))
        caption = "The rig (another engine's echoes; our array, call, processing and LiDAR):"
        return About(
            {"description": description, "use": USE, "engine": engine, "sim": config["sim"]},
            (FactTable(caption, rows),),
        )


def elevations_of(settings, suite: str = SUITE):
    """The beamformer's elevations that `--set` asks of the set: the one setting it takes (its
    rig is its own; ValueError for any other)."""
    from ..config import SimConfig
    from ..settings import apply_settings

    rig, default = apply_settings(SimConfig(), settings), SimConfig()
    elevation_deg = rig.processing.elevation_deg
    if rig != replace(default, processing=replace(default.processing, elevation_deg=elevation_deg)):
        raise ValueError(
            f"the {suite} test set is another engine's: of --set, only processing.elevation_deg applies to it"
        )
    return elevation_deg


def _settings(frames: int, seed: int, episode_frames: int, rough: bool, elevation_deg) -> dict:
    pra = _need_pyroomacoustics()
    rig = {"lidar": asdict(LidarConfig.hokuyo_ust20lx()), "sonar": asdict(SonarConfig.ertis())}
    rig["processing"] = asdict(ProcessingConfig(elevation_deg=elevation_deg))
    engine = {"name": ENGINE, "version": pra.__version__, "order": IMAGE_ORDER, "sample_rate_hz": SAMPLE_RATE_HZ}
    engine |= {"speed_m_s": SPEED_M_S, "dt_s": DT_S, "episode_frames": episode_frames, "plans": FLOOR_PLANS}
    if rough:  # only here, so the specular set's plan (and its plan id) is what it was
        model = "random point scatterers on the walls, Gaussian amplitudes, Lambert's law"
        engine["rough_walls"] = {"model": model, "density_per_m2": DENSITY_PER_M2, "scattering_range": SCATTERING_RANGE}
    return {"frames": frames, "seed": seed, "engine": engine, "sim": rig}


def plan_crossengine(
    out: str | Path,
    *,
    frames: int,
    seed: int = 0,
    episode_frames: int = EPISODE_FRAMES,
    rough: bool = False,
    elevation_deg: float | tuple[float, ...] = 0.0,
    keep_signals: bool = False,
) -> list[ShardTask]:
    """The test set's shard tasks: one per drive of `episode_frames` frames (the last one shorter),
    drive i in a room of the floor-plan family i mod 5, each drive seeded from (`seed`, i); `rough`:
    the rough-wall variant; `elevation_deg`: the beamformer's elevations (`ProcessingConfig`);
    `keep_signals`: the microphone signals stored too."""
    if frames < 1 or episode_frames < 1:
        raise ValueError(f"frames and episode_frames must be >= 1, got {frames} and {episode_frames}")
    check_seed(seed, "seed")
    config = _settings(frames, seed, episode_frames, rough, elevation_deg)
    kept = {"keep_signals": True} if keep_signals else {}  # only then: the plan id of a set without is unchanged
    run_id = plan_id(config | kept | {"format_version": FORMAT_VERSION, "scenes_revision": scenes.REVISION})
    suite = {"name": SUITE_ROUGH if rough else SUITE, "config": config}
    tasks = []
    for i, start in enumerate(range(0, frames, episode_frames)):
        kind = i % len(FLOOR_PLANS)
        episode_seed = int(np.random.default_rng([seed, i]).integers(2**31 - 1))
        length = min(episode_frames, frames - start)
        drive = Episode(i, kind, FLOOR_PLANS[kind], "polygon_room", {"plan": FLOOR_PLANS[kind]}, length, episode_seed)
        path = str(Path(out) / f"shard-{i:05d}.h5")
        tasks.append(
            ShardTask(
                path=path,
                variant="",
                shard=i,
                plan_id=run_id,
                seed=seed,
                suite=suite,
                physics={},
                episodes=(drive,),
                keep_signals=keep_signals,
            )
        )
    return tasks


def generate_crossengine(
    out: str | Path,
    *,
    frames: int = 1000,
    seed: int = 0,
    device: str = "cpu",
    workers: int = 1,
    progress: bool = True,
    episode_frames: int = EPISODE_FRAMES,
    rough: bool = False,
    elevation_deg: float | tuple[float, ...] = 0.0,
    keep_signals: bool = False,
) -> dict:
    """Write (or finish) the crossengine test set (`rough`: its rough-wall variant) in `out` with
    generate's machinery (`make_dataset`: plan.json, lock, resume, repair of damaged shards,
    manifest.json with its `use`, and the dataset card); returns the same summary as `generate`.
    `elevation_deg`: the beamformer's elevations, one or an increasing sequence; `keep_signals`: the
    microphone signals stored too (what `calibrate` fits to)."""
    tasks = plan_crossengine(
        out,
        frames=frames,
        seed=seed,
        episode_frames=episode_frames,
        rough=rough,
        elevation_deg=elevation_deg,
        keep_signals=keep_signals,
    )
    meta = {"suite": tasks[0].suite["name"], "frames": frames, "shards": len(tasks), "seed": seed}
    meta |= {"engine": tasks[0].suite["config"]["engine"], "use": USE}
    return make_dataset(
        tasks, CrossEngineRenderer(), out, plan_meta=meta, device=device, workers=workers, progress=progress
    )
