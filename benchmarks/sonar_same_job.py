"""`Sonar.simulate` end to end for several commits of the simulator, in one job, so their ratios hold.

    python benchmarks/sonar_same_job.py --device cuda:0 --revs base=8debdf9 --revs now=HEAD

A speed change is only trusted beside the code it replaces measured on the same machine in the
same run (lent GPUs of one kind differ by ~10 %). Each revision's `acoustic_sim`, `scenes` and `clitools` are
taken with `git archive` into a temporary folder and timed in a process of their own, through the
public interface only (`Sonar(SonarConfig.ertis(), max_bounces, ray_count).simulate(scene, poses,
batch)`), which every revision since the first benchmark keeps. A revision is a commit (`HEAD` is
the last commit, not uncommitted edits). The workload is bench_sonar's: the reference office, a
drive of `--batches` batches of 256 pings (the steady state of a trajectory), 3 bounces, at each
`--rays`. Each round times every revision once, and the order turns by one each round (a b c,
b c a, c a b), so neither drift nor going first falls on one revision; each figure is the median
over rounds. Writes sonar_same_job_<device>.json and .md under --out.

The lent GPU machine has no git: export the revisions here, carry the folder, and name the exports:

    python benchmarks/sonar_same_job.py --revs base=cbd9c98 --revs now=HEAD --export-to .device/revs
    python benchmarks/sonar_same_job.py --revs base=.device/revs/base --revs now=.device/revs/now  # there
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402


def load_simulator(tree: Path) -> tuple[str, str]:
    """Imports `acoustic_sim` and `scenes` from `tree`, ahead of anything else on sys.path (the
    working directory or an installed copy), and returns the folders they came from."""
    sys.path.insert(0, str(tree))
    import acoustic_sim
    import scenes

    return str(Path(acoustic_sim.__file__).parent), str(Path(scenes.__file__).parent)


def child(tree: Path, rays: list[int], bounces: int, pings: int, batches: int, device: str) -> dict:
    """Runs in a process of its own for the revision exported to `tree`: energyscapes/s per ray
    count, after a first call (kernel compile or cache load) that is reported apart, and where
    the simulator was imported from."""
    imported = load_simulator(tree)
    import warp as wp

    import acoustic_sim as sim

    wp.config.quiet = True
    sys.path.append(str(ROOT))  # the office and poses of the working tree; they use the revision's simulator
    from benchmarks.bench_lidar import load_office, random_poses

    scene = load_office()
    drive = random_poses(pings * batches, 3)
    out = {"imported": list(imported)}
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


def run_checked(cmd: list[str], what: str, **kwargs) -> subprocess.CompletedProcess:
    """subprocess.run that ends the benchmark with the command's own error output when it fails."""
    done = subprocess.run(cmd, capture_output=True, **kwargs)
    if done.returncode:
        err = done.stderr if isinstance(done.stderr, str) else done.stderr.decode(errors="replace")
        raise SystemExit(f"{what} failed (exit {done.returncode}):\n{err.strip()}")
    return done


# What an export holds: the simulator, and the command-line helpers it imports (writing a shard
# and `python -m acoustic_sim` need clitools, which older revisions lack).
PACKAGES = ("acoustic_sim", "scenes", "clitools")


def export(rev: str, into: Path, *, repo: Path = ROOT) -> str:
    """The revision's simulator (PACKAGES it holds) of the git repository `repo` under `into`
    (with its full commit id in `into/COMMIT`); returns that id. A `rev` that is a folder made so
    (on a machine without git) is copied, and its COMMIT read."""
    exported = Path(rev)
    if (exported / "COMMIT").is_file() and (exported / "acoustic_sim").is_dir():
        shutil.copytree(exported, into)
        return (exported / "COMMIT").read_text().strip()
    commit = run_checked(
        ["git", "rev-parse", "--verify", "--quiet", rev + "^{commit}"], f"revision {rev!r}", cwd=repo, text=True
    ).stdout.strip()
    into.mkdir(parents=True)
    held = [p for p in PACKAGES if subprocess.run(["git", "cat-file", "-e", f"{commit}:{p}"], cwd=repo).returncode == 0]
    archive = run_checked(["git", "archive", commit, *held], f"git archive {rev}", cwd=repo).stdout
    run_checked(["tar", "-x", "-C", str(into)], f"unpacking {rev}", input=archive)
    (into / "COMMIT").write_text(commit + "\n")
    return commit


def imported_from(result: dict, tree: Path) -> bool:
    return all(Path(folder).is_relative_to(tree) for folder in result["imported"])


