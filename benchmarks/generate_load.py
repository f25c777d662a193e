"""Where generation's time goes on a machine of several GPUs: frames/s beside the host's CPU use and
each GPU's utilisation over each run, for settings compared in rounds.

    python benchmarks/generate_load.py --settings cuda:0/5,auto/10,auto/10/block,pair/5 --frames 75000 --out DIR

A setting is DEVICE/WORKERS[/WAIT[/HELPERS[/NICENESS[/POOL[/QUEUES]]]]]: WAIT is how the workers' CUDA waits
(spin, CUDA's default, or block: SONAR2LIDAR_CUDA_WAIT), HELPERS the host processes per worker
(generate's choice if left out or `-`), NICENESS how far below its rendering process a helper is
scheduled (SONAR2LIDAR_HELPER_NICENESS, 0 if left out), POOL what a GPU's memory pool does with freed
memory (keep, the package's default, or release, CUDA's: SONAR2LIDAR_CUDA_POOL), QUEUES the work queues
of each worker's CUDA context (CUDA_DEVICE_MAX_CONNECTIONS; `-` or left out: as this environment has it,
else the workers' default of one); with --rounds 2 and
settings that differ in one field, the rounds alternate them on the same warm machine. DEVICE `pair`
runs two `generate` commands at once, one on cuda:0 and one on cuda:1, with WORKERS each and half the
frames each: whether two GPUs slow each other through the host rather than through one command's
machinery. Each run is a fresh process, as a `generate` command is. Beside its frames/s: the share
of the host's CPU time busy over the run (/proc/stat), the CPU time and page faults of the run's whole
process tree (getrusage), each GPU's utilisation (nvidia-smi every 250 ms: the mean and median of all
samples; over the timed run its mean and its idle seconds, those of the run's first and last 4 s apart,
where two GPUs lose most), which processes hold a context on which GPU (6 s into the run), and with
--spy, a py-spy recording of one more run of each named setting (`pip install py-spy`), summed by
what the busy threads were doing. Writes DIR/generate_load.json and .md (and the
raw samples beside them).
"""

from __future__ import annotations

import argparse
import collections
import itertools
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acoustic_sim.datasets.workers import QUEUES_ENV, WORKER_QUEUES  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402

CHILD = """
import json, os, sys, time
from pathlib import Path
import acoustic_sim.datasets.generate as engine
from acoustic_sim.datasets.suites import load_suite
spec = json.loads(sys.argv[1])
called, started, make_dataset = time.time(), None, engine.make_dataset
def timed(*args, **kwargs):  # generate's seconds count from here: after its imports, plan and scene checks
    global started
    started = time.time()
    return make_dataset(*args, **kwargs)
engine.make_dataset = timed
summary = engine.generate(load_suite(spec["suite"]), Path(spec["out"]), frames=spec["frames"], device=spec["device"],
                   workers=spec["workers"], progress=False, helpers=spec["helpers"])
keep = ("frames", "seconds", "frames_per_s", "seconds_by_part", "devices", "helpers")
import resource
used = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
tree = {"user_s": sum(u.ru_utime for u in used), "system_s": sum(u.ru_stime for u in used),
        "minor_faults": sum(u.ru_minflt for u in used)}  # this process and every process it waited for
from acoustic_sim.devices import cuda_pool
from acoustic_sim.datasets.workers import QUEUES_ENV
queues = os.environ.get(QUEUES_ENV)
mine = {"tree": tree, "pool": cuda_pool(), "queues": queues, "called": called, "started": started}
print("RESULT " + json.dumps({k: summary.get(k) for k in keep} | mine))
"""
WARM_FRAMES = 3000  # the untimed run before the timed ones
SAMPLE_S = 0.25  # nvidia-smi's sampling interval
EDGE_S = 4.0  # a run's start and end, where two GPUs lose most of their idle time (multi_gpu/session39)
PARTS_SHOWN = ("start-up", "prepare", "lidar", "sonar", "assemble", "write")  # generate's seconds by part, summed
# What a sampled thread was doing, by the first of these functions found in its stack.
ACTIVITIES = (
    ("checksum", "fletcher32"),
    ("compress", "encode"),
    ("write HDF5", "write_shard"),
    ("prepare episodes", "prepare_episode"),
    ("wait for the GPU", "synchronize_event"),
    ("wait for the GPU", "synchronize_device"),
    ("load kernels", "load_cuda"),
    ("pickle", "dumps"),
    ("unpickle", "loads"),
    ("pipe", "_send_bytes"),
    ("pipe", "_recv_bytes"),
    ("ship a shard", "_hand_to_writer"),
    ("render (host side)", "simulate_episode"),
)


