"""The learner's inputs as a fault-injection probe feeds them (issue 38): shards of two runs, or
one shard twice, in a folder; labels, scenario indices and layouts our writer never makes (no
checksum, external or virtual datasets, links); energyscapes beyond float16; checkpoints with NaN
weights, an infinite dB floor or a network too large for memory; headers that claim more than the
machine holds; FIFOs and devices in place of files; broken JSON. Each is refused with one line
that names the file and the field, before anything is allocated; none hangs or answers NaN.

Crafted shards are copies of the session's tiny dataset (two shards, episodes 0 and 1, 8 frames
each) edited with h5py; crafted checkpoints are the shipped one, edited. Cases that would hang
without their check (FIFOs) run as subprocesses under a timeout.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

import learn
import learn.inputs
from clitools import limits
from learn.cli import main
from learn.data import DataConfig, DataError, load_frames
from learn.predict import predict

CKPT = Path(learn.PRETRAINED_CHECKPOINT)
GRID = (240, 181)  # the tiny suite's and the shipped model's (range, azimuth) grid


def copy_of(dataset: Path, tmp_path: Path) -> Path:
    folder = tmp_path / "data"
    shutil.copytree(dataset, folder)
    return folder


def replace(shard: Path, name: str, data=None, **options) -> None:
    """Put `data` (or a dataset made from `options` alone) in place of the shard's `name`."""
    with h5py.File(shard, "a") as f:
        del f[name]
        f.create_dataset(name, data=data, **options)


def edit(shard: Path, name: str, change) -> None:
    """Apply `change(array)` to the shard's dataset `name`, in place (same layout and filters)."""
    with h5py.File(shard, "a") as f:
        values = f[name][()]
        change(values)
        f[name][...] = values


def delete(shard: Path, name: str) -> None:
    with h5py.File(shard, "a") as f:
        del f[name]


def set_attr(shard: Path, key: str, value) -> None:
    with h5py.File(shard, "a") as f:
        if value is None:
            del f.attrs[key]
        else:
            f.attrs[key] = value


def cli_error(capsys, argv: list[str]) -> str:
    """`python -m learn ARGV` in-process: exit code 2 and one `error:` line, which is returned."""
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


# ---------------------------------------------------------------------------------------------
# Mixed data: one folder, one run, every shard once


def _other_run(folder: Path):
    set_attr(folder / "shard-00001.h5", "plan_id", "0123456789abcdef")
    return "shard-00001.h5", "shard-00000.h5", "mixes shards of two runs"


def _symlink(folder: Path):
    (folder / "shard-00002.h5").symlink_to(folder / "shard-00000.h5")
    return "shard-00002.h5", "shard-00000.h5", "same file"


def _hard_link(folder: Path):
    os.link(folder / "shard-00001.h5", folder / "shard-00002.h5")
    return "shard-00002.h5", "shard-00001.h5", "same file"


def _copy(folder: Path):
    shutil.copy(folder / "shard-00000.h5", folder / "shard-00002.h5")
    return "shard-00002.h5", "shard-00000.h5", "repeats shard 0"


def _stale_manifest(folder: Path):
    manifest = json.loads((folder / "manifest.json").read_text())
    (folder / "manifest.json").write_text(json.dumps(manifest | {"plan_id": "0123456789abcdef"}))
    return "manifest.json", "shard-00000.h5", "mixes two runs"


def _episode_in_two_shards(folder: Path):
    edit(folder / "shard-00001.h5", "episode", lambda e: e.fill(0))  # shard 0 holds episode 0
    return "shard-00001.h5", "shard-00000.h5", "episode 0 is also in"


@pytest.mark.parametrize(
    "craft",
    [_other_run, _symlink, _hard_link, _copy, _stale_manifest, _episode_in_two_shards],
    ids=lambda c: c.__name__,
)
def test_a_folder_mixing_runs_or_repeating_a_shard_is_refused_naming_both(tiny_dataset, tmp_path, craft):
    """Episode ids restart at 0 in every run: shards of two runs, or one shard twice, in one folder
    would make windows that join unrelated drives. The error names both files."""
    folder = copy_of(tiny_dataset, tmp_path)
    assert len(load_frames(folder)) == 16  # the copy itself is fine
    first, second, words = craft(folder)
    with pytest.raises(DataError, match=words) as err:
        load_frames(folder)
    assert first in str(err.value) and second in str(err.value)


