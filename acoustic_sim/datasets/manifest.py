"""What a finished dataset says about itself: manifest.json (shards, scenarios, seeds, counts),
README.md (the dataset card) and card.png (example frames). The counts and the card's layout are
every dataset's; what it was made with (rig, physics, another engine) its renderer says (`About`)."""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clitools import counted

from .plan import ShardTask
from .shards import FORMAT, FORMAT_VERSION, energyscapes


@dataclass(frozen=True)
class FactTable:
    """A table of a dataset card: the sentence above it, its (name, value) rows and its column heads."""

    caption: str
    rows: tuple[tuple[str, str], ...]
    columns: tuple[str, str] = ("", "")


@dataclass(frozen=True)
class About:
    """What a renderer says of one variant's dataset: fields for manifest.json (a `description`
    at least) and the tables of facts on its card."""

    fields: dict
    tables: tuple[FactTable, ...] = ()


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


def write_manifest(folder: Path, tasks: list[ShardTask], about: About) -> Path:
    """manifest.json (shards, scenarios, seeds, counts, and `about`'s fields) and the dataset card
    of one variant (its tasks, all written)."""
    entries = [shard_entry(t) for t in tasks]
    scenarios = Counter()
    for e in entries:
        scenarios.update(e["scenarios"])
    manifest = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "plan_id": tasks[0].plan_id,
        "suite": tasks[0].suite["name"],
        "variant": tasks[0].variant,
        "seed": tasks[0].seed,
        "frames": sum(e["frames"] for e in entries),
        "episodes": sum(len(e["episodes"]) for e in entries),
        "scenarios": dict(scenarios),
    }
    manifest |= about.fields | {"shards": entries}
    path = folder / "manifest.json"
    tmp = path.with_name("manifest.json.tmp")
    tmp.write_text(json.dumps(manifest, indent=1))
    tmp.replace(path)
    write_card(folder, manifest, about.tables)
    return path


def write_card(folder: Path, manifest: dict, tables: tuple[FactTable, ...] = ()) -> None:
    """README.md and card.png: what the dataset holds, how to read it, example frames."""
    import h5py

    from ..config import PolarGrid, level_index
    from ..render import render_elevations, render_examples

    examples, stack, seen = [], None, set()
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
                (energy,), elevations = energyscapes(f, slice(k, k + 1))
                lidar, level = f["lidar/image"][k], level_index(elevations)
                if len(elevations) > 1:
                    name = f"{name} at {elevations[level]:g} deg elevation"
                    if stack is None:  # the first example at every elevation
                        stack = (f"frame {k}", energy, lidar, elevations)
                examples.append((f"{name}, frame {k}", energy[level], lidar))
    grid = PolarGrid(**manifest["sim"]["processing"]["grid"])  # the run's grid
    render_examples(examples, grid, folder / "card.png")
    if stack is not None:
        render_elevations(*stack, grid, folder / "card_elevations.png")
    title = manifest["suite"] + (f" / {manifest['variant']}" if manifest["variant"] else "")
    rows = "\n".join(f"| {name} | {count:,} |" for name, count in manifest["scenarios"].items())
    facts = "".join(_table_text(table) for table in tables)
    counts = f"{counted(manifest['frames'], 'frame')} in {counted(manifest['episodes'], 'episode')} (robot drives), "
    counts += counted(len(manifest["shards"]), "shard")
    stack_text = (
        "\nOne frame at each of its elevations, each in dB below its own peak (the level slice is the LiDAR's "
        "plane; floor echoes lie below, the ceiling above):\n\n![one frame at every elevation](card_elevations.png)\n"
        if stack is not None
        else ""
    )
    text = f"""# Dataset: {title}

{manifest["description"]}

{counts},
seed {manifest["seed"]}, {FORMAT} format version {FORMAT_VERSION}. Made by `python -m acoustic_sim generate`;
rerunning the same command resumes or verifies it.

![example frames: energyscape (dB) with the LiDAR label on top](card.png)
{stack_text}
| scenario | frames |
|---|---|
{rows}
{facts}
Each `shard-*.h5` holds `energyscape` (frame, elevation, range, azimuth) float16, `lidar/ranges`,
`lidar/image` (the label, frame x range x azimuth), `pose`, `time`, `episode`, `scenario`, and the
axes `elevation_deg`, `range_m`, `azimuth_rad`; its attributes hold every config as JSON and one
record per episode (its scene, seed and draws). Read it with h5py:

```python
import h5py
with h5py.File("{manifest["shards"][0]["file"]}") as f:
    energyscape, label = f["energyscape"][:10], f["lidar/image"][:10]
```
"""
    (folder / "README.md").write_text(text)


def _table_text(table: FactTable) -> str:
    head = "|" + "|".join(f" {c} " if c else " " for c in table.columns) + "|"
    rows = "".join(f"| {name} | {value} |\n" for name, value in table.rows)
    return f"\n{table.caption}\n\n{head}\n|---|---|\n{rows}"


def rig_facts(sim: dict, settings: list[str]) -> tuple[tuple[str, str], ...]:
    """Our engine's rig in headline numbers for a dataset card, read from the rig itself (`sim`:
    `SimConfig.to_dict()`; never from a suite's prose): the tracer's, then `sensor_facts`."""
    tracer = sim["tracer"]
    facts = [
        ("secondary bounces (max_bounces)", tracer["max_bounces"]),
        ("rays per ping", f"{tracer['ray_count']:,}"),
        ("edge and rough-surface scattering", "on" if tracer["scattering"] else "off"),
        *sensor_facts(sim),
    ]
    if settings:
        facts.append(("settings given", ", ".join(f"`{s}`" for s in settings)))
    return tuple((k, str(v)) for k, v in facts)


def sensor_facts(sim: dict) -> tuple[tuple[str, str], ...]:
    """The call, the grid and the LiDAR of a rig (`sim`, as `SimConfig.to_dict()` or its sonar,
    lidar and processing alone) in headline numbers for a dataset card."""
    chirp, grid = sim["sonar"]["chirp"], sim["processing"]["grid"]
    facts = [
        (
            "call",
            f"{chirp['start_frequency_hz'] / 1e3:g} -> {chirp['stop_frequency_hz'] / 1e3:g} kHz, "
            f"{chirp['duration_s'] * 1e3:g} ms, {chirp['sweep']}, sampled at {chirp['sample_rate_hz'] / 1e3:g} kHz",
        ),
        (
            "grid",
            f"{grid['range_min_m']:g}-{grid['range_max_m']:g} m in {grid['range_bin_m']:g} m bins x "
            f"{grid['azimuth_min_deg']:g}..{grid['azimuth_max_deg']:g} deg in {grid['azimuth_step_deg']:g} deg",
        ),
        ("LiDAR", f"{sim['lidar']['azimuth_count']:,} beams per scan, noise {sim['lidar']['noise']}"),
    ]
    return tuple((k, str(v)) for k, v in facts)