def parse_revs(items: list[str]) -> dict[str, str]:
    """{name: revision} from NAME=REV items, in order; names are identifiers (they become folders)."""
    revs = {}
    for item in items:
        name, sep, rev = item.partition("=")
        if not sep or not name.isidentifier() or not rev or name in revs:
            raise SystemExit(f"--revs wants distinct NAME=REV with NAME an identifier, got {item!r}")
        revs[name] = rev
    if len(revs) < 2:
        raise SystemExit("--revs: name at least two revisions to compare (e.g. base=8debdf9 now=HEAD)")
    return revs


def ray_counts(text: str) -> list[int]:
    try:
        counts = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"rays per ping, comma-separated integers, got {text!r}") from None
    if not counts or min(counts) < 1:
        raise argparse.ArgumentTypeError(f"rays per ping must be >= 1, got {text!r}")
    return counts


def positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--revs",
        action="append",
        default=[],
        metavar="NAME=REV",
        help="a revision to time, oldest first (repeatable; each is compared with every earlier one)",
    )
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--rays", type=ray_counts, default="20000,100000", help="rays per ping, comma-separated")
    parser.add_argument("--bounces", type=int, default=3)
    parser.add_argument("--pings", type=int, default=256, help="batch size")
    parser.add_argument("--batches", type=int, default=8, help="batches per end-to-end run")
    parser.add_argument("--rounds", type=positive, default=3, help="timed runs per revision, in turning order")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    parser.add_argument(
        "--export-to", type=Path, help="only export each revision to FOLDER/NAME (with git), to time them elsewhere"
    )
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)  # an exported tree to time
    args = parser.parse_args(argv)
    rays = args.rays
    if args.child:  # one revision, in its own process
        print(json.dumps(child(args.child, rays, args.bounces, args.pings, args.batches, args.device)))
        return {}
    revs = parse_revs(args.revs)
    if args.export_to:
        for name, rev in revs.items():
            print(f"{name}: {rev} = {export(rev, args.export_to / name)} in {args.export_to / name}")
        return {}
    runs: dict[str, list[dict]] = {name: [] for name in revs}
    with tempfile.TemporaryDirectory() as tmp:
        commits = {name: export(rev, Path(tmp) / name) for name, rev in revs.items()}
        names = list(revs)
        for r in range(args.rounds):
            for name in names[r % len(names) :] + names[: r % len(names)]:
                tree = Path(tmp) / name
                cmd = [sys.executable, __file__, "--child", str(tree), "--device", args.device]
                cmd += ["--rays", ",".join(map(str, rays))]
                cmd += ["--bounces", str(args.bounces), "--pings", str(args.pings), "--batches", str(args.batches)]
                done = run_checked(cmd, f"{name} ({revs[name]}), round {r + 1}", text=True)
                result = json.loads(done.stdout.strip().splitlines()[-1])
                if not imported_from(result, tree):
                    raise SystemExit(f"{name}: imported {result['imported']}, not the revision's tree {tree}")
                runs[name].append(result)
                rates = ", ".join(f"{c:,} rays {result[str(c)]['energyscapes_per_s']:,.0f}/s" for c in rays)
                print(f"round {r + 1}, {name}: {rates}", flush=True)
    return write(args, revs, commits, runs, rays)


def write(args, revs: dict, commits: dict, runs: dict, rays: list[int]) -> dict:
    import warp as wp

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
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
    res = write_json(out / f"{stem}.json", res, device=str(device))
    names = list(revs)
    pairs = [(later, earlier) for i, later in enumerate(names) for earlier in names[:i]]
    lines = [
        f"# `Sonar.simulate` end to end, {len(names)} revisions in one job, on {res['device_name']} ({res['device']})",
        "",
        f"Reference office, max_bounces={args.bounces}, {args.batches} batches of {args.pings} pings per run, warp "
        f"{res['warp']}, {res['date']}. Energyscapes/s, median of {args.rounds} rounds (the order turns each "
        "round); ratios of the medians, each revision against every earlier one.",
        "",
        "| revision | commit |",
        "|---|---|",
        *(f"| {name} | {revs[name]} = {commits[name][:10]} |" for name in names),
        "",
        "| rays per ping | " + " | ".join(names) + " | " + " | ".join(f"{a} / {b}" for a, b in pairs) + " |",
        "|---|" + "---|" * (len(names) + len(pairs)),
    ]
    for count in rays:
        median = {n: m["median"] for n, m in res["energyscapes_per_s"][str(count)].items()}
        rates = [f"{median[n]:,.0f}" for n in names]
        ratios = [f"{median[a] / median[b]:.2f}x" for a, b in pairs]
        lines.append(f"| {count:,} | " + " | ".join(rates + ratios) + " |")
    lines += ["", provenance_line(res["provenance"])]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
