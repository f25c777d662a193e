"""The learner's side of issue 38's second fault-injection probe: every bad input or fault that
hung, printed a traceback, was accepted with a wrong or silent result, or ended in a line that
named neither file nor field, now ends in one `error:` line (exit 2) that names them. By class:
config fields of any type or size (options, `--set`, a hand-edited `--config`), the progress and
optimizer state of a `--resume`d last.pt, weights of another dtype, checkpoint axes out of order,
paths that are folders or FIFOs, run folders inside the dataset, datasets too small to split or
window, `predict --mcap`'s frame times, evaluation splits with no window, and the JSON files
the study summaries read.

Each case runs `python -m learn ...` as its own process (tests/cli_runner.py forks them from one
interpreter that imported torch once), on a coarse tiny dataset (48 ranges x 31 azimuths, four
6-frame episodes) and a width-2 model trained on it once.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from learn.cli import main

from .cli_runner import run_commands

TRAIN = "--frames 3 --width 2 --batch-size 2 --val-fraction 0.25 --max-train-windows 4 --loss bce --quiet --epochs 1"
GRID = (48, 31)


# -- what each case starts from: f(case folder w, fixtures) -> None ------------------------------


def copy_data(w, fx):
    shutil.copytree(fx["data"], w / "d")


def shard_edit(change):
    def setup(w, fx):
        copy_data(w, fx)
        with h5py.File(w / "d" / "shard-00000.h5", "a") as f:
            change(f)

    return setup


def replace_dataset(f, name, data):
    del f[name]
    f.create_dataset(name, data=data, fletcher32=True)


def first_frames(count):
    def change(f):
        for name in ("energyscape", "lidar/image", "episode", "scenario"):
            data = f[name][:count]
            del f[name]
            chunks = (1, *data.shape[1:]) if data.ndim >= 3 else (1,)
            maxshape = (None, *data.shape[1:])
            f.create_dataset(
                name, shape=data.shape, dtype=data.dtype, chunks=chunks, maxshape=maxshape, fletcher32=True
            )
            if count:
                f[name][...] = data

    return change


def one_range_bin(f):
    replace_dataset(f, "energyscape", f["energyscape"][:, :, :1, :])
    replace_dataset(f, "lidar/image", f["lidar/image"][:, :1, :])
    replace_dataset(f, "range_m", f["range_m"][:1])


def checkpoint(change, name="c.pt"):
    def setup(w, fx):
        ckpt = torch.load(fx["run"] / "best.pt", weights_only=True)
        change(ckpt)
        torch.save(ckpt, w / name)

    return setup


def run_with(change):
    """A copy of the trained run whose last.pt is changed."""

    def setup(w, fx):
        shutil.copytree(fx["run"], w / "r")
        ckpt = torch.load(w / "r" / "last.pt", weights_only=True)
        change(ckpt)
        torch.save(ckpt, w / "r" / "last.pt")

    return setup


def config_file(change=None, text=None):
    def setup(w, fx):
        if text is not None:
            (w / "config.json").write_text(text)
            return
        record = json.loads((fx["run"] / "config.json").read_text())
        change(record)
        (w / "config.json").write_text(json.dumps(record))

    return setup


def fifo(name):
    return lambda w, fx: os.mkfifo(w / name)


def both(*setups):
    def setup(w, fx):
        for s in setups:
            s(w, fx)

    return setup


def evaluations(text_b=None, change_b=None, name="metrics.json"):
    """Folders a/ and b/ of metrics.json (b's text or content changed)."""

    def setup(w, fx):
        for folder in ("a", "b"):
            (w / folder).mkdir()
            record = json.loads((fx["report"] / "metrics.json").read_text())
            text = json.dumps(change_b(record) if change_b and folder == "b" else record)
            (w / folder / name).write_text(text_b if text_b is not None and folder == "b" else text)

    return setup


def study_json(name, text, *, folders=("a", "b")):
    def setup(w, fx):
        for folder in folders:
            (w / folder).mkdir(parents=True)
            (w / folder / name).write_text(text)

    return setup


def scored_run(last=None):
    """An ablation suite of one variant and a run of it to score (`--score-only`), its last.pt set by `last`."""

    def setup(w, fx):
        (w / "abl").mkdir()
        shutil.copytree(fx["data"], w / "abl" / "bounces_0")
        run = w / "o" / "bounces_0"
        run.mkdir(parents=True)
        shutil.copy(fx["run"] / "best.pt", run / "best.pt")
        last(run, fx)

    return setup


def _no_state(run, fx):
    ckpt = torch.load(fx["run"] / "last.pt", weights_only=True)
    ckpt.pop("state")
    torch.save(ckpt, run / "last.pt")


def _set_state(**values):
    return run_with(lambda c: c["state"].update(values))


def _opt_moment_shape(c):
    c["optimizer"]["state"][0]["exp_avg"] = torch.zeros(7)


def _integer_weights(c):
    c["model"] = {k: v.long() if v.is_floating_point() else v for k, v in c["model"].items()}


def _no_results(record):
    return {"windows": 4}


def _text_mean(record):
    record["results"]["model"]["all"]["scan_f1"]["mean"] = "high"
    return record


T2_ROW = {c: {"scan_f1": {"mean": 0.1}} for c in ("minimal", "many", "noisy")}
TR = "train --data {data} --out {w}/o " + TRAIN
RESUME = "train --data {data} --out {w}/r --resume " + TRAIN.replace("--epochs 1", "--epochs 3")
SCORE = "sim2real --ablation {w}/abl --reality {data} --out {w}/o --score-only " + TRAIN
PREDICT = "predict --input {data} --out {w}/p.npz --checkpoint "
MCAP = "predict --checkpoint {ckpt} --input {w}/d --out {w}/p.npz --mcap {w}/p.mcap"
SEEDS = "seeds-summary {w}/a {w}/b --out {w}/s"

# (id, argv, setup or None, words the error line must hold)
CASES = [
    # config fields: any value an option, --set or --config can give
    ("max-train-windows-0", TR + " --max-train-windows 0", None, "train.max_train_windows (--max-train-windows)"),
    (
        "max-train-windows-neg",
        TR + " --max-train-windows -1",
        None,
        "must be an integer >= 1 (or none for all), got -1",
    ),
    ("max-val-windows-neg", TR + " --max-val-windows -5", None, "train.max_val_windows"),
    ("seed-negative", TR + " --seed -1", None, "train.seed (--seed) must be an integer in 0.."),
    ("seed-huge", TR + " --seed 99999999999999999999999", None, "train.seed"),
    ("split-seed-negative", TR + " --split-seed -2", None, "train.split_seed"),
    ("folds-zero", TR + " --folds 0", None, "--folds must be an integer >= 1"),
    ("band-masks-huge", TR + " --set augment.band_masks=1000000000", None, "augment.band_masks must be an integer in"),
    ("range-tilt-huge", TR + " --set augment.range_tilt_db=1e6", None, "augment.range_tilt_db must be a number of dB"),
    ("floor-db-huge", TR + " --set data.floor_db=1e300", None, "floor_db must be a finite number of dB in (0, 300]"),
    (
        "config-epochs-float",
        TR + " --config {w}/config.json",
        config_file(lambda r: r["train_config"].update(epochs=2.5)),
        "config.json: train.epochs (--epochs) must be an integer >= 1, got 2.5",
    ),
    (
        "config-seed-text",
        TR + " --config {w}/config.json",
        config_file(lambda r: r["train_config"].update(seed="5")),
        "train.seed (--seed) must be an integer in 0..",
    ),
    (
        "config-amp-text",
        TR + " --config {w}/config.json",
        config_file(lambda r: r["train_config"].update(amp="yes")),
        "train.amp must be true or false, got 'yes'",
    ),
    (
        "config-lr-text",
        TR + " --config {w}/config.json",
        config_file(lambda r: r["train_config"].update(lr="0.1")),
        "train.lr must be a finite number > 0, got '0.1'",
    ),
    (
        "config-masks-float",
        TR + " --config {w}/config.json",
        config_file(lambda r: r["train_config"]["augment"].update(band_masks=1.5)),
        "augment.band_masks",
    ),
    (
        "config-section-list",
        TR + " --config {w}/config.json",
        config_file(lambda r: r.update(model_config=[1])),
        "its model_config is list, not settings",
    ),
    (
        "config-deep",
        TR + " --config {w}/config.json",
        config_file(text="[" * 100_000 + "]" * 100_000),
        "nests its JSON too deeply",
    ),
    ("config-folder", TR + " --config {w}", None, "is a folder"),
    ("config-fifo", TR + " --config {w}/config.json", fifo("config.json"), "is a FIFO"),
    # --resume: the progress and optimizer state of last.pt
    ("resume-epoch-text", RESUME, _set_state(epoch="x"), "state.epoch is 'x', not a count"),
    ("resume-epoch-huge", RESUME, _set_state(epoch=10**9), "state.history is not one row"),
    ("resume-history-empty", RESUME, _set_state(epoch=5, history=[]), "state.history is not one row"),
    ("resume-best-nan", RESUME, _set_state(best=float("nan")), "state.best is nan, not a score"),
    ("resume-stale-negative", RESUME, _set_state(stale=-100), "state.stale is -100"),
    ("resume-moment-shape", RESUME, run_with(_opt_moment_shape), "exp_avg is [7] for weights of"),
    (
        "resume-lr-nan",
        RESUME,
        run_with(lambda c: c["optimizer"]["param_groups"][0].update(lr=float("nan"))),
        "its optimizer state has lr nan, not finite",
    ),
    ("resume-integer-weights", RESUME, run_with(_integer_weights), "holds torch.int64 in the file, torch.float32"),
    ("resume-and-overwrite", RESUME + " --overwrite", run_with(lambda c: None), "give one of them"),
    ("init-from-folder", TR + " --init-from {w}", None, "--init-from checkpoint"),
    ("init-from-fifo", TR + " --init-from {w}/p.pt", fifo("p.pt"), "is a FIFO"),
    # run folders and datasets
    ("out-is-data", "train --data {w}/d --out {w}/d " + TRAIN, copy_data, "inside the dataset folder"),
    ("out-inside-data", "train --data {w}/d --out {w}/d/run " + TRAIN, copy_data, "inside the dataset folder"),
    ("out-dangling-link", TR, lambda w, fx: (w / "o").symlink_to(w / "nowhere"), "cannot make the run folder"),
    (
        "one-episode",
        "train --data {w}/d --out {w}/o " + TRAIN,
        shard_edit(lambda f: f["episode"].__setitem__(slice(None), 0)),
        "holds 1 episode with whole windows",
    ),
    ("folds-beyond-episodes", TR + " --folds 9", None, "holds 4 episodes with whole windows; --folds 9 needs"),
    ("empty-shard", "train --data {w}/d --out {w}/o " + TRAIN, shard_edit(first_frames(0)), "holds no frames"),
    (
        "one-range-bin",
        "train --data {w}/d --out {w}/o " + TRAIN,
        shard_edit(one_range_bin),
        "1 ranges x 31 azimuths is smaller than the 7 x 7",
    ),
    ("window-longer-than-episodes", TR + " --frames 7", None, "(the longest has 6)"),
    # checkpoints for predict and evaluate
    ("integer-weights", PREDICT + "{w}/c.pt", checkpoint(_integer_weights), "holds torch.int64 in the file"),
    (
        "range-decreasing-npy",
        "predict --checkpoint {w}/c.pt --input {w}/x.npy --out {w}/p.npz",
        both(
            checkpoint(lambda c: c.update(range_m=c["range_m"][::-1])),
            lambda w, fx: np.save(w / "x.npy", np.ones((4, *GRID), np.float32)),
        ),
        "range_m is not increasing",
    ),
    (
        "no-threshold",
        PREDICT + "{w}/c.pt",
        checkpoint(lambda c: c.pop("threshold")),
        "c.pt has no calibrated return threshold (it predates calibration): give one with --threshold",
    ),
    (
        "png-format",
        "predict --checkpoint {ckpt} --input {data} --out {w}/p.npz --png {w}/p.txt",
        None,
        "matplotlib draws no .txt pictures",
    ),
    ("mcap-no-time", MCAP, shard_edit(lambda f: f.__delitem__("time")), "has no time dataset"),
    ("mcap-time-nan", MCAP, shard_edit(lambda f: f["time"].__setitem__(3, np.nan)), "time holds NaN or inf"),
    ("mcap-time-short", MCAP, shard_edit(lambda f: replace_dataset(f, "time", np.arange(5.0))), "time of shape (5,)"),
    (
        "val-episodes-absent",
        "evaluate --data {data} --out {w}/e --split val --checkpoint {w}/c.pt",
        checkpoint(lambda c: c["dataset"].update(val_episodes=[99])),
        "score every window with --split all",
    ),
    ("checkpoint-empty-name", "evaluate --data {data} --out {w}/e --checkpoint ={ckpt}", None, "has an empty name"),
    # the JSON files the summaries read
    ("seeds-not-json", SEEDS, evaluations(text_b="{oops"), "b/metrics.json is not valid JSON (line 1, column 2"),
    ("seeds-list", SEEDS, evaluations(text_b="[1]"), "b/metrics.json holds a JSON list"),
    ("seeds-no-results", SEEDS, evaluations(change_b=_no_results), "b/metrics.json has no results"),
    (
        "seeds-text-mean",
        SEEDS,
        evaluations(change_b=_text_mean),
        "b/metrics.json: results.model.all.scan_f1.mean is 'high', not a number",
    ),
    (
        "seeds-fifo",
        SEEDS,
        both(evaluations(name="x.json"), lambda w, fx: os.mkfifo(w / "a" / "metrics.json")),
        "a/metrics.json is a FIFO",
    ),
    ("seeds-twice", "seeds-summary {w}/a {w}/a --out {w}/s", evaluations(), "is given twice"),
    (
        "s2r-summary-empty",
        "sim2real-summary {w}/a {w}/b --out {w}/s",
        study_json("sim2real.json", "{}"),
        "holds no rows of trained variants",
    ),
    (
        "s2r-summary-list",
        "sim2real-summary {w}/a {w}/b --out {w}/s",
        study_json("sim2real.json", "[1]"),
        "holds a JSON list",
    ),
    (
        "t2-summary-one-row",
        "table2-summary {w}/a {w}/b --out {w}/s",
        study_json("table2.json", json.dumps({"K = 1": T2_ROW})),
        "or fewer than two",
    ),
    (
        "t2-summary-no-reports",
        "table2-summary {w}/a {w}/b --out {w}/s",
        study_json("table2.json", json.dumps({"K = 1": T2_ROW, "K = 5": T2_ROW})),
        "a/k5/minimal/metrics.json does not exist: give folders written by `learn table2`",
    ),
    # the studies' own inputs
    ("ablation-file", "sim2real --ablation {ckpt} --reality {data} --out {w}/o " + TRAIN, None, "is not a folder"),
    ("ablation-missing", "sim2real --ablation {w}/none --reality {data} --out {w}/o " + TRAIN, None, "does not exist"),
    ("score-last-garbage", SCORE, scored_run(lambda run, fx: (run / "last.pt").write_text("x")), "can read safely"),
    ("score-last-fifo", SCORE, scored_run(lambda run, fx: os.mkfifo(run / "last.pt")), "last.pt is a FIFO"),
    ("score-last-no-state", SCORE, scored_run(_no_state), "holds no training progress"),
]


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory, device):
    """The coarse dataset, a run trained on it and an evaluation of it."""
    from acoustic_sim.datasets.generate import generate
    from acoustic_sim.datasets.suites import SUITES, Physics

    root = tmp_path_factory.mktemp("probe_learn")
    grid = ("processing.grid.range_bin_m=0.1", "processing.grid.azimuth_step_deg=6")
    suite = dataclasses.replace(SUITES["tiny"], variants={"": Physics(ray_count=2000)}, episode_frames=6, settings=grid)
    generate(suite, root / "data", frames=24, shards=1, seed=3, device=device, progress=False)
    argv = ["train", "--data", str(root / "data"), "--out", str(root / "run"), *TRAIN.split(), "--epochs", "2"]
    assert main(argv) == 0
    argv = ["evaluate", "--checkpoint", str(root / "run" / "best.pt"), "--data", str(root / "data")]
    assert main([*argv, "--out", str(root / "report"), "--quiet"]) == 0
    return {"data": root / "data", "run": root / "run", "report": root / "report", "root": root}


