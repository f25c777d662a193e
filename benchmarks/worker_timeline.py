"""Where a `generate` run's wall time goes, worker by worker: a timeline of one run.

    python benchmarks/worker_timeline.py --suite paper --frames 12500 --workers 4 --device cuda:0 --out DIR

Runs one `generate` in a fresh process (as the command runs) with each worker's device-ready
moment, every episode's render and every shard's write logged (wall clock, by process), then
writes DIR/timeline.json (the events and a summary) and DIR/timeline.md: per worker, when its
device was ready, when its first episode started and how long it took (CUDA context, kernel
modules, sensors), its median episode after that, when its last episode ended and when its last
shard was written. The fixed costs of a run (start-up, first episode, last write) read off it
directly; `bench_generate` gives only their sums.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402

EVENTS_ENV = "WORKER_TIMELINE_EVENTS"  # the folder each process appends its events to


def log(event: str, **extra) -> None:
    record = {"t": time.time(), "pid": os.getpid(), "ppid": os.getppid(), "event": event} | extra
    with open(Path(os.environ[EVENTS_ENV]) / f"{os.getpid()}.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")


_WRITE = None  # the runner's shard write, wrapped by `timed_write`


def timed_write(renderer, shard, device, threads=None):
    """The runner's shard write, logged (module level: a helper process receives it by name)."""
    log("write_start")
    try:
        return _WRITE(renderer, shard, device, threads)
    finally:
        log("write_end")


def logged(function, event: str):
    """`function`, logging `event` when it returns."""

    def call(*args, **kwargs):
        try:
            return function(*args, **kwargs)
        finally:
            log(event)

    return call


def child(spec: dict) -> dict:
    """One `generate` with its renders, writes and workers' device-ready moments logged."""
    global _WRITE
    from acoustic_sim.datasets import generate as gen
    from acoustic_sim.datasets import runner, workers
    from acoustic_sim.datasets.suites import load_suite

    render, resolve = gen.SuiteRenderer.render, workers.resolve_device

    def logged_render(self, *args, **kwargs):
        log("render_start")
        try:
            return render(self, *args, **kwargs)
        finally:
            log("render_end")

    def logged_resolve(device, index=0):  # a worker, CUDA up, picks its device (then reports ready)
        picked = resolve(device, index)
        log("worker_up", launched=workers._LAUNCHED, device=picked)
        return picked

    gen.SuiteRenderer.render, workers.resolve_device = logged_render, logged_resolve
    _WRITE, runner._write = runner._write, timed_write
    runner.helper_pool = logged(runner.helper_pool, "helpers_up")  # twice a worker: preparers, writers
    pool = workers.LocalWorkers
    pool.wait_ready, pool.run = logged(pool.wait_ready, "all_ready"), logged(pool.run, "run_end")
    log("call_start")
    summary = gen.generate(
        load_suite(spec["suite"]),
        spec["out"],
        frames=spec["frames"],
        shards=spec["shards"],
        device=spec["device"],
        workers=spec["workers"],
        helpers=spec["helpers"],
        progress=False,
    )
    log("call_end")
    return {k: summary[k] for k in ("seconds", "frames_per_s", "devices", "workers", "helpers", "seconds_by_part")}


