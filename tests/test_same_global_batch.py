"""benchmarks/same_global_batch.py on run folders written here with known curves: the best epoch,
the DDP-minus-one difference paired by seed, and the verdict against the seed-to-seed spread."""

import json

import pytest

from benchmarks import same_global_batch

COLUMNS = ("epoch", "train_loss", "val_scan_f1", "val_chamfer_m", "samples_per_s")


def write_run(root, name, *, seed, processes, batch, curve, rates=(50.0, 100.0, 110.0), val=(3, 7)):
    run = root / name
    run.mkdir()
    group = {"backend": "nccl", "processes": processes} if processes > 1 else None
    config = {"train_config": {"seed": seed, "batch_size": batch}, "process_group": group}
    config["dataset"] = {"val_episodes": list(val), "split_seed": 0, "plan_id": "p1"}
    config["model_config"] = {"name": "polar_unet"}
    (run / "config.json").write_text(json.dumps(config))
    rows = [(e + 1, 0.4 - 0.01 * e, f, 1.0 - f, rates[e]) for e, f in enumerate(curve)]
    (run / "history.csv").write_text(",".join(COLUMNS) + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    return run


def test_within_noise_and_the_files(tmp_path):
    runs = [
        write_run(tmp_path, "one0", seed=0, processes=1, batch=16, curve=(0.30, 0.50, 0.45)),
        write_run(tmp_path, "one1", seed=1, processes=1, batch=16, curve=(0.30, 0.40, 0.46)),
        write_run(tmp_path, "ddp0", seed=0, processes=2, batch=8, curve=(0.20, 0.44, 0.47)),
        write_run(tmp_path, "ddp1", seed=1, processes=2, batch=8, curve=(0.45, 0.42, float("nan"))),
    ]
    result = same_global_batch.main([*map(str, runs), "--out", str(tmp_path / "out")])
    # best scan F1: one 0.50 / 0.46, DDP 0.47 / 0.45 (the NaN epoch is not a best)
    assert result["paired_difference"] == pytest.approx({0: -0.03, 1: -0.01})
    assert result["seed_spread"] == pytest.approx({1: 0.04, 2: 0.02})
    assert result["within"] is True
    saved = json.loads((tmp_path / "out" / "same_global_batch.json").read_text())
    assert [r["best_epoch"] for r in saved["runs"]] == [2, 3, 3, 1]
    assert saved["runs"][0]["windows_per_s"] == 105.0  # the median after the warm-up epoch
    assert "within the larger spread" in (tmp_path / "out" / "same_global_batch.md").read_text()
    assert (tmp_path / "out" / "same_global_batch.png").stat().st_size > 0


def test_a_difference_larger_than_the_seed_spread_is_outside(tmp_path):
    runs = [
        write_run(tmp_path, "one0", seed=0, processes=1, batch=16, curve=(0.50, 0.50, 0.50)),
        write_run(tmp_path, "one1", seed=1, processes=1, batch=16, curve=(0.49, 0.49, 0.49)),
        write_run(tmp_path, "ddp0", seed=0, processes=2, batch=8, curve=(0.40, 0.40, 0.40)),
    ]
    result = same_global_batch.compare([same_global_batch.load_run(r) for r in runs])
    assert result["within"] is False and result["noise"] == pytest.approx(0.01)
    assert "**outside**" in same_global_batch.markdown([same_global_batch.load_run(r) for r in runs], result)


def test_runs_at_different_global_batches_are_refused(tmp_path):
    runs = [
        write_run(tmp_path, "one0", seed=0, processes=1, batch=16, curve=(0.5,)),
        write_run(tmp_path, "ddp0", seed=0, processes=2, batch=16, curve=(0.5,)),
    ]
    with pytest.raises(ValueError, match="global batch"):
        same_global_batch.compare([same_global_batch.load_run(r) for r in runs])


def test_runs_validated_on_different_episodes_are_refused(tmp_path):
    runs = [
        write_run(tmp_path, "one0", seed=0, processes=1, batch=16, curve=(0.5,)),
        write_run(tmp_path, "one1", seed=1, processes=1, batch=16, curve=(0.4,), val=(2, 7)),
        write_run(tmp_path, "ddp0", seed=0, processes=2, batch=8, curve=(0.5,)),
    ]
    with pytest.raises(ValueError, match="split-seed"):
        same_global_batch.compare([same_global_batch.load_run(r) for r in runs])


def test_runs_of_another_recipe_or_the_same_seed_twice_are_refused(tmp_path):
    one = write_run(tmp_path, "one0", seed=0, processes=1, batch=16, curve=(0.5,))
    ddp = write_run(tmp_path, "ddp0", seed=0, processes=2, batch=8, curve=(0.5,))
    again = write_run(tmp_path, "ddp0b", seed=0, processes=2, batch=8, curve=(0.4,))
    with pytest.raises(ValueError, match="same process count and seed"):
        same_global_batch.compare([same_global_batch.load_run(r) for r in (one, ddp, again)])
    config = json.loads((ddp / "config.json").read_text())
    config["train_config"]["lr"] = 0.1
    (ddp / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match="differ in more than seed"):
        same_global_batch.compare([same_global_batch.load_run(r) for r in (one, ddp)])