@pytest.fixture(scope="module")
def results(fixtures):
    commands, folders = {}, {}
    for name, argv, setup, _ in CASES:
        w = fixtures["root"] / "cases" / name
        w.mkdir(parents=True)
        if setup:
            setup(w, fixtures)
        text = argv.format(w=w, data=fixtures["data"], ckpt=fixtures["run"] / "best.pt")
        commands[name], folders[name] = ("learn", text.split()), w
    env = os.environ | {"OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore", "CUDA_VISIBLE_DEVICES": ""}
    done = run_commands(commands, env=env, parallel=2 * (os.cpu_count() or 1), timeout=120)
    return done, folders


@pytest.mark.parametrize(("name", "argv", "setup", "words"), CASES, ids=[c[0] for c in CASES])
def test_a_probed_fault_is_one_line_naming_it(results, name, argv, setup, words):
    done = results[0][name]
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert lines and lines[-1].startswith("error: ") and words in lines[-1], lines[-3:]
    assert sum("error: " in line for line in lines) == 1, lines


def test_refused_runs_wrote_nothing_into_the_data(results):
    """A run refused before training leaves neither checkpoints nor a run folder in the dataset."""
    _, folders = results
    for name in ("out-is-data", "out-inside-data"):
        data = folders[name] / "d"
        assert sorted(p.name for p in data.iterdir() if p.suffix in (".pt", ".json", ".csv")) == [
            "manifest.json",
            "plan.json",
        ], name
        assert not (data / "run").exists()


