"""benchmarks/start_costs.py: a worker's start, step by step, for processes started together (CPU)."""

import json
import sys

import pytest

from benchmarks import start_costs


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="its workers are forked, as generate's are")
def test_every_process_times_every_step(tmp_path, monkeypatch):
    monkeypatch.delenv(start_costs.QUEUES_ENV, raising=False)
    res = start_costs.main(["--device", "cpu", "--processes", "2", "--out", str(tmp_path)])
    (row,) = res["rows"]
    assert row["processes"] == 2 and [w["index"] for w in row["workers"]] == [0, 1]
    for worker in row["workers"]:
        assert all(worker[step] >= 0 for step in start_costs.STEPS) and worker["episode"] > 0
    saved = json.loads((tmp_path / "start_costs.json").read_text())
    assert saved["provenance"]["commit"] and "| 2 |" in (tmp_path / "start_costs.md").read_text()
    assert saved["driver_env"][start_costs.QUEUES_ENV] == "1"  # as a generate worker starts CUDA
