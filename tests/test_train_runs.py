"""Training run folders (issue 38): one `learn train` at a time per folder, a resume after kill -9
or Ctrl-C that gives the uninterrupted run's weights bit for bit, a full disk while saving, files
given to --resume / --init-from that do not fit refused in one line naming file and difference,
and an epoch line that accounts for every true return and says why an epoch is kept.

The runs train a width-2 polar UNet on a tiny dataset on a coarse grid (48 ranges x 31 azimuths,
four 6-frame episodes), 4 windows an epoch, in subprocesses of one thread each."""

from __future__ import annotations

import dataclasses
import errno
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from clitools.locks import FolderLocked, folder_lock
from learn.checkpoint import save_checkpoint
from learn.cli import main
from learn.config import TrainConfig
from learn.progress import epoch_line, sizes_line
from learn.runs import LOCK_FILE, clear_run
from learn.scan import scan_scores
from learn.train import _keep

from .crafted import sigint_as_from_a_terminal

EPOCHS = 3
TRAIN = ["--frames", "3", "--width", "2", "--batch-size", "2", "--val-fraction", "0.25", "--max-train-windows", "4"]
TRAIN += ["--loss", "bce", "--lr", "3e-3", "--seed", "5", "--device", "cpu", "--quiet", "--epochs", str(EPOCHS)]
ENV = os.environ | {"OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}  # same threads in every run
HOLD_LOCK = """
import sys
from clitools.locks import folder_lock
with folder_lock(sys.argv[1], sys.argv[2], command="a test"):
    print("held", flush=True)
    sys.stdin.read()
"""


@pytest.fixture(scope="module")
def coarse(tmp_path_factory, device):
    """The tiny suite on a 0.1 m x 6 deg grid: 24 frames, four episodes of 6 (one validates)."""
    from acoustic_sim.datasets.generate import generate
    from acoustic_sim.datasets.suites import SUITES, Physics

    grid = ("processing.grid.range_bin_m=0.1", "processing.grid.azimuth_step_deg=6")
    suite = dataclasses.replace(SUITES["tiny"], variants={"": Physics(ray_count=2000)}, episode_frames=6, settings=grid)
    out = tmp_path_factory.mktemp("coarse")
    generate(suite, out, frames=24, shards=1, seed=3, device=device, progress=False)
    return out


def learn(*argv) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "learn", *map(str, argv)]
    return subprocess.run(command, capture_output=True, text=True, env=ENV, timeout=300)


@pytest.fixture(scope="module")
def reference(coarse, tmp_path_factory):
    """An uninterrupted run: (folder, its stdout)."""
    out = tmp_path_factory.mktemp("uninterrupted") / "run"
    done = learn("train", "--data", coarse, "--out", out, *TRAIN)
    assert done.returncode == 0, done.stderr
    return out, done.stdout


