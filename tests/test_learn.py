"""The learner on a tiny simulated dataset: windows and folds never leak, training writes
checkpoints that round-trip and resume, evaluation and prediction write their outputs, DDP runs."""

import csv
import dataclasses
import json
import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest
import torch

from learn.augment import AugmentConfig
from learn.checkpoint import load_checkpoint, strip_checkpoint
from learn.config import LearnConfig, TrainConfig
from learn.data import DataConfig, DataError, Windows, load_frames, normalise, split_groups, validation_split
from learn.evaluate import evaluate
from learn.models import ModelConfig
from learn.predict import predict
from learn.train import train

MODEL = ModelConfig(name="polar_unet", frames=3, width=4)
DATA = DataConfig(frames=3)
QUICK = TrainConfig(epochs=2, batch_size=4, lr=1e-3, loss="bce", val_fraction=0.5, max_val_windows=8)
RUN = LearnConfig(model=MODEL, data=DATA, train=QUICK)


def recipe(**changes) -> LearnConfig:
    """RUN with these TrainConfig fields changed."""
    return dataclasses.replace(RUN, train=dataclasses.replace(QUICK, **changes))


def test_windows_take_the_middle_frame_label(tiny_dataset):
    """K = 3 windows: 6 per 8-frame episode; the input is frames s..s+2 normalised to [0, 1] with
    each frame's peak at 1; the label is the LiDAR image of frame s + 1."""
    frames = load_frames(tiny_dataset)
    windows = Windows(frames, DATA)
    assert len(frames) == 16 and len(windows) == 12
    x, y = windows.batch([0, 7])
    assert x.shape == (2, 1, 3, 240, 181) and y.shape == (2, 1, 240, 181)
    assert torch.allclose(x.amax(dim=(-2, -1)), torch.ones(2, 1, 3))
    start = windows.starts[7]
    np.testing.assert_array_equal(y[1, 0].numpy(), frames.label[start + 1])
    expected = normalise(torch.from_numpy(frames.energyscape[start : start + 3]), 40.0)
    torch.testing.assert_close(x[1], expected.transpose(0, 1))  # (E, K, R, A): one elevation
    assert (windows.episode == frames.episode[windows.starts]).all()


def test_folds_and_validation_keep_episodes_apart():
    groups = np.repeat(np.arange(10), 7)
    fold = split_groups(groups, 4, seed=1)
    for g in range(10):
        assert len(set(fold[groups == g])) == 1
    assert set(fold) == {0, 1, 2, 3}
    held = validation_split(groups, 0.2, seed=1)
    assert set(groups[held]).isdisjoint(groups[~held]) and len(set(groups[held])) == 2
    with pytest.raises(ValueError):
        split_groups(groups, 11)


def test_bad_dataset_folders(tmp_path, tiny_dataset):
    with pytest.raises(DataError, match="not a folder"):
        load_frames(tmp_path / "missing")
    with pytest.raises(DataError, match="no shard"):
        load_frames(tmp_path)
    copy = tmp_path / "copy"
    copy.mkdir()
    (copy / "shard-00000.h5").write_bytes((tiny_dataset / "shard-00000.h5").read_bytes())
    with h5py.File(copy / "shard-00000.h5", "a") as f:
        f.attrs["format_version"] = 3
    with pytest.raises(DataError, match="format_version 3"):
        load_frames(copy)


