"""Dataset generation throughput: frames/s of `generate` for a suite, on a device, end to end.

    python benchmarks/bench_generate.py --device cpu --suite paper --frames 300 --workers 1,2
    python benchmarks/bench_generate.py --device cuda:0 --suite paper --frames 12500 --workers 1,4,8

Writes benchmarks/results/generate_<cpu|cuda>.json and .md. A short warm-up run first loads (or
compiles) every Warp kernel, reported apart; then, for each worker count, fresh datasets are
written into a temporary folder (scenes, drives, LiDAR, sonar, HDF5 shards with compression,
manifest and card) with each worker's parts in turn and overlapped (`generate(overlap=...)`), and
where the time goes (`seconds_by_part`) beside the rate the simulator alone allows.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acoustic_sim.generate import PARTS, generate  # noqa: E402
from acoustic_sim.suites import load_suite  # noqa: E402


def timed_runs(suite, device, tmp: Path, args, workers: int, overlap: bool) -> dict:
    """Median seconds of `repeats` fresh runs, and the time by part of the median run."""
    runs = []
    for r in range(args.repeats):
        folder = tmp / f"w{workers}_{'overlap' if overlap else 'in_turn'}_{r}"
        summary = generate(
            suite,
            folder,
            frames=args.frames,
            shards=args.shards,
            device=str(device),
            workers=workers,
            progress=False,
            overlap=overlap,
        )
        summary["bytes"] = sum(p.stat().st_size for p in folder.rglob("*.h5"))
        runs.append(summary)
        shutil.rmtree(folder)
    median = sorted(runs, key=lambda s: s["seconds"])[len(runs) // 2]
    parts = median["seconds_by_part"]
    return {
        "workers": workers,
        "overlap": overlap,
        "seconds": [s["seconds"] for s in runs],
        "median_s": median["seconds"],
        "frames_per_s": median["frames"] / median["seconds"],
        "seconds_by_part": parts,
        # The device work alone: frames over the LiDAR and sonar time of one process (`Sonar.simulate`'s
        # rate plus the LiDAR's, for these scenes and settings); only meaningful with one worker.
        "simulator_frames_per_s": median["frames"] / (parts["lidar"] + parts["sonar"]),
        **{k: median[k] for k in ("frames", "shards", "bytes")},
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--suite", default="paper")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--workers", default="1", help="worker counts to compare, comma-separated, e.g. 1,8")
    parser.add_argument("--shards", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=3, help="runs per setting (the median is reported)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    suite = load_suite(args.suite)
    counts = [int(w) for w in args.workers.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        generate(suite, Path(tmp) / "warmup", frames=2, shards=1, device=str(device), progress=False)
        warmup_s = time.perf_counter() - t0
        rows = [timed_runs(suite, device, Path(tmp), args, w, overlap) for w in counts for overlap in (False, True)]
    res = {
        "device": str(device),
        "device_name": device.name if device.is_cuda else platform.processor() or "CPU",
        "cpu_count": os.cpu_count(),
        "warp": wp.__version__,
        "date": time.strftime("%Y-%m-%d"),
        "suite": suite.name,
        "frames": args.frames,
        "variants": len(suite.variants),
        "repeats": args.repeats,
        "warmup_s": warmup_s,
        "runs": rows,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"generate_{'cuda' if device.is_cuda else 'cpu'}"
    (out / f"{stem}.json").write_text(json.dumps(res, indent=1))
    (out / f"{stem}.md").write_text(markdown(res, suite.name, args))
    print((out / f"{stem}.md").read_text())
    return res


def markdown(res: dict, suite: str, args) -> str:
    lines = [
        f"# Dataset generation on {res['device_name']} ({res['device']}, {res['cpu_count']} CPU cores)",
        "",
        f"`generate --suite {suite} --frames {args.frames} --workers W`, warp {res['warp']}, {res['date']}; "
        f"medians of {args.repeats} fresh runs per row; kernels loaded by a warm-up run first "
        f"({res['warmup_s']:.1f} s). *in turn*: each worker prepares an episode (scene, drive, draws), "
        "renders it (LiDAR, sonar) and writes each shard one after another; *overlapped* (the default): "
        "the next episode is prepared and the last shard written beside the rendering. Parts are seconds "
        "summed over workers; *start-up* is a worker process from its launch to Warp and its device ready; "
        "*waiting* is the rendering thread blocked on a preparation or a write. "
        "*simulator* is frames over the LiDAR + sonar seconds of one worker: the rate the device work "
        "alone allows.",
        "",
        "| workers | parts | seconds | frames/s | " + " | ".join(PARTS).replace("lidar", "LiDAR") + " | "
        "simulator frames/s | vs simulator | MB |",
        "|---|---|---|---|" + "---|" * len(PARTS) + "---|---|---|",
    ]
    simulator = {r["overlap"]: r["simulator_frames_per_s"] for r in res["runs"] if r["workers"] == 1}
    for r in res["runs"]:
        p = r["seconds_by_part"]
        ref = simulator.get(r["overlap"])
        lines.append(
            f"| {r['workers']} | {'overlapped' if r['overlap'] else 'in turn'} | {r['median_s']:.1f} | "
            f"**{r['frames_per_s']:,.1f}** | "
            + " | ".join(f"{p[k]:.1f}" for k in PARTS)
            + " | "
            + (f"{r['simulator_frames_per_s']:,.1f}" if r["workers"] == 1 else "-")
            + " | "
            + (f"{r['frames_per_s'] / ref:.0%}" if ref else "-")
            + f" | {r['bytes'] / 1e6:,.0f} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