def stopped_after_first_epoch(coarse, out, sig) -> tuple[int, str]:
    """Start a run and send `sig` as soon as its first last.pt appears: (exit status, stderr)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "learn", "train", "--data", str(coarse), "--out", str(out), *TRAIN],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
        preexec_fn=sigint_as_from_a_terminal,
    )
    deadline = time.monotonic() + 300  # a hang guard, not a timing assert
    while not (out / "last.pt").exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "no last.pt appeared"
        time.sleep(0.002)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=300)
    return proc.returncode, err


def epoch_of(path) -> int:
    return torch.load(path, weights_only=True)["state"]["epoch"]


def assert_same_run(got, want):
    """Bit for bit: the weights and optimizer state of last.pt and best.pt, and the history's
    losses and validation scores (the timing columns aside)."""
    for name in ("last.pt", "best.pt"):
        a, b = (torch.load(folder / name, weights_only=True) for folder in (got, want))
        assert a["state"]["epoch"] == b["state"]["epoch"] and a["state"]["step"] == b["state"]["step"]
        for key, tensor in b["model"].items():
            assert torch.equal(a["model"][key], tensor), (name, key)
        for slot, moments in b["optimizer"]["state"].items():
            for key, tensor in moments.items():
                assert torch.equal(a["optimizer"]["state"][slot][key], tensor), (name, slot, key)
        assert a["threshold"] == b["threshold"]
    drop = {"train_seconds", "samples_per_s"}
    histories = [torch.load(f / "last.pt", weights_only=True)["state"]["history"] for f in (got, want)]
    rows = [[{k: str(v) for k, v in r.items() if k not in drop} for r in history] for history in histories]
    assert rows[0] == rows[1]  # as text: nan (no true positive yet) equals nan, and floats all digits


def test_resume_after_kill_is_the_uninterrupted_run(coarse, reference, tmp_path):
    """kill -9 right after epoch 1's last.pt appears leaves last.pt whole and a stale lock file;
    --resume takes the lock over, removes a killed write's temporary file, and ends with the
    uninterrupted run's weights, optimizer state and history, bit for bit (the window order and
    augmentation come from (seed, epoch))."""
    out = tmp_path / "killed"
    status, _ = stopped_after_first_epoch(coarse, out, signal.SIGKILL)
    assert status == -signal.SIGKILL
    assert 1 <= epoch_of(out / "last.pt") < EPOCHS and (out / LOCK_FILE).exists()
    (out / "best.pt.tmp").write_bytes(b"PK\x03\x04 as a kill while writing best.pt leaves it")
    done = learn("train", "--data", coarse, "--out", out, *TRAIN, "--resume")
    assert done.returncode == 0, done.stderr
    assert_same_run(out, reference[0])
    assert not (out / LOCK_FILE).exists() and not list(out.glob("*.tmp"))


def test_ctrl_c_leaves_a_resumable_run_and_one_line(coarse, reference, tmp_path):
    """SIGINT after epoch 1: exit status 130 and one line on stderr saying which epoch last.pt
    keeps and to resume; no temporary file, the lock released; --resume ends bit for bit as the
    uninterrupted run."""
    out = tmp_path / "interrupted"
    status, err = stopped_after_first_epoch(coarse, out, signal.SIGINT)
    kept = epoch_of(out / "last.pt")
    assert status == 130 and kept < EPOCHS
    assert err.strip().splitlines() == [
        f"interrupted: {out / 'last.pt'} keeps epoch {kept} of {EPOCHS}: the same command with --resume continues "
        "the run"
    ]
    assert not list(out.glob("*.tmp")) and not (out / LOCK_FILE).exists()
    assert learn("train", "--data", coarse, "--out", out, *TRAIN, "--resume").returncode == 0
    assert_same_run(out, reference[0])


def test_the_run_says_what_it_validates_on_and_why_it_keeps(reference):
    """The uninterrupted run's stdout: the sizes line first (a single validation episode named as
    such), then one line per epoch, the first kept as the first epoch."""
    lines = reference[1].strip().splitlines()
    assert lines[0].startswith("training on 12 windows of 3 episodes (4 per epoch, drawn anew each epoch)")
    assert "validating on 4 windows of 1 episode only: the scores are one scene's" in lines[0]
    assert lines[1].startswith(f"epoch 1/{EPOCHS}: ") and lines[1].endswith("| kept: first epoch")
    assert all(" at the wrong range, " in line for line in lines[1 : EPOCHS + 1])


def cli_error(capsys, *argv) -> str:
    """`python -m learn ARGV` in-process: exit status 2 and one `error:` line, which is returned."""
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def test_a_live_lock_refuses_a_second_run(coarse, tmp_path, capsys):
    """A folder locked by a live process (as a running `learn train` holds it) refuses another run
    by the holder's pid; once that process is killed, its lock file is free to take."""
    out = tmp_path / "busy"
    out.mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_LOCK, str(out), LOCK_FILE], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        line = cli_error(capsys, "train", "--data", coarse, "--out", out, *TRAIN)
        assert f"--out {out} is in use by pid {holder.pid} on " in line and "a test since" in line
        assert sorted(p.name for p in out.iterdir()) == [LOCK_FILE]  # nothing written beside it
    finally:
        holder.kill()
        holder.wait()
    assert (out / LOCK_FILE).exists()  # left by the killed holder
    with folder_lock(out, LOCK_FILE, command="next"):
        with pytest.raises(FolderLocked, match=f"pid {os.getpid()}"):
            with folder_lock(out, LOCK_FILE, command="third"):
                pass
    assert not (out / LOCK_FILE).exists()


def test_resume_with_best_pt_alone_is_refused(coarse, reference, tmp_path, capsys):
    """best.pt without last.pt: --resume would start from scratch and overwrite it; refused, untouched."""
    out = tmp_path / "best_only"
    out.mkdir()
    shutil.copy(reference[0] / "best.pt", out / "best.pt")
    before = (out / "best.pt").read_bytes()
    line = cli_error(capsys, "train", "--data", coarse, "--out", out, *TRAIN, "--resume")
    assert f"{out} has best.pt but no last.pt" in line and f"--init-from {out / 'best.pt'}" in line
    assert (out / "best.pt").read_bytes() == before and sorted(p.name for p in out.iterdir()) == ["best.pt"]