def summarise(events: list[dict]) -> dict:
    """Per rendering process (seconds from the workers' launch, or from the call's start where it
    rendered alone): CUDA up, its helpers up, first episode, median episode after it, last episode's
    end, last shard written; and the parent's moments: all workers up (tasks fed), the workers'
    run over, the call's end."""
    ups = [e for e in events if e["event"] == "worker_up"]
    t0 = ups[0]["launched"] if ups else min(e["t"] for e in events if e["event"] == "call_start")
    by_pid: dict[int, list[dict]] = {}
    for e in sorted(events, key=lambda e: e["t"]):
        by_pid.setdefault(e["pid"], []).append(e)
    rows = []
    for pid, own in by_pid.items():
        begun = [e["t"] - t0 for e in own if e["event"] == "render_start"]
        if not begun:
            continue  # the parent of workers, or a helper
        up = [e for e in own if e["event"] == "worker_up"]
        helpers_up = [e["t"] - t0 for e in own if e["event"] == "helpers_up"]
        ended = [e["t"] - t0 for e in own if e["event"] == "render_end"]
        writes = [
            e["t"] - t0 for q, es in by_pid.items() for e in es if e["event"] == "write_end" and pid in (q, e["ppid"])
        ]
        later = sorted(b - a for a, b in zip(begun[1:], ended[1:], strict=True))
        rows.append(
            {
                "pid": pid,
                "device": up[0]["device"] if up else None,
                "up_s": up[0]["t"] - t0 if up else 0.0,
                "helpers_up_s": max(helpers_up) if helpers_up else None,
                "first_episode_at_s": begun[0],
                "first_episode_s": ended[0] - begun[0],
                "median_episode_s": later[len(later) // 2] if later else None,
                "episodes": len(begun),
                "last_episode_end_s": ended[-1],
                "last_write_end_s": max(writes),
            }
        )
    moments = {e["event"]: e["t"] - t0 for e in events if e["event"] in ("all_ready", "run_end", "call_end")}
    if rows:
        moments["last_episode_end"] = max(r["last_episode_end_s"] for r in rows)
    return {"workers": sorted(rows, key=lambda r: r["up_s"]), "moments_s": moments}


def markdown(res: dict) -> str:
    s, run = res["spec"], res["run"]
    lines = [
        f"# A `generate` run's timeline on {res['device_name']}",
        "",
        f"`generate --suite {s['suite']} --frames {s['frames']} --workers {s['workers']} --device {s['device']}`: "
        f"{run['frames_per_s']:,.0f} frames/s, {run['seconds']:.2f} s, on {', '.join(run['devices'])} "
        f"({run['helpers']} helpers a worker). Seconds from the workers' launch; *CUDA up*: the worker "
        "has started CUDA and picks its device; the first episode includes its kernel modules and sensors.",
        "",
        "| worker | device | CUDA up | helpers up | first episode at | first episode s | median episode s | episodes "
        "| last episode ends | last shard written |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for i, w in enumerate(res["summary"]["workers"]):
        median = f"{w['median_episode_s']:.3f}" if w["median_episode_s"] is not None else "-"
        helpers = f"{w['helpers_up_s']:.2f}" if w.get("helpers_up_s") is not None else "-"
        lines.append(
            f"| {i} | {w.get('device') or '-'} | {w['up_s']:.2f} | {helpers} | {w['first_episode_at_s']:.2f} | "
            f"{w['first_episode_s']:.2f} | {median} | {w['episodes']} | {w['last_episode_end_s']:.2f} | "
            f"{w['last_write_end_s']:.2f} |"
        )
    moments = res["summary"].get("moments_s", {})
    said = {"all_ready": "all workers up (tasks fed)", "last_episode_end": "last episode ends"}
    said |= {"run_end": "workers done", "call_end": "generate returns"}
    if moments:
        told = ", ".join(f"{said[k]} {moments[k]:.2f}" for k in said if k in moments)
        lines += ["", f"The run's moments (s): {told}"]
    return "\n".join(lines) + "\n\n" + provenance_line(res["provenance"]) + "\n"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suite", default="paper")
    parser.add_argument("--frames", type=int, default=12500)
    parser.add_argument("--shards", type=int, default=None)
    parser.add_argument("--workers", type=int, default=4)
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--helpers", type=int, default=None, help="helper processes a worker (default: the rule's)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return {}
    spec = {"suite": args.suite, "frames": args.frames, "shards": args.shards, "workers": args.workers}
    spec |= {"device": args.device, "helpers": args.helpers}
    with tempfile.TemporaryDirectory() as tmp:
        events_dir = Path(tmp) / "events"
        events_dir.mkdir()
        command = [sys.executable, __file__, "--child", json.dumps(spec | {"out": str(Path(tmp) / "data")})]
        done = subprocess.run(command, capture_output=True, text=True, env=os.environ | {EVENTS_ENV: str(events_dir)})
        if done.returncode != 0:
            raise RuntimeError(f"generate failed:\n{done.stderr[-3000:]}")
        run = json.loads(done.stdout.strip().splitlines()[-1])
        events = [json.loads(line) for f in sorted(events_dir.iterdir()) for line in f.read_text().splitlines()]
    device = run["devices"][0]
    if device.startswith("cuda"):
        import warp as wp

        name = wp.get_device(device).name
    else:
        name = "CPU"
    res = {"spec": spec, "device_name": name, "run": run, "summary": summarise(events), "events": events}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = write_json(out / "timeline.json", res, device=device)
    (out / "timeline.md").write_text(markdown(res))
    print(markdown(res))
    return res


if __name__ == "__main__":
    main()
