"""Printed words that say what the numbers are: counts in the singular where there is one, a
picture's title that says how much of the ping it draws, a report that names a suite as a suite
and whose examples run in the order it says."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from clitools import counted


def test_counts_read_in_the_singular_for_one():
    assert counted(1, "shard") == "1 shard" and counted(2, "shard") == "2 shards"
    assert counted(0, "episode") == "0 episodes" and counted(12000, "frame") == "12,000 frames"
    assert counted(1, "echo", "echoes") == "1 echo" and counted(3, "echo", "echoes") == "3 echoes"


def test_sonar_picture_title_says_how_many_echoes_it_draws():
    from acoustic_sim.render import MAX_ECHO_POINTS, reflection_points_title

    assert reflection_points_title("max_bounces=3", 19938) == (
        f"max_bounces=3: last reflection points of the {MAX_ECHO_POINTS:,} strongest of 19,938 echoes"
    )
    assert reflection_points_title("max_bounces=0", 812) == "max_bounces=0: last reflection points of 812 echoes"


def _report(suite, variant) -> dict:
    from learn.report import METRICS, OTHER_METRICS

    stats = {key: {"mean": 0.5, "std": 0.1} for key, _, _ in METRICS + OTHER_METRICS}
    return {
        "results": {"model": {"all": stats, "office": stats | {"windows": 3}}},
        "checkpoint": "runs/unet/best.pt",
        "model": {"name": "polar_unet"},
        "data_config": {"frames": 5},
        "windows": 3,
        "split": "all",
        "data": "data/drive",
        "suite": suite,
        "variant": variant,
    }


def test_report_names_the_suite_as_a_suite_and_says_which_way_examples_run():
    from learn.report import report_markdown

    title = report_markdown(_report("paper", None)).splitlines()[0]
    assert title == "# Evaluation: polar_unet (K = 5) on the `paper` suite", title
    variant = report_markdown(_report("ablation", "bounces_0")).splitlines()[0]
    assert variant.endswith("on the `ablation` suite, variant `bounces_0`"), variant
    recording = report_markdown(_report(None, None))
    assert recording.splitlines()[0].endswith("on `data/drive`")
    assert "poorest at the top and its best at the bottom" in recording


def test_example_rows_run_from_poor_to_good():
    """Ten windows of known scan F1: the four picked (quantiles 0.1 ... 0.9) come in rising F1,
    whatever their window order (0.1, 0.3, 0.6, 0.8 here, in windows 1, 3, 8, 6)."""
    from learn.evaluate import _example_rows

    f1 = np.array([0.9, 0.1, 0.5, 0.3, 0.7, 0.2, 0.8, 0.4, 0.6, 0.0])
    per_window = {"model": {"scan_f1": f1, "beam_accuracy": f1}, "echo peak": {"scan_f1": np.zeros(10)}}
    windows = SimpleNamespace(
        config=SimpleNamespace(label_offset=0),
        level=0,
        scenario=np.zeros(10, int),
        batch=lambda idx: (torch.zeros(1, 1, 1, 2, 2), torch.zeros(1, 1, 2, 2)),
    )
    predictors = {"model": (lambda x: torch.zeros(1, 1, 2, 2), 0.5, windows)}
    frames = SimpleNamespace(scenarios=["office"])
    rows = _example_rows(predictors, "model", "model", per_window, windows, np.arange(10), frames, 4)
    shown = [float(f1[int(row["title"].rpartition("window ")[2])]) for row in rows]
    assert shown == [0.1, 0.3, 0.6, 0.8], shown


def test_predict_shows_a_bar_and_says_what_it_wrote(tiny_dataset, tmp_path):
    """`learn predict` on the tiny dataset (two 8-frame drives; K = 5: 4 windows each) draws a
    progress bar on stderr and ends with one line: the frames predicted, of what, where, on how
    many beams, at which threshold; --quiet keeps the line and drops the bar."""
    import subprocess
    import sys

    import learn

    out = tmp_path / "pred.npz"
    command = [sys.executable, "-m", "learn", "predict", "--checkpoint", str(learn.PRETRAINED_CHECKPOINT)]
    command += ["--input", str(tiny_dataset)]
    done = subprocess.run([*command, "--out", str(out)], capture_output=True, text=True, timeout=300, check=True)
    saved = np.load(out)
    frames = sorted(saved["frame"].tolist())
    assert len(frames) == 8 and "predicting:" in done.stderr and "/8 [" in done.stderr, done.stderr  # the bar
    assert done.stdout.strip().startswith(f"wrote {out}: LiDAR images and scans for 8 frames of {tiny_dataset} ")
    assert f"(label frames {frames[0]}..{frames[-1]}; 181 beams, return threshold " in done.stdout, done.stdout
    quiet = [*command, "--out", str(tmp_path / "quiet.npz"), "--quiet"]
    quiet = subprocess.run(quiet, capture_output=True, text=True, timeout=300, check=True)
    assert quiet.stderr == "" and quiet.stdout.startswith(f"wrote {tmp_path / 'quiet.npz'}: "), quiet.stderr