def test_overwrite_clears_the_old_run_only(reference, tmp_path):
    """--overwrite removes the replaced run's files (also of its folds and TensorBoard), so no
    config.json of one run stands beside checkpoints of another; other files stay."""
    out = tmp_path / "old"
    shutil.copytree(reference[0], out)
    (out / "fold_3").mkdir()
    (out / "fold_3" / "last.pt").write_bytes(b"x")
    (out / "tensorboard").mkdir()
    (out / "tensorboard" / "events.out.tfevents.1.host").write_bytes(b"x")
    (out / "notes.txt").write_text("mine")
    (out / "last.pt.tmp").write_bytes(b"half")
    clear_run(out, keep_run=True)  # as --resume does: a killed write's debris only
    assert not (out / "last.pt.tmp").exists() and (out / "last.pt").exists() and (out / "fold_3").exists()
    clear_run(out)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_overwrite_never_deletes_an_input_of_the_run(coarse, reference, tmp_path, capsys):
    """--overwrite with --init-from or --config inside --out would delete the checkpoint the run
    starts from or the config it was read from: refused, the folder untouched."""
    out = tmp_path / "own"
    shutil.copytree(reference[0], out)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    for given in (["--init-from", out / "best.pt"], ["--config", out / "config.json"]):
        line = cli_error(capsys, "train", "--data", coarse, "--out", out, *TRAIN, *given, "--overwrite")
        assert f"--overwrite would delete {given[1]}, an input of this run" in line, line
        assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