def test_the_table_of_cases_is_wide():
    assert len(CASES) >= 60 and len({c[0] for c in CASES}) == len(CASES)


CTRL_C_WHILE_IMPORTING = """
import runpy, sys
class CtrlC:
    def find_spec(self, name, path=None, target=None):
        if name == "learn.cli":
            raise KeyboardInterrupt
sys.meta_path.insert(0, CtrlC())
sys.argv = ["learn", "train", "--data", "d", "--out", "o"]
runpy.run_module("learn", run_name="__main__")
"""


def test_ctrl_c_while_the_command_line_imports_is_one_line(tmp_path):
    """Ctrl-C in the seconds before the command line has imported (the probe's SIGINT at 1.2 s on a
    busy machine): one `interrupted:` line and 130, as after them, not a KeyboardInterrupt trace."""
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-c", CTRL_C_WHILE_IMPORTING],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env=os.environ | {"PYTHONPATH": str(Path(__file__).resolve().parents[1])},
    )
    assert done.returncode == 130 and done.stderr.strip().startswith("interrupted:"), done.stderr
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="finds torch's import by the process's mapped files")
@pytest.mark.parametrize("delay_s", [0.0, 0.05, 0.2])
def test_a_real_ctrl_c_while_torch_imports_is_one_line(delay_s, tmp_path):
    """A SIGINT while `python -m learn` imports torch (~2 s on the 2-core CPU): held until the
    imports end, then one `interrupted:` line and 130. Unheld, one landing in the import machinery's
    weakref callbacks was only printed and the command ran on (here: to its error on --data). Timed
    from torch's library being mapped, so it lands inside the import: at a fixed 1.0 s after the
    start it came after the whole command on a machine with torch's files cached."""
    from .crafted import ctrl_c_after

    command = ["-m", "learn", "train", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]
    code, err = ctrl_c_after(command, delay_s, Path(__file__).resolve().parents[1], loaded="libtorch")
    assert code == 130 and err.strip().startswith("interrupted"), err[-3000:]
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err[-3000:]
