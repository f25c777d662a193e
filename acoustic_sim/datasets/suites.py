"""Scenario suites: which scenes, robot drives and sensor physics a generated dataset holds.

A suite is a list of scenario families (a scene builder with fixed and randomised arguments)
and one or more physics variants (the same scenes and drives rendered with different sensor
physics, e.g. max_bounces 0, 1 and 3 in the `ablation` suite). Suites are plain frozen
dataclasses; `load_suite` reads one from a TOML or JSON file that may start from a named suite.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import scenes
from clitools.outputs import check_name
from scenes.surfaces import SURFACE_CLASSES

from ..config import check_finite
from .mesh_scenarios import MESH_BUILDER, MESH_FIELDS, MeshFile, mesh_file
from .physics import Physics, draw_value, rig
from .suite_file import read_suite_file

DRIVE = {"speed_m_s": 0.3, "sensor_height_m": 0.3, "turn_rate_rad_s": 1.0}
"""A suite's drive settings and their defaults."""

__all__ = ["SUITES", "Physics", "Scenario", "Suite", "load_suite", "rig"]  # Physics and rig live in physics.py


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """One scenario family: a scene builder with fixed and randomised arguments, or a mesh file.

    Attributes:
        name: Identifier, unique within the suite; stored per frame.
        builder: Key of `scenes.BUILDERS` ("box_room", "corridor", "office", "random_world"), or
            "mesh" for the scene of `mesh` (then without params or vary: the file is the scene).
        params: Fixed builder arguments.
        vary: Randomised builder arguments, drawn per episode: [low, high] (uniform; integers
            if both ends are integers) or {"choice": [...]}. A list of [low, high] pairs
            varies a sequence argument (e.g. a room size) element by element; plain numbers in
            it stay fixed.
        weight: Share of the suite's episodes (relative).
        mesh: The mesh file of a "mesh" scenario (`mesh_scenarios.mesh_file` checks it), else None.
    """

    name: str
    builder: str
    params: dict = field(default_factory=dict)
    vary: dict = field(default_factory=dict)
    weight: float = 1.0
    mesh: MeshFile | None = None

    def __post_init__(self) -> None:
        if self.builder == MESH_BUILDER:
            if not isinstance(self.mesh, MeshFile):
                raise ValueError(f'scenario {self.name!r}: a mesh scenario needs its file: mesh = "building.obj"')
            if given := [k for k in ("params", "vary") if getattr(self, k)]:
                raise ValueError(
                    f"scenario {self.name!r}: {' and '.join(given)} {'apply' if len(given) > 1 else 'applies'} to "
                    "builders, not to a mesh file (its scene is the file, the same in every episode); drop them, give "
                    "more scenarios for more scenes, and draw the physics per episode with [physics] vary and surfaces"
                )
        elif self.mesh is not None:
            raise ValueError(f"scenario {self.name!r}: give a builder or a mesh, not both (builder {self.builder!r})")
        elif self.builder not in scenes.BUILDERS:
            raise ValueError(
                f"scenario {self.name!r}: unknown builder {self.builder!r}; use {sorted(scenes.BUILDERS)}, "
                'or give a mesh file (mesh = "building.obj")'
            )
        if not 0 < self.weight < np.inf:  # an infinite weight deals episodes by NaN shares
            raise ValueError(f"scenario {self.name!r}: weight must be a finite number > 0, got {self.weight}")
        for key, spec in self.vary.items():
            draw_value(np.random.default_rng(0), key, spec)  # validates the spec

    def scene_params(self, rng: np.random.Generator, seed: int) -> dict:
        """Builder arguments of one episode: fixed ones, drawn ones and the scene seed (a mesh
        scenario's: what its file is, by name and hash)."""
        out = self.mesh.to_json() if self.mesh else dict(self.params)
        for key, spec in sorted(self.vary.items()):
            out[key] = draw_value(rng, key, spec)
        out["seed"] = seed
        return out


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
        sensor_height_m: Sensor height above the floor [m].
        turn_rate_rad_s: Fastest turn on the spot [rad/s].
            These three may each be [low, high], drawn per episode (the same for every variant).
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
    speed_m_s: float | list[float] = 0.3
    sensor_height_m: float | list[float] = DRIVE["sensor_height_m"]
    turn_rate_rad_s: float | list[float] = DRIVE["turn_rate_rad_s"]
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
            if variant:
                check_name(variant, f"suite {self.name!r}: variant name")
        if self.frames < 1 or self.episode_frames < 1 or not self.dt_s > 0:
            raise ValueError(f"suite {self.name!r}: frames, episode_frames >= 1, dt_s > 0")
        for name, low in (("speed_m_s", 0.0), ("sensor_height_m", 0.0), ("turn_rate_rad_s", 1e-3)):
            spec = getattr(self, name)
            ends = [spec, spec] if np.ndim(spec) == 0 else spec
            draw_value(np.random.default_rng(0), name, list(ends), where=f"suite {self.name!r}: {name}")
            if min(ends) < low:
                raise ValueError(f"suite {self.name!r}: {name} must be >= {low}, got {spec}")

    def to_json(self) -> dict:
        out = dataclasses.asdict(self) | {"variants": {k: p.to_json() for k, p in self.variants.items()}}
        out["scenarios"] = [_scenario_json(s) for s in self.scenarios]
        for name, default in DRIVE.items():  # left out at their defaults, as suites before them had
            if out[name] == default:
                del out[name]
        if not out["settings"]:  # so that suites without settings keep the plan ids of earlier runs
            del out["settings"]
        return out