def test_full_disk_while_saving_a_checkpoint(coarse, tmp_path, capsys, monkeypatch):
    """ENOSPC while epoch 2's last.pt is written (after part of it): one error line naming the
    file and what to do, no *.tmp left, last.pt still epoch 1's whole checkpoint, the lock freed."""
    real_save = torch.save

    def full_disk(obj, f, *args, **kwargs):
        if f.name.endswith("last.pt.tmp") and obj["state"]["epoch"] == 2:
            f.write(b"PK\x03\x04 half a checkpoint")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_save(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", full_disk)
    out = tmp_path / "full"
    line = cli_error(capsys, "train", "--data", coarse, "--out", out, *TRAIN)
    assert line == (
        f"error: could not write {out / 'last.pt'} (No space left on device); last.pt is as it was before: "
        "free space on that disk, then continue the run with --resume"
    )
    assert not list(out.glob("*.tmp")) and not (out / LOCK_FILE).exists()
    assert epoch_of(out / "last.pt") == 1 and epoch_of(out / "best.pt") in (1, 2)  # both whole


def test_ctrl_c_while_saving_leaves_no_temporary_file(tmp_path, monkeypatch):
    """Ctrl-C inside torch.save: the interrupt goes on, the temporary file is gone, last.pt as it was."""

    def interrupted(obj, f, *args, **kwargs):
        f.write(b"part")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", interrupted)
    (tmp_path / "last.pt").write_bytes(b"before")
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint({"a": 1}, tmp_path / "last.pt")
    assert (
        sorted(p.name for p in tmp_path.iterdir()) == ["last.pt"] and (tmp_path / "last.pt").read_bytes() == b"before"
    )


def test_files_that_do_not_fit_are_one_line(coarse, reference, tmp_path, capsys):
    """--resume / --init-from / evaluate with a file that is no checkpoint, or one of another model,
    window length or grid, or one whose window length disagrees with its weights or its data config:
    one error line naming the file and what differs."""
    best = reference[0] / "best.pt"
    ckpt = torch.load(best, weights_only=True)

    def crafted(name, **changes):
        path = tmp_path / name
        torch.save(ckpt | changes, path)
        return path

    text = tmp_path / "notes.pt"
    text.write_text("not a checkpoint")
    torch.save([1, 2], tmp_path / "list.pt")
    frames5 = {"model_config": ckpt["model_config"] | {"frames": 5}, "data_config": ckpt["data_config"] | {"frames": 5}}
    cases = [  # (option, file, extra options, what the line must say)
        ("--init-from", text, [], "is not a checkpoint this learner can read safely: not a PyTorch file"),
        ("--init-from", tmp_path / "list.pt", [], "is not a learn checkpoint for dataset format 1 or 2 (found None)"),
        ("--init-from", best, ["--width", "4"], "holds another model than this run builds (model.width 2 -> 4)"),
        ("--init-from", best, ["--frames", "5"], "(model.frames 3 -> 5)"),
        ("--init-from", crafted("no_model.pt", model=None), [], "is not a whole learn checkpoint: it has no model"),
        ("--init-from", crafted("grid.pt", range_m=ckpt["range_m"][:-1]), [], "was trained on 47 ranges"),
        ("--resume", text, [], "is not a checkpoint this learner can read safely: not a PyTorch file"),
        ("--resume", best, ["--width", "4"], "was trained with another model or windows (model.width 2 -> 4)"),
        (
            "--resume",
            crafted("frames5.pt", **frames5),
            ["--frames", "5"],
            "its weights do not fit the model it names (polar_unet, frames 5, width 2): enc_0.0.conv.weight is "
            "[2, 5, 3, 3] in the file, [2, 7, 3, 3] in that model",
        ),
    ]
    for k, (option, path, extra, says) in enumerate(cases):
        out = tmp_path / f"run{k}"
        if option == "--resume":
            out.mkdir()
            shutil.copy(path, out / "last.pt")
            shutil.copy(best, out / "best.pt")
            path = out / "last.pt"
        argv = [*TRAIN, *extra, option] + ([] if option == "--resume" else [path])
        line = cli_error(capsys, "train", "--data", coarse, "--out", out, *argv)
        assert str(path) in line and says in line, (k, line)
        assert option == "--resume" or not out.exists(), k  # a refused new run leaves no folder
    mixed = crafted("mixed.pt", data_config=ckpt["data_config"] | {"frames": 5})
    line = cli_error(capsys, "evaluate", "--checkpoint", mixed, "--data", coarse, "--out", tmp_path / "e")
    assert f"{mixed} is inconsistent: its model reads windows of 3 frames, its data config cuts 5" in line


def test_epoch_lines_say_why_an_epoch_is_kept():
    """Three epochs through `_keep`: scan F1 0 first (kept as the first epoch, not as good), a
    better one (kept, naming the one it beat), a worse one (not kept, patience counted); every
    true return is accounted for (found + wrong range + missed)."""
    recipe = TrainConfig(epochs=5, patience=2)
    state = {"epoch": 0, "step": 0, "best": -np.inf, "stale": 0, "history": []}
    scores = {"val_return_precision": 0.25, "val_return_recall": 0.15, "val_wrong_range": 0.42, "val_missed": 0.43}
    lines = []
    for epoch, f1 in enumerate([0.0, 0.4, 0.3, 0.35], start=1):
        row = {"epoch": epoch, "train_loss": 0.5, "val_scan_f1": f1, "val_threshold": 0.35, "val_false": 0.0} | scores
        previous = state.get("best_epoch")
        lines.append(epoch_line(row, recipe, state, _keep(state, row, "scan_f1"), previous))
    assert lines[0] == (
        "epoch 1/5: train loss 0.5 | val scan F1 0.000 at threshold 0.35 (precision 0.25; true returns 0.15 found, "
        "0.42 at the wrong range, 0.43 missed; false 0.00) | kept: first epoch"
    )
    assert lines[1].endswith("| kept: best scan F1 so far (0.000 in epoch 1)")
    assert lines[2].endswith("| not kept: epoch 2 stays best (scan F1 0.400); 1 of 2 epochs without a better one")
    assert lines[3].endswith("2 of 2 epochs without a better one; stopping")


def test_sizes_line_names_a_single_validation_episode():
    one = sizes_line(train_windows=90, train_episodes=9, per_epoch=90, val_windows=8, val_of=10, val_episodes=1)
    assert one == (
        "training on 90 windows of 9 episodes; validating on 8 windows (a fixed draw of 8 of 10) of 1 episode only: "
        "the scores are one scene's (more episodes: raise --val-fraction or generate more)"
    )
    many = sizes_line(train_windows=90, train_episodes=9, per_epoch=90, val_windows=10, val_of=10, val_episodes=2)
    assert many.endswith("validating on 10 windows of 2 episodes")


def test_wrong_range_completes_the_true_returns():
    """On 200 seeded random scans of 30 beams (a third without a true return, a third without a
    predicted one), wrong_range is the share of true returns predicted more than 0.1 m off, counted
    in numpy, and found (recall) + wrong range + missed = 1 on every scan with returns."""
    rng = np.random.default_rng(7)
    true = np.where(rng.random((200, 30)) < 0.7, rng.uniform(0.2, 5.0, (200, 30)), np.inf)
    pred = np.where(
        rng.random((200, 30)) < 0.7, np.where(np.isfinite(true), true, 2.0) + rng.normal(0, 0.15, (200, 30)), np.inf
    )
    true[:66] = np.inf
    pred[66:133] = np.inf
    got = {k: v.numpy() for k, v in scan_scores(torch.tensor(pred), torch.tensor(true), tolerance_m=0.1).items()}
    both = np.isfinite(pred) & np.isfinite(true)
    off = both & (np.abs(np.where(both, pred, 0) - np.where(both, true, 0)) > 0.1 + 1e-9)
    returns = np.isfinite(true).sum(1)
    want = np.where(returns > 0, off.sum(1) / np.maximum(returns, 1), 0.0)
    np.testing.assert_allclose(got["wrong_range"], want, atol=1e-12)
    sums = got["return_recall"] + got["wrong_range"] + got["missed"]
    np.testing.assert_allclose(sums[returns > 0], 1.0, atol=1e-12)