def test_train_checkpoint_resume_and_evaluate(tiny_dataset, tmp_path):
    """Two epochs write last/best checkpoints, history.csv and curves.png; the checkpoint restores
    the same predictions; --resume to 3 epochs adds one epoch (and to 4 from a checkpoint without
    optimizer state, with a warning, written before a model field existed); evaluate writes its report."""
    run = tmp_path / "run"
    summary = train(tiny_dataset, run, RUN, progress=False)
    assert summary["epochs"] == 2 and summary["val_windows"] > 0
    for name in ("last.pt", "best.pt", "history.csv", "curves.png", "summary.json"):
        assert (run / name).exists(), name
    model, ckpt = load_checkpoint(run / "last.pt")
    on_data = dataclasses.replace(MODEL, elevation_deg=(0.0,))  # training sets the data's elevations
    assert ckpt["model_config"] == dataclasses.asdict(on_data) and ckpt["state"]["epoch"] == 2
    windows = Windows(load_frames(tiny_dataset), DATA)
    x, _ = windows.batch([0, 1])
    with torch.no_grad():
        again, _ = load_checkpoint(run / "last.pt")
        torch.testing.assert_close(model(x), again(x))
    more = recipe(epochs=3)
    summary = train(tiny_dataset, run, more, resume=True, progress=False)
    assert summary["epochs"] == 3 and len(open(run / "history.csv").read().strip().splitlines()) == 4
    # what it learns may not change on resume
    for other in (recipe(epochs=3, lr=2e-3), dataclasses.replace(more, augment=AugmentConfig.none())):
        with pytest.raises(ValueError, match="another recipe"):
            train(tiny_dataset, run, other, resume=True, progress=False)
    strip_checkpoint(run / "last.pt", run / "last.pt")  # as packed to move between machines
    older = torch.load(run / "last.pt", weights_only=True)
    del older["model_config"]["row_contrast"]  # as written before that field existed: it resumes at its default
    del older["train_config"]["augment"]  # ... and before augmentation: it trained with none, and resumes so
    torch.save(older, run / "last.pt")
    with pytest.raises(ValueError, match="augment"):
        train(tiny_dataset, run, more, resume=True, progress=False)
    with pytest.warns(UserWarning, match="no optimizer state"):
        none = dataclasses.replace(recipe(epochs=4), augment=AugmentConfig.none())
        summary = train(tiny_dataset, run, none, resume=True, progress=False)
    assert summary["epochs"] == 4
    report = evaluate(run / "best.pt", tiny_dataset, run / "eval", timing=False)
    assert report["split"] == "val" and set(report["results"]) == {
        "model",
        "echo peak",
        "empty",
        "occupancy grid (echo peak)",
        "occupancy grid (model)",
    }
    assert np.isfinite(report["results"]["model"]["all"]["ssim"]["mean"])
    text = (run / "eval" / "report.md").read_text()
    assert (run / "eval" / "examples.png").exists() and "scan F1 @0.10 m" in text
    assert "nan" not in text and "`-`: no window defines it" in text  # the empty image has no true positive
    one = evaluate(run / "best.pt", tiny_dataset, run / "one", episodes=[1], timing=False, examples=1)
    assert one["split"] == "episodes" and one["windows"] == 6  # one 8-frame episode, K = 3
    with pytest.raises(ValueError, match="none of the episodes"):
        evaluate(run / "best.pt", tiny_dataset, run / "none", episodes=[99], timing=False)
    # windows past each drive's first frames (a calibration's pings): two 8-frame drives, K = 3: starts 4 and 5 of each
    late = evaluate(run / "best.pt", tiny_dataset, run / "late", split="all", from_frame=4, timing=False, examples=1)
    assert late["windows"] == 4 and "from frame 4 of each episode" in (run / "late" / "report.md").read_text()
    for too_far, complaint in ((6, "starts 6 or more frames"), (-1, "from_frame must be >= 0")):
        with pytest.raises(ValueError, match=complaint):
            evaluate(run / "best.pt", tiny_dataset, run / "none", split="all", from_frame=too_far, timing=False)
    energy = load_frames(tiny_dataset).energyscape[:8].astype(np.float32)
    np.save(tmp_path / "recorded.npy", energy)
    out = predict(run / "best.pt", tmp_path / "recorded.npy", tmp_path / "pred.npz")
    pred = np.load(out)
    assert pred["prediction"].shape == (6, 240, 181) and list(pred["frame"]) == [1, 2, 3, 4, 5, 6]
    kept = torch.load(run / "best.pt", weights_only=True)
    assert float(pred["threshold"]) == report["thresholds"]["model"] == kept["threshold"]


def test_validation_predicts_once_and_scores_as_evaluation_does(tiny_dataset, monkeypatch):
    """`validate` keeps the windows' predictions for both the threshold sweep and the scores (one
    forward pass); it equals `calibrate_threshold` + `score`, and so does its two-pass fallback
    when the windows would not fit its memory budget."""
    import learn.train as train_module
    from learn.evaluate import calibrate_threshold, model_predictor, score
    from learn.models import build_model

    torch.manual_seed(0)
    model = build_model(MODEL)
    windows, indices = Windows(load_frames(tiny_dataset), DATA), np.arange(10)
    predict = model_predictor(model)
    calls = []
    monkeypatch.setattr(model, "forward", lambda x, f=model.forward: calls.append(len(x)) or f(x))
    threshold, _ = calibrate_threshold(predict, windows, indices)
    per = score(predict, windows, indices, threshold=threshold)
    want = {k: float(np.nanmean(v)) if np.isfinite(v).any() else float("nan") for k, v in per.items()}
    want["threshold"] = threshold
    assert sum(calls) == 20
    for budget, passes in ((train_module.VALIDATION_KEEP_BYTES, 1), (0, 2)):
        calls.clear()
        monkeypatch.setattr(train_module, "VALIDATION_KEEP_BYTES", budget)
        got = train_module.validate(model, windows, indices)
        assert sum(calls) == 10 * passes
        assert got.keys() == want.keys()
        np.testing.assert_allclose([got[k] for k in want], [want[k] for k in want], rtol=1e-12, equal_nan=True)


def test_predict_reads_scans_at_the_threshold(tiny_dataset, tmp_path):
    """predict's scans are the nearest cell >= the checkpoint's threshold of each predicted image
    (inf where none), and --threshold overrides it."""
    from learn.metrics import first_return_ranges

    run = tmp_path / "run"
    train(tiny_dataset, run, RUN, progress=False)
    best = torch.load(run / "best.pt", weights_only=True)
    for override in (None, 0.3):
        got = np.load(predict(run / "best.pt", tiny_dataset, tmp_path / f"p{override}.npz", threshold=override))
        threshold = best["threshold"] if override is None else override
        assert float(got["threshold"]) == threshold and got["ranges"].shape == (12, 181)
        want = first_return_ranges(
            torch.from_numpy(got["prediction"].astype(np.float32)), got["range_m"], threshold=threshold
        )
        np.testing.assert_array_equal(got["ranges"], want.float().numpy())