def cpu_ticks() -> tuple[int, int]:
    """(all, idle) jiffies of the machine so far; (0, 0) where /proc/stat is absent."""
    try:
        with open("/proc/stat") as f:
            values = list(map(int, f.readline().split()[1:]))
    except OSError:
        return 0, 0
    return sum(values), values[3] + values[4]


def start_sampler(path: Path):
    """nvidia-smi writing each GPU's utilisation every 250 ms to `path`; None without nvidia-smi."""
    if shutil.which("nvidia-smi") is None:
        return None
    fields = "--query-gpu=timestamp,index,utilization.gpu"
    query = ["nvidia-smi", fields, "--format=csv,noheader,nounits", "-lms", str(int(SAMPLE_S * 1000))]
    return subprocess.Popen(query, stdout=path.open("w"), stderr=subprocess.DEVNULL)


def utilisation(path: Path, window: tuple[float, float] | None = None) -> dict:
    """Per GPU: the mean and median of all its samples, and over `window` (the timed run's start and end,
    time.time()): the mean, the seconds busy (utilisation x time), the seconds idle, and of those the
    idle seconds in the window's first and last EDGE_S. A sample is nvidia-smi's share of the time
    some kernel ran on the GPU lately, so these are estimates to ~0.25 s. Lines: `timestamp, gpu, %`."""
    by_gpu: dict[int, list[tuple[float, int]]] = collections.defaultdict(list)
    for line in path.read_text().splitlines():
        try:
            stamp, gpu, value = (x.strip() for x in line.split(","))
            by_gpu[int(gpu)].append((datetime.strptime(stamp, "%Y/%m/%d %H:%M:%S.%f").timestamp(), int(value)))
        except ValueError:
            continue  # nvidia-smi's "[N/A]" or a line cut by the run's end
    return {gpu: _gpu_use(samples, window) for gpu, samples in by_gpu.items()}


def _gpu_use(samples: list[tuple[float, int]], window: tuple[float, float] | None) -> dict:
    values = [value for _, value in samples]
    use = {"mean": statistics.fmean(values), "median": statistics.median(values), "in_use_mean": 0.0}
    start, end = window or (samples[0][0], samples[-1][0])
    run = [(t, value) for t, value in samples if start <= t <= end]
    if not run:
        return use
    times = [t for t, _ in run]
    steps = [b - a for a, b in itertools.pairwise(times)]
    steps.append(statistics.median(steps) if steps else SAMPLE_S)  # the last sample's share of time
    idle = [(t, (1 - value / 100) * step) for (t, value), step in zip(run, steps, strict=True)]
    return use | {
        "in_use_mean": statistics.fmean(value for _, value in run),
        "busy_s": sum(value / 100 * step for (_, value), step in zip(run, steps, strict=True)),
        "idle_s": sum(s for _, s in idle),
        "idle_first_s": sum(s for t, s in idle if t < start + EDGE_S),
        "idle_last_s": sum(s for t, s in idle if t > end - EDGE_S),
    }


def contexts() -> str:
    """Which process holds a context on which GPU, and how much memory (nvidia-smi's words)."""
    if shutil.which("nvidia-smi") is None:
        return ""
    query = ["nvidia-smi", "--query-compute-apps=pid,gpu_bus_id,used_memory", "--format=csv,noheader"]
    return subprocess.run(query, capture_output=True, text=True).stdout


