"""Scenario suites: which scenes, robot drives and sensor physics a generated dataset holds.

A suite is a list of scenario families (a scene builder with fixed and randomised arguments)
and one or more physics variants (the same scenes and drives rendered with different sensor
physics, e.g. max_bounces 0, 1 and 3 in the `ablation` suite). Suites are plain frozen
dataclasses; `load_suite` reads one from a TOML or JSON file that may start from a named suite.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import scenes

from .config import (
    NOISE_KINDS,
    ConfigError,
    LidarConfig,
    NoiseKind,
    ProcessingConfig,
    SimConfig,
    SonarConfig,
    TracerConfig,
    check_finite,
)
from .settings import apply_settings


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """One scenario family: a scene builder with fixed and randomised arguments.

    Attributes:
        name: Identifier, unique within the suite; stored per frame.
        builder: Key of `scenes.BUILDERS` ("box_room", "corridor", "office", "random_world").
        params: Fixed builder arguments.
        vary: Randomised builder arguments, drawn per episode: [low, high] (uniform; integers
            if both ends are integers) or {"choice": [...]}. A list of [low, high] pairs
            varies a sequence argument (e.g. a room size) element by element; plain numbers in
            it stay fixed.
        weight: Share of the suite's episodes (relative).
    """

    name: str
    builder: str
    params: dict = field(default_factory=dict)
    vary: dict = field(default_factory=dict)
    weight: float = 1.0

    def __post_init__(self) -> None:
        if self.builder not in scenes.BUILDERS:
            raise ValueError(f"scenario {self.name!r}: unknown builder {self.builder!r}; use {sorted(scenes.BUILDERS)}")
        if not self.weight > 0:
            raise ValueError(f"scenario {self.name!r}: weight must be > 0")
        for key, spec in self.vary.items():
            _draw(np.random.default_rng(0), key, spec)  # validates the spec

    def scene_params(self, rng: np.random.Generator, seed: int) -> dict:
        """Builder arguments of one episode: fixed ones, drawn ones and the scene seed."""
        out = dict(self.params)
        for key, spec in sorted(self.vary.items()):
            out[key] = _draw(rng, key, spec)
        out["seed"] = seed
        return out


def _draw(rng: np.random.Generator, key: str, spec):
    if isinstance(spec, dict):
        if set(spec) != {"choice"} or not spec["choice"]:
            raise ValueError(f"vary.{key}: a dict must be {{'choice': [values]}}")
        return spec["choice"][int(rng.integers(len(spec["choice"])))]
    if isinstance(spec, list | tuple) and any(isinstance(s, list | tuple | dict) for s in spec):
        # Element by element; plain numbers stay fixed (e.g. a room size with a fixed height).
        return [_draw(rng, key, s) if isinstance(s, list | tuple | dict) else s for s in spec]
    if not (isinstance(spec, list | tuple) and len(spec) == 2 and spec[0] <= spec[1]):
        raise ValueError(f"vary.{key}: expected [low, high], {{'choice': [...]}} or a list of [low, high]")
    low, high = spec
    if isinstance(low, int) and isinstance(high, int):
        return int(rng.integers(low, high + 1))
    return float(rng.uniform(low, high))


VARYING_SECTIONS = ("sonar", "tracer")
"""Rig sections `Physics.vary` may draw per episode; the LiDAR and the processing fix a dataset's
arrays and grids (the LiDAR's noise has its own Physics fields)."""

DRAWN_FIELDS = {
    "sonar.atmosphere.temperature_c": "temperature_c",
    "sonar.microphones_m": "mic_position_sigma_m",
    "sonar.microphone_gain": "mic_gain_sigma_db",
    "sonar.microphone_delay_s": "mic_delay_sigma_s",
}
"""Rig fields that Physics fields of their own draw per episode: `vary` refuses them."""


@dataclass(frozen=True, kw_only=True)
class Physics:
    """Sensor physics of one variant. Ranges (low, high) are drawn per episode.

    The first four fields are the variant's `TracerConfig` (checked by it: the same limits as a
    `Sonar` built by hand); the others are drawn or applied per episode (`episode`). `vary`
    reaches any other field of the sonar and the tracer.

    Attributes:
        max_bounces: Specular bounces after the first reflection (0..MAX_BOUNCES).
        ray_count: Path-tracer rays per ping.
        scattering: Diffuse/edge echoes on or off.
        edge_width_m: Band along sharp edges that scatters everything; None = half a wavelength,
            0 = no edge echoes ("minimal reflectors").
        sonar_noise: "none", "gaussian" or "uniform" microphone noise.
        snr_db: Signal-to-noise ratio of that noise [dB], per episode.
        lidar_noise: "none", "gaussian" or "uniform" (the paper) range noise.
        lidar_noise_m: Its size (std or half-width) [m].
        lidar_dropout_probability: Share of LiDAR beams that return nothing.
        temperature_c: Air temperature per episode [C]; the beamformer always assumes 343 m/s.
        mic_position_sigma_m, mic_gain_sigma_db, mic_delay_sigma_s: Channel mismatch of the
            simulated array per episode (the beamformer assumes the nominal array).
        vary: Rig fields drawn per episode, by dotted path under `sonar` or `tracer`, each as
            [low, high] (integers if both ends are), {"choice": [...]} or, for a sequence field,
            a list of those and fixed numbers: e.g. {"sonar.emitter_radius_m": [0.0, 0.02],
            "tracer.max_bounces": [1, 6]}; a drawn tracer field replaces the Physics field of
            that name for the episode. Limits are the configs' own: both ends of every range
            (every choice) are checked when the variant is made. Drawn values are recorded per
            episode.
    """

    max_bounces: int = 3
    ray_count: int = 20_000
    scattering: bool = True
    edge_width_m: float | None = None
    sonar_noise: NoiseKind = "gaussian"
    snr_db: tuple[float, float] = (25.0, 35.0)
    lidar_noise: NoiseKind = "uniform"
    lidar_noise_m: float = 0.01
    lidar_dropout_probability: float = 0.0
    temperature_c: tuple[float, float] = (20.0, 20.0)
    mic_position_sigma_m: float = 0.0
    mic_gain_sigma_db: float = 0.0
    mic_delay_sigma_s: float = 0.0
    vary: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "snr_db", _pair(self.snr_db, "snr_db"))
        object.__setattr__(self, "temperature_c", _pair(self.temperature_c, "temperature_c"))
        check_finite(self)
        self.tracer()  # refuses max_bounces outside 0..MAX_BOUNCES, ray_count < 1, edge_width_m < 0
        for name in ("sonar_noise", "lidar_noise"):
            if getattr(self, name) not in NOISE_KINDS:
                raise ValueError(f"Physics.{name} must be one of {NOISE_KINDS}, got {getattr(self, name)!r}")
        sigmas = (self.mic_position_sigma_m, self.mic_gain_sigma_db, self.mic_delay_sigma_s, self.lidar_noise_m)
        if min(sigmas) < 0:
            raise ValueError("Physics: noise sizes and mismatch sigmas must be >= 0")
        nominal = rig(self)
        for key, spec in self.vary.items():
            if key in DRAWN_FIELDS:
                raise ValueError(f"Physics.vary {key!r}: Physics.{DRAWN_FIELDS[key]} draws it")
            if key.split(".")[0] not in VARYING_SECTIONS or "." not in key:
                raise ValueError(f"Physics.vary {key!r}: only fields under {' or '.join(VARYING_SECTIONS)} vary")
            _draw(np.random.default_rng(0), key, spec)  # validates the spec
            for end in _extremes(spec):
                _drawn_rig(nominal, {key: end})  # refuses a value its config refuses, naming the key

    def draw(self, nominal: SimConfig, rng: np.random.Generator) -> tuple[SimConfig, dict]:
        """`nominal` with this variant's `vary` drawn from `rng` (keys in sorted order) ->
        (the episode's rig, the drawn values)."""
        draws = {key: _draw(rng, key, self.vary[key]) for key in sorted(self.vary)}
        return _drawn_rig(nominal, draws), draws

    def to_json(self) -> dict:
        out = dataclasses.asdict(self)
        if not out["vary"]:  # so that variants without draws keep the plan ids of earlier runs
            del out["vary"]
        return out

    def tracer(self) -> TracerConfig:
        """The path tracer's settings of this variant."""
        fields = ("max_bounces", "ray_count", "scattering", "edge_width_m")
        return TracerConfig(**{name: getattr(self, name) for name in fields})


