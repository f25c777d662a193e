"""What a generate worker's start costs, step by step, against how many processes start at once.

    python benchmarks/start_costs.py --device auto --processes 1,2,4,8,10 --out DIR

On two H200s each added worker process made every worker's CUDA start ~0.04 s and its first
episode ~0.11 s longer (benchmarks/results/multi_gpu/h200x2_session28): some step is served one
process at a time. Here N processes are forked at once (as `generate` forks its workers, the
parent never starting CUDA), released together, and each times its own steps in order:

- `warp`: Warp up (`wp.init`: its libraries and the CUDA driver) and the device picked;
- `context`: the device's CUDA context made (Warp makes it on first use; on two H100s one took 0.12 s
  alone, 1.2-1.5 s each for 12 processes at once: benchmarks/results/multi_gpu/session39);
- `sensors`: the sonar and the LiDAR built (the tracer's rays on the device; the recorder's and the
  beamformer's kernels made);
- `modules`: every kernel module registered by then loaded from the kernel cache (`wp.force_load`);
- `pinned`: two page-locked host buffers of one batch's float16 energyscapes (the BatchCopies');
- `device`: the tracer's device buffers for one batch (a first trace of one ping);
- `episode`: one ping simulated and one scan, everything loaded (what is left of a first episode).

With --own-gpu G, process i sees only GPU i % G (CUDA_VISIBLE_DEVICES, set before Warp starts
CUDA): whether a driver that starts one GPU per process starts sooner than one that starts all.
Each process makes its context with one work queue, as a generate worker does, unless
CUDA_DEVICE_MAX_CONNECTIONS is set on the command line (8 is CUDA's default); other variables the
driver reads are tried the same way. Writes DIR/start_costs.json and .md: per process count, each
step's median and slowest over the processes, beside one process's.
"""

from __future__ import annotations

import argparse
import importlib
import multiprocessing
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acoustic_sim.datasets.generate import ENGINE_MODULES  # noqa: E402
from acoustic_sim.datasets.workers import QUEUES_ENV, WORKER_QUEUES  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402

STEPS = ("warp", "context", "sensors", "modules", "pinned", "device", "episode")


def worker(index: int, device: str, start, results, own_gpu: int = 0) -> None:
    """One process's steps, timed after all are released together by `start`."""
    os.environ.setdefault(QUEUES_ENV, WORKER_QUEUES)  # as a generate worker does (both read at cuInit)
    if own_gpu:
        os.environ["CUDA_VISIBLE_DEVICES"] = str(index % own_gpu)
    start.wait()
    try:
        results.put({"index": index, **steps(index, device)})
    except BaseException:
        results.put({"index": index, "error": traceback.format_exc()})


def steps(index: int, device: str) -> dict:
    times = {}
    t = time.perf_counter()
    import warp as wp

    from acoustic_sim.devices import quiet_warp, resolve_device

    quiet_warp()
    device = resolve_device(device, index)
    times["warp"] = time.perf_counter() - t
    t = time.perf_counter()
    if wp.get_device(device).is_cuda:
        _ = wp.get_device(device).context  # made here, not inside the next step's first allocation
    times["context"] = time.perf_counter() - t
    t = time.perf_counter()
    scene, pose, sonar, lidar = sensors(device)
    times["sensors"] = time.perf_counter() - t
    t = time.perf_counter()
    wp.force_load(device=device)  # every module registered so far, each from the kernel cache
    times["modules"] = time.perf_counter() - t
    t = time.perf_counter()
    if wp.get_device(device).is_cuda:
        pinned = [wp.empty((256, 240, 181), dtype=wp.float16, device="cpu", pinned=True) for _ in range(2)]
        del pinned
    times["pinned"] = time.perf_counter() - t
    t = time.perf_counter()
    sonar.trace(scene, pose)
    wp.synchronize_device(device)
    times["device"] = time.perf_counter() - t
    t = time.perf_counter()
    lidar.scan(scene, pose)
    sonar.simulate(scene, pose, dtype=np.float16)
    wp.synchronize_device(device)
    times["episode"] = time.perf_counter() - t
    return {"device": device, **times}


