"""A physics variant of a suite: the sensor physics its episodes simulate, and the per-episode
draws (SNR, air temperature, channel mismatch, and any sonar or tracer field by its path in the
config tree), checked against the configs' own limits."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field

import numpy as np

from scenes.surfaces import SURFACE_CLASSES

from ..config import (
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
from ..settings import apply_settings


def draw_value(rng: np.random.Generator, key: str, spec, *, where: str | None = None):
    """A value drawn by `spec` ([low, high], {"choice": [...]}, or a list of them and numbers)
    for `key`; ValueError naming `where` (default: vary.KEY) for a spec that draws nothing real."""
    where = where or f"vary.{key}"
    if isinstance(spec, dict):
        if set(spec) != {"choice"} or not spec["choice"]:
            raise ValueError(f"{where}: a dict must be {{'choice': [values]}}")
        return spec["choice"][int(rng.integers(len(spec["choice"])))]
    if isinstance(spec, list | tuple) and any(isinstance(s, list | tuple | dict) for s in spec):
        # Element by element; plain numbers stay fixed (e.g. a room size with a fixed height).
        return [draw_value(rng, key, s, where=where) if isinstance(s, list | tuple | dict) else s for s in spec]
    numbers = isinstance(spec, list | tuple) and all(_is_number(v) for v in spec)
    if not (numbers and len(spec) == 2):
        raise ValueError(f"{where}: expected [low, high], {{'choice': [...]}} or a list of [low, high], got {spec!r}")
    low, high = spec
    if not (np.isfinite([low, high]).all() and low <= high):
        raise ValueError(f"{where}: expected [low, high] of finite numbers, low <= high, got [{low}, {high}]")
    if isinstance(low, int) and isinstance(high, int):
        return int(rng.integers(low, high + 1))
    return float(rng.uniform(low, high))


def _is_number(value) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)


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
        air_absorption: False: the air absorbs nothing (ISO 9613-1 left out), as in recordings
            made by an engine that leaves it out (a fit `calibrate --no-air-absorption` made).
        mic_position_sigma_m, mic_gain_sigma_db, mic_delay_sigma_s: Channel mismatch of the
            simulated array per episode (the beamformer assumes the nominal array).
        mic_gain_db, mic_delay_s: Each microphone's gain [dB] and extra delay [s] (a fit's,
            `calibrate`): the simulated array's, around which the sigmas draw; empty: 0 dB, 0 s.
        vary: Rig fields drawn per episode, by dotted path under `sonar` or `tracer`, each as
            [low, high] (integers if both ends are), {"choice": [...]} or, for a sequence field,
            a list of those and fixed numbers: e.g. {"sonar.emitter_radius_m": [0.0, 0.02],
            "tracer.max_bounces": [1, 6]}; a drawn tracer field replaces the Physics field of
            that name for the episode. Limits are the configs' own: both ends of every range
            (every choice) are checked when the variant is made. Drawn values are recorded per
            episode.
        surfaces: Acoustics of each surface class drawn per episode, as energy fractions in
            0..1: {"walls": {"reflection": [0.5, 0.99], "scattering": [0.0, 0.5]}, "floor": ...,
            "ceiling": ..., "objects": ...}; `scenes.surfaces` says which faces a class holds.
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
    air_absorption: bool = True
    mic_position_sigma_m: float = 0.0
    mic_gain_sigma_db: float = 0.0
    mic_delay_sigma_s: float = 0.0
    mic_gain_db: tuple[float, ...] = ()
    mic_delay_s: tuple[float, ...] = ()
    vary: dict = field(default_factory=dict)
    surfaces: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "snr_db", _pair(self.snr_db, "snr_db"))
        object.__setattr__(self, "temperature_c", _pair(self.temperature_c, "temperature_c"))
        for name in ("mic_gain_db", "mic_delay_s"):
            value = getattr(self, name)
            if np.ndim(value) != 1 or not all(_is_number(v) for v in value):
                raise ValueError(f"Physics.{name} must be a list of numbers, one per microphone, got {value!r}")
            object.__setattr__(self, name, tuple(float(v) for v in value))
        if self.mic_gain_db and self.mic_delay_s and len(self.mic_gain_db) != len(self.mic_delay_s):
            raise ValueError("Physics.mic_gain_db and mic_delay_s must give one value per microphone each")
        check_finite(self)
        self.tracer()  # refuses max_bounces outside 0..MAX_BOUNCES, ray_count < 1, edge_width_m < 0
        for name in ("sonar_noise", "lidar_noise"):
            if getattr(self, name) not in NOISE_KINDS:
                raise ValueError(f"Physics.{name} must be one of {NOISE_KINDS}, got {getattr(self, name)!r}")
        sigmas = (self.mic_position_sigma_m, self.mic_gain_sigma_db, self.mic_delay_sigma_s, self.lidar_noise_m)
        if min(sigmas) < 0:
            raise ValueError("Physics: noise sizes and mismatch sigmas must be >= 0")
        nominal = rig(self) if self.vary else None
        for key, spec in self.vary.items():
            if key in DRAWN_FIELDS:
                raise ValueError(f"Physics.vary {key!r}: Physics.{DRAWN_FIELDS[key]} draws it")
            if key.split(".")[0] not in VARYING_SECTIONS or "." not in key:
                raise ValueError(f"Physics.vary {key!r}: only fields under {' or '.join(VARYING_SECTIONS)} vary")
            draw_value(np.random.default_rng(0), key, spec)  # validates the spec
            for end in _extremes(spec):
                _drawn_rig(nominal, {key: end})  # refuses a value its config refuses, naming the key
        for surface, acoustics in self.surfaces.items():
            if surface not in SURFACE_CLASSES or not set(acoustics) <= {"reflection", "scattering"}:
                raise ValueError(
                    f"Physics.surfaces {surface!r}: classes are {SURFACE_CLASSES}, each with reflection "
                    f"and/or scattering ranges, got {acoustics!r}"
                )
            for name, spec in acoustics.items():
                draw_value(np.random.default_rng(0), f"surfaces.{surface}.{name}", spec)
                if not all(0.0 <= end <= 1.0 for end in _extremes(spec)):
                    raise ValueError(f"Physics.surfaces {surface}.{name}: energy fractions lie in 0..1, got {spec}")

    def draw(self, nominal: SimConfig, rng: np.random.Generator) -> tuple[SimConfig, dict]:
        """`nominal` with this variant's `vary` drawn from `rng` (keys in sorted order) ->
        (the episode's rig, the drawn values)."""
        draws = {key: draw_value(rng, key, self.vary[key]) for key in sorted(self.vary)}
        return _drawn_rig(nominal, draws), draws

    def draw_surfaces(self, rng: np.random.Generator) -> dict:
        """One episode's acoustics per surface class, drawn from `rng` in sorted order."""
        return {
            surface: {name: draw_value(rng, name, spec) for name, spec in sorted(self.surfaces[surface].items())}
            for surface in sorted(self.surfaces)
        }

    def to_json(self) -> dict:
        out = dataclasses.asdict(self)
        for name in ("vary", "surfaces", "mic_gain_db", "mic_delay_s"):  # left out when empty: shards stay lean
            if not out[name]:
                del out[name]
        if self.air_absorption:  # named only when off: the plans (and plan ids) of absorbing air stay as they were
            del out["air_absorption"]
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
