"""generate_load.py: frames/s beside the machine's load, its readers of nvidia-smi and py-spy; spy_rendering.py."""

import json
import sys

import pytest

from benchmarks import generate_load


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/stat, as on the GPU hosts")
def test_a_run_reports_its_rate_and_the_cpu_it_kept_busy(tmp_path):
    res = generate_load.main(
        [
            "--settings",
            "cpu/1/spin/0/0/release/4",
            "--suite",
            "tiny",
            "--frames",
            "24",
            "--rounds",
            "1",
            "--out",
            str(tmp_path),
        ]
    )
    (row,) = res["rows"]
    assert row["setting"] == "cpu/1/spin/0/0/release/4" and row["frames"] == 24 and row["helpers"] == 0
    assert row["pool"] == "release" and row["queues"] == "4"  # the setting's fields reach the generate process
    assert row["frames_per_s"] == pytest.approx(24 / row["seconds"]) and 0 < row["cpu_busy"] <= 1
    assert row["seconds_by_part"]["sonar"] > 0 and row["devices"] == ["cpu"]
    assert row["cpu_ms_per_frame"]["user"] > 0 and row["minor_faults_per_frame"] > 0
    # timed from make_dataset's call, as generate's seconds are: after its imports, plan and scene checks
    assert row["before_s"] > 0 and row["timed"][1] - row["timed"][0] == pytest.approx(row["seconds"])
    saved = json.loads((tmp_path / "generate_load.json").read_text())
    assert (
        saved["provenance"]["commit"]
        and "| cpu/1/spin/0/0/release/4 | 0 |" in (tmp_path / "generate_load.md").read_text()
    )


def test_utilisation_is_read_over_the_timed_run_with_its_idle_ends(tmp_path):
    """Samples before the run (a previous process's tail) and after it count in the plain mean
    alone; within the run, busy and idle seconds from each sample's share of time, and the idle
    seconds of the run's first and last EDGE_S apart."""
    from datetime import datetime

    def stamp(second: float) -> str:
        return datetime.fromtimestamp(1_800_000_000 + second).strftime("%Y/%m/%d %H:%M:%S.%f")[:-3]

    # one sample a second; GPU 0: a stale 11 % first, idle to 9 s, busy 9-17 s, idle after; GPU 1 idle
    lines = []
    for second in range(21):
        busy = 100 if 9 <= second < 18 else (11 if second == 0 else 0)
        lines += [f"{stamp(second)}, 0, {busy}", f"{stamp(second)}, 1, 0"]
    samples = tmp_path / "u.csv"
    samples.write_text("\n".join([*lines, "[N/A]", f"{stamp(21)}, 0"]) + "\n")
    got = generate_load.utilisation(samples, window=(1_800_000_000 + 5, 1_800_000_000 + 19))
    zero = got[0]
    assert zero["mean"] == pytest.approx((11 + 9 * 100) / 21)  # every sample
    assert zero["busy_s"] == pytest.approx(9) and zero["idle_s"] == pytest.approx(6)  # 15 samples of 1 s in 5..19
    assert zero["in_use_mean"] == pytest.approx(900 / 15)
    assert zero["idle_first_s"] == pytest.approx(4) and zero["idle_last_s"] == pytest.approx(2)  # 5-8; 18, 19
    assert got[1]["busy_s"] == 0 and got[1]["idle_s"] == pytest.approx(15)


def test_spy_summary_sums_busy_samples_by_activity(tmp_path):
    raw = tmp_path / "spy.txt"
    command = 'process 7:"python -c \nimport json; print("a;b")\n {"out": "x"}"'
    raw.write_text(
        f"{command};thread (0x1);_write (runner.py:1);encode (chunks.py:2);fletcher32 (chunks.py:3) 6\n"
        f'{command};process 8:"python";thread (0x2);encode (chunks.py:2);compress (isal:1) 3\n'
        f"{command};thread (0x3);BatchCopies._land (sonar.py:9);synchronize_event (context.py:1) 1\n"
        f"{command};thread (0x4);Queue._feed (queues.py:1);ForkingPickler.dumps (reduction.py:1) 8\n"
        f"{command};thread (0x5);select (selectors.py:1) 2\n"
    )
    assert generate_load.spy_summary(raw) == {
        "pickle": 0.4,
        "checksum": 0.3,
        "compress": 0.15,
        "other": 0.1,
        "wait for the GPU": 0.05,
    }


def test_spy_rendering_counts_the_rendering_threads_alone(tmp_path):
    """Samples of a worker's rendering thread count; those of helpers forked from it (their stacks
    hold the fork's frames), of its landing and hand-over threads and of the parent do not."""
    from benchmarks import spy_rendering

    worker = 'process 9:"python";thread (0x1);_serve (workers.py:1);run_tasks (runner.py:2)'
    raw = tmp_path / "spy.txt"
    raw.write_text(
        f"{worker};_Run.render (runner.py:3);WarpScene.lidar_mesh (scene.py:4);Mesh.__init__ (types.py:5) 3\n"
        f"{worker};_Run.render (runner.py:3);ping_seeds (signals.py:6) 1\n"
        f"{worker};helper_pool (helper_processes.py:7);BaseProcess._bootstrap (process.py:8);_write (shards.py:9) 50\n"
        f"{worker};BatchCopies._land (sonar.py:10);synchronize_event (context.py:11) 20\n"
        f"{worker};_hand_over (runner.py:12);SharedFrames.share (shared_frames.py:13) 30\n"
        'process 1:"python";thread (0x2);make_dataset (generate.py:14) 40\n'
    )
    table = spy_rendering.table([("run", str(raw), 2)], rate=100.0)
    assert "| all, ms an episode | 20.0 |" in table  # 4 samples of 10 ms over 2 episodes
    assert "| of which the LiDAR's own tree | 75.0 % (15.0) |" in table
    assert "| ping seeds | 25.0 % (5.0) |" in table
    assert "| shard into shared memory | 0.0 % (0.0) |" in table