def test_evaluate_compares_checkpoints_side_by_side(tiny_dataset, tmp_path, capsys):
    """Two named checkpoints and the baselines are scored on the same windows at each model's own
    threshold; the report names each checkpoint and draws examples for both; checkpoints that
    read other windows (K) are refused; with `progress` a bar counts the windows of each predictor."""
    a, b, k5 = tmp_path / "a", tmp_path / "b", tmp_path / "k5"
    for run, seed in ((a, 0), (b, 1)):
        train(tiny_dataset, run, recipe(epochs=1, seed=seed), progress=False)
    named = {"first": a / "best.pt", "second": b / "best.pt"}
    report = evaluate([f"{k}={v}" for k, v in named.items()], tiny_dataset, tmp_path / "cmp", split="all", timing=False)
    grids = ["occupancy grid (echo peak)", "occupancy grid (first)"]  # fed by the first model without memory
    assert list(report["results"]) == ["first", "second", "echo peak", "empty", *grids]
    assert report["thresholds"]["second"] == torch.load(b / "best.pt", weights_only=True)["threshold"]
    recorded = {k: os.path.relpath(v) for k, v in named.items()}  # relative to the working folder: no machine path
    assert report["windows"] == 12 and report["checkpoints"] == recorded
    text = (tmp_path / "cmp" / "report.md").read_text()
    assert f"| second | `{recorded['second']}` |" in text and "examples_second.png" in text
    assert (tmp_path / "cmp" / "examples.png").exists() and (tmp_path / "cmp" / "examples_second.png").exists()
    rows = list(csv.DictReader(open(tmp_path / "cmp" / "per_window.csv")))
    assert len(rows) == 6 * 12 and rows[0]["predictor"] == "first" and list(rows[0])[4] == "scan_f1"
    second = [float(r["scan_f1"]) for r in rows if r["predictor"] == "second"]
    assert np.mean(second) == pytest.approx(report["results"]["second"]["all"]["scan_f1"]["mean"], abs=1e-5)
    capsys.readouterr()
    alone = evaluate(b / "best.pt", tiny_dataset, tmp_path / "alone", split="all", timing=False, progress=True)
    bars = capsys.readouterr().err
    assert all(f"scoring {name}" in bars for name in ("model", "echo peak", "empty")) and "12/12" in bars, bars
    assert _same(alone["results"]["model"], report["results"]["second"])
    train(tiny_dataset, k5, recipe(epochs=1).with_frames(5), progress=False)
    with pytest.raises(ValueError, match="other windows"):
        evaluate({"a": a / "best.pt", "k5": k5 / "best.pt"}, tiny_dataset, tmp_path / "bad", timing=False)


def test_checkpoints_never_run_pickled_code(tmp_path):
    """A .pt whose unpickling would run code is refused with a clear error, and the code never runs."""
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    torch.save({"model": Payload()}, tmp_path / "evil.pt")
    with pytest.raises(ValueError, match="not a checkpoint this learner can read safely"):
        load_checkpoint(tmp_path / "evil.pt")
    assert not marker.exists()


def test_silent_model_warning():
    """The kept model warns when it predicts no return on >= 90 % of the validation beams, not below."""
    from learn.progress import warn_if_silent

    row = {"epoch": 3, "val_no_return": 0.95, "val_threshold": 0.5, "val_scan_f1": 0.01}
    with pytest.warns(UserWarning, match="predicts no return on 95% of the validation beams"):
        warn_if_silent(row, "run")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_silent(row | {"val_no_return": 0.5}, "run")


def test_train_help_shows_every_default():
    """Every option of `learn train --help` with a value by default states it (they come from the
    config dataclasses); flags that are off and options that are unset by default say nothing."""
    from learn.cli import build_parser

    help_text = build_parser()._subparsers._group_actions[0].choices["train"].format_help()
    options = [a for a in build_parser()._subparsers._group_actions[0].choices["train"]._actions if a.option_strings]
    flat = " ".join(help_text.split())
    for action in options:
        if action.dest != "help" and action.default not in (None, False):
            assert f"(default: {action.default})" in flat, action.dest
    assert "(default: scan_f1)" in flat and "(default: 0.0001)" in flat