def _drawn_rig(nominal: SimConfig, values: dict) -> SimConfig:
    try:
        return apply_settings(nominal, [f"{key}={json.dumps(value)}" for key, value in values.items()])
    except ConfigError as err:
        raise ConfigError(f"Physics.vary: {err}") from None


def _extremes(spec) -> list:
    """The values a `vary` spec can reach at its ends: both ends of a range, every choice."""
    if isinstance(spec, dict):
        return list(spec.get("choice") or [])
    if isinstance(spec, list | tuple) and any(isinstance(s, list | tuple | dict) for s in spec):
        ends = [_extremes(s) if isinstance(s, list | tuple | dict) else [s] for s in spec]
        return [[e[0] for e in ends], [e[-1] for e in ends]]
    return list(spec)


def _pair(value, name: str) -> tuple[float, float]:
    pair = (float(value), float(value)) if np.ndim(value) == 0 else tuple(float(v) for v in value)
    if not np.isfinite(pair).all():
        raise ConfigError(f"Physics.{name} must be finite, got {value!r}")
    if len(pair) != 2 or pair[0] > pair[1]:
        raise ValueError(f"{name} must be a number or [low, high], got {value!r}")
    return pair


@dataclass(frozen=True, kw_only=True)
class Suite:
    """A named dataset recipe.

    Attributes:
        name, description: Shown in the manifest and dataset card.
        scenarios: Scenario families; episodes are dealt to them by weight.
        variants: Physics per variant name; one variant named "" writes the shards straight into
            the output folder, several write one sub-folder (a dataset of its own) each, with
            identical scenes, drives and noise seeds.
        frames: Default frame count (per variant).
        episode_frames: Frames per robot drive (an episode); windows never cross episodes.
        dt_s: Time between frames [s] (the sonar rate).
        speed_m_s: Robot speed [m/s].
        settings: `section.field=value` changes to every variant's rig (`rig`), applied after
            its physics: e.g. "lidar=multibeam_64x1024" (a preset), "processing.grid.range_max_m=4".
    """

    name: str
    description: str
    scenarios: tuple[Scenario, ...]
    variants: dict[str, Physics] = field(default_factory=lambda: {"": Physics()})
    frames: int = 300
    episode_frames: int = 100
    dt_s: float = 0.1
    speed_m_s: float = 0.3
    settings: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        check_finite(self)
        object.__setattr__(self, "settings", tuple(self.settings))
        for physics in self.variants.values():
            rig(physics, self.settings)  # refuses unknown or out-of-range settings now, not in a worker
        if not self.scenarios:
            raise ValueError(f"suite {self.name!r} has no scenarios")
        names = [s.name for s in self.scenarios]
        if len(set(names)) != len(names):
            raise ValueError(f"suite {self.name!r}: scenario names repeat: {names}")
        if not self.variants or ("" in self.variants and len(self.variants) > 1):
            raise ValueError(f"suite {self.name!r}: variants need names when there are several")
        for variant in self.variants:  # a variant is a folder under --out: never a path that leaves it
            if variant and not (
                variant.replace("_", "").replace("-", "").replace(".", "").isalnum() and variant[0] != "."
            ):
                raise ValueError(
                    f"suite {self.name!r}: variant name {variant!r} must be letters, digits, '_', '-' or '.' "
                    "(not starting with '.'): it names a folder under --out"
                )
        if self.frames < 1 or self.episode_frames < 1 or not self.dt_s > 0 or self.speed_m_s < 0:
            raise ValueError(f"suite {self.name!r}: frames, episode_frames >= 1, dt_s > 0, speed_m_s >= 0")

    def to_json(self) -> dict:
        out = dataclasses.asdict(self) | {"variants": {k: p.to_json() for k, p in self.variants.items()}}
        if not out["settings"]:  # so that suites without settings keep the plan ids of earlier runs
            del out["settings"]
        return out


