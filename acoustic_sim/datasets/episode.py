"""One episode's simulation: its scene and drive, the sensors its physics variant draws, the LiDAR
scan and the sonar frames. Everything comes from the episode's seed, so it is reproducible on
its own (in any process, in any order)."""

from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np

from scenes.surfaces import with_surfaces

from ..config import SimConfig, SonarConfig
from .mesh_scenarios import MESH_BUILDER, MeshFile, mesh_scene
from .physics import Physics
from .plan import Episode
from .suites import episode_drive


def episode_sonar_config(physics: Physics, nominal: SonarConfig, rng: np.random.Generator) -> tuple[SonarConfig, float]:
    """The simulated sensor of one episode and its SNR [dB]: the nominal sonar with air temperature
    and channel mismatch drawn from `rng` (always in the same order, so variants that differ
    elsewhere draw the same values) around the physics' own gains and delays per microphone."""
    mics = nominal.microphone_count
    snr_db = float(rng.uniform(*physics.snr_db))
    temperature = float(rng.uniform(*physics.temperature_c))
    position = rng.normal(0.0, 1.0, (mics, 3)) * physics.mic_position_sigma_m
    gain = 10.0 ** (rng.normal(0.0, 1.0, mics) * physics.mic_gain_sigma_db / 20.0)
    delay = np.abs(rng.normal(0.0, 1.0, mics)) * physics.mic_delay_sigma_s
    for name in ("mic_gain_db", "mic_delay_s"):
        if len(getattr(physics, name)) not in (0, mics):
            raise ValueError(f"Physics.{name} gives {len(getattr(physics, name))} microphones, the sonar has {mics}")
    mismatch = {}
    if physics.mic_position_sigma_m > 0:
        mismatch["microphones_m"] = tuple(map(tuple, np.asarray(nominal.microphones_m) + position))
    if physics.mic_gain_sigma_db > 0 or physics.mic_gain_db:
        mismatch["microphone_gain"] = tuple(gain * 10.0 ** (np.asarray(physics.mic_gain_db or 0.0) / 20.0))
    if physics.mic_delay_sigma_s > 0 or physics.mic_delay_s:
        mismatch["microphone_delay_s"] = tuple(delay + np.asarray(physics.mic_delay_s or 0.0))
    atmosphere = dataclasses.replace(nominal.atmosphere, temperature_c=temperature)
    config = dataclasses.replace(nominal, atmosphere=atmosphere, **mismatch)
    return config, snr_db


@dataclasses.dataclass
class PreparedEpisode:
    """The host half of an episode (see `prepare_episode`), ready for the device."""

    episode: Episode
    scene: object  # scenes.Scene
    poses: np.ndarray
    drive: dict
    acoustics: dict
    drawn: SimConfig
    draws: dict
    sonar_config: SonarConfig
    snr_db: float


def build_scene(episode: Episode, suite_name: str, meshes: dict[str, MeshFile] | None = None):
    """The episode's scene (`scenes.Scene`) from its scenario's builder, or its mesh file (`meshes`:
    by scenario name; loaded once per process); a builder's refusal (SceneError, a wrong argument)
    names the suite, the scenario and the arguments it was given."""
    import scenes

    if episode.builder == MESH_BUILDER:
        if episode.scenario_name not in (meshes or {}):
            raise ValueError(
                f"suite {suite_name!r}, scenario {episode.scenario_name!r}: its mesh file "
                f"{episode.scene_params.get('file')!r} was not given to this renderer (SuiteRenderer(meshes=...))"
            )
        return mesh_scene(meshes[episode.scenario_name])
    try:
        return scenes.BUILDERS[episode.builder](**episode.scene_params)
    except (TypeError, ValueError) as err:
        given = {k: v for k, v in episode.scene_params.items() if k != "seed"}
        raise ValueError(
            f"suite {suite_name!r}, scenario {episode.scenario_name!r}: {episode.builder}({given}) refused: {err}; "
            "fix the scenario's params or vary"
        ) from None


def prepare_episode(
    episode: Episode, physics: Physics, nominal: SimConfig, suite: dict, meshes: dict[str, MeshFile] | None = None
) -> PreparedEpisode:
    """Everything of an episode that runs on the host: its scene, drive and drawn physics. Needs no
    device, so `generate` prepares the next episode while the GPU renders this one. `meshes`: the
    mesh files of the suite's mesh scenarios, by name (`suites.mesh_files`)."""
    import scenes

    scene = build_scene(episode, suite["name"], meshes)
    drive = episode_drive(suite, episode.seed)
    acoustics = physics.draw_surfaces(np.random.default_rng([episode.seed, 4]))
    if acoustics:
        scene = with_surfaces(scene, acoustics)
    try:
        poses = scenes.trajectory(
            scene,
            frames=episode.frames,
            dt=suite["dt_s"],
            speed=drive["speed_m_s"],
            sensor_height=drive["sensor_height_m"],
            turn_rate=drive["turn_rate_rad_s"],
            seed=episode.seed,
        )
    except scenes.SceneError as err:
        mesh = f" (mesh {episode.scene_params['file']})" if episode.builder == MESH_BUILDER else ""
        raise scenes.SceneError(
            f"suite {suite['name']!r}, scenario {episode.scenario_name!r}{mesh} (episode {episode.index}): no drive "
            f"of {episode.frames} frames: {err}; give the scenario a larger scene or the suite other drive settings"
        ) from None
    drawn, draws = physics.draw(nominal, np.random.default_rng([episode.seed, 3]))
    sonar_config, snr_db = episode_sonar_config(physics, drawn.sonar, np.random.default_rng([episode.seed, 2]))
    return PreparedEpisode(episode, scene, poses, drive, acoustics, drawn, draws, sonar_config, snr_db)