@pytest.mark.parametrize("processes", [2, 1])
def test_ddp_under_torchrun_on_cpu(tiny_dataset, tmp_path, processes):
    """gloo processes under torchrun train one epoch; rank 0 writes the checkpoint. One process
    joins a process group too (the path a one-GPU NCCL check must take); a plain run joins none."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(processes)]
    cmd += [
        "-m",
        "learn",
        "train",
        "--data",
        str(tiny_dataset),
        "--out",
        str(tmp_path / "ddp"),
        "--model",
        "polar_unet",
    ]
    cmd += ["--width", "4", "--frames", "3", "--epochs", "1", "--batch-size", "2", "--loss", "bce"]
    cmd += ["--val-fraction", "0.5", "--quiet"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads((tmp_path / "ddp" / "summary.json").read_text())
    assert summary["epochs"] == 1
    group = json.loads((tmp_path / "ddp" / "config.json").read_text())["process_group"]
    assert group == {"backend": "gloo", "processes": processes}
    if processes == 1:
        plain = tmp_path / "plain"
        train(tiny_dataset, plain, RUN, progress=False)
        assert json.loads((plain / "config.json").read_text())["process_group"] is None


def test_monitor_picks_best_checkpoint_by_chamfer(tiny_dataset, tmp_path):
    """With monitor="chamfer_m" best.pt is the epoch of the lowest validation Chamfer distance,
    and it stores that epoch's calibrated threshold."""
    config = recipe(epochs=3, monitor="chamfer_m", patience=3)
    summary = train(tiny_dataset, tmp_path / "run", config, progress=False)
    rows = [line.split(",") for line in (tmp_path / "run" / "history.csv").read_text().strip().splitlines()]
    chamfer = [float(r[rows[0].index("val_chamfer_m")]) for r in rows[1:]]
    assert summary["best_epoch"] == 1 + int(np.argmin(chamfer))
    best = torch.load(tmp_path / "run" / "best.pt", weights_only=True)
    assert best["state"]["epoch"] == summary["best_epoch"]
    assert best["threshold"] == float(rows[summary["best_epoch"]][rows[0].index("val_threshold")])
    with pytest.raises(ValueError, match="monitor"):
        TrainConfig(monitor="iou")


def test_split_seed_holds_the_validation_episodes_while_the_seed_varies(tiny_dataset, tmp_path):
    """With `split_seed` the validation episodes no longer follow `seed`: runs of several seeds are
    scored on one validation set, so their spread is training noise alone (the DDP comparison
    needs that). The seed taken here is one whose own split differs from seed 0's."""
    episodes = load_frames(tiny_dataset).episode
    own = [tuple(np.unique(episodes[validation_split(episodes, 0.5, seed=s)])) for s in range(20)]
    seed = next(s for s in range(1, 20) if own[s] != own[0])
    train(tiny_dataset, tmp_path / "run", recipe(epochs=1, seed=seed, split_seed=0), progress=False)
    written = json.loads((tmp_path / "run" / "config.json").read_text())
    assert tuple(written["dataset"]["val_episodes"]) == own[0] != own[seed]
    assert written["train_config"]["split_seed"] == 0 and written["train_config"]["seed"] == seed
    assert written["dataset"]["split_seed"] == 0  # what drew the episodes and the validated windows


def test_resuming_with_the_split_seed_named_is_the_same_recipe():
    """A run of seed 3 drew its split with seed 3: resuming it with --split-seed 3 is the same
    recipe, while another split seed is refused by name."""
    from types import SimpleNamespace

    from learn.checkpoint import check_compatible
    from learn.config import to_record

    ckpt = to_record(recipe(seed=3)) | {"dataset": {"plan_id": "p"}}
    windows = SimpleNamespace(frames=SimpleNamespace(info={"plan_id": "p"}))
    check_compatible(ckpt, recipe(seed=3, split_seed=3), windows)
    with pytest.raises(ValueError, match="split_seed None -> 4"):
        check_compatible(ckpt, recipe(seed=3, split_seed=4), windows)


def _same(a: dict, b: dict) -> bool:
    """Equal nested metrics, where nan (an undefined metric) equals nan."""
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


@pytest.fixture
def studies_draw_no_examples(monkeypatch):
    """The studies' evaluations without their example pictures: these tests read the tables, and
    evaluate's own tests draw and check the pictures (picking and drawing the examples took about
    40 % of the sim2real test's time). The studies' other pictures are still drawn."""
    import learn.evaluate
    import learn.plots
    import learn.studies

    evaluate_and_draw = learn.studies.evaluate

    def evaluate_without_examples(*args, **kwargs):
        with monkeypatch.context() as inside:
            inside.setattr(learn.evaluate, "_example_rows", lambda *a, **k: [])
            inside.setattr(learn.plots, "plot_examples", lambda *a, **k: None)
            return evaluate_and_draw(*args, **kwargs)

    monkeypatch.setattr(learn.studies, "evaluate", evaluate_without_examples)