def rig(physics: Physics, settings: tuple[str, ...] = ()) -> SimConfig:
    """The rig a physics variant simulates before any per-episode draw: the Hokuyo with the
    variant's range noise, the nominal eRTIS, the variant's tracer and the eRTIS processing, then
    the suite's `settings`. The beamformer assumes this nominal array and its processing's speed
    of sound whatever an episode draws (temperature, mismatch), as the real sensor does."""
    lidar = LidarConfig.hokuyo_ust20lx(
        noise=physics.lidar_noise,
        noise_m=physics.lidar_noise_m if physics.lidar_noise != "none" else 0.0,
        dropout_probability=physics.lidar_dropout_probability,
    )
    nominal = SimConfig(lidar=lidar, sonar=SonarConfig.ertis(), tracer=physics.tracer(), processing=ProcessingConfig())
    return apply_settings(nominal, settings)


def _scenario(name: str, builder: str, weight: float = 1.0, **params) -> Scenario:
    vary = {k: v for k, v in params.items() if isinstance(v, list | dict)}  # tuples stay fixed
    fixed = {k: v for k, v in params.items() if k not in vary}
    return Scenario(name=name, builder=builder, params=fixed, vary=vary, weight=weight)


# The paper's twelve kinds of simulated worlds, in 3D: corridors and rooms with few or many
# reflectors, offices, and its random worlds of walls and cylinders with object size, count and
# rotation varied (rotation and placement come from each episode's scene seed).
PAPER_SCENARIOS = (
    _scenario("corridor_few", "corridor", reflectors="few", length=[10.0, 20.0], width=[1.6, 2.6]),
    _scenario("corridor_many", "corridor", reflectors="many", length=[10.0, 20.0], width=[1.6, 2.6]),
    _scenario("room_empty", "box_room", size=[[4.0, 8.0], [3.0, 6.0], [2.5, 3.2]]),
    _scenario("office_low", "office", clutter="low", size=[[6.0, 10.0], [5.0, 8.0], [2.7, 3.2]]),
    _scenario("office_medium", "office", clutter="medium", size=[[6.0, 10.0], [5.0, 8.0], [2.7, 3.2]]),
    _scenario("office_high", "office", clutter="high", size=[[7.0, 10.0], [6.0, 8.0], [2.7, 3.2]]),
    _scenario("random_small_objects", "random_world", object_scale=[0.4, 0.8]),
    _scenario("random_large_objects", "random_world", object_scale=[1.2, 1.6]),
    _scenario("random_walls", "random_world", wall_count=[4, 8], cylinder_count=0),
    _scenario("random_cylinders", "random_world", wall_count=0, cylinder_count=[5, 10]),
    _scenario("random_dense", "random_world", size=(8.0, 8.0, 3.0), wall_count=[5, 8], cylinder_count=[6, 10]),
    _scenario("random_sparse", "random_world", size=(12.0, 12.0, 3.0), wall_count=[1, 3], cylinder_count=[1, 3]),
)

