"""What elevation beams cost: energyscapes/s at E = 1, 3 and 5 elevations, end to end and beamforming alone.

    python benchmarks/bench_elevation.py --device cuda:0
    python benchmarks/bench_elevation.py --device cpu --pings 2 --rays 2000 --repeats 1 --out out/elevation

Reference office, max_bounces=3, as `bench_sonar.py`'s headline row. For each elevation count E
(`ProcessingConfig.elevation_deg`: the default scalar 0 for E = 1, then beams 15 deg apart centred
on the horizon): energyscapes/s end to end (`Sonar.simulate` of --batches batches: trace + record +
beamform, the (E, R, A) energyscapes copied to the host) and pings/s of the beamformer alone on one
recorded batch kept on the device. The E values are timed in turn in each of --repeats rounds, after
a first call each (compile, allocation) reported apart; medians, and their ratios to E = 1. On a
GPU, one more beamformer call per E under Warp's CUDA activity timing gives each kernel's GPU time,
which shows where the cost of more elevations lies. Writes benchmarks/results/elevation_<cpu|cuda>.json
and .md.
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
from benchmarks.bench_lidar import load_office, random_poses  # noqa: E402
from benchmarks.profile_sonar import classify, stage_kernels  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402

ELEVATIONS_DEG = {1: 0.0, 3: (-15.0, 0.0, 15.0), 5: (-30.0, -15.0, 0.0, 15.0, 30.0)}


def once(fn, device) -> float:
    """Seconds of one call of `fn`, the device's queue drained before and after."""
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    fn()
    wp.synchronize_device(device)
    return time.perf_counter() - t0


def kernel_ms(fn, device) -> dict[str, float]:
    """GPU time [ms] of each kernel (and copy or memset) of one call of `fn`, by Warp's CUDA timing."""
    wp.synchronize_device(device)
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    fn()
    wp.synchronize_device(device)
    names, ms = stage_kernels(), {}
    for r in wp.timing_end():
        short = classify(r.name, names)[1]
        ms[short] = ms.get(short, 0.0) + r.elapsed
    return dict(sorted(ms.items(), key=lambda kv: -kv[1]))


def measure(args, device) -> dict:
    """First-call and median seconds, end to end and beamforming alone, for each E."""
    from acoustic_sim.engine.beamform import Beamformer
    from acoustic_sim.engine.lidar import check_poses
    from acoustic_sim.engine.signals import recorder

    scene = load_office()
    drive = random_poses(args.pings * args.batches, 3)  # end to end: a run of batches, as bench_sonar
    sonar = sim.Sonar(sim.SonarConfig.ertis(), max_bounces=3, ray_count=args.rays, device=device)
    echoes = next(iter(sonar.tracer.traced(scene, check_poses(drive[: args.pings]), args.pings)))[2]
    signals = recorder(sonar.config, True, str(device))(
        echoes.buffers(), echoes.pose_count
    )  # one batch of microphone signals, on the device
    runs = {}
    for count, elevation in ELEVATIONS_DEG.items():
        processing = sim.ProcessingConfig(elevation_deg=elevation)
        former = Beamformer(sonar.config, samples=sonar.config.record_samples, processing=processing, device=device)
        runs[count] = {
            "elevation_deg": elevation,
            "end_to_end": lambda p=processing: sonar.simulate(scene, drive, batch=args.pings, processing=p),
            "beamform": lambda f=former: f(signals),
        }
    res = {}
    for count, run in runs.items():  # first calls apart: compile, allocations, pinned copy buffers
        res[count] = {
            "elevation_deg": run["elevation_deg"],
            "first_end_to_end_s": once(run["end_to_end"], device),
            "first_beamform_s": once(run["beamform"], device),
            "end_to_end_s": [],
            "beamform_s": [],
        }
    for _ in range(args.repeats):  # rounds over E, so drifts of a shared machine fall on every E alike
        for count, run in runs.items():
            res[count]["end_to_end_s"].append(once(run["end_to_end"], device))
            res[count]["beamform_s"].append(once(run["beamform"], device))
    for count, r in res.items():
        end, beam = float(np.median(r["end_to_end_s"])), float(np.median(r["beamform_s"]))
        r |= {
            "end_to_end_median_s": end,
            "energyscapes_per_s": len(drive) / end,
            "beamform_median_s": beam,
            "beamform_pings_per_s": echoes.pose_count / beam,
        }
        if device.is_cuda:
            r["beamform_kernel_ms"] = kernel_ms(runs[count]["beamform"], device)
    return {"energyscapes_end_to_end": len(drive), "pings_beamformed": echoes.pose_count, "by_elevations": res}