@pytest.mark.usefixtures("studies_draw_no_examples")
def test_sim2real_table_matches_its_reports_and_summarises_runs(tiny_dataset, tmp_path):
    """The study's table carries the numbers of each variant's evaluation report, and the summary
    over runs is their mean and spread with paired per-run differences. (Plumbing only: both
    'variants' here are one tiny dataset.)"""
    from learn.studies import sim2real, sim2real_summary

    ablation = tmp_path / "ablation"
    ablation.mkdir()
    for name in ("bounces_0", "bounces_3"):
        (ablation / name).symlink_to(tiny_dataset, target_is_directory=True)
    config = recipe(epochs=1)
    runs = [tmp_path / f"seed{s}" for s in (0, 1)]
    model = ModelConfig(width=4, frames=3, row_contrast=True)
    for seed, run in enumerate(runs):
        seeded = dataclasses.replace(recipe(epochs=1, seed=seed), model=model)
        sim2real(ablation, tiny_dataset, run, config=seeded, progress=False)
    table = json.loads((runs[1] / "sim2real.json").read_text())
    trained = torch.load(runs[0] / "bounces_3" / "best.pt", weights_only=True)["model_config"]
    on_data = dataclasses.replace(model, elevation_deg=(0.0,))  # and the data's elevations
    assert trained == dataclasses.asdict(on_data)  # the whole network config reaches every variant's run
    assert list(table) == ["bounces_0", "bounces_3"]
    report = json.loads((runs[1] / "bounces_3" / "reality" / "metrics.json").read_text())
    assert _same(table["bounces_3"]["reality"], report["results"]["model"]["all"])
    assert (
        f"| bounces_3 | {table['bounces_3']['in_domain']['scan_f1']['mean']:.4f} |"
        in (runs[1] / "sim2real.md").read_text()
    )

    assert (runs[1] / "examples_reality.png").stat().st_size > 10_000  # each variant's median window
    rescored = sim2real(ablation, tiny_dataset, runs[1], score_only=True, config=config, progress=False)
    assert _same(rescored, table)  # score_only reads the trained runs and scores them alike
    with pytest.raises(ValueError, match=r"no best\.pt to score"):
        sim2real(ablation, tiny_dataset, tmp_path / "none", score_only=True, config=config, progress=False)
    cut = recipe(epochs=3, max_minutes=1e-6)  # stops on its budget after epoch 1
    for v in ("bounces_0", "bounces_3"):
        train(ablation / v, tmp_path / "cut" / v, cut, progress=False)
    with pytest.warns(UserWarning, match="training has not stopped"):
        sim2real(ablation, tiny_dataset, tmp_path / "cut", score_only=True, config=config, progress=False)

    summary = sim2real_summary(runs, tmp_path / "summary")
    per_run = [json.loads((r / "sim2real.json").read_text())["bounces_3"]["reality"]["iou"]["mean"] for r in runs]
    assert summary["bounces_3"]["reality"]["iou"]["mean"] == pytest.approx(np.mean(per_run))
    assert summary["bounces_3"]["reality"]["iou"]["std"] == pytest.approx(np.std(per_run))
    f1 = [summary[v]["reality"]["scan_f1"]["runs"] for v in ("bounces_0", "bounces_3")]
    diffs = " | ".join(f"{b - a:+.4f}" for a, b in zip(*f1, strict=True))
    text = (tmp_path / "summary" / "sim2real.md").read_text()
    assert f"| bounces_3 minus bounces_0 | {diffs} |" in text and (tmp_path / "summary" / "sim2real.png").exists()
    with pytest.raises(ValueError, match="at least two"):
        sim2real_summary(runs[:1], tmp_path / "one")

    # one named variant (part 4 of the study trains only its best), scored as in the full table
    one = sim2real(
        ablation, tiny_dataset, runs[1], score_only=True, config=config, progress=False, variants=["bounces_3"]
    )
    assert list(one) == ["bounces_3"] and _same(one["bounces_3"], table["bounces_3"])
    with pytest.raises(ValueError, match=r"not all in .*holds \['bounces_0', 'bounces_3'\]"):
        sim2real(
            ablation,
            tiny_dataset,
            runs[1],
            score_only=True,
            config=config,
            progress=False,
            variants=["bounces_1"],
        )