# Held out from training: other sizes and mixes of the same builders (and other seeds, since
# every suite draws its own).
REALITY_SCENARIOS = (
    _scenario("corridor_long", "corridor", reflectors="many", length=[20.0, 30.0], width=[2.2, 3.0]),
    _scenario("office_large", "office", clutter={"choice": ["medium", "high"]}, size=[[9.0, 12.0], [7.0, 9.0], 3.0]),
    _scenario("random_mixed", "random_world", size=[[9.0, 11.0], [9.0, 11.0], 2.8], object_scale=[0.7, 1.3]),
)

SUITES: dict[str, Suite] = {
    s.name: s
    for s in (
        Suite(
            name="paper",
            description="The paper's kinds of scenarios in 3D with multipath: corridors and rooms with few "
            "or many reflectors, offices, random worlds of walls and cylinders (object size, count and "
            "rotation varied); 3 secondary bounces; 10 Hz drives at 0.3 m/s.",
            scenarios=PAPER_SCENARIOS,
            frames=12_500,
        ),
        Suite(
            name="table2",
            description="The paper's Table 2 test cases in a complex environment (offices and random "
            "worlds): 'minimal' reflectors (specular echoes only: no edge or rough-surface scattering), "
            "'many' reflectors (edges and rough surfaces echo), and 'noisy' input (many reflectors, "
            "10-15 dB SNR, 3 cm LiDAR noise).",
            scenarios=tuple(s for s in PAPER_SCENARIOS if s.builder in ("office", "random_world")),
            variants={
                "minimal": Physics(scattering=False),
                "many": Physics(),
                "noisy": Physics(snr_db=(10.0, 15.0), lidar_noise_m=0.03),
            },
            frames=3_000,
        ),
        Suite(
            name="ablation",
            description="The same scenes, drives and noise rendered with max_bounces 0, 1 and 3, to train "
            "models with and without multipath and compare them on the 'reality' suite.",
            scenarios=PAPER_SCENARIOS,
            variants={f"bounces_{b}": Physics(max_bounces=b) for b in (0, 1, 3)},
            frames=6_000,
        ),
        Suite(
            name="reality",
            description="Held-out stand-in for real data: unseen layouts, 6 secondary bounces, per-episode "
            "microphone position (0.3 mm), gain (1 dB) and delay (2 us) mismatch, air at 5-35 C (the "
            "beamformer assumes 343 m/s), 15-25 dB SNR, Gaussian LiDAR noise and dropouts.",
            scenarios=REALITY_SCENARIOS,
            variants={
                "": Physics(
                    max_bounces=6,
                    snr_db=(15.0, 25.0),
                    lidar_noise="gaussian",
                    lidar_noise_m=0.012,
                    lidar_dropout_probability=0.01,
                    temperature_c=(5.0, 35.0),
                    mic_position_sigma_m=3e-4,
                    mic_gain_sigma_db=1.0,
                    mic_delay_sigma_s=2e-6,
                )
            },
            frames=1_500,
        ),
        Suite(
            name="tiny",
            description="A few short drives in three small scenes: for tests and quick looks.",
            scenarios=(
                _scenario("room", "box_room", size=[[4.0, 5.0], [3.0, 4.0], 2.8]),
                _scenario("corridor", "corridor", reflectors="many", length=8.0, width=2.0),
                _scenario("random", "random_world", size=(6.0, 6.0, 2.8), wall_count=[1, 2], cylinder_count=[1, 3]),
            ),
            variants={"": Physics(ray_count=5_000)},
            frames=24,
            episode_frames=8,
        ),
    )
}