def markdown(res: dict) -> str:
    runs = res["by_elevations"]
    base = runs[1]
    lines = [
        f"# Elevation beams: what E elevations cost on {res['device_name']} ({res['device']})",
        "",
        f"Reference office, max_bounces=3, {res['rays_per_ping']:,} rays per ping, {res['pings']} pings per batch "
        f"({res['batches_end_to_end']} per end-to-end run), default grid (240 x 181), warp {res['warp']}, "
        f"{res['date']}. Medians of {res['repeats']} rounds (the E values timed in turn in each).",
        "",
        "| E | elevations [deg] | end to end, energyscapes/s | vs E = 1 | beamforming alone, pings/s | vs E = 1 |",
        "|---|---|---|---|---|---|",
    ]
    for count, r in runs.items():
        elevations = ", ".join(f"{e:g}" for e in np.atleast_1d(r["elevation_deg"]))
        end_ratio = r["energyscapes_per_s"] / base["energyscapes_per_s"]
        beam_ratio = r["beamform_pings_per_s"] / base["beamform_pings_per_s"]
        lines.append(
            f"| {count} | {elevations} | {r['energyscapes_per_s']:,.1f} | {end_ratio:.2f} | "
            f"{r['beamform_pings_per_s']:,.1f} | {beam_ratio:.2f} |"
        )
    lines += [
        "",
        "End to end: `Sonar.simulate` (trace + record + beamform, the (E, R, A) energyscapes copied to the host). "
        "Beamforming alone: `Beamformer` on one recorded batch kept on the device. "
        "Ratios are rates at E over the rate at E = 1 (1.00 = free; 1 / E = every step scales with E).",
    ]
    if "beamform_kernel_ms" in base:
        names = list(dict.fromkeys(name for r in runs.values() for name in r["beamform_kernel_ms"]))
        lines += [
            "",
            f"GPU time of one beamformer call ({res['pings']} pings) per kernel [ms], Warp's CUDA activity timing:",
            "",
            "| kernel | " + " | ".join(f"E = {count}" for count in runs) + " |",
            "|---|" + "---|" * len(runs),
        ]
        for name in names:
            cells = " | ".join(f"{r['beamform_kernel_ms'].get(name, 0.0):.2f}" for r in runs.values())
            lines.append(f"| `{name}` | {cells} |")
        totals = " | ".join(f"**{sum(r['beamform_kernel_ms'].values()):.2f}**" for r in runs.values())
        lines.append(f"| **all** | {totals} |")
    lines += ["", provenance_line(res["provenance"]), ""]
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--pings", type=int, default=None, help="batch size; default 256 on CUDA, 8 on CPU")
    parser.add_argument("--rays", type=int, default=20_000)
    parser.add_argument(
        "--batches", type=int, default=None, help="batches per end-to-end run; default 8 on CUDA, 1 on CPU"
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    device = wp.get_device(args.device)
    args.pings = args.pings or (256 if device.is_cuda else 8)
    args.batches = args.batches or (8 if device.is_cuda else 1)
    res = {
        "device": str(device),
        "device_name": device.name if device.is_cuda else "CPU",
        "warp": wp.__version__,
        "pings": args.pings,
        "batches_end_to_end": args.batches,
        "rays_per_ping": args.rays,
        "repeats": args.repeats,
        "date": time.strftime("%Y-%m-%d"),
    } | measure(args, device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"elevation_{'cuda' if device.is_cuda else 'cpu'}"
    res = write_json(out / f"{stem}.json", res, device=str(device))
    text = markdown(res)
    (out / f"{stem}.md").write_text(text)
    print(text)
    return res


if __name__ == "__main__":
    main()
