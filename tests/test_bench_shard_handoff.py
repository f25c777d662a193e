"""benchmarks/bench_shard_handoff.py: a shard handed to a writer process both ways, each timed (CPU)."""

import json
import sys

import pytest

from benchmarks import bench_shard_handoff


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="shared memory in /dev/shm, forked helpers")
def test_both_handoffs_reach_the_writer_and_are_timed(tmp_path):
    res = bench_shard_handoff.main(["--shards", "1", "--repeats", "1", "--out", str(tmp_path)])
    assert set(res["modes"]) == {"pickled", "shared"}
    for row in res["modes"].values():
        assert row["wall_ms"] > 0 and row["sender_cpu_ms"] >= 0 and row["writer_cpu_ms"] >= 0
    saved = json.loads((tmp_path / "shard_handoff.json").read_text())
    assert saved["provenance"]["commit"] and "| shared |" in (tmp_path / "shard_handoff.md").read_text()
