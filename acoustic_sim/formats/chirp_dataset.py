"""The dataset folder a CHIRP recording becomes on import (`chirp.import_chirp`): one shard per
episode, a manifest and a card, from pings already processed."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..datasets.shards import FORMAT, FORMAT_VERSION, ShardFrames, write_shard


@dataclass(frozen=True)
class ImportedPings:
    """Every ping of a recording as our shards hold it (first axis: ping)."""

    stamps: np.ndarray  # Unix time [s], float64
    energyscape: np.ndarray  # float16 (pings, E, R, A)
    elevation_deg: np.ndarray  # the E images' elevations [deg], float64 (E,)
    lidar_ranges: np.ndarray  # [m] float32 (pings, beams), inf = no return
    lidar_image: np.ndarray  # the label (pings, R, A)
    pose: np.ndarray  # sonar-to-odom (pings, 4, 4)
    episode: np.ndarray  # int64, from 0


def write_shards(out: Path, pings: ImportedPings, grid, config: dict, *, plan_id: str, scenario: str) -> list[dict]:
    """One shard per episode, times from its first ping; returns the manifest's shard entries."""
    from .. import __version__

    entries = []
    for k in range(pings.episode[-1] + 1):
        frames = np.flatnonzero(pings.episode == k)
        shard = ShardFrames(
            energyscape=[pings.energyscape[frames]],
            lidar_ranges=[pings.lidar_ranges[frames]],
            lidar_image=[pings.lidar_image[frames]],
            pose=[pings.pose[frames]],
            time=[pings.stamps[frames] - pings.stamps[frames[0]]],
            episode=[np.full(len(frames), k)],
            scenario=[np.zeros(len(frames))],
        )
        record = {"index": k, "frames": len(frames), "start_unix_s": float(pings.stamps[frames[0]])}
        attrs = {
            "suite": "chirp",
            "variant": "",
            "shard": k,
            "plan_id": plan_id,
            "package_version": __version__,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "config": config,
            "episodes": [record],
            "scenarios": [scenario],
        }
        file = out / f"shard-{k:05d}.h5"
        write_shard(
            file,
            shard,
            attrs=attrs,
            range_m=grid.range_m,
            azimuth_rad=grid.azimuth_rad,
            elevation_deg=pings.elevation_deg,
        )
        entries.append({"file": file.name, "frames": len(frames), "episodes": [k], "bytes": file.stat().st_size})
    return entries


def write_manifest(
    out: Path, entries: list[dict], config: dict, *, plan_id: str, scenario: str, lidar: str | None
) -> None:
    """manifest.json: the dataset's shards, where its pings came from and how they were imported."""
    source = config["source"]
    manifest = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "plan_id": plan_id,
        "suite": "chirp",
        "variant": "",
        "description": f"the CHIRP recording {source['file']}, imported",
        "frames": source["pings"],
        "episodes": len(entries),
        "scenarios": {scenario: source["pings"]},
        "source": source,
        "import": config["import"] | {"lidar": lidar, "poses": config["poses"]},
        "sim": config["sim"],
        "shards": entries,
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1, default=float))


def write_card(
    out: Path, pings: ImportedPings, grid, config: dict, *, lidar: str | None, microphones: int, rate_hz: float
) -> None:
    """card.png (three pings at the level elevation, with their labels), for several elevations
    card_elevations.png (the middle ping at each, highest first), and a README.md that says what
    was imported how."""
    from ..config import level_index
    from ..render import render_elevations, render_examples

    count, options, elevations = len(pings.stamps), config["import"], pings.elevation_deg
    level = level_index(elevations)  # the LiDAR's plane
    at = f" at {elevations[level]:g} deg" if len(elevations) > 1 else ""
    shown = [
        (f"ping {i}{at}", pings.energyscape[i, level], pings.lidar_image[i])
        for i in np.unique(np.linspace(0, count - 1, 3).round().astype(int))
    ]
    render_examples(shown, grid, out / "card.png")
    stack = ""
    if len(elevations) > 1:
        middle = count // 2
        render_elevations(
            f"ping {middle}",
            pings.energyscape[middle],
            pings.lidar_image[middle],
            elevations,
            grid,
            out / "card_elevations.png",
        )
        stack = (
            f"\nEach ping is imaged at {len(elevations)} elevations ({', '.join(f'{e:g}' for e in elevations)} deg; "
            "`elevation_deg` in each shard); one ping at each, highest first:\n\n"
            "![one ping at every elevation](card_elevations.png)\n"
        )
    returns = np.isfinite(pings.lidar_ranges).sum(axis=1)
    (out / "README.md").write_text(
        f"# Dataset: the CHIRP recording {config['source']['file']}\n\n{count:,} pings in {pings.episode[-1] + 1} "
        f"episodes (a pause over {options['episode_gap_s']:g} s starts one), imported by `python -m acoustic_sim "
        f"import --format chirp`: energyscapes by our processing with the file's {microphones} microphones at "
        f"{rate_hz / 1e3:g} kHz and our call; LiDAR labels from the points of {lidar or 'no LiDAR'} within "
        f"{options['plane_tolerance_m']:g} m of the sonar's plane ({returns.mean():.0f} returns per scan on average); "
        f"poses: {config['poses']}.\n\n"
        f"![pings: energyscape (dB){at} with the LiDAR label on top](card.png)\n{stack}"
    )
