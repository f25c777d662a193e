"""benchmarks/worker_timeline.py: a generate run's per-worker timeline (CPU, two forked workers)."""

import json
import sys

import pytest

from benchmarks import worker_timeline


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="workers are forked on Linux")
def test_a_two_worker_run_has_each_workers_moments_in_order(tmp_path):
    args = ["--suite", "tiny", "--frames", "24", "--shards", "2", "--workers", "2", "--device", "cpu"]
    res = worker_timeline.main([*args, "--out", str(tmp_path)])
    rows = res["summary"]["workers"]
    assert len(rows) == 2 and all(r["episodes"] >= 1 for r in rows)  # 2 shards, one each
    for r in rows:  # each worker: CUDA up (here the device picked), first episode, its end, its last write
        assert 0 <= r["up_s"] <= r["first_episode_at_s"]
        assert r["first_episode_at_s"] + r["first_episode_s"] <= r["last_episode_end_s"] <= r["last_write_end_s"]
    assert res["run"]["workers"] == 2
    saved = json.loads((tmp_path / "timeline.json").read_text())
    assert saved["provenance"]["commit"] and saved["events"]  # names the code it measured; keeps the events
    assert "| 1 |" in (tmp_path / "timeline.md").read_text()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="helpers are forked on Linux")
def test_a_helpers_writes_and_the_runs_moments_are_logged(tmp_path):
    args = ["--suite", "tiny", "--frames", "24", "--shards", "2", "--workers", "1", "--helpers", "1", "--device", "cpu"]
    res = worker_timeline.main([*args, "--out", str(tmp_path)])
    (row,) = res["summary"]["workers"]  # one process renders: the call's own
    assert row["episodes"] >= 2 and row["helpers_up_s"] is not None
    by_helper = [e for e in res["events"] if e["event"] == "write_end" and e["ppid"] == row["pid"]]
    assert len(by_helper) == 1  # the first shard went to the helper, the last was written here
    moments = res["summary"]["moments_s"]
    assert row["helpers_up_s"] <= row["first_episode_at_s"] and moments["last_episode_end"] <= moments["call_end"]
