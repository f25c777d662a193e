"""`Sonar.simulate` end to end for several commits of the simulator, in one job, so their ratios hold.

    python benchmarks/sonar_same_job.py --device cuda:0 --revs base=8debdf9 --revs now=HEAD

A speed change is only trusted beside the code it replaces measured on the same machine in the
same run (lent GPUs of one kind differ by ~10 %). Each revision's `acoustic_sim` and `scenes` are
taken with `git archive` into a temporary folder and timed in a process of their own, through the
public interface only (`Sonar(SonarConfig.ertis(), max_bounces, ray_count).simulate(scene, poses,
batch)`), which every revision since the first benchmark keeps. The workload is bench_sonar's: the
reference office, a drive of `--batches` batches of 256 pings (the steady state of a trajectory),
3 bounces, at each `--rays`. Rounds alternate the revisions (base, now, base, now, ...) so drift of
the machine falls on all of them; each figure is the median over rounds. Writes
sonar_same_job_<device>.json and .md under --out.
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

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def child(rays: list[int], bounces: int, pings: int, batches: int, device: str) -> dict:
    """Runs inside one revision's tree (first on sys.path): energyscapes/s per ray count, after a
    first call (kernel compile or cache load) that is reported apart."""
    import warp as wp

    wp.config.quiet = True
    sys.path.append(str(ROOT))  # after the revision's tree: bench_lidar gets the revision's modules
    import acoustic_sim as sim
    from benchmarks.bench_lidar import load_office, random_poses

    scene = load_office()
    drive = random_poses(pings * batches, 3)
    out = {"acoustic_sim": str(Path(sim.__file__).parent)}
    for count in rays:
        sonar = sim.Sonar(sim.SonarConfig.ertis(), max_bounces=bounces, ray_count=count, device=device)
        times = []
        for _ in range(2):
            t0 = time.perf_counter()
            sonar.simulate(scene, drive, batch=pings)
            wp.synchronize_device(device)
            times.append(time.perf_counter() - t0)
        out[str(count)] = {"first_s": times[0], "s": times[1], "energyscapes_per_s": len(drive) / times[1]}
    return out


def export(rev: str, into: Path) -> str:
    """The revision's simulator (acoustic_sim, scenes) under `into`; returns its full commit id."""
    commit = subprocess.run(
        ["git", "rev-parse", "--verify", rev + "^{commit}"], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout.strip()
    into.mkdir(parents=True)
    archive = subprocess.run(
        ["git", "archive", commit, "acoustic_sim", "scenes"], cwd=ROOT, check=True, capture_output=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return commit


def parse_revs(items: list[str]) -> dict[str, str]:
    revs = {}
    for item in items:
        name, sep, rev = item.partition("=")
        if not sep or not name or not rev or name in revs:
            raise SystemExit(f"--revs wants distinct NAME=REV, got {item!r}")
        revs[name] = rev
    if len(revs) < 2:
        raise SystemExit("--revs: name at least two revisions to compare (e.g. base=8debdf9 now=HEAD)")
    return revs


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--revs",
        action="append",
        default=[],
        metavar="NAME=REV",
        help="a revision to time (repeatable; the first is the reference of the ratios)",
    )
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--rays", default="20000,100000", help="rays per ping, comma-separated")
    parser.add_argument("--bounces", type=int, default=3)
    parser.add_argument("--pings", type=int, default=256, help="batch size")
    parser.add_argument("--batches", type=int, default=8, help="batches per end-to-end run")
    parser.add_argument("--rounds", type=int, default=3, help="timed runs per revision, alternating")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    rays = [int(r) for r in args.rays.split(",")]
    if args.child:  # one revision, in its own process
        print(json.dumps(child(rays, args.bounces, args.pings, args.batches, args.device)))
        return {}
    revs = parse_revs(args.revs)
    runs: dict[str, list[dict]] = {name: [] for name in revs}
    with tempfile.TemporaryDirectory() as tmp:
        commits = {name: export(rev, Path(tmp) / name) for name, rev in revs.items()}
        for r in range(args.rounds):
            for name in revs:
                env = dict(
                    os.environ, PYTHONPATH=os.pathsep.join([str(Path(tmp) / name), os.environ.get("PYTHONPATH", "")])
                )
                cmd = [
                    sys.executable,
                    __file__,
                    "--child",
                    "--device",
                    args.device,
                    "--rays",
                    args.rays,
                    "--bounces",
                    str(args.bounces),
                    "--pings",
                    str(args.pings),
                    "--batches",
                    str(args.batches),
                ]
                done = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True)
                result = json.loads(done.stdout.strip().splitlines()[-1])
                if not result["acoustic_sim"].startswith(tmp):
                    raise SystemExit(f"{name}: imported {result['acoustic_sim']}, not the revision's tree")
                runs[name].append(result)
                rates = ", ".join(f"{c:,} rays {result[str(c)]['energyscapes_per_s']:,.0f}/s" for c in rays)
                print(f"round {r + 1}, {name}: {rates}", flush=True)
    return write(args, revs, commits, runs, rays)


def write(args, revs: dict, commits: dict, runs: dict, rays: list[int]) -> dict:
    import warp as wp

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    first = next(iter(revs))
    res = {
        "device": str(device),
        "device_name": device.name if device.is_cuda else "CPU",
        "warp": wp.__version__,
        "date": time.strftime("%Y-%m-%d"),
        "max_bounces": args.bounces,
        "pings": args.pings,
        "batches": args.batches,
        "rounds": args.rounds,
        "revisions": {name: {"rev": revs[name], "commit": commits[name]} for name in revs},
        "energyscapes_per_s": {},
    }
    for count in rays:
        res["energyscapes_per_s"][str(count)] = {
            name: {
                "median": float(np.median([run[str(count)]["energyscapes_per_s"] for run in runs[name]])),
                "rounds": [run[str(count)]["energyscapes_per_s"] for run in runs[name]],
            }
            for name in revs
        }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"sonar_same_job_{'cuda' if device.is_cuda else 'cpu'}"
    (out / f"{stem}.json").write_text(json.dumps(res, indent=1))
    names = list(revs)
    lines = [
        f"# `Sonar.simulate` end to end, {len(names)} revisions in one job, on {res['device_name']} ({res['device']})",
        "",
        f"Reference office, max_bounces={args.bounces}, {args.batches} batches of {args.pings} pings per run, warp "
        f"{res['warp']}, {res['date']}. Energyscapes/s, median of {args.rounds} rounds (revisions alternate); "
        f"ratios against `{first}`.",
        "",
        "| revision | commit |",
        "|---|---|",
        *(f"| {name} | {revs[name]} = {commits[name][:10]} |" for name in names),
        "",
        "| rays per ping | " + " | ".join(names) + " | " + " | ".join(f"{n} / {first}" for n in names[1:]) + " |",
        "|---|" + "---|" * (2 * len(names) - 1),
    ]
    for count in rays:
        row = res["energyscapes_per_s"][str(count)]
        ref = row[first]["median"]
        lines.append(
            f"| {count:,} | "
            + " | ".join(f"{row[n]['median']:,.0f}" for n in names)
            + " | "
            + " | ".join(f"{row[n]['median'] / ref:.2f}x" for n in names[1:])
            + " |"
        )
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