# ---------------------------------------------------------------------------------------------
# Shard contents: values and layouts our writer never makes


def _external(shard: Path, tmp_path: Path) -> None:
    outside = tmp_path / "outside.bin"  # any file on the machine: here axis values, so a read would work
    outside.write_bytes(np.linspace(0.21, 4.99, GRID[0]).tobytes())
    replace(shard, "range_m", shape=(GRID[0],), dtype="<f8", external=[(str(outside), 0, GRID[0] * 8)])


def _virtual(shard: Path, tmp_path: Path) -> None:
    source = tmp_path / "elsewhere.h5"
    with h5py.File(source, "w") as f:
        f.create_dataset("e", data=np.ones((8, *GRID), np.float16))
    layout = h5py.VirtualLayout(shape=(8, *GRID), dtype=np.float16)
    layout[:] = h5py.VirtualSource(str(source), "e", shape=(8, *GRID))
    with h5py.File(shard, "a") as f:
        del f["energyscape"]
        f.create_virtual_dataset("energyscape", layout)


def _external_link(shard: Path, tmp_path: Path) -> None:
    with h5py.File(tmp_path / "times.h5", "w") as f:
        f.create_dataset("t", data=np.arange(8.0), fletcher32=True)
    with h5py.File(shard, "a") as f:
        del f["time"]
        f["time"] = h5py.ExternalLink(str(tmp_path / "times.h5"), "/t")


def _label_nan(shard: Path, tmp_path: Path) -> None:
    label = np.zeros((8, *GRID), np.float32)
    label[2, 10, 10] = np.nan
    replace(shard, "lidar/image", label, chunks=(1, *GRID), fletcher32=True)


def _split_episode(shard: Path, tmp_path: Path) -> None:
    edit(shard, "episode", lambda e: e.__setitem__(slice(0, 3), 7))  # 7 7 7 0 0 0 0 0 ... then 7 again below
    edit(shard, "episode", lambda e: e.__setitem__(slice(6, 8), 7))


SHARD_CASES = {
    "label-7": (lambda s, t: edit(s, "lidar/image", lambda a: a.__setitem__((0, 5, 5), 7)), r"lidar/image holds 7"),
    "label-nan": (_label_nan, r"lidar/image holds nan at frame 2 .*outside \{0, 1\} or NaN"),
    "scenario-minus-1": (
        lambda s, t: edit(s, "scenario", lambda a: a.__setitem__(3, -1)),
        r"scenario holds index -1 at frame 3, outside 0\.\.2",
    ),
    "scenario-too-large": (
        lambda s, t: edit(s, "scenario", lambda a: a.__setitem__(4, 101)),
        r"scenario holds index 101 at frame 4",
    ),
    "no-checksum": (
        lambda s, t: replace(s, "episode", np.zeros(8, np.int32)),
        r"episode is stored without the Fletcher-32 checksum",
    ),
    "external-dataset": (_external, r"range_m is an HDF5 external dataset reading .*outside\.bin"),
    "virtual-dataset": (_virtual, r"energyscape is an HDF5 virtual dataset reading .*elsewhere\.h5"),
    "external-link": (_external_link, r"time is a link to .*times\.h5:/t"),
    "beyond-float16": (
        lambda s, t: replace(
            s, "energyscape", np.full((8, 1, *GRID), 1.2e6, np.float32), chunks=(1, 1, *GRID), fletcher32=True
        ),
        r"energyscape holds values above float16's 65,504 \(max 1\.2e\+06\)",
    ),
    "nan-energyscape": (
        lambda s, t: edit(s, "energyscape", lambda a: a.__setitem__((1, 0, 2, 3), np.nan)),
        r"energyscape holds 1 NaN or inf",
    ),
    "missing-dataset": (lambda s, t: delete(s, "range_m"), r"the range_m dataset is missing"),
    "scenarios-not-json": (
        lambda s, t: set_attr(s, "scenarios", '["room", '),
        r"scenarios attribute is not valid JSON",
    ),
    "scenarios-a-dict": (lambda s, t: set_attr(s, "scenarios", '{"room": 1}'), r"scenarios attribute is a JSON dict"),
    "no-plan-id": (lambda s, t: set_attr(s, "plan_id", None), r"lacks the plan_id"),
    "format-version-text": (lambda s, t: set_attr(s, "format_version", "one"), r"format_version 'one'"),
    "episode-split": (_split_episode, r"an episode's frames are split in two runs"),
    "axis-not-increasing": (
        lambda s, t: edit(s, "azimuth_rad", lambda a: a.__setitem__(slice(None), a[::-1].copy())),
        r"azimuth_rad is not a finite, increasing axis",
    ),
}