def _scenario_json(scenario: Scenario) -> dict:
    """A scenario as plans and manifests record it: a mesh by file name and hash, never its path;
    builders' without the `mesh` field, so that their suites keep the plan ids of earlier runs."""
    out = dataclasses.asdict(scenario)
    if scenario.mesh is None:
        del out["mesh"]
    else:
        out["mesh"] = scenario.mesh.to_json()
    return out


def mesh_files(suite: Suite) -> dict[str, MeshFile]:
    """The mesh file of each mesh scenario of `suite`, by scenario name."""
    return {s.name: s.mesh for s in suite.scenarios if s.mesh is not None}


def episode_drive(suite: dict, seed: int) -> dict:
    """Speed, sensor height and turn rate of one episode's drive: the suite's, drawn where it gives
    [low, high] (from the episode's seed, so every variant drives alike)."""
    rng = np.random.default_rng([seed, 5])
    drive = {}
    for name, default in DRIVE.items():
        spec = suite.get(name, default)
        drive[name] = draw_value(rng, name, spec) if isinstance(spec, list | tuple) else spec
    return drive


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
    _scenario("office_large", "office", clutter={"choice": ["medium", "high"]}, size=[[10.0, 12.0], [8.0, 9.0], 3.0]),
    _scenario("random_mixed", "random_world", size=[[9.0, 11.0], [9.0, 11.0], 2.8], object_scale=[0.7, 1.3]),
)

# Empty rooms with polygon floor plans, floor to ceiling 2.2-5 m, a fifth of them open to the sky.
POLYGON_SCENARIOS = tuple(
    _scenario(
        f"empty_{plan}",
        "polygon_room",
        plan=plan,
        height=[2.2, 5.0],
        ceiling={"choice": ["ceiling_tile"] * 4 + [None]},
    )
    for plan in scenes.FLOOR_PLANS
)

