"""Where `Sonar.simulate`'s time goes on a GPU: GPU time per kernel and stage, and the host's share.

    python benchmarks/profile_sonar.py --device cuda:0

Reference office, 3 bounces, batches of 256 pings, at 20,000 and 100,000 rays per ping. For each:
energyscapes/s end to end without instrumentation (median of --repeats runs of --batches
batches), then one run under Warp's CUDA activity timing (`wp.timing_begin`), which records every
kernel, copy and memset with CUDA events. The GPU-busy time is their sum (one stream: they do
not overlap); the rest of the wall time is the host's (Python, launches, synchronisations) while
the GPU idles. Writes benchmarks/results/sonar_profile_cuda.json and .md.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import acoustic_sim as sim  # noqa: E402
from benchmarks.bench_lidar import load_office, random_poses  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402

STAGES = ("trace", "record", "energyscape")
BATCH = 256


def stage_kernels() -> dict[str, str]:
    """Kernel function name -> stage, from the modules that define each stage's kernels."""
    from acoustic_sim.engine.kernels import beamform, curved, image_sources, lidar, paths, signals

    names = {}
    for stage, modules in (
        ("trace", (paths, image_sources, curved, lidar)),
        ("record", (signals,)),
        ("energyscape", (beamform,)),
    ):
        for module in modules:
            for obj in vars(module).values():
                if isinstance(obj, wp.Kernel):
                    names[obj.func.__name__] = stage
    # Kernels made by factories (sizes fixed at build time): their inner function names.
    names |= {"convolve": "record", "accumulate_rows": "record", "bound_stretches": "record"}
    names |= {"fft_rows": "energyscape", "ifft_rows": "energyscape", "beamform": "energyscape"}
    names["beamform_tiles"] = "energyscape"
    names["envelope_on_grid"] = "energyscape"
    return names


def classify(name: str, kernels: dict[str, str]) -> tuple[str, str]:
    """(stage, short name) of one timing record's name, e.g. 'forward kernel accumulate_echoes_1a2b'."""
    if not name.startswith("forward kernel "):
        return "copies and memsets", name.split(" ")[0]
    key = name.removeprefix("forward kernel ")
    for fn in sorted(kernels, key=len, reverse=True):  # longest first: 'ifft_rows' before 'fft_rows'
        if fn in key:
            return kernels[fn], fn
    return "other", key


def summarise(results, wall_s: float, pings: int, kernels: dict[str, str]) -> dict:
    """Per-kernel and per-stage GPU time [ms per 1,000 pings] and the host's share of the wall time."""
    per_kernel = defaultdict(lambda: {"ms": 0.0, "launches": 0, "stage": ""})
    for r in results:
        stage, short = classify(r.name, kernels)
        k = per_kernel[short]
        k["ms"] += r.elapsed
        k["launches"] += 1
        k["stage"] = stage
    busy_ms = sum(k["ms"] for k in per_kernel.values())
    stages = defaultdict(float)
    for k in per_kernel.values():
        stages[k["stage"]] += k["ms"]
    scale = 1000.0 / pings  # ms per 1,000 pings
    return {
        "pings": pings,
        "wall_ms_per_1000_pings": 1000.0 * wall_s * scale,
        "gpu_busy_ms_per_1000_pings": busy_ms * scale,
        "host_share": max(0.0, 1.0 - busy_ms / (1000.0 * wall_s)),
        "stages_ms_per_1000_pings": {s: v * scale for s, v in sorted(stages.items(), key=lambda kv: -kv[1])},
        "kernels": {
            name: {"stage": k["stage"], "ms_per_1000_pings": k["ms"] * scale, "launches": k["launches"]}
            for name, k in sorted(per_kernel.items(), key=lambda kv: -kv[1]["ms"])
        },
    }


def profile(rays: int, batches: int, repeats: int, device) -> dict:
    scene = load_office()
    poses = random_poses(BATCH * batches, 7)
    sonar = sim.Sonar(sim.SonarConfig.ertis(), max_bounces=3, ray_count=rays, device=device)
    sonar.simulate(scene, poses[:BATCH], batch=BATCH)  # compile and warm up
    times = []
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        sonar.simulate(scene, poses, batch=BATCH)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    plain_s = float(np.median(times))
    wp.synchronize_device(device)
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    t0 = time.perf_counter()
    sonar.simulate(scene, poses, batch=BATCH)
    wp.synchronize_device(device)
    timed_s = time.perf_counter() - t0
    results = wp.timing_end()
    out = summarise(results, timed_s, len(poses), stage_kernels())
    return out | {
        "rays_per_ping": rays,
        "energyscapes_per_s": len(poses) / plain_s,
        "energyscapes_per_s_timed": len(poses) / timed_s,
    }


def markdown(res: dict) -> str:
    lines = [
        f"# Where `Sonar.simulate`'s time goes on {res['device_name']} ({res['device']})",
        "",
        f"Reference office, max_bounces=3, batches of {BATCH} pings, warp {res['warp']}, {res['date']}. "
        "GPU time from Warp's CUDA activity timing (events around every kernel, copy and memset); host = "
        "wall time while the GPU idles. Rates are medians of uninstrumented runs.",
        "",
    ]
    for run in res["runs"]:
        lines += [
            f"## {run['rays_per_ping']:,} rays per ping: {run['energyscapes_per_s']:,.0f} energyscapes/s "
            f"({run['pings']:,} pings)",
            "",
            f"Per 1,000 pings: wall {run['wall_ms_per_1000_pings']:.1f} ms under timing "
            f"({run['energyscapes_per_s_timed']:,.0f}/s), GPU busy {run['gpu_busy_ms_per_1000_pings']:.1f} ms, "
            f"host (GPU idle) {100 * run['host_share']:.0f} %.",
            "",
            "| stage | GPU ms per 1,000 pings | share of GPU time |",
            "|---|---|---|",
        ]
        busy = run["gpu_busy_ms_per_1000_pings"]
        for stage, ms in run["stages_ms_per_1000_pings"].items():
            lines.append(f"| {stage} | {ms:.1f} | {100 * ms / busy:.0f} % |")
        lines += ["", "| kernel | stage | GPU ms per 1,000 pings | launches |", "|---|---|---|---|"]
        for name, k in list(run["kernels"].items())[:15]:
            lines.append(f"| `{name}` | {k['stage']} | {k['ms_per_1000_pings']:.2f} | {k['launches']} |")
        lines.append("")
    if "provenance" in res:
        lines += [provenance_line(res["provenance"]), ""]
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--rays", default="20000,100000", help="rays per ping, comma-separated")
    parser.add_argument("--batches", type=int, default=8, help="batches of 256 pings per run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    if not device.is_cuda:
        raise SystemExit("profile_sonar.py times CUDA activity: give a GPU (--device cuda:0)")
    res = {
        "device": str(device),
        "device_name": device.name,
        "warp": wp.__version__,
        "date": time.strftime("%Y-%m-%d"),
        "runs": [profile(int(r), args.batches, args.repeats, device) for r in args.rays.split(",")],
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = write_json(out / "sonar_profile_cuda.json", res, device=str(device))
    text = markdown(res)
    (out / "sonar_profile_cuda.md").write_text(text)
    print(text)
    return res


if __name__ == "__main__":
    main()
