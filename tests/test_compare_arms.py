"""benchmarks/compare_arms.py on study folders written here with known scores: paired differences
by seed, the choice made on the choose set only, and the stop reason read from the history."""

import json
import sys

import pytest

from benchmarks import compare_arms

SETS = ("in_domain", "reality", "crossengine")


def write_arm(root, name, scores, epochs=10, best_epoch=6, patience=4, summary_epochs=None):
    """An arm folder as `learn sim2real` leaves it: seed*/sim2real.json and seed*/bounces_3 run files
    (summary_epochs: the summary an earlier call left, when the last was killed mid-run)."""
    for seed, by_set in enumerate(scores):
        run = root / name / f"seed{seed}" / "bounces_3"
        run.mkdir(parents=True)
        result = {s: {"scan_f1": {"mean": v}} for s, v in zip(SETS, by_set, strict=True)}
        result |= {f"{s}_echo_peak": {"scan_f1": {"mean": 0.1}} for s in SETS[1:]}
        (run.parent / "sim2real.json").write_text(json.dumps({"bounces_3": result}))
        (run / "config.json").write_text(json.dumps({"train_config": {"patience": patience}}))
        (run / "summary.json").write_text(json.dumps({"epochs": summary_epochs or epochs, "best_epoch": best_epoch}))
        (run / "history.csv").write_text("epoch,val_scan_f1\n" + "".join(f"{e},0.5\n" for e in range(1, epochs + 1)))
    return root / name


def test_paired_differences_and_choice_on_the_choose_set_only(tmp_path, monkeypatch, capsys):
    plain = write_arm(tmp_path, "plain", [(0.7, 0.50, 0.40), (0.7, 0.52, 0.42), (0.7, 0.54, 0.41)])
    # best on the report set but not on the choose set: the rule must not pick it
    greedy = write_arm(
        tmp_path, "greedy", [(0.7, 0.50, 0.60), (0.7, 0.51, 0.61), (0.7, 0.52, 0.62)], epochs=8, best_epoch=7
    )
    steady = write_arm(tmp_path, "steady", [(0.7, 0.56, 0.43), (0.7, 0.57, 0.44), (0.7, 0.58, 0.45)])
    out = tmp_path / "out"
    argv = ["compare_arms", f"plain={plain}", f"greedy={greedy}", f"steady={steady}", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    compare_arms.main()
    text = (out / "compare_arms.md").read_text()
    assert "**steady**" in text and "**greedy**" not in text
    assert "+0.060 / +0.050 / +0.040" in text  # steady minus plain on reality, seed by seed
    assert "+0.200 / +0.190 / +0.210" in text  # greedy minus plain on crossengine
    assert "crossengine 0.440 ± 0.008 (4.4x the echo peak)" in text
    assert "early stop, 10 (6)" in text and "time budget, 8 (7)" in text
    assert (out / "compare_arms.png").stat().st_size > 0


def test_arms_with_other_seeds_than_the_reference_are_refused(tmp_path):
    plain = write_arm(tmp_path, "plain", [(0.7, 0.5, 0.4)] * 3)
    short = write_arm(tmp_path, "short", [(0.7, 0.5, 0.4)] * 2)
    arms = {"plain": compare_arms.load_arm(plain, "bounces_3"), "short": compare_arms.load_arm(short, "bounces_3")}
    with pytest.raises(ValueError, match="seeds"):
        compare_arms.compare(arms, "plain", list(SETS))
    with pytest.raises(ValueError, match="no variant"):
        compare_arms.load_arm(plain, "bounces_1")


def test_a_run_killed_mid_call_is_cut_off_not_early_stopped(tmp_path):
    """31 epochs in the history, the summary from a call that ended at epoch 11 with 11 kept: 31 - 11
    exceeds the patience, yet nothing stopped the run but its kill."""
    arm = write_arm(tmp_path, "killed", [(0.7, 0.5, 0.4)], epochs=31, best_epoch=11, summary_epochs=11)
    assert compare_arms.stop_reason(arm / "seed0" / "bounces_3") == "cut off, 31 (summary of 11)"