@pytest.mark.usefixtures("studies_draw_no_examples")
def test_table2_scores_every_row_on_the_same_validation_episodes(tiny_dataset, tmp_path):
    """K = 1, 3, 5 models and the fine-tuned K = 5 rows are scored on each case's validation
    episodes (those the fine-tuning never saw), and the table carries the reports' numbers."""
    from learn.studies import TABLE2_CASES, table2

    cases = tmp_path / "cases"
    cases.mkdir()
    for c in TABLE2_CASES:
        (cases / c).symlink_to(tiny_dataset, target_is_directory=True)
    rows = table2(tiny_dataset, cases, tmp_path / "t2", config=recipe(epochs=1))
    assert list(rows) == ["K = 1", "K = 3", "K = 5", "K = 5 fine-tuned"]
    held = torch.load(tmp_path / "t2" / "k5_finetuned_noisy" / "best.pt", weights_only=True)["dataset"]["val_episodes"]
    k5 = json.loads((tmp_path / "t2" / "k5" / "noisy" / "metrics.json").read_text())
    tuned = json.loads((tmp_path / "t2" / "k5_finetuned_noisy" / "eval" / "metrics.json").read_text())
    assert k5["split"] == tuned["split"] == "episodes" and k5["windows"] == tuned["windows"] == 4 * len(held)
    assert _same(rows["K = 5"]["noisy"], k5["results"]["model"]["all"])
    text = (tmp_path / "t2" / "table2.md").read_text()
    assert f"{rows['K = 5 fine-tuned']['many']['mse']['mean']:.4f}" in text
    assert text.index("scan F1") < text.index("MSE") and f"{rows['K = 1']['minimal']['scan_f1']['mean']:.4f}" in text

    from learn.studies import table2_summary

    copy = tmp_path / "t2_again"  # a second run with the same numbers: std 0, its differences the run's
    shutil.copytree(tmp_path / "t2", copy, ignore=shutil.ignore_patterns("*.pt"))
    summary = table2_summary([tmp_path / "t2", copy], tmp_path / "sum")
    f1 = {r: rows[r]["noisy"]["scan_f1"]["mean"] for r in rows}
    assert summary["K = 3"]["noisy"]["mean"] == pytest.approx(f1["K = 3"]) and summary["K = 3"]["noisy"]["std"] == 0
    assert summary["echo peak"]["noisy"]["mean"] == pytest.approx(k5["results"]["echo peak"]["all"]["scan_f1"]["mean"])
    diff = f1["K = 5 fine-tuned"] - f1["K = 5"]
    assert (
        f"| K = 5 fine-tuned minus K = 5 | noisy | {diff:+.3f} | {diff:+.3f} |"
        in (tmp_path / "sum" / "table2.md").read_text()
    )


def test_pretrained_model_reads_walls_on_a_fresh_drive(tiny_dataset, tmp_path):
    """The shipped polar UNet (learn/pretrained/, trained on the H100) loads safely, reads at its
    calibrated threshold, and finds the walls of the tiny suite's room and corridor, scenes it never
    saw: scan F1 >= 0.8 and >= 2x the echo peak's (0.999 and 0.26 when it was shipped)."""
    import learn

    _, ckpt = load_checkpoint(learn.PRETRAINED_CHECKPOINT)
    shipped = {"name": "polar_unet", "frames": 5, "width": 16, "elevation_deg": [0.0]}  # read as the level slice
    assert ckpt["model_config"] == shipped and 0 < ckpt["threshold"] < 1
    assert "optimizer" not in ckpt
    report = evaluate(learn.PRETRAINED_CHECKPOINT, tiny_dataset, tmp_path / "eval", timing=False, examples=1)
    f1 = {name: r["all"]["scan_f1"]["mean"] for name, r in report["results"].items()}
    assert report["split"] == "all" and report["thresholds"]["model"] == ckpt["threshold"]
    assert f1["model"] >= 0.8 and f1["model"] >= 2 * f1["echo peak"], f1


@pytest.mark.filterwarnings("ignore:.*predicts no return")  # one epoch: the model may not place walls yet
def test_set_reaches_fields_no_option_names_and_the_run_records_them(tiny_dataset, tmp_path):
    """`learn train --set` changes fields without an option of their own; config.json, written
    before the first epoch, records every setting of the run."""
    from learn.cli import main

    run = tmp_path / "run"
    argv = ["train", "--data", str(tiny_dataset), "--out", str(run), "--frames", "3", "--width", "4", "--epochs", "1"]
    argv += ["--batch-size", "4", "--loss", "bce", "--val-fraction", "0.5", "--max-val-windows", "8", "--quiet"]
    argv += ["--set", "train.pos_weight=5", "--set", "data.floor_db=50", "--set", "train.max_val_windows=none"]
    argv += ["--set", "model.row_contrast=true"]
    assert main(argv) == 0
    written = json.loads((run / "config.json").read_text())
    assert written["train_config"]["pos_weight"] == 5.0 and written["train_config"]["max_val_windows"] is None
    assert written["data_config"] == {
        "frames": 3,
        "label": "middle",
        "floor_db": 50.0,
        "history": 0,
        "history_stride": 1,
    }
    model = {"name": "polar_unet", "frames": 3, "width": 4, "row_contrast": True, "history": 0, "extent": None}
    model["elevation_deg"] = [0.0]  # the data's: one level slice
    assert written["model_config"] == model
    assert written["dataset"]["plan_id"] == load_frames(tiny_dataset).info["plan_id"] and not written["resumed"]
    from learn.cli import _recorded_config, build_parser
    from learn.cli_training import run_config
    from learn.config import from_record

    ran = run_config(build_parser().parse_args(argv))  # the whole config, in both places
    ran = dataclasses.replace(ran, model=dataclasses.replace(ran.model, elevation_deg=(0.0,)))  # with the data's
    assert from_record(written) == from_record(load_checkpoint(run / "best.pt")[1]) == ran
    again = ["train", "--data", str(tiny_dataset), "--out", "again", "--config", str(run / "config.json")]
    assert run_config(build_parser(_recorded_config(again)).parse_args(again)) == ran  # a repeat of it