def simulate_episode(
    episode: Episode | PreparedEpisode,
    physics: Physics,
    nominal: SimConfig,
    suite: dict,
    *,
    device,
    keep_signals=False,
    keep_arrivals=False,
    on_frames=None,
    seconds: dict | None = None,
) -> tuple[dict, dict]:
    """Scene, drive, LiDAR and sonar of one episode -> (arrays, episode record for the shard).
    `nominal` is the variant's rig (`suites.rig`) before this episode's draws; `episode` may come
    prepared already (`prepare_episode`); `on_frames(n)` is called as the sonar finishes each batch
    of n frames; `seconds`, if given, adds the time of each part ("prepare", "lidar", "sonar",
    "assemble")."""
    from ..engine.lidar import lidar_image

    seconds = {} if seconds is None else seconds
    t0 = time.perf_counter()
    ready = episode if isinstance(episode, PreparedEpisode) else prepare_episode(episode, physics, nominal, suite)
    t1 = time.perf_counter()
    episode, scene, poses = ready.episode, ready.scene, ready.poses
    # The sensors before any work is queued: a sonar drawn per episode is new, and the upload of its
    # recorder's ~0.5 MB of filters waited for the LiDAR's scan (py-spy on an H100, multi_gpu/session37).
    sonar = _sonar(ready.sonar_config, ready.drawn.tracer, str(device))
    sonar.recorder(physics.air_absorption)
    t2 = time.perf_counter()
    # The scan is queued first and its ranges read after the sonar: one wait for the device less.
    scan = _lidar(nominal.lidar, str(device)).scan_begin(scene, poses, seed=episode.seed)
    t3 = time.perf_counter()
    result = sonar.simulate(
        scene,
        poses,
        noise=physics.sonar_noise,
        snr_db=ready.snr_db,
        seed=episode.seed,
        absorption=physics.air_absorption,
        keep_signals=keep_signals,
        processing=nominal.processing,
        assumed_array=nominal.sonar,
        on_pings=on_frames,
        dtype=np.float16,  # as shards store them (converted on a GPU, half the bytes to the host)
    )
    t4 = time.perf_counter()
    ranges = scan.ranges()
    t5 = time.perf_counter()
    arrays = {
        "energyscape": result.energyscape,
        "lidar_ranges": ranges,
        "lidar_image": lidar_image(ranges, nominal.lidar, nominal.processing.grid, np.uint8),  # as shards store it
        "pose": poses,
        "time": np.arange(episode.frames) * suite["dt_s"],
        "signals": result.signals,
    }
    t6 = time.perf_counter()
    if keep_arrivals:  # traced again, on the device: the sonar's time
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
    t7 = time.perf_counter()
    sonar_config = ready.sonar_config
    record = dataclasses.asdict(episode) | {
        "scene": scene.describe(),
        "snr_db": ready.snr_db,
        "temperature_c": sonar_config.atmosphere.temperature_c,
        "sonar_config": dataclasses.asdict(sonar_config) if sonar_config != nominal.sonar else None,
        "lidar_config": dataclasses.asdict(nominal.lidar),
    }
    if ready.draws:  # only then: records of variants without draws stay as they were
        record |= {"draws": ready.draws, "tracer_config": dataclasses.asdict(ready.drawn.tracer)}
    if ready.acoustics:
        record["surfaces"] = ready.acoustics
    if any(isinstance(suite.get(name), list | tuple) for name in ready.drive):
        record["drive"] = ready.drive
    t8 = time.perf_counter()
    for part, dt in (
        ("prepare", t1 - t0),
        ("lidar", t3 - t2 + t5 - t4),
        ("sonar", t2 - t1 + t4 - t3 + t7 - t6),  # with the sensors' own start
        ("assemble", t6 - t5 + t8 - t7),  # the LiDAR image and the record: host work between renderings
    ):
        seconds[part] = seconds.get(part, 0.0) + dt
    return arrays, record


# The sensors of the episodes a process renders, reused by the next episode with the same rig: a
# new Sonar builds its tracer's rays and device buffers (~60 ms on the H100 machine, three times
# the GPU time of a 100-frame episode), a new Lidar its buffers. Results never depend on reuse (the
# LiDAR's noise seed is the episode's; the tracer's buffers are filled anew for every batch).
@functools.lru_cache(maxsize=2)
def _sonar(config: SonarConfig, tracer, device: str):
    from ..engine.sonar import Sonar

    return Sonar(config, tracer, device=device)


@functools.lru_cache(maxsize=2)
def _lidar(config, device: str):
    from ..engine.lidar import Lidar

    return Lidar(config, device=device)
