"""The README's figures of a clean clone: `make demo` and `make test` timed, the demo's scores, the
count of CLI error cases. Nothing of it is typed by hand.

    python benchmarks/clean_clone_run.py [--out benchmarks/results]

Clones HEAD (the last commit, not uncommitted edits) into a temporary folder and, there, in turn:
the set-up both make targets share (`make .venv/.installed`: the venv, torch's CPU build, the
package with its test extra), `make demo`, `make test` with `PYTEST_ADDOPTS=--durations=15`, and
`pytest --collect-only tests/test_cli_errors.py`. Reads the demo's scores from the evaluate step's
`out/report/metrics.json` (scan F1 and beam accuracy of the pretrained model, the smoke run, the
echo peak and the empty image), the suite's counts and its 15 slowest tests from pytest's output,
and lists any line of the demo's output that mentions Warp or CUDA (the README promises none).
Writes clean_clone_cpu.json and .md under --out with the commit, the machine (CPU model, cores,
memory) and the date. About 15 minutes on a 2-core CPU; needs the network for pip and make.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import machine, strip_machine_paths, write_json  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402

CLI_ERRORS = "tests/test_cli_errors.py"
CLI_CASE_TEST = "test_user_error_is_one_line"  # one subprocess per case of the file's CASES
DEMO_METRICS = Path("out") / "report" / "metrics.json"
DEMO_SCORES = ("scan_f1", "beam_accuracy")
PYTEST_COUNTS = ("passed", "failed", "skipped", "xfailed", "xpassed", "errors", "error", "deselected", "warnings")
WARP_OR_CUDA = re.compile(r"\bwarp\b|\bcuda\b", re.IGNORECASE)


def clone_head(root: Path, dest: Path) -> str:
    """A fresh clone of `root`'s HEAD commit in `dest`; returns the commit id."""
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True)
    commit = commit.stdout.strip()
    subprocess.run(["git", "clone", "--quiet", "--no-checkout", str(root), str(dest)], check=True)
    subprocess.run(["git", "checkout", "--quiet", commit], cwd=dest, check=True)
    return commit


def timed(command: list[str], cwd: Path, env: dict | None = None) -> dict:
    """Runs `command` in `cwd`, echoing its output; wall time [s], exit code and the output (stdout
    and stderr together, the clone's folder written as '.')."""
    print(f"$ {' '.join(command)}", flush=True)
    t0 = time.perf_counter()
    done = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    output = (done.stdout + done.stderr).replace(str(cwd), ".")
    print(output[-3000:], flush=True)
    return {"command": " ".join(command), "seconds": seconds, "returncode": done.returncode, "output": output}


def pytest_summary(output: str) -> dict:
    """Counts and seconds of pytest's last summary line, e.g. '812 passed, 3 skipped in 421.07s (0:07:01)'."""
    lines = [line for line in output.splitlines() if re.search(r"\bin [\d.]+s\b", line)]
    if not lines:
        raise ValueError("no pytest summary line (N passed ... in Xs) in the output")
    line = lines[-1].strip("= ")
    counts = {name: int(n) for n, name in re.findall(r"(\d+) (\w+)", line) if name in PYTEST_COUNTS}
    return {"counts": counts, "seconds": float(re.search(r"\bin ([\d.]+)s\b", line).group(1)), "line": line}


def slowest_tests(output: str) -> list[dict]:
    """The entries of pytest's '--durations' table: seconds, phase (setup/call/teardown) and test id."""
    found = []
    for seconds, phase, test in re.findall(r"^([\d.]+)s (setup|call|teardown)\s+(\S+)", output, re.M):
        found.append({"seconds": float(seconds), "phase": phase, "test": test})
    return found


def cli_error_cases(collect_output: str) -> dict:
    """From `pytest --collect-only -q` of the CLI error tests: the subprocess cases and all items."""
    items = [line.strip() for line in collect_output.splitlines() if line.startswith(f"{CLI_ERRORS}::")]
    cases = [item for item in items if item.split("::")[1].startswith(CLI_CASE_TEST + "[")]
    if not cases:
        raise ValueError(f"no {CLI_CASE_TEST}[...] items in the collected tests")
    return {"cases": len(cases), "collected": len(items)}


def demo_scores(metrics: dict) -> dict:
    """{predictor: {score: mean over windows}} from the demo's evaluate metrics.json, with the drive's size."""
    scores = {
        name: {key: float(result["all"][key]["mean"]) for key in DEMO_SCORES}
        for name, result in metrics["results"].items()
    }
    return {"windows": metrics["windows"], "data": metrics["data"], "scores": scores}


