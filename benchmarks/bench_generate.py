"""Dataset generation throughput: frames/s of `generate` for a suite, on a device, end to end.

    python benchmarks/bench_generate.py --device cpu --suite paper --frames 300 --workers 2
    python benchmarks/bench_generate.py --device cuda:0 --suite paper --frames 12500 --workers 4

Writes benchmarks/results/generate_<cpu|cuda>.json and .md. A short warm-up run first loads (or
compiles) every Warp kernel, reported apart; then the timed run writes a fresh dataset into a
temporary folder (scenes, drives, LiDAR, sonar, HDF5 shards with compression, manifest and card).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acoustic_sim.generate import generate  # noqa: E402
from acoustic_sim.suites import load_suite  # noqa: E402


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--suite", default="paper")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--shards", type=int, default=None)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    suite = load_suite(args.suite)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        generate(
            suite,
            Path(tmp) / "warmup",
            frames=2,
            shards=1,
            device=str(device),
            progress=False,
        )
        warmup_s = time.perf_counter() - t0
        summary = generate(
            suite,
            Path(tmp) / "run",
            frames=args.frames,
            shards=args.shards,
            device=str(device),
            workers=args.workers,
            progress=False,
        )
        size = sum(p.stat().st_size for p in (Path(tmp) / "run").rglob("*.h5"))
    res = {
        "device": str(device),
        "device_name": device.name if device.is_cuda else platform.processor() or "CPU",
        "cpu_count": os.cpu_count(),
        "warp": wp.__version__,
        "date": time.strftime("%Y-%m-%d"),
        "suite": suite.name,
        "variants": len(suite.variants),
        "workers": args.workers,
        "warmup_s": warmup_s,
        "bytes": size,
        **{k: summary[k] for k in ("frames", "shards", "seconds", "frames_per_s")},
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"generate_{'cuda' if device.is_cuda else 'cpu'}"
    (out / f"{stem}.json").write_text(json.dumps(res, indent=1))
    lines = [
        f"# Dataset generation on {res['device_name']} ({res['device']}, {res['cpu_count']} CPU cores)",
        "",
        f"`generate --suite {suite.name} --frames {args.frames} --workers {args.workers}`, warp {res['warp']}, "
        f"{res['date']}; kernels loaded by a warm-up run first ({warmup_s:.1f} s).",
        "",
        "| suite | frames | shards | workers | seconds | frames/s | MB written |",
        "|---|---|---|---|---|---|---|",
        f"| {suite.name} | {res['frames']:,} | {res['shards']} | {args.workers} | {res['seconds']:.1f} | "
        f"**{res['frames_per_s']:,.1f}** | {size / 1e6:,.0f} |",
    ]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