# Everything about the sensor and the surfaces that a real deployment could differ in, drawn per
# episode: emitter directivity (piston radius 1-20 mm) and offset, what walls, floor, ceiling and
# objects reflect and scatter, air temperature, SNR, microphone mismatch, LiDAR noise.
RANDOMISED_PHYSICS = dict(
    snr_db=(10.0, 35.0),
    temperature_c=(0.0, 35.0),
    mic_position_sigma_m=3e-4,
    mic_gain_sigma_db=1.0,
    mic_delay_sigma_s=2e-6,
    lidar_noise="gaussian",
    lidar_noise_m=0.012,
    lidar_dropout_probability=0.01,
    vary={"sonar.emitter_radius_m": [0.001, 0.02], "sonar.emitter_m": [[-0.03, 0.03], [-0.03, 0.03], [0.0, 0.08]]},
    surfaces={c: {"reflection": [0.5, 0.99], "scattering": [0.0, 0.5]} for c in SURFACE_CLASSES},
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
            name="randomised",
            description="Randomised physics for sim-to-real: the paper's cluttered scenarios and empty L, T, U, "
            "junction and hall rooms (2.2-5 m high, some open), with emitter directivity and offset, per-class "
            "wall/floor/ceiling/object reflection and scattering, air, SNR, microphone mismatch, sensor height "
            "(0.15-0.6 m), speed and turn rate drawn per episode; rendered with max_bounces 0, 1 and 3, and "
            "1-6 drawn per episode.",
            scenarios=(*PAPER_SCENARIOS, *(dataclasses.replace(s, weight=1.2) for s in POLYGON_SCENARIOS)),
            variants={
                **{f"bounces_{b}": Physics(max_bounces=b, **RANDOMISED_PHYSICS) for b in (0, 1, 3)},
                "bounces_1to6": Physics(
                    **RANDOMISED_PHYSICS | {"vary": RANDOMISED_PHYSICS["vary"] | {"tracer.max_bounces": [1, 6]}}
                ),
            },
            frames=12_500,
            speed_m_s=[0.2, 0.5],
            sensor_height_m=[0.15, 0.6],
            turn_rate_rad_s=[0.5, 1.5],
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
        [[scenarios]]             # a mesh file of your building, read from this file's folder
        name = "my_lab"
        mesh = "lab.obj"
        materials = "lab_materials.toml"   # optional: [materials] file name or glob -> ours
        up = "z"                  # optional: auto (y for glTF, z otherwise), z or y
        units = "m"               # optional: auto (metres, checked), m, cm, mm, in or ft
    """
    text = str(name_or_path)
    if text in SUITES:
        return SUITES[text]
    path = Path(text)
    if not path.suffix:
        raise ValueError(f"unknown suite {text!r}; named suites are {sorted(SUITES)}, or give a .toml/.json file")
    data = read_suite_file(path, sorted(SUITES))  # every key known, every value of its type, or refused by name
    base = SUITES[data.pop("base")] if "base" in data else None
    if base is None and "scenarios" not in data:
        raise ValueError(f"{path}: give `scenarios` or a `base` suite (one of {sorted(SUITES)})")
    for key in ("frames", "episode_frames"):  # whole numbers, also when written 1e4
        if key in data:
            data[key] = int(data[key])
    values = dataclasses.asdict(base) if base else {}
    scenarios = data.pop("scenarios", None)
    if scenarios is None:
        values["scenarios"] = [Scenario(**s) for s in values.get("scenarios", [])]
    else:
        values["scenarios"] = [
            _file_scenario(s, path.parent, f"{path}: scenarios[{i}] ({s['name']!r})") for i, s in enumerate(scenarios)
        ]
    variants = data.pop("variants", None) or values.get("variants") or {"": {}}
    physics = data.pop("physics", {})
    values["variants"] = {
        name: _built(
            Physics,
            {**(dataclasses.asdict(p) if isinstance(p, Physics) else p), **physics},
            f"{path}: {_variant_where(name, physics)}",
        )
        for name, p in variants.items()
    }
    if base and "description" not in data:  # the base's prose may name settings this file changes
        data["description"] = f"custom suite from {path.name}, based on `{base.name}` (the rig as simulated is below)"
    if base:  # named after the file unless it says otherwise: manifests and cards must not call it the base
        data.setdefault("name", path.stem)
    values.update(data)
    values.setdefault("name", path.stem)
    values.setdefault("description", f"custom suite from {path.name}")
    values["scenarios"] = tuple(values["scenarios"])
    return _built(Suite, values, str(path))


def _file_scenario(table: dict, folder: Path, where: str) -> Scenario:
    """A scenario of a suite file; one naming a mesh file (paths relative to `folder`, the suite
    file's) has it checked and hashed now (`mesh_scenarios.mesh_file`)."""
    if not any(k in table for k in MESH_FIELDS):
        return _built(Scenario, table, where)
    if "mesh" not in table:
        given = ", ".join(k for k in MESH_FIELDS if k in table)
        raise ValueError(f'{where}: {given} describe a mesh file; give it too (mesh = "building.obj") or drop them')
    if table.get("builder", MESH_BUILDER) != MESH_BUILDER:
        raise ValueError(f"{where}: give a builder or a mesh, not both (builder {table['builder']!r})")
    fields = {k: v for k, v in table.items() if k not in MESH_FIELDS}
    if any(fields.get(k) for k in ("params", "vary")):  # refused by Scenario before the mesh is loaded
        return _built(Scenario, fields | {"builder": MESH_BUILDER, "mesh": MeshFile(path="", sha256="")}, where)
    return _built(Scenario, fields | {"builder": MESH_BUILDER, "mesh": mesh_file(table, folder, where)}, where)


def _variant_where(name: str, physics: dict) -> str:
    """Where a variant's physics comes from, for a message: its table, and [physics] on top."""
    table = f"variants.{name}" if name else "the suite's variant"
    return f"{table} with [physics]" if physics else table


def _built(cls, fields: dict, where: str):
    """`cls(**fields)`, its refusal prefixed with `where` (the file and the table it came from)."""
    try:
        return cls(**fields)
    except TypeError as err:  # a required field missing, or a value its checks cannot compare
        raise ValueError(f"{where}: {err}") from None
    except ValueError as err:
        raise type(err)(f"{where}: {err}") from None