def load_suite(name_or_path: str | Path) -> Suite:
    """A named suite, or one read from a .toml/.json file.

    The file may name a `base` suite and override any of its fields; `physics` overrides every
    variant's physics; `scenarios` (a list of tables) and `variants` (tables of Physics fields)
    replace the base's. Example:

        base = "paper"
        frames = 2000
        [physics]
        max_bounces = 1
        [[scenarios]]
        name = "long_corridors"
        builder = "corridor"
        params = { reflectors = "many" }
        vary = { length = [20.0, 30.0] }
    """
    text = str(name_or_path)
    if text in SUITES:
        return SUITES[text]
    path = Path(text)
    if not path.suffix:
        raise ValueError(f"unknown suite {text!r}; named suites are {sorted(SUITES)}, or give a .toml/.json file")
    if not path.is_file():
        raise FileNotFoundError(f"suite file {path} does not exist")
    try:
        data = tomllib.loads(path.read_text()) if path.suffix == ".toml" else json.loads(path.read_text())
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"suite file {path} is not valid {path.suffix[1:].upper()}: {err}") from None
    base = SUITES.get(data.pop("base", None)) if "base" in data else None
    if base is None and "scenarios" not in data:
        raise ValueError(f"{path}: give `scenarios` or a `base` suite (one of {sorted(SUITES)})")
    fields = {f.name for f in dataclasses.fields(Suite)} | {"physics"}
    if unknown := set(data) - fields:
        raise ValueError(f"{path}: unknown keys {sorted(unknown)}; allowed: {sorted(fields)}")
    values = dataclasses.asdict(base) if base else {}
    values["scenarios"] = [Scenario(**s) for s in data.pop("scenarios", values.get("scenarios", []))]
    variants = data.pop("variants", None) or values.get("variants") or {"": {}}
    physics = data.pop("physics", {})
    values["variants"] = {
        name: Physics(**{**(dataclasses.asdict(p) if isinstance(p, Physics) else p), **physics})
        for name, p in variants.items()
    }
    values.update(data)
    values.setdefault("name", path.stem)
    values.setdefault("description", f"custom suite from {path.name}")
    values["scenarios"] = tuple(values["scenarios"])
    return Suite(**values)
