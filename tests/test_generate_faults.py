"""Faults during generation: a failed write leaves no temporary file, a shard damaged after it
was written is found by its checksums and written again (and refused by the learner), two runs
never write one folder, and workers die with their parent."""

import dataclasses
import errno
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

import acoustic_sim.generate as gen
from acoustic_sim.dataset import DatasetError, ShardFrames, verify_shard, write_shard
from acoustic_sim.suites import SUITES, Physics
from learn.data import DataError, load_frames

SUITE = dataclasses.replace(SUITES["tiny"], variants={"": Physics(ray_count=2000)})


def test_a_failed_write_removes_its_temporary_file(tmp_path, monkeypatch):
    """A full disk while writing: the error comes through, and neither the shard nor its .tmp stays."""
    frames = ShardFrames(
        energyscape=[np.zeros((2, 3, 4))],
        lidar_ranges=[np.zeros((2, 5))],
        lidar_image=[np.zeros((2, 3, 4))],
        pose=[np.tile(np.eye(4), (2, 1, 1))],
        time=[np.zeros(2)],
        episode=[np.zeros(2)],
        scenario=[np.zeros(2)],
    )
    real = h5py.Group.create_dataset

    def full_disk(self, name, *args, **kwargs):
        if name == "lidar/image":
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", full_disk)
    with pytest.raises(OSError, match="No space left"):
        write_shard(tmp_path / "shard-00000.h5", frames, attrs={}, range_m=np.arange(3.0), azimuth_rad=np.arange(4.0))
    assert list(tmp_path.iterdir()) == []


def test_a_damaged_shard_is_found_and_written_again(tmp_path, device):
    """Bytes flipped inside the energyscape's first chunk (the file still opens, its attributes
    read fine): training data refuses it, and a rerun moves it aside and writes it again, equal to
    the original."""
    out = tmp_path / "d"
    gen.generate(SUITE, out, frames=8, shards=1, seed=2, device=device, progress=False)
    shard = out / "shard-00000.h5"
    verify_shard(shard)
    original = load_frames(out).energyscape.copy()
    with h5py.File(shard, "r") as f:
        chunk = f["energyscape"].id.get_chunk_info(0)
    raw = bytearray(shard.read_bytes())
    middle = chunk.byte_offset + chunk.size // 2
    raw[middle : middle + 16] = bytes(255 - b for b in raw[middle : middle + 16])
    shard.write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match="damaged"):
        verify_shard(shard)
    with pytest.raises(DataError, match="damaged"):
        load_frames(out)
    with pytest.warns(UserWarning, match="writing the shard again"):
        summary = gen.generate(SUITE, out, frames=8, shards=1, seed=2, device=device, progress=False)
    assert summary["shards_written"] == 1 and (out / "shard-00000.h5.damaged").exists()
    np.testing.assert_array_equal(load_frames(out).energyscape, original)


def test_two_runs_never_write_one_folder(tmp_path, device):
    """A lock held by a live process refuses a second run; a lock left by a dead one is taken over."""
    out = tmp_path / "l"
    gen._check_plan_file(out, gen.plan(SUITE, out, frames=8, shards=1, seed=2), {"suite": "tiny"})  # as a run does
    lock = out / gen.LOCK_FILE
    lock.write_text(f"{os.getpid()} {os.uname().nodename}")
    with pytest.raises(DatasetError, match="another generate"):
        gen.generate(SUITE, out, frames=8, shards=1, seed=2, device=device, progress=False)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    lock.write_text(f"{dead.pid} {os.uname().nodename}")
    summary = gen.generate(SUITE, out, frames=8, shards=1, seed=2, device=device, progress=False)
    assert summary["shards_written"] == 1 and not lock.exists()


def _cmdline(pid: int) -> bytes:
    with open(f"/proc/{pid}/cmdline", "rb") as f:
        return f.read()


def _children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = open(f"/proc/{entry}/stat").read()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry))
    return out


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads the process table from /proc (Linux)")
def test_workers_exit_when_the_parent_is_killed(tmp_path):
    """SIGKILL to `generate --workers 2`: its (forked) worker processes end within seconds
    instead of simulating on for nobody."""
    script = tmp_path / "run.py"
    script.write_text(
        "import dataclasses, sys\n"
        "from acoustic_sim.generate import generate\n"
        "from acoustic_sim.suites import SUITES, Physics\n"
        "if __name__ == '__main__':\n"
        "    suite = dataclasses.replace(SUITES['tiny'], variants={'': Physics(ray_count=20000)})\n"
        "    generate(suite, sys.argv[1], frames=400, shards=4, workers=2, device='cpu', progress=False)\n"
    )
    parent = subprocess.Popen([sys.executable, str(script), str(tmp_path / "out")], stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while len(_children(parent.pid)) < 2 and time.time() < deadline:  # 2 workers (+ a resource tracker if spawned)
        time.sleep(0.5)
    children = _children(parent.pid)
    assert len(children) >= 2, "the workers never started"
    forked = [c for c in children if _cmdline(c) == _cmdline(parent.pid)]  # a spawned one runs spawn_main
    assert len(forked) == 2, "a fresh parent (no CUDA started) forks its workers"
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait()
    deadline = time.time() + 15
    while any(os.path.exists(f"/proc/{c}") for c in children) and time.time() < deadline:
        time.sleep(0.5)
    alive = [c for c in children if os.path.exists(f"/proc/{c}")]
    for c in alive:
        os.kill(c, signal.SIGKILL)
    assert not alive