def sensors(device: str):
    """A box room, one pose, and the sonar and LiDAR of the default rig on `device`, with the
    recorder's and the beamformer's kernels made (as a first `simulate` makes them)."""
    import scenes
    from acoustic_sim import Lidar, LidarConfig, Sonar, SonarConfig
    from acoustic_sim.engine.beamform import beamformer
    from acoustic_sim.engine.signals import recorder

    config = SonarConfig.ertis()
    recorder(config, True, device)
    beamformer(config, samples=config.record_samples, device=device)
    scene = scenes.box_room((6.0, 4.0, 3.0))
    pose = scenes.pose(3.0, 2.0, 0.3, 0.5)
    return scene, pose, Sonar(config, device=device), Lidar(LidarConfig.hokuyo_ust20lx(), device=device)


def warm_up(device: str) -> None:
    """Fill the kernel cache (compiling where needed) in a process of its own."""
    context = multiprocessing.get_context("spawn")
    with context.Pool(1) as pool:
        pool.apply(steps, (0, device))


def run(device: str, processes: int, own_gpu: int = 0) -> list[dict]:
    """`processes` forked workers released together; each one's step times. The engine is imported
    here first, as `generate` imports it before forking its workers (without it each worker's
    first steps carried the imports: 1.6 and 3.3 s alone on an H100 host)."""
    for module in (*ENGINE_MODULES, "scenes"):
        importlib.import_module(module)
    context = multiprocessing.get_context("fork")
    start, results = context.Event(), context.Queue()
    workers = [context.Process(target=worker, args=(i, device, start, results, own_gpu)) for i in range(processes)]
    for p in workers:
        p.start()
    time.sleep(0.5)  # all forked and waiting
    start.set()
    found = [results.get(timeout=300) for _ in workers]
    for p in workers:
        p.join()
    for r in found:
        if "error" in r:
            raise RuntimeError(f"worker {r['index']} failed:\n{r['error']}")
    return sorted(found, key=lambda r: r["index"])


def markdown(res: dict) -> str:
    lines = [
        f"# A worker's start, step by step, on {res['device_name']} ({res['cpu_count']} cores)",
        "",
        "N processes forked and released together; per step the median and the slowest over them [s].",
        f"Each process sees only its own GPU: {'yes' if res.get('own_gpu') else 'no'}; the driver's environment: "
        + (", ".join(f"{k}={v}" for k, v in res.get("driver_env", {}).items()) or "CUDA's defaults")
        + ".",
        "",
        "| processes | " + " | ".join(STEPS) + " | all |",
        "|---|" + "---|" * (len(STEPS) + 1),
    ]
    for row in res["rows"]:
        cells = []
        for step in (*STEPS, "all"):
            values = [sum(r[s] for s in STEPS) if step == "all" else r[step] for r in row["workers"]]
            cells.append(f"{np.median(values):.3f} / {max(values):.3f}")
        lines.append(f"| {row['processes']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\n" + provenance_line(res["provenance"]) + "\n"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="cpu, cuda:0, or auto (the GPUs in turn)")
    parser.add_argument("--processes", default="1,2,4", help="process counts to try, comma-separated")
    parser.add_argument("--own-gpu", type=int, default=0, help="GPUS: process i sees only GPU i %% GPUS")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)
    warm_up(args.device)
    rows = [{"processes": n, "workers": run(args.device, n, args.own_gpu)} for n in map(int, args.processes.split(","))]
    import warp as wp

    from acoustic_sim.devices import quiet_warp, resolve_device

    quiet_warp()
    device = resolve_device(args.device)
    name = wp.get_device(device).name if wp.get_device(device).is_cuda else "CPU"
    res = {"device": args.device, "device_name": name, "cpu_count": os.cpu_count(), "own_gpu": args.own_gpu}
    driver_env = {k: v for k, v in os.environ.items() if k.startswith("CUDA_")}
    res |= {"driver_env": {QUEUES_ENV: WORKER_QUEUES} | driver_env, "rows": rows}  # the processes' own
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = write_json(out / "start_costs.json", res, device=device)
    (out / "start_costs.md").write_text(markdown(res))
    print(markdown(res))
    return res


if __name__ == "__main__":
    main()