def warp_or_cuda_lines(output: str) -> list[str]:
    """Lines of the demo's output that mention Warp or CUDA, without the commands make echoes."""
    return [
        strip_machine_paths(line)[0]
        for line in output.splitlines()
        if WARP_OR_CUDA.search(line) and " -m acoustic_sim " not in line and " -m learn " not in line
    ]


def minutes(seconds: float) -> str:
    whole = round(seconds)
    return f"{whole // 60} min {whole % 60} s"


def markdown(record: dict) -> str:
    """The record as the results' markdown page."""
    steps, demo, test = record["steps"], record["demo"], record["test"]
    lines = [
        f"# A clean clone of {record['commit'][:12]}: `make demo` and `make test` on the CPU",
        "",
        f"`python benchmarks/clean_clone_run.py`, {record['date']}, on {record['machine']['cpu']} "
        f"({record['machine']['usable_cores']} cores usable, {record['machine']['memory_gib']} GiB).",
        "",
        "| step | wall time | exit |",
        "|---|---|---|",
        *(f"| `{s['command']}` | {minutes(s['seconds'])} | {s['returncode']} |" for s in steps.values()),
        "",
        f"Set-up and demo together: **{minutes(record['demo_with_setup_s'])}**; set-up and tests together: "
        f"**{minutes(record['test_with_setup_s'])}**.",
        "",
        f"## The demo's scores (a fresh {demo['windows']}-window drive, `{demo['data']}`)",
        "",
        "| predictor | scan F1 @0.10 m | beam accuracy |",
        "|---|---|---|",
        *(f"| {n} | {s['scan_f1']:.3f} | {s['beam_accuracy']:.3f} |" for n, s in demo["scores"].items()),
        "",
        "Lines of the demo's output that mention Warp or CUDA: "
        + (", ".join(f"`{line}`" for line in record["warp_or_cuda_lines"]) or "none")
        + ".",
        "",
        f"## The suite: {test['summary']['line']}",
        "",
        f"`{CLI_ERRORS}` runs **{record['cli_errors']['cases']}** CLI error cases as subprocesses "
        f"({record['cli_errors']['collected']} tests collected in the file).",
        "",
        "| seconds | phase | test (15 slowest) |",
        "|---|---|---|",
        *(f"| {t['seconds']:.1f} | {t['phase']} | `{t['test']}` |" for t in test["slowest"]),
    ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        clone = Path(tmp) / "sonar2lidar"
        commit = clone_head(ROOT, clone)
        env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
        steps = {"setup": timed(["make", ".venv/.installed"], clone, env)}
        if "No rule to make target" in steps["setup"]["output"]:  # a Makefile without the target: the demo sets up
            steps["setup"] |= {"seconds": 0.0, "returncode": 0, "command": "(set-up inside make demo)"}
        steps["demo"] = timed(["make", "demo"], clone, env)
        steps["test"] = timed(["make", "test"], clone, env | {"PYTEST_ADDOPTS": "--durations=15"})
        collect = [".venv/bin/python", "-m", "pytest", "--collect-only", "-q", CLI_ERRORS]
        steps["collect"] = timed(collect, clone, env)
        if steps["demo"]["returncode"] or steps["setup"]["returncode"]:
            raise SystemExit("make demo failed: nothing written")
        metrics = json.loads((clone / DEMO_METRICS).read_text())
    record = {
        "commit": commit,
        "date": time.strftime("%Y-%m-%d"),
        "machine": machine(),
        "steps": {k: {key: s[key] for key in ("command", "seconds", "returncode")} for k, s in steps.items()},
        "demo_with_setup_s": steps["setup"]["seconds"] + steps["demo"]["seconds"],
        "test_with_setup_s": steps["setup"]["seconds"] + steps["test"]["seconds"],
        "demo": demo_scores(metrics),
        "warp_or_cuda_lines": warp_or_cuda_lines(steps["demo"]["output"]),
        "test": {"summary": pytest_summary(steps["test"]["output"]), "slowest": slowest_tests(steps["test"]["output"])},
        "cli_errors": cli_error_cases(steps["collect"]["output"]),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    # The stamp names the clone's commit (clean by construction), not this tree's, which may have moved on.
    os.environ |= {"SONAR2LIDAR_COMMIT": commit, "SONAR2LIDAR_DIRTY": "0"}
    record = write_json(args.out / "clean_clone_cpu.json", record, device="cpu")
    text = markdown(record) + "\n" + provenance_line(record["provenance"]) + "\n"
    (args.out / "clean_clone_cpu.md").write_text(text)
    print(text)
    return record


if __name__ == "__main__":
    main()
