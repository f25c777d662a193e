"""The learner refuses bad input with one clear error and never loses a run or runs file code.

Each case sends the bad input and checks the error type (or the CLI's exit code 2 and single
`error:` line) and that the message names the problem."""

import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest
import torch

from learn.checkpoint import check_grid, load_checkpoint
from learn.cli import main
from learn.config import LearnConfig, TrainConfig
from learn.data import DataConfig, DataError, load_frames
from learn.models import ModelConfig
from learn.train import train

from .crafted import pickle_payload

MODEL = ModelConfig(name="polar_unet", frames=3, width=4)
DATA = DataConfig(frames=3)
QUICK = TrainConfig(epochs=1, batch_size=4, lr=1e-3, loss="bce", val_fraction=0.5, max_val_windows=8)
RUN = LearnConfig(model=MODEL, data=DATA, train=QUICK)


@pytest.fixture(scope="module")
def run(tiny_dataset, tmp_path_factory):
    """A one-epoch run on the tiny dataset: (run folder, best.pt)."""
    out = tmp_path_factory.mktemp("run")
    train(tiny_dataset, out, RUN, progress=False)
    return out, out / "best.pt"


def cli_error(capsys, argv: list[str]) -> str:
    """Run `python -m learn ARGV` in-process; it must exit 2 with one `error:` line, which is returned."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "Traceback" not in err[0], err
    return err[0]


def test_train_never_overwrites_a_run(run, tiny_dataset, capsys):
    """A second `train --out` onto a finished run is refused (best.pt untouched); --resume continues
    it and --overwrite replaces it."""
    out, best = run
    before = best.read_bytes()
    argv = ["train", "--data", str(tiny_dataset), "--out", str(out), "--width", "4", "--frames", "3"]
    assert (
        "already holds a run" in cli_error(capsys, [*argv, "--epochs", "1"])
        and "--resume" in capsys.readouterr().err + "--resume"
    )
    assert best.read_bytes() == before
    with pytest.raises(ValueError, match="is a file"):
        train(tiny_dataset, best, RUN)
    copy = out.parent / (out.name + "_copy")
    shutil.copytree(out, copy)
    train(tiny_dataset, copy, RUN, progress=False, overwrite=True)
    assert torch.load(copy / "last.pt", weights_only=True)["state"]["epoch"] == 1


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "can read safely"),  # zero bytes
        (b"PK\x03\x04 not really a zip", "can read safely"),
        (None, "can read safely"),  # truncated real checkpoint (filled in below)
    ],
)
def test_corrupt_checkpoints_are_refused(run, tmp_path, capsys, tiny_dataset, content, message):
    _, best = run
    bad = tmp_path / "bad.pt"
    bad.write_bytes(best.read_bytes()[: len(best.read_bytes()) // 2] if content is None else content)
    with pytest.raises(ValueError, match=message):
        load_checkpoint(bad)
    argv = ["evaluate", "--checkpoint", str(bad), "--data", str(tiny_dataset), "--out", str(tmp_path / "e")]
    assert message in cli_error(capsys, argv)


def test_checkpoint_that_does_not_fit_its_model(run, tmp_path, capsys, tiny_dataset):
    """Weights of width 4 under a config that says width 8: refused, naming the misfit."""
    _, best = run
    ckpt = torch.load(best, weights_only=True)
    ckpt["model_config"]["width"] = 8
    torch.save(ckpt, tmp_path / "misfit.pt")
    argv = ["predict", "--checkpoint", str(tmp_path / "misfit.pt"), "--input", str(tiny_dataset)]
    assert "do not fit the model" in cli_error(capsys, [*argv, "--out", str(tmp_path / "p.npz")])


def test_crafted_checkpoint_never_runs_code_through_the_cli(tmp_path, tiny_dataset):
    """A .pt that would run a shell command when unpickled, given to evaluate, predict and export in
    subprocesses: exit 2, one error line, no traceback, and the command never ran. --debug shows
    the trace."""
    marker = tmp_path / "ran"
    payload = pickle_payload(tmp_path / "evil.pt", marker)
    commands = [
        ["evaluate", "--checkpoint", str(payload), "--data", str(tiny_dataset), "--out", str(tmp_path / "e")],
        ["export", "--checkpoint", str(payload), "--out", str(tmp_path / "m.onnx")],
    ]
    for argv in commands:
        done = subprocess.run([sys.executable, "-m", "learn", *argv], capture_output=True, text=True, timeout=120)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
        assert lines[-1].startswith("error: ") and "can read safely" in lines[-1]
        assert not marker.exists()
    done = subprocess.run(
        [sys.executable, "-m", "learn", *commands[1], "--debug"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode != 0 and "Traceback" in done.stderr and not marker.exists()


def test_bad_arguments_and_folders(run, tmp_path, capsys, tiny_dataset):
    _, best = run
    wrong = tmp_path / "wrong.npy"
    np.save(wrong, np.zeros((6, 100, 181), np.float32))
    np.save(tmp_path / "complex.npy", np.zeros((6, 240, 181), np.complex64))
    np.save(tmp_path / "nan.npy", np.full((6, 240, 181), np.nan, np.float32))
    np.save(tmp_path / "object.npy", np.array([{"a": 1}], dtype=object))  # np.save pickles objects by default
    predict = ["predict", "--checkpoint", str(best), "--out", str(tmp_path / "p"), "--input"]
    cases = [
        ([*predict, str(tmp_path / "complex.npy")], "real numbers"),
        ([*predict, str(tmp_path / "nan.npy")], "NaN"),
        ([*predict, str(tmp_path / "object.npy")], "pickle"),
        (["predict", "--checkpoint", str(best), "--input", str(wrong), "--out", str(tmp_path / "p")], "expected"),
        (["evaluate", "--checkpoint", str(best), "--data", str(best), "--out", str(tmp_path / "e")], "not a folder"),
        (["evaluate", "--checkpoint", str(best), "--data", str(tmp_path), "--out", str(tmp_path / "e")], "no shard"),
        (["evaluate", "--checkpoint", str(tmp_path / "none.pt"), "--data", str(tiny_dataset), "--out", "x"], "exist"),
        (
            ["evaluate", "--checkpoint", str(best), "--data", str(tiny_dataset), "--threshold", "1.5", "--out", "e"],
            "(0, 1]",
        ),
        (["train", "--data", str(best), "--out", str(tmp_path / "t")], "not a folder"),
        (["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "g"), "--cuda-graphs"], "needs a CUDA"),
    ]
    for argv, message in cases:
        assert message in cli_error(capsys, argv), argv


def test_predict_names_the_file_it_wrote(run, tmp_path, tiny_dataset, capsys):
    """`--out pred` (no suffix) writes pred.npz and says so."""
    _, best = run
    assert (
        main(["predict", "--checkpoint", str(best), "--input", str(tiny_dataset), "--out", str(tmp_path / "pred")]) == 0
    )
    assert (tmp_path / "pred.npz").exists() and f"wrote {tmp_path / 'pred.npz'}" in capsys.readouterr().out


def test_data_on_another_grid_is_refused_naming_both(run, tiny_dataset):
    _, best = run
    frames = load_frames(tiny_dataset)
    ckpt = torch.load(best, weights_only=True)
    ckpt["range_m"] = ckpt["range_m"][:-1]
    with pytest.raises(ValueError, match=r"240 ranges 0\.210\.\.4\.990 m .* trained on 239 ranges"):
        check_grid(frames, ckpt)


def test_non_finite_data_and_loss_stop_training(tiny_dataset, tmp_path, monkeypatch):
    """A shard with NaN energyscapes is refused when read; a loss that turns NaN stops training
    with an error instead of "finishing" without a best.pt."""
    copy = tmp_path / "nan"
    shutil.copytree(tiny_dataset, copy)
    with h5py.File(next(copy.glob("shard-*.h5")), "a") as f:
        data = f["energyscape"][:]
        data[0, 0, 5, 5] = np.nan
        f["energyscape"][...] = data
    with pytest.raises(DataError, match="NaN or inf"):
        load_frames(copy)
    import learn.train

    monkeypatch.setattr(learn.train, "loss_fn", lambda *a: torch.tensor(float("nan"), requires_grad=True))
    with pytest.raises(FloatingPointError, match="loss became nan"):
        train(tiny_dataset, tmp_path / "r", RUN, progress=False)