@pytest.mark.parametrize("case", list(SHARD_CASES))
def test_a_bad_shard_is_refused_naming_it_and_the_dataset(tiny_dataset, tmp_path, case):
    """One line names the shard and the dataset or attribute at fault, and what to do."""
    folder = copy_of(tiny_dataset, tmp_path)
    craft, words = SHARD_CASES[case]
    craft(folder / "shard-00000.h5", tmp_path)
    with pytest.raises(DataError, match=words) as err:
        load_frames(folder)
    assert "shard-00000.h5" in str(err.value)
    assert len(str(err.value).splitlines()) == 1


def test_a_shard_claiming_billions_of_frames_is_refused_before_allocating(tiny_dataset, tmp_path):
    """Datasets of 2e9 frames that hold no data (a small file): refused with the figure from the
    header, not by running out of memory."""
    folder = copy_of(tiny_dataset, tmp_path)
    shard, frames = folder / "shard-00000.h5", 2_000_000_000
    with h5py.File(shard, "a") as f:
        for name, dtype, shape in (("energyscape", np.float16, (1, *GRID)), ("lidar/image", np.uint8, GRID)):
            del f[name]
            f.create_dataset(name, shape=(frames, *shape), dtype=dtype, chunks=(1, *shape), fletcher32=True)
        for name in ("episode", "scenario"):
            del f[name]
            f.create_dataset(name, shape=(frames,), dtype=np.int32, chunks=(4096,), fletcher32=True)
    assert shard.stat().st_size < 10**7
    with pytest.raises(learn.inputs.TooLarge, match=r"2,000,000,008 frames of 240 x 181\) needs [\d.,]+ TB"):
        load_frames(folder)


def test_memory_is_checked_with_the_figure(tiny_dataset, monkeypatch):
    """16 frames of 240 x 181: 2,085,376 bytes held (float16, uint8 and two int64 per frame) and
    two shards' worth of 1,042,560 bytes as read: 4.2 MB, refused where 1 MB is available."""
    monkeypatch.setattr(limits, "available_memory_bytes", lambda: 1_000_000)
    with pytest.raises(
        learn.inputs.TooLarge, match=r"16 frames of 240 x 181\) needs 4\.2 MB, more than the 1\.0 MB of memory free"
    ):
        load_frames(tiny_dataset)
    monkeypatch.setattr(limits, "available_memory_bytes", lambda: 4_170_496)
    assert len(load_frames(tiny_dataset)) == 16


@pytest.mark.parametrize(
    "text, words",
    [('{plan_id: "x"}', r"line 1, column 2: Expecting property name"), ("[1, 2]", r"holds a JSON list")],
)
def test_a_broken_manifest_is_refused_naming_it_and_the_place(tiny_dataset, tmp_path, text, words):
    folder = copy_of(tiny_dataset, tmp_path)
    (folder / "manifest.json").write_text(text)
    with pytest.raises(ValueError, match=words) as err:
        load_frames(folder)
    assert "manifest.json" in str(err.value) and "remove manifest.json" in str(err.value)


