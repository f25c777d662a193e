"""Threads per block of the ray-walking kernels: LiDAR rays/s and sonar energyscapes/s on the office
for each block size, in one job.

    python benchmarks/bench_block_sizes.py --device cuda:0 --blocks 64,128,256

Warp launches 256 threads a block unless told otherwise. A BVH walk takes a different number of
steps for every ray, so a block of rays finishes only when its slowest warp does; smaller blocks let
an SM start the next block sooner. This sweeps the LiDAR's scan kernel (`lidar.SCAN_BLOCK_DIM`:
2D scans of 1,081 beams and 3D scans of 64 x 1,024, device-resident as bench_lidar's) and the sonar
tracer's ray kernel (`path_stages.RAY_BLOCK_DIM`: `Sonar.simulate` end to end at 3 bounces on 8
batches of 256 pings, at each --rays). Rounds repeat the sweep in the same order (the figures are
medians over rounds); the package's own values are what its modules hold when the script starts.
Writes block_sizes_<device>.json and .md under --out.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import acoustic_sim as sim  # noqa: E402
from acoustic_sim.engine import lidar as lidar_module  # noqa: E402
from acoustic_sim.engine import path_stages  # noqa: E402
from benchmarks.bench_lidar import load_office, median_time, random_poses  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--blocks", default="64,128,256")
    parser.add_argument("--rays", default="20000,100000", help="sonar rays per ping, comma-separated")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)
    wp.config.quiet = True
    warnings.simplefilter("ignore")  # the office's random poses: some stand inside furniture
    device = wp.get_device(args.device)
    blocks = [int(b) for b in args.blocks.split(",")]
    package = {"lidar": lidar_module.SCAN_BLOCK_DIM, "sonar": path_stages.RAY_BLOCK_DIM}
    office = load_office()
    scans = {
        "lidar2d": (sim.LidarConfig.hokuyo_ust20lx(range_min_m=0.0, range_max_m=30.0), 20000),
        "lidar3d": (sim.LidarConfig.multibeam_64x1024(range_min_m=0.0, range_max_m=30.0), 300),
    }
    drive = random_poses(2048, 3)
    runs: dict[str, dict[int, list[float]]] = {}
    for _ in range(args.rounds):
        for name, (config, count) in scans.items():
            lidar, poses = sim.Lidar(config, device=device), random_poses(count, 1)
            for block in blocks:
                lidar_module.SCAN_BLOCK_DIM = block
                _, seconds = median_time(lambda lidar=lidar, poses=poses: lidar.cast(office, poses), 5, device)
                runs.setdefault(name, {}).setdefault(block, []).append(count * lidar.beam_count / seconds / 1e6)
        for rays in map(int, args.rays.split(",")):
            sonar = sim.Sonar(sim.SonarConfig.ertis(), max_bounces=3, ray_count=rays, device=device)
            for block in blocks:
                path_stages.RAY_BLOCK_DIM = block
                sonar.simulate(office, drive[:256], batch=256)  # this block size's kernel loaded
                wp.synchronize_device(device)
                t0 = time.perf_counter()
                sonar.simulate(office, drive, batch=256)
                wp.synchronize_device(device)
                runs.setdefault(f"sonar_{rays}", {}).setdefault(block, []).append(
                    len(drive) / (time.perf_counter() - t0)
                )
        print({k: {b: round(v[-1], 1) for b, v in r.items()} for k, r in runs.items()}, flush=True)
    lidar_module.SCAN_BLOCK_DIM, path_stages.RAY_BLOCK_DIM = package["lidar"], package["sonar"]
    res = {"device": str(device), "device_name": device.name if device.is_cuda else "CPU", "warp": wp.__version__}
    res |= {"date": time.strftime("%Y-%m-%d"), "rounds": args.rounds, "package_blocks": package}
    res["medians"] = {name: {str(b): float(np.median(v)) for b, v in r.items()} for name, r in runs.items()}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"block_sizes_{'cuda' if device.is_cuda else 'cpu'}"
    res = write_json(out / f"{stem}.json", res, device=str(device))
    lines = [
        f"# Threads per block of the ray-walking kernels on {res['device_name']} ({res['device']})",
        "",
        f"Medians of {args.rounds} rounds; LiDAR device-resident [M rays/s], sonar end to end at 3 bounces, "
        f"{len(drive)} pings [energyscapes/s]; in brackets the ratio to {blocks[-1]} threads. The package "
        f"launches the LiDAR in blocks of {package['lidar']}, the tracer's rays in blocks of {package['sonar']}.",
        "",
        "| kernel, workload | " + " | ".join(f"{b} threads" for b in blocks) + " |",
        "|---|" + "---|" * len(blocks),
    ]
    for name, medians in res["medians"].items():
        last = medians[str(blocks[-1])]
        lines.append(
            f"| {name} | "
            + " | ".join(f"{medians[str(b)]:,.1f} ({medians[str(b)] / last:.2f}x)" for b in blocks)
            + " |"
        )
    lines += ["", provenance_line(res["provenance"])]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
