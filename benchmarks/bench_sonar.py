"""Sonar throughput on the reference office (85k triangles), stage by stage, with a peer in the same run.

    python benchmarks/bench_sonar.py --device cpu
    python benchmarks/bench_sonar.py --device cuda:0

Writes benchmarks/results/sonar_<cpu|cuda>.json and .md (sonar_<cpu|cuda>_r<rays> for another --rays
than 20,000): for max_bounces 0, 1, 3 the path tracer's pings/s and BVH ray queries/s (counted by
the kernels: bounce rays, scattering shadow rays and the image-source checks) and energyscapes/s end
to end (`Sonar.simulate` of `--batches` batches: the steady state of a trajectory, where each
batch's copy back runs behind the next); pings/s of `Sonar.trace` to host Arrivals, recording and
energyscapes at 3 bounces; on the CPU also end to end with one thread (`Sonar(cpu_threads=1)`)
beside the default of every core (the stage rows record and beamform in one thread).
Peer: pyroomacoustics' image-source model of a shoebox of the office's size, order 3, timed per
ping (room build + image sources), if installed. Medians after a first call reported apart.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import acoustic_sim as sim  # noqa: E402
from benchmarks.bench_lidar import load_office, random_poses  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402

DEFAULT_RAYS = 20_000
HOST_PINGS = 32  # pings whose arrivals `Sonar.trace` copies and sorts on the host (the host-copy row)


def timed(fn, repeats: int, device) -> tuple[float, float, object]:
    """(first call [s], median of later calls [s], last result)."""
    times, result = [], None
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        result = fn()
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return times[0], float(np.median(times[1:])), result


def peer_pyroomacoustics(repeats: int) -> dict | None:
    try:
        import pyroomacoustics as pra
    except Exception:
        return None

    def ping():
        room = pra.ShoeBox([10.0, 8.0, 3.0], fs=450000, max_order=3)
        room.add_source([5.0, 4.0, 0.35])
        room.add_microphone([5.0, 4.0, 0.3])
        room.image_source_model()
        return room

    times = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        ping()
        times.append(time.perf_counter() - t0)
    dt = float(np.median(times[1:]))
    return {"name": "pyroomacoustics ShoeBox image sources, order 3", "s_per_ping": dt, "pings_per_s": 1 / dt}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--pings", type=int, default=None, help="batch size; default 256 on CUDA, 8 on CPU")
    parser.add_argument("--rays", type=int, default=DEFAULT_RAYS)
    parser.add_argument(
        "--batches",
        type=int,
        default=None,
        help="batches per end-to-end run (steady state); default 8 on CUDA, 1 on CPU",
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    device = wp.get_device(args.device)
    pings = args.pings or (256 if device.is_cuda else 8)
    batches = args.batches or (8 if device.is_cuda else 1)
    scene = load_office()
    drive = random_poses(pings * batches, 3)  # end to end: a run of batches, as a trajectory is simulated
    poses = drive[:pings]  # the stage rows: one batch
    res = {
        "device": str(device),
        "device_name": device.name if device.is_cuda else platform.processor() or "CPU",
        "warp": wp.__version__,
        "pings": pings,
        "batches_end_to_end": batches,
        "rays_per_ping": args.rays,
        "date": time.strftime("%Y-%m-%d"),
        "cpu_count": os.cpu_count(),
        "trace": {},
    }
    from acoustic_sim.engine.beamform import Beamformer
    from acoustic_sim.engine.lidar import check_poses
    from acoustic_sim.engine.signals import recorder

    checked = check_poses(poses)
    for bounces in (0, 1, 3):
        sonar = sim.Sonar(sim.SonarConfig.ertis(), max_bounces=bounces, ray_count=args.rays, device=device)
        # Device side: the echoes stay on the GPU, as inside `Sonar.simulate`.
        # A ping that overflows its sequence table is traced again: the time includes that, the
        # query count only the kept traces (so queries/s errs low).
        _, dt, parts = timed(lambda s=sonar: list(s.tracer.traced(scene, checked, pings)), args.repeats, device)
        queries = sum(int(echoes.ray_queries.numpy()[keep].sum()) for _, keep, echoes in parts)  # one batch
        _, end_s, _ = timed(lambda s=sonar: s.simulate(scene, drive, batch=pings), args.repeats, device)
        res["trace"][bounces] = {
            "s": dt,
            "pings_per_s": pings / dt,
            "ray_queries_per_ping": queries / pings,
            "ray_queries_per_s": queries / dt,
            "end_to_end_s": end_s,
            "energyscapes_per_s": len(drive) / end_s,
        }
        print(
            f"max_bounces={bounces}: trace {pings / dt:,.1f} pings/s, end to end {len(drive) / end_s:,.1f}/s",
            flush=True,
        )
    # Stages of the 3-bounce chain, and the host copy that `Sonar.trace` adds: on fewer pings, as
    # sorting tens of thousands of arrivals a ping on the host is slow (256 pings at 100k rays
    # outlasted a 10-minute call on the H100), and its rate per ping does not depend on the count.
    host_pings = min(pings, HOST_PINGS)
    _, host_s, arrivals = timed(lambda: sonar.trace(scene, poses[:host_pings]), args.repeats, device)
    rec = recorder(sonar.config, True, str(device))
    former = Beamformer(sonar.config, samples=sonar.config.record_samples, device=device)
    # The batch's echoes, traced again: the end-to-end runs above left other poses in the buffers.
    echoes = next(iter(sonar.tracer.traced(scene, checked, pings)))[2]
    count = echoes.pose_count
    _, record_s, signals = timed(lambda: rec(echoes.buffers(), count), args.repeats, device)
    _, energy_s, _ = timed(lambda: former(signals), args.repeats, device)
    res["trace_to_host_3_bounces"] = {
        "s": host_s,
        "pings": host_pings,
        "pings_per_s": host_pings / host_s,
        "arrivals_per_ping": len(arrivals) / host_pings,
    }
    res["record"] = {"s": record_s, "pings_per_s": count / record_s}
    res["energyscape"] = {"s": energy_s, "pings_per_s": count / energy_s}
    res["end_to_end_3_bounces"] = {
        "s": res["trace"][3]["end_to_end_s"],
        "energyscapes_per_s": res["trace"][3]["energyscapes_per_s"],
    }
    if device.is_cpu:  # Warp runs a CPU launch on one core: `simulate` records and beamforms in threads
        one = sim.Sonar(sim.SonarConfig.ertis(), max_bounces=3, ray_count=args.rays, device=device, cpu_threads=1)
        _, one_s, _ = timed(lambda: one.simulate(scene, drive, batch=pings), args.repeats, device)
        res["end_to_end_3_bounces_one_thread"] = {"s": one_s, "energyscapes_per_s": len(drive) / one_s}
        res["cpu_threads"] = sonar.cpu_threads
    peer = peer_pyroomacoustics(args.repeats)
    if peer:
        res["peer"] = peer
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"sonar_{'cuda' if device.is_cuda else 'cpu'}"
    if args.rays != DEFAULT_RAYS:  # a run at another ray count keeps the default's results
        stem += f"_r{args.rays}"
    res = write_json(out / f"{stem}.json", res, device=str(device))
    lines = [
        f"# Sonar throughput on {res['device_name']} ({res['device']})",
        "",
        f"Reference office (84,612 triangles), {pings} pings per batch ({batches} per end-to-end run), "
        f"{args.rays:,} rays per ping, warp "
        f"{res['warp']}, {res['date']}. Medians of {args.repeats} runs.",
        "",
        "| stage | pings/s | note |",
        "|---|---|---|",
    ]
    for bounces, r in res["trace"].items():
        lines.append(
            f"| trace, max_bounces={bounces} | {r['pings_per_s']:,.1f} | kept in Warp arrays; "
            f"{r['ray_queries_per_ping']:,.0f} ray queries/ping = {r['ray_queries_per_s'] / 1e6:,.1f} M ray queries/s |"
        )
    host = res["trace_to_host_3_bounces"]
    lines += [
        f"| `Sonar.trace`, max_bounces=3 | {host['pings_per_s']:,.1f} | to host Arrivals, "
        f"{host['arrivals_per_ping']:,.0f} per ping (sorted numpy records; {host.get('pings', res['pings'])} pings) |",
        f"| record (32 mics x 16,384 samples) | {res['record']['pings_per_s']:,.1f} | kept in Warp arrays |",
        f"| energyscape (181 azimuths) | {res['energyscape']['pings_per_s']:,.1f} | kept in Warp arrays |",
    ]
    for bounces, r in res["trace"].items():
        bold = "**" if bounces == 3 else ""
        lines.append(
            f"| {bold}end to end, max_bounces={bounces}{bold} | {bold}{r['energyscapes_per_s']:,.1f}{bold} | "
            f"`Sonar.simulate` of {batches} batch{'es' if batches > 1 else ''}: trace + record + energyscape, "
            "energyscapes copied to the host |"
        )
    if "end_to_end_3_bounces_one_thread" in res:
        one = res["end_to_end_3_bounces_one_thread"]["energyscapes_per_s"]
        lines.append(
            f"| end to end, max_bounces=3, `cpu_threads=1` | {one:,.1f} | the rows above trace, record and beamform in "
            f"{res['cpu_threads']} threads: {res['trace'][3]['energyscapes_per_s'] / one:.2f}x this |"
        )
    if peer:
        lines.append(f"| peer: {peer['name']} | {peer['pings_per_s']:,.1f} | image sources only, no signals |")
    lines += ["", provenance_line(res["provenance"])]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