# ---------------------------------------------------------------------------------------------
# predict's .npy input


def _npy_claiming(path: Path, shape: tuple[int, ...]) -> Path:
    """A .npy whose header claims `shape` (float32) over 64 bytes of data."""
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": shape})
        f.write(bytes(64))
    return path


def test_npy_inputs_that_would_go_wrong_are_refused(tmp_path, capsys, monkeypatch):
    """float16 that overflowed to inf (raw counts saved as float16), float64 beyond float32,
    a header claiming 2e9 frames, a .npz, text: one line each, naming the file."""
    pred = str(tmp_path / "p.npz")
    raw = np.full((6, *GRID), 1.0, np.float64)
    raw[0, 0, 0] = 1.2e6
    with np.errstate(over="ignore"):
        np.save(tmp_path / "counts16.npy", raw.astype(np.float16))  # 1.2e6 -> inf in float16
    raw[0, 0, 0] = 1e40
    np.save(tmp_path / "huge64.npy", raw)
    np.savez(tmp_path / "scapes.npz", energyscape=np.ones((6, *GRID), np.float32))
    (tmp_path / "notes.npy").write_text("not numbers")
    cases = {
        "counts16.npy": r"counts16\.npy: 1 of its values are NaN or inf: float16 overflows to inf above 65,504",
        "huge64.npy": r"huge64\.npy: 1 of its values .* beyond float32's 3\.4e38",
        "scapes.npz": r"scapes\.npz is a file, not a \.npy",
        "notes.npy": r"notes\.npy is not a \.npy file",
    }
    _npy_claiming(tmp_path / "claims.npy", (2_000_000_000, *GRID))
    cases["claims.npy"] = r"claims\.npy is truncated: its header says shape \(2000000000, 240, 181\)"
    for name, words in cases.items():
        line = cli_error(capsys, ["predict", "--checkpoint", str(CKPT), "--input", str(tmp_path / name), "--out", pred])
        assert re.search(words, line), line
    np.save(tmp_path / "fine.npy", np.ones((6, *GRID), np.float32))
    monkeypatch.setattr(limits, "available_memory_bytes", lambda: 1_000_000)
    line = cli_error(
        capsys, ["predict", "--checkpoint", str(CKPT), "--input", str(tmp_path / "fine.npy"), "--out", pred]
    )
    assert "6 energyscapes of 240 x 181) needs 2.3 MB" in line  # 6 x 43,440 cells x 9 bytes
    assert not Path(pred).exists()


def test_energyscapes_above_float16_range_predict_as_scaled_down_ones(tiny_dataset, tmp_path):
    """Energyscapes are normalised to each frame's peak, so their scale does not matter: the tiny
    dataset's frames times 2**20 (up to ~1e5, beyond float16) predict exactly what the frames do
    (2**20 is exact in float32), with no NaN."""
    frames = load_frames(tiny_dataset).energyscape[:7].astype(np.float32)
    np.save(tmp_path / "plain.npy", frames)
    np.save(tmp_path / "large.npy", frames * 2.0**20)
    assert (frames * 2.0**20).max() > 65_504
    plain = np.load(predict(CKPT, tmp_path / "plain.npy", tmp_path / "plain.npz"))
    large = np.load(predict(CKPT, tmp_path / "large.npy", tmp_path / "large.npz"))
    assert np.isfinite(large["prediction"].astype(np.float32)).all() and np.isfinite(large["ranges"]).any()
    np.testing.assert_array_equal(large["prediction"], plain["prediction"])
    np.testing.assert_array_equal(large["ranges"], plain["ranges"])


# ---------------------------------------------------------------------------------------------
# Checkpoints: the content they are read for


def _nan_weight(ckpt: dict) -> None:
    ckpt["model"]["head.weight"][0, 3] = float("nan")