def launch(spec: dict, env: dict) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", CHILD, json.dumps(spec)],
        cwd=ROOT,
        env=env | {"PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def result(child: subprocess.Popen) -> dict:
    text = child.communicate()[0]
    found = [json.loads(line[7:]) for line in text.splitlines() if line.startswith("RESULT ")]
    if child.returncode or not found:
        raise RuntimeError(f"a generate run failed (exit {child.returncode}):\n{text[-3000:]}")
    return found[0]


def run(setting: str, args, work: Path, out: Path, tag: str, spy: bool = False) -> dict:
    """One run of `setting`, with the machine's load over it."""
    device, workers, *rest = setting.split("/")
    wait = rest[0] if rest else "spin"
    helpers = int(rest[1]) if len(rest) > 1 and rest[1] != "-" else None
    niceness = rest[2] if len(rest) > 2 else "0"
    pool = rest[3] if len(rest) > 3 else "keep"
    env = dict(os.environ, SONAR2LIDAR_CUDA_WAIT=wait, SONAR2LIDAR_HELPER_NICENESS=niceness, SONAR2LIDAR_CUDA_POOL=pool)
    if len(rest) > 4 and rest[4] != "-":
        env[QUEUES_ENV] = rest[4]
    spec = {"suite": args.suite, "frames": args.frames, "workers": int(workers), "helpers": helpers}
    shutil.rmtree(work, ignore_errors=True)
    sampler = start_sampler(out / f"utilisation_{tag}.csv")
    t0, (all0, idle0) = time.perf_counter(), cpu_ticks()
    pair = device == "pair"
    halves = [("cuda:0", args.frames // 2), ("cuda:1", args.frames // 2)] if pair else [(device, args.frames)]
    children = [launch(spec | {"device": d, "frames": n, "out": str(work / d)}, env) for d, n in halves]
    recorder = None
    try:
        if spy:
            time.sleep(args.spy_delay)
            command = ["py-spy", "record", "--subprocesses", "--nonblocking", "-r", "40", "-d", str(args.spy_seconds)]
            command += ["-f", "raw", "-o", str(out / f"spy_{tag}.txt"), "-p", str(children[0].pid)]
            recorder = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(min(6.0, args.frames / 20000))
        held = contexts()
        results = [result(child) for child in children]
        all1, idle1 = cpu_ticks()
        wall = time.perf_counter() - t0
    finally:  # a failed run leaves no sampler or other generate behind
        for process in [*children, sampler]:
            if process is not None and process.poll() is None:
                process.terminate()
            if process is not None:
                process.wait()
        if recorder is not None:
            recorder.wait()  # it ends with its --duration or its target, its recording written
    seconds = max(r["seconds"] for r in results)
    timed = (min(r["started"] for r in results), max(r["started"] + r["seconds"] for r in results))
    frames = sum(r["frames"] for r in results)
    parts, tree = collections.Counter(), collections.Counter()
    for r in results:
        parts.update(r["seconds_by_part"])
        tree.update(r["tree"])
    return {
        "setting": setting,
        "frames": frames,
        "seconds": seconds,
        "frames_per_s": frames / seconds,
        "each_frames_per_s": [r["frames_per_s"] for r in results],
        "wall_s": wall,
        "timed": timed,  # time.time() of the timed run's start and end, against the raw nvidia-smi samples
        "before_s": max(r["started"] - r["called"] for r in results),  # generate's imports, plan and scene checks
        "cpu_busy": 1 - (idle1 - idle0) / (all1 - all0) if all1 > all0 else None,
        "gpus": utilisation(out / f"utilisation_{tag}.csv", timed) if sampler is not None else {},
        "contexts": held,
        "seconds_by_part": dict(parts),
        "cpu_ms_per_frame": {k: 1e3 * tree[f"{k}_s"] / frames for k in ("user", "system")},
        "minor_faults_per_frame": tree["minor_faults"] / frames,
        "helpers": results[0]["helpers"],
        "pool": results[0]["pool"],
        # what the rendering processes' contexts were made with (None: CUDA's default, one process)
        "queues": results[0]["queues"] or (WORKER_QUEUES if int(workers) > 1 else None),
        "devices": sorted({d for r in results for d in r["devices"]}),
    }


def spy_summary(path: Path) -> dict[str, float]:
    """A py-spy raw recording (--subprocesses) summed by activity: the share of all samples of
    busy threads (py-spy leaves idle ones out) whose stack holds each activity's function."""
    text = re.sub(r'process (\d+):".*?"(?=;)', r"process \1", path.read_text(), flags=re.S)
    counts, total = collections.Counter(), 0
    for line in text.splitlines():
        stack, _, n = line.rpartition(" ")
        if not n.isdigit():
            continue
        functions = {frame.split(" (")[0].rsplit(".", 1)[-1] for frame in stack.split(";")}  # unqualified
        activity = next((name for name, function in ACTIVITIES if function in functions), "other")
        counts[activity] += int(n)
        total += int(n)
    return {name: count / total for name, count in counts.most_common()} if total else {}


def markdown(res: dict) -> str:
    lines = [
        f"# Generation and the machine's load: `{res['suite']}`, {res['frames']:,} frames a run",
        "",
        f"On {res['device_name']} ({res['cpu_count']} cores); each setting once a round, {res['rounds']} rounds, "
        "each run a fresh process. *CPU busy*: the share of all cores' time not idle over the whole run "
        "(its start and end included); *CPU ms a frame* and *page faults a frame*: the run's process tree's "
        "own (getrusage), start-up included; *GPU in use*: each GPU's mean utilisation over the timed run "
        "(`generate`'s seconds; in brackets: over all samples, the process's imports and end included); *GPU "
        f"idle*: each GPU's idle seconds in the timed run, of which in its first and its last {EDGE_S:g} s "
        "(from nvidia-smi's samples: estimates).",
        "",
        "| setting | round | frames/s | seconds | CPU busy | CPU ms a frame (user + system) | page faults a frame "
        "| GPU in use (mean) | GPU idle s (first, last) | helpers | " + " | ".join(PARTS_SHOWN) + " |",
        "|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(PARTS_SHOWN),
    ]
    for row in res["rows"]:
        gpus = ", ".join(f"{g}: {u['in_use_mean']:.0f} % ({u['mean']:.0f})" for g, u in row["gpus"].items()) or "-"
        idle = [
            f"{g}: {u['idle_s']:.1f} ({u['idle_first_s']:.1f}, {u['idle_last_s']:.1f})"
            for g, u in row["gpus"].items()
            if "idle_s" in u
        ]
        busy = f"{row['cpu_busy']:.2f}" if row["cpu_busy"] is not None else "-"
        part, cpu = row["seconds_by_part"], row["cpu_ms_per_frame"]
        lines.append(
            f"| {row['setting']} | {row['round']} | {row['frames_per_s']:,.0f} | {row['seconds']:.1f} | {busy} | "
            f"{cpu['user']:.2f} + {cpu['system']:.2f} | {row['minor_faults_per_frame']:.0f} | "
            f"{gpus} | {', '.join(idle) or '-'} | {row['helpers']} | "
            + " | ".join(f"{part.get(k, 0):.1f}" for k in PARTS_SHOWN)
            + " |"
        )
    for setting, summary in res.get("spy", {}).items():
        lines += ["", f"py-spy, `{setting}`: busy threads' samples by activity", ""]
        lines += [f"- {name}: {share:.1%}" for name, share in summary.items()]
    return "\n".join(lines) + "\n\n" + provenance_line(res["provenance"]) + "\n"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--settings", required=True, help="DEVICE/WORKERS[/WAIT[/HELPERS[/NICENESS[/POOL]]]], comma-separated"
    )
    parser.add_argument("--suite", default="paper")
    parser.add_argument("--frames", type=int, default=75000)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--spy", default="", help="settings to record once more under py-spy")
    parser.add_argument("--spy-delay", type=float, default=6.0, help="seconds into the run before recording")
    parser.add_argument("--spy-seconds", type=int, default=5)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "generate_load"))
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, spied = [], {}
    with tempfile.TemporaryDirectory(prefix="generate_load") as folder:
        work = Path(folder) / "data"
        # Fill the kernel cache first, so that no timed run compiles: enough frames for every kind of
        # scene and rig of the suite (after 800 warm-up frames of `randomised`, 7 of 12 workers' first
        # episodes still took 2.1-2.7 s: benchmarks/results/multi_gpu/session39).
        subprocess.run(
            [sys.executable, "-c", CHILD, json.dumps({"suite": args.suite, "frames": min(args.frames, WARM_FRAMES),
             "device": args.settings.split(",")[0].split("/")[0].replace("pair", "auto"), "workers": 1,
             "helpers": 0, "out": str(work)})],
            cwd=ROOT, capture_output=True, check=False,
        )  # fmt: skip
        for round_ in range(args.rounds):
            for i, setting in enumerate(args.settings.split(",")):
                row = run(setting, args, work, out, f"{round_}_{i}")
                rows.append(row | {"round": round_})
                print(f"round {round_} {setting}: {row['frames_per_s']:,.0f} frames/s, CPU busy {row['cpu_busy']}")
        for i, setting in enumerate(filter(None, args.spy.split(","))):
            run(setting, args, work, out, f"spy{i}", spy=True)
            raw = out / f"spy_spy{i}.txt"
            if raw.exists():  # its command lines name this machine's folders: summed, then removed
                spied[setting] = spy_summary(raw)
                raw.unlink()
    res = {"suite": args.suite, "frames": args.frames, "rounds": args.rounds, "rows": rows, "spy": spied}
    res |= {"cpu_count": os.cpu_count(), "device_name": _device_name()}
    record = write_json(out / "generate_load.json", res, device="cuda" if shutil.which("nvidia-smi") else "cpu")
    res["provenance"] = record["provenance"]
    (out / "generate_load.md").write_text(markdown(res))
    return res


def _device_name() -> str:
    if shutil.which("nvidia-smi") is None:
        return "CPU"
    names = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True)
    listed = names.stdout.split("\n")
    return f"{len([n for n in listed if n])} x {listed[0]}" if listed[0] else "GPUs"


if __name__ == "__main__":
    main()
