"""benchmarks/sonar_same_job.py without a GPU: revisions are named and exported as git has them,
and the table reports medians over rounds with ratios against the first revision."""

import argparse
import json
import subprocess

import pytest

from benchmarks import sonar_same_job

ROOT = sonar_same_job.ROOT


@pytest.mark.parametrize("items", [["base=HEAD"], ["base=HEAD", "base=HEAD~1"], ["base=HEAD", "now"], ["=HEAD", "a=b"]])
def test_revisions_need_distinct_names_and_two_at_least(items):
    with pytest.raises(SystemExit):
        sonar_same_job.parse_revs(items)


def test_export_is_the_commits_simulator(tmp_path):
    commit = sonar_same_job.export("HEAD", tmp_path / "now")
    assert (
        commit == subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    )
    for path in ("acoustic_sim/sonar.py", "scenes/__init__.py"):
        at_head = subprocess.run(["git", "show", f"HEAD:{path}"], cwd=ROOT, capture_output=True, check=True).stdout
        assert (tmp_path / "now" / path).read_bytes() == at_head
    assert not (tmp_path / "now" / "learn").exists()  # the simulator only
    with pytest.raises(subprocess.CalledProcessError):
        sonar_same_job.export("no-such-revision", tmp_path / "bad")


def test_table_is_median_of_rounds_with_ratios_to_the_first(tmp_path):
    args = argparse.Namespace(device="cpu", bounces=3, pings=256, batches=8, rounds=3, out=str(tmp_path))
    revs = {"base": "8debdf9", "now": "HEAD"}
    commits = {"base": "a" * 40, "now": "b" * 40}

    def rounds(*rates):
        return [{"20000": {"energyscapes_per_s": r}} for r in rates]

    runs = {"base": rounds(90.0, 100.0, 400.0), "now": rounds(150.0, 140.0, 160.0)}
    sonar_same_job.write(args, revs, commits, runs, [20000])
    table = (tmp_path / "sonar_same_job_cpu.md").read_text()
    assert "| 20,000 | 100 | 150 | 1.50x |" in table
    saved = json.loads((tmp_path / "sonar_same_job_cpu.json").read_text())
    assert saved["energyscapes_per_s"]["20000"]["base"]["rounds"] == [90.0, 100.0, 400.0]
    assert saved["revisions"]["now"] == {"rev": "HEAD", "commit": "b" * 40}