CHECKPOINT_CASES = {
    "nan-weight": (_nan_weight, r"model weight head\.weight holds 1 NaN or inf values"),
    "inf-floor": (lambda c: c["data_config"].update(floor_db=float("inf")), r"floor_db must be a finite number"),
    "width-30000": (
        lambda c: c["model_config"].update(width=30_000),
        r"model_config: model polar_unet \(frames 5, width 30000: [\d,]+ weights\) needs 3\.\d TB",
    ),
    "width-text": (lambda c: c["model_config"].update(width="16"), r"width must be an integer, got '16'"),
    "no-range": (lambda c: c.pop("range_m"), r"range_m is None, not a list of finite numbers"),
    "nan-azimuth": (lambda c: c["azimuth_rad"].__setitem__(0, float("nan")), r"azimuth_rad is .*not a list of finite"),
    "threshold-text": (lambda c: c.update(threshold="0.5"), r"threshold is '0\.5', not a number in \(0, 1\]"),
    "frames-disagree": (
        lambda c: c["data_config"].update(frames=3),
        r"its model reads windows of 5 frames, its data config cuts 3",
    ),
    "plan-id-number": (lambda c: c["dataset"].update(plan_id=7), r"dataset\.plan_id is 7, not text"),
}


@pytest.mark.parametrize("case", list(CHECKPOINT_CASES))
def test_a_bad_checkpoint_is_refused_naming_it_and_the_field(tmp_path, capsys, case):
    """Predict, evaluate and export load through one check: the file and the field are named."""
    change, words = CHECKPOINT_CASES[case]
    ckpt = torch.load(CKPT, weights_only=True)
    change(ckpt)
    bad = tmp_path / "bad.pt"
    torch.save(ckpt, bad)
    pred = tmp_path / "p.npz"
    np.save(tmp_path / "x.npy", np.ones((6, *GRID), np.float32))
    line = cli_error(
        capsys, ["predict", "--checkpoint", str(bad), "--input", str(tmp_path / "x.npy"), "--out", str(pred)]
    )
    assert re.search(words, line) and "bad.pt" in line, line
    assert not pred.exists()


def test_configs_refuse_wrong_types_and_an_infinite_floor():
    with pytest.raises(ValueError, match="floor_db"):
        DataConfig(floor_db=float("inf"))
    with pytest.raises(ValueError, match="frames must be an integer"):
        DataConfig(frames=5.0)


# ---------------------------------------------------------------------------------------------
# Files that are not regular files: they would block a read forever (subprocesses, with a timeout)


def test_fifos_and_devices_are_refused_without_hanging(tiny_dataset, tmp_path):
    """A FIFO as a shard, as the .npy, as the checkpoint; /dev/urandom behind a link as the .npy:
    `learn predict` exits 2 within the timeout, naming the file and what it is."""
    folder = copy_of(tiny_dataset, tmp_path)
    (folder / "shard-00001.h5").unlink()
    os.mkfifo(folder / "shard-00001.h5")
    os.mkfifo(tmp_path / "pipe.npy")
    os.mkfifo(tmp_path / "pipe.pt")
    (tmp_path / "random.npy").symlink_to("/dev/urandom")
    cases = {
        "fifo-shard": (CKPT, folder, "shard-00001.h5 is a FIFO"),
        "fifo-npy": (CKPT, tmp_path / "pipe.npy", "pipe.npy is a FIFO"),
        "fifo-checkpoint": (tmp_path / "pipe.pt", folder, "pipe.pt is a FIFO"),
        "device-npy": (CKPT, tmp_path / "random.npy", "random.npy is a character device"),
    }
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    running = {}
    for name, (checkpoint, source, _) in cases.items():
        argv = ["predict", "--checkpoint", str(checkpoint), "--input", str(source), "--out", str(tmp_path / name)]
        running[name] = subprocess.Popen(
            [sys.executable, "-m", "learn", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
    try:
        for name, process in running.items():
            _, err = process.communicate(timeout=120)
            assert process.returncode == 2 and err.count("\n") == 1 and cases[name][2] in err, (name, err)
    finally:
        for process in running.values():
            process.kill()