def test_config_option_starts_from_a_recorded_run(tmp_path, capsys):
    """`learn train --config RUN/config.json`: the run's settings become the options' defaults, so the
    same command repeats it; options and --set still change single fields; a record from before
    augmentation had a section reads as none; an unreadable file is one `error:` line."""
    from learn.cli import build_parser, main
    from learn.cli_training import run_config
    from learn.config import read_run_config, to_record

    recorded = dataclasses.replace(recipe(seed=7, max_minutes=30.0, amp=False), augment=AugmentConfig(mirror=0.1))
    recorded = dataclasses.replace(recorded, model=dataclasses.replace(MODEL, row_contrast=True))
    path = tmp_path / "config.json"
    path.write_text(json.dumps(to_record(recorded) | {"dataset": {"plan_id": "p"}, "device": "cpu"}))

    def configs(*extra):
        from learn.cli import _recorded_config

        argv = ["train", "--data", "d", "--out", "o", "--config", str(path), *extra]
        return run_config(build_parser(_recorded_config(argv)).parse_args(argv))

    assert recorded != LearnConfig() and configs() == recorded
    assert configs("--epochs", "9", "--set", "augment.mirror=0.2") == dataclasses.replace(
        recorded, train=dataclasses.replace(recorded.train, epochs=9), augment=AugmentConfig(mirror=0.2)
    )
    assert configs("--no-augment").augment == AugmentConfig.none()
    older = to_record(recorded)
    del older["train_config"]["augment"], older["model_config"]["row_contrast"]
    path.write_text(json.dumps(older))
    assert read_run_config(path) == dataclasses.replace(recorded, augment=AugmentConfig.none(), model=MODEL)
    broken = (("{", "is not valid JSON"), ('{"model_config": {}}', "not this version's"), ("[]", "holds a JSON list"))
    for content, words in broken:
        path.write_text(content)
        assert main(["train", "--data", "d", "--out", str(tmp_path / "o"), "--config", str(path)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: --config {path}") and words in err, err
    assert main(["train", "--data", "d", "--out", "o", "--config", str(tmp_path / "none.json")]) == 2
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.parametrize(
    "setting, message",
    [
        ("train.lr", "--set wants section.field=value (sections: model, data, augment, train)"),
        ("optim.lr=1", "no section 'optim'; the sections are model, data, augment, train"),
        ("train.speed=1", "train has no field 'speed'"),
        ("train.epochs=1.5", "'1.5' is not a valid value: give an integer"),
        ("train.amp=maybe", "'maybe' is not a valid value: give true or false"),
        ("train.epochs=none", "'none' is not a valid value: give an integer"),
        ("train.loss=hinge", "'hinge' is not a valid value: give one of 'mse', 'bce'"),
        ("data.label=first", "'first' is not a valid value: give one of 'middle', 'last'"),
        ("model.frames=3", "must agree: set the window length with --frames"),
    ],
)
def test_bad_learner_settings_are_refused_by_name(setting, message, capsys):
    from learn.cli import main

    assert main(["train", "--data", "nowhere", "--out", "nowhere", "--set", setting]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err
    assert setting in err or "must agree" in message


def test_augmentations_change_training_windows_as_stated(tiny_dataset):
    """Off: the plain batch. Mirror: input and label flipped together. Floor jitter, range tilt
    and band masks: other inputs in [0, 1], the label untouched, the same draws from the same seed."""
    from learn.augment import augmented_batch

    windows = Windows(load_frames(tiny_dataset), DATA)
    x, y = windows.batch([0, 1, 2])

    def draw(config, seed=0):
        return augmented_batch(windows, [0, 1, 2], config, torch.Generator().manual_seed(seed))

    plain = draw(AugmentConfig.none())
    torch.testing.assert_close(plain[0], x)
    torch.testing.assert_close(plain[1], y)
    only = AugmentConfig.none()
    mirrored = draw(dataclasses.replace(only, mirror=1.0))
    torch.testing.assert_close(mirrored[0], x.flip(-1))
    torch.testing.assert_close(mirrored[1], y.flip(-1))
    assert not torch.equal(x, x.flip(-1)) and not torch.equal(y, y.flip(-1))  # so the comparison can fail
    for config in (
        dataclasses.replace(only, floor_jitter_db=10.0),
        dataclasses.replace(only, range_tilt_db=6.0),
        dataclasses.replace(only, band_masks=3),
    ):
        changed, label = draw(config)
        assert changed.min() >= 0 and changed.max() <= 1 and not torch.equal(changed, x)
        torch.testing.assert_close(label, y)
        torch.testing.assert_close(draw(config)[0], changed)
        assert not torch.equal(draw(config, seed=1)[0], changed)
    masked, _ = draw(dataclasses.replace(only, band_masks=3))
    assert ((masked == 0).all(dim=-1).sum() > (x == 0).all(dim=-1).sum()).item()  # whole rows at the floor
    with pytest.raises(ValueError, match="probability"):
        AugmentConfig(mirror=1.5)


@pytest.mark.filterwarnings("ignore:.*predicts no return")
def test_training_with_augmentation_records_it(tiny_dataset, tmp_path):
    from learn.cli import main

    run = tmp_path / "run"
    argv = ["train", "--data", str(tiny_dataset), "--out", str(run), "--frames", "3", "--width", "4", "--epochs", "1"]
    argv += ["--batch-size", "4", "--loss", "bce", "--val-fraction", "0.5", "--max-val-windows", "8", "--quiet"]
    assert main([*argv, "--set", "augment.mirror=0.25", "--set", "augment.floor_jitter_db=0"]) == 0
    augment = json.loads((run / "config.json").read_text())["train_config"]["augment"]
    assert augment == {
        "mirror": 0.25,
        "floor_jitter_db": 0.0,
        "range_tilt_db": 6.0,
        "band_masks": 2,
        "odometry_drift": 0.0,
    }  # the rest: defaults
    assert load_checkpoint(run / "best.pt")[1]["train_config"]["augment"]["mirror"] == 0.25
    plain = tmp_path / "plain"  # --no-augment starts from none; a --set after it adds one back
    assert main([*argv[:4], str(plain), *argv[5:], "--no-augment", "--set", "augment.mirror=0.5"]) == 0
    augment = json.loads((plain / "config.json").read_text())["train_config"]["augment"]
    assert augment == {
        "mirror": 0.5,
        "floor_jitter_db": 0.0,
        "range_tilt_db": 0.0,
        "band_masks": 0,
        "odometry_drift": 0.0,
    }


@pytest.mark.filterwarnings("ignore:.*predicts no return")
def test_sim2real_scores_every_named_test_set_beside_its_echo_peak(tiny_dataset, tmp_path, capsys):
    """Each test set gets its own model and echo-peak columns, report folder and paired table."""
    from learn.cli import main

    ablation = tmp_path / "ablation"
    (ablation / "bounces_0").mkdir(parents=True)
    for shard in tiny_dataset.glob("*"):
        (ablation / "bounces_0" / shard.name).symlink_to(shard)
    argv = ["sim2real", "--ablation", str(ablation), "--reality", str(tiny_dataset), "--frames", "3", "--width", "4"]
    argv += ["--epochs", "1", "--batch-size", "4", "--loss", "bce", "--val-fraction", "0.5", "--quiet"]
    assert main([*argv, "--test", f"crossengine={tiny_dataset}", "--out", str(tmp_path / "s")]) == 0
    table = json.loads((tmp_path / "s" / "sim2real.json").read_text())["bounces_0"]
    assert list(table) == ["in_domain", "reality", "reality_echo_peak", "crossengine", "crossengine_echo_peak"]
    report = json.loads((tmp_path / "s" / "bounces_0" / "crossengine" / "metrics.json").read_text())
    assert _same(table["crossengine_echo_peak"], report["results"]["echo peak"]["all"])
    header = (tmp_path / "s" / "sim2real.md").read_text().splitlines()[4]
    assert "scan F1 in-domain | scan F1 reality | scan F1 crossengine" in header
    assert main([*argv, "--test", "reality=x", "--out", str(tmp_path / "t")]) == 2
    assert "--test wants NAME=FOLDER" in capsys.readouterr().err


def test_tensorboard_logs_every_epoch(tiny_dataset, tmp_path, monkeypatch, capsys):
    """`--tensorboard`: every history column as a scalar per epoch (equal to history.csv) and the
    example windows as pictures; without TensorBoard installed, an error that names the extra
    (one `error:` line from the command line)."""
    event_accumulator = pytest.importorskip("tensorboard.backend.event_processing.event_accumulator")
    run = tmp_path / "run"
    train(tiny_dataset, run, RUN, progress=False, tensorboard=True)
    board = event_accumulator.EventAccumulator(str(run / "tensorboard"), size_guidance={"images": 0})
    board.Reload()
    history = list(csv.DictReader(open(run / "history.csv")))
    f1 = board.Scalars("val/scan_f1")
    assert [e.step for e in f1] == [1, 2]
    assert [e.value for e in f1] == pytest.approx([float(r["val_scan_f1"]) for r in history], abs=1e-6)
    assert {"train/loss", "val/threshold", "speed/samples_per_s"} <= set(board.Tags()["scalars"])
    pictures = board.Tags()["images"]
    assert len(pictures) == 3 and all(len(board.Images(tag)) == 2 for tag in pictures)
    height, width = board.Images(pictures[0])[0].height, board.Images(pictures[0])[0].width
    frames = load_frames(tiny_dataset)
    assert (height, width) == (len(frames.range_m), 3 * len(frames.azimuth_rad))  # sonar | label | prediction
    assert {"speed/samples_per_s", "speed/train_seconds"} <= set(board.Tags()["scalars"])
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)
    with pytest.raises(ImportError, match=r"sonar2lidar\[tensorboard\]"):
        train(tiny_dataset, tmp_path / "no", RUN, tensorboard=True)
    assert not (tmp_path / "no").exists()  # refused before anything was written
    from learn.cli import main

    argv = ["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "cli"), "--tensorboard", "--quiet"]
    assert main(argv) == 2 and "error: --tensorboard needs TensorBoard" in capsys.readouterr().err
