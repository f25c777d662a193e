"""Which BVH the scenes' Warp meshes are built with: LiDAR rays/s and sonar energyscapes/s on the
reference office for each (constructor, leaf size), in one job.

    python benchmarks/bench_bvh.py --device cuda:0 --variants sah:4,sah:2,sah:1,cubql:0

Every ray query of the LiDAR and of the sonar's tracer walks the mesh's BVH, so its build decides
much of their speed (issue 42: the trace is 60 % of `Sonar.simulate` at 100k rays; the LiDAR must
stay 1.1x ahead of a bare Warp kernel). Warp's documentation advises leaves of one triangle for
ray queries; the package builds SAH trees with Warp's default of four. For each variant the
office is built again (`acoustic_sim.engine.scene.BVH_CONSTRUCTOR` / `BVH_LEAF_SIZE`), then timed:
2D scans (1,081 beams) and 3D scans (64 x 1,024) device-resident as bench_lidar's, and
`Sonar.simulate` end to end at 3 bounces at each --rays on a drive of --batches batches of 256
pings. Rounds turn the variants' order (a b c, b c a, ...); figures are medians over rounds. Every
variant's LiDAR ranges are checked against the first's (a BVH changes speed, not hits).
Writes bvh_<device>.json and .md under --out.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import acoustic_sim as sim  # noqa: E402
from acoustic_sim.engine import scene as scene_module  # noqa: E402
from benchmarks.bench_lidar import load_office, median_time, random_poses  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402


def built(variant: str):
    """The office with a fresh Warp mesh built as `variant` ("constructor:leaf size"), and its build time."""
    constructor, leaf = variant.split(":")
    scene_module.BVH_CONSTRUCTOR, scene_module.BVH_LEAF_SIZE = constructor, int(leaf)
    scene_module.LIDAR_BVH_LEAF_SIZE = int(leaf)  # the LiDAR casts through a tree of its own
    office = load_office()  # a new Scene object: nothing cached for it
    return office


def time_variant(variant: str, device, lidar_poses: dict, drive: np.ndarray, rays: list[int]) -> dict:
    office = built(variant)
    t0 = time.perf_counter()
    scene_module.warp_scene(office, device)
    wp.synchronize_device(device)
    out = {"build_s": time.perf_counter() - t0}
    for name, (lidar, poses) in lidar_poses.items():
        _, seconds = median_time(lambda lidar=lidar, poses=poses: lidar.cast(office, poses), 5, device)
        out[name] = {"mrays_per_s": len(poses) * lidar.beam_count / seconds / 1e6}
        out[name]["ranges"] = lidar.scan(office, poses[:50])
    for count in rays:
        sonar = sim.Sonar(sim.SonarConfig.ertis(), max_bounces=3, ray_count=count, device=device)
        sonar.simulate(office, drive[:256], batch=256)  # kernels loaded, buffers sized
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        sonar.simulate(office, drive, batch=256)
        wp.synchronize_device(device)
        out[f"sonar_{count}"] = {"energyscapes_per_s": len(drive) / (time.perf_counter() - t0)}
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--variants", default="sah:4,sah:2,sah:1,cubql:0")
    parser.add_argument("--rays", default="20000,100000", help="sonar rays per ping, comma-separated")
    parser.add_argument("--batches", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--scale", type=float, default=1.0, help="fraction of the LiDAR poses and sonar drive")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    variants = args.variants.split(",")
    rays = [int(r) for r in args.rays.split(",")]
    lidar_poses = {
        "lidar2d": (
            sim.Lidar(sim.LidarConfig.hokuyo_ust20lx(range_min_m=0.0, range_max_m=30.0), device=device),
            random_poses(max(1, int(20000 * args.scale)), 1),
        ),
        "lidar3d": (
            sim.Lidar(sim.LidarConfig.multibeam_64x1024(range_min_m=0.0, range_max_m=30.0), device=device),
            random_poses(max(1, int(300 * args.scale)), 2),
        ),
    }
    drive = random_poses(max(1, int(256 * args.batches * args.scale)), 3)
    rounds = {v: [] for v in variants}
    for r in range(args.rounds):
        order = variants[r % len(variants) :] + variants[: r % len(variants)]
        for variant in order:
            rounds[variant].append(time_variant(variant, device, lidar_poses, drive, rays))
            run = rounds[variant][-1]
            speeds = [f"{k} {next(iter(v.values())):,.1f}" for k, v in run.items() if isinstance(v, dict)]
            print(f"round {r}, {variant}: build {run['build_s']:.2f} s, " + ", ".join(speeds), flush=True)
    keys = ["lidar2d", "lidar3d"] + [f"sonar_{c}" for c in rays]
    res = {"device": str(device), "device_name": device.name if device.is_cuda else "CPU", "warp": wp.__version__}
    res |= {"date": time.strftime("%Y-%m-%d"), "rounds": args.rounds, "sonar_pings": len(drive), "variants": {}}
    reference = rounds[variants[0]][0]
    for variant, runs in rounds.items():
        row = {"build_s": float(np.median([run["build_s"] for run in runs]))}
        for key in keys:
            unit = "mrays_per_s" if key.startswith("lidar") else "energyscapes_per_s"
            row[key] = float(np.median([run[key][unit] for run in runs]))
        for name in ("lidar2d", "lidar3d"):
            a, b = reference[name]["ranges"], runs[0][name]["ranges"]
            both = np.isfinite(a) & np.isfinite(b)
            row[f"{name}_same_hits"] = bool((np.isfinite(a) == np.isfinite(b)).all())
            row[f"{name}_max_range_difference_m"] = float(np.abs(a[both] - b[both]).max(initial=0.0))
        res["variants"][variant] = row
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"bvh_{'cuda' if device.is_cuda else 'cpu'}"
    res = write_json(out / f"{stem}.json", res, device=str(device))
    first = res["variants"][variants[0]]
    lines = [
        f"# The office's BVH: speed per (constructor, leaf size) on {res['device_name']} ({res['device']})",
        "",
        f"Medians of {args.rounds} rounds in turning order; LiDAR device-resident [M rays/s]; sonar end to end at 3 "
        f"bounces, {len(drive)} pings [energyscapes/s]; in brackets the ratio to {variants[0]}.",
        "",
        "| constructor:leaf | build [ms] | " + " | ".join(keys) + " | same hits (2D, 3D) |",
        "|---|---|" + "---|" * len(keys) + "---|",
    ]
    for variant, row in res["variants"].items():
        cells = [f"{row[k]:,.1f} ({row[k] / first[k]:.2f}x)" for k in keys]
        same = f"{row['lidar2d_same_hits']}, {row['lidar3d_same_hits']}"
        lines.append(f"| {variant} | {1e3 * row['build_s']:.0f} | " + " | ".join(cells) + f" | {same} |")
    lines += ["", provenance_line(res["provenance"])]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
