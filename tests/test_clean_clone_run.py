"""benchmarks/clean_clone_run.py reads its figures from what make and pytest print and what the demo
writes, on small hand-written inputs; its whole run is checked with the make steps replaced by
fakes (the real run takes ~15 CPU minutes: the lead runs it)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks import clean_clone_run as ccr  # noqa: E402
from benchmarks.provenance import machine_paths  # noqa: E402

PYTEST_OUTPUT = """\
All checks passed!
........................................................................ [ 10%]
============================= slowest 15 durations =============================
95.31s call     tests/test_generate_faults.py::test_killed_worker_is_replaced
41.02s setup    tests/test_learn.py::test_train_writes_everything
0.51s teardown tests/test_paths.py::test_shoebox[3]
=========================== short test summary info ============================
812 passed, 3 skipped, 1 deselected, 14 warnings in 421.07s (0:07:01)
"""
COLLECT_OUTPUT = """\
tests/test_cli_errors.py::test_user_error_is_one_line[bad-device]
tests/test_cli_errors.py::test_user_error_is_one_line[no-such-file]
tests/test_cli_errors.py::test_user_error_is_one_line[checkpoint-names-twice]
tests/test_cli_errors.py::test_the_audit_is_wide_and_no_case_ran_file_code
tests/test_cli_errors.py::test_debug_shows_the_trace

5 tests collected in 1.61s
"""
SCORES = {"pretrained": (0.923, 0.906), "smoke run": (0.630, 0.601), "echo peak": (0.344, 0.31), "empty": (0.0, 0.12)}


def fake_metrics() -> dict:
    """What `learn evaluate` writes, reduced to the keys the script reads (and one it does not)."""
    results = {
        name: {"all": {"scan_f1": {"mean": f1, "std": 0.1}, "beam_accuracy": {"mean": acc, "std": 0.1}, "iou": {}}}
        for name, (f1, acc) in SCORES.items()
    }
    return {"windows": 192, "data": "out/drive", "results": results}


def test_pytest_summary_and_slowest_tests():
    summary = ccr.pytest_summary(PYTEST_OUTPUT)
    assert summary["counts"] == {"passed": 812, "skipped": 3, "deselected": 1, "warnings": 14}
    assert summary["seconds"] == 421.07
    assert ccr.slowest_tests(PYTEST_OUTPUT) == [
        {"seconds": 95.31, "phase": "call", "test": "tests/test_generate_faults.py::test_killed_worker_is_replaced"},
        {"seconds": 41.02, "phase": "setup", "test": "tests/test_learn.py::test_train_writes_everything"},
        {"seconds": 0.51, "phase": "teardown", "test": "tests/test_paths.py::test_shoebox[3]"},
    ]
    with pytest.raises(ValueError, match="no pytest summary"):
        ccr.pytest_summary("All checks passed!\n")


def test_cli_error_cases_counts_the_subprocess_cases():
    """Three cases of the parametrised test among five collected items."""
    assert ccr.cli_error_cases(COLLECT_OUTPUT) == {"cases": 3, "collected": 5}
    with pytest.raises(ValueError):
        ccr.cli_error_cases("tests/test_cli_errors.py::test_debug_shows_the_trace\n")


def test_demo_scores_from_metrics():
    got = ccr.demo_scores(fake_metrics())
    assert got["windows"] == 192 and got["data"] == "out/drive"
    assert got["scores"] == {n: {"scan_f1": f1, "beam_accuracy": acc} for n, (f1, acc) in SCORES.items()}


def test_warp_or_cuda_lines_skip_the_echoed_commands():
    output = (
        ".venv/bin/python -m acoustic_sim render --scene office --device cpu --out out/office.png\n"
        ".venv/bin/python -m learn train --data out/data --out out/run --device cpu\n"
        "Warp 1.19.0 initialized:\n"
        "   CUDA not enabled in this build\n"
        "Module acoustic_sim.engine.kernels.paths 1a2b load on device 'cpu' took 0.4 ms  (cached)\n"
        "report: out/report/report.md\n"
    )
    assert ccr.warp_or_cuda_lines(output) == ["Warp 1.19.0 initialized:", "   CUDA not enabled in this build"]


def test_minutes():
    assert (ccr.minutes(446.2), ccr.minutes(59.6), ccr.minutes(600)) == ("7 min 26 s", "1 min 0 s", "10 min 0 s")


def test_clone_head_is_the_last_commit(tmp_path: Path):
    """The clone holds HEAD's files, not an uncommitted edit."""
    repo = tmp_path / "repo"
    repo.mkdir()
    env = ["-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(["git", "init", "-q"], cwd=repo, check=True)
    (repo / "f.txt").write_text("committed\n")
    subprocess.run(["git", "add", "."], cwd=repo, check=True)
    subprocess.run(["git", *env, "commit", "-qm", "one"], cwd=repo, check=True)
    (repo / "f.txt").write_text("edited, not committed\n")
    commit = ccr.clone_head(repo, tmp_path / "clone")
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, check=True)
    assert commit == head.stdout.strip()
    assert (tmp_path / "clone" / "f.txt").read_text() == "committed\n"


def test_main_writes_the_record(tmp_path: Path, monkeypatch):
    """With each command faked (the demo writes its metrics.json), main writes a JSON and a markdown
    page with the commit, machine, step times, the demo's scores, the suite and the CLI case count,
    stamped with its provenance and free of machine paths."""
    seconds = {"make .venv/.installed": 100.0, "make demo": 346.0, "make test": 421.5}

    def fake_timed(command, cwd, env=None):
        line = " ".join(command)
        output = {"make test": PYTEST_OUTPUT, "make demo": f"wrote {cwd}/out/report\n"}.get(line, COLLECT_OUTPUT)
        if line == "make demo":
            (cwd / ccr.DEMO_METRICS).parent.mkdir(parents=True)
            (cwd / ccr.DEMO_METRICS).write_text(json.dumps(fake_metrics()))
        if line == "make test":
            assert env["PYTEST_ADDOPTS"] == "--durations=15"
        return {"command": line, "seconds": seconds.get(line, 2.0), "returncode": 0, "output": output}

    cloned = "c" * 40  # not this tree's HEAD: the stamp must name the clone's commit, not where the script runs

    def fake_clone(root, dest):
        dest.mkdir(parents=True)
        return cloned

    monkeypatch.setattr(ccr, "timed", fake_timed)
    monkeypatch.setattr(ccr, "clone_head", fake_clone)
    for name in ("SONAR2LIDAR_COMMIT", "SONAR2LIDAR_DIRTY"):  # restored after the test, whatever main sets
        monkeypatch.setenv(name, "")
    record = ccr.main(["--out", str(tmp_path)])
    written = json.loads((tmp_path / "clean_clone_cpu.json").read_text())
    assert written == json.loads(json.dumps(record))
    assert written["commit"] == cloned == written["provenance"]["commit"] and written["provenance"]["dirty"] is False
    assert written["demo_with_setup_s"] == 446.0 and written["test_with_setup_s"] == 521.5
    assert written["demo"]["scores"]["pretrained"] == {"scan_f1": 0.923, "beam_accuracy": 0.906}
    assert written["cli_errors"] == {"cases": 3, "collected": 5}
    assert written["test"]["summary"]["counts"]["passed"] == 812
    assert {"cpu", "cores", "memory_gib"} <= set(written["machine"]) and written["date"]
    text = (tmp_path / "clean_clone_cpu.md").read_text()
    assert "| pretrained | 0.923 | 0.906 |" in text and "**7 min 26 s**" in text and "**3** CLI error cases" in text
    assert "Warp or CUDA: none." in text and "Provenance:" in text
    assert machine_paths(text + json.dumps(written)) == []
