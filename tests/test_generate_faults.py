"""Faults during generation: a failed write leaves no temporary file, a shard damaged after it
was written is found by its checksums and written again (and refused by the learner), two runs
never write one folder, and workers die with their parent."""

import dataclasses
import errno
import multiprocessing
import os
import signal
import subprocess
import sys
import time
import types

import h5py
import numpy as np
import pytest

import acoustic_sim.datasets.folder as folder
import acoustic_sim.datasets.generate as gen
from acoustic_sim.datasets.shards import DatasetError, ShardFrames, verify_shard, write_shard
from acoustic_sim.datasets.suites import SUITES, Physics
from acoustic_sim.datasets.workers import QUEUES_ENV, WORKER_QUEUES, LocalWorkers
from learn.data import DataError, load_frames

from .crafted import damage_energyscape_chunk

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
    damage_energyscape_chunk(shard)
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
    folder.check_plan_file(out, gen.plan(SUITE, out, frames=8, shards=1, seed=2), {"suite": "tiny"})  # as a run does
    lock = out / folder.LOCK_FILE
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
        "from acoustic_sim.datasets.generate import generate\n"
        "from acoustic_sim.datasets.suites import SUITES, Physics\n"
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


_FAKE_OUT = None  # the folder fake_worker_share reports into (set before the fork, inherited)


def fake_worker_share(tasks, device, on_frames, *, renderer, overlap, helpers=0):
    """Worker 0 fails on its first task; worker 1 works on for 2 s, then notes whether the lock is
    still held."""
    from acoustic_sim.datasets import workers

    if workers._INDEX == 0:
        # Fail on the first task: tasks come only once every worker is up, so this process cannot
        # finish early and also take worker 1's call (as it did in a busy full run).
        next(tasks, None)
        raise ValueError("boom in worker 0")
    time.sleep(2)
    (_FAKE_OUT / "lock_held_at_worker_1_end").write_text(str((_FAKE_OUT / folder.LOCK_FILE).exists()))
    return {}


@pytest.fixture
def forked(monkeypatch):
    """Forked workers (they inherit this test's patches); skipped where this process has started CUDA."""
    from acoustic_sim.datasets import workers

    if workers.start_method() != "fork":
        pytest.skip("this process has started CUDA (or is not on Linux): its workers cannot be forked")
    monkeypatch.setenv(workers.START_ENV, "fork")


def test_a_worker_error_stops_the_others_before_the_lock_is_released(tmp_path, monkeypatch, forked):
    """One worker fails mid-run: the error comes through, and the other worker has finished while
    the output lock was still held (no worker writes into a folder nobody holds); none is left."""
    global _FAKE_OUT
    _FAKE_OUT = tmp_path / "out"
    monkeypatch.setattr(gen, "_worker_share", fake_worker_share)
    with pytest.raises(ValueError, match="boom in worker 0"):
        gen.generate(SUITE, _FAKE_OUT, frames=16, shards=2, seed=3, workers=2, device="cpu", progress=False)
    assert (_FAKE_OUT / "lock_held_at_worker_1_end").read_text() == "True"
    assert not (_FAKE_OUT / folder.LOCK_FILE).exists() and not multiprocessing.active_children()


def test_a_refused_folder_leaves_no_worker_running(tmp_path):
    """The workers start before the folder is checked: a refusal still ends them all."""
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not a dataset folder"):
        gen.generate(SUITE, tmp_path, frames=16, shards=2, workers=2, device="cpu", progress=False)
    assert not multiprocessing.active_children() and sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_a_worker_that_dies_starting_is_an_error_not_a_wait(tmp_path, monkeypatch, forked):
    from concurrent.futures.process import BrokenProcessPool

    from acoustic_sim.datasets import workers

    monkeypatch.setattr(workers, "resolve_device", lambda *args: os._exit(3))
    with pytest.raises(BrokenProcessPool):
        gen.generate(SUITE, tmp_path / "out", frames=16, shards=2, workers=2, device="cpu", progress=False)
    assert not (tmp_path / "out").exists() and not multiprocessing.active_children()


def work_queues(tasks, device, on_frames) -> dict:
    """A worker's share that reports the work queues its CUDA context would be made with."""
    return {"queues": float(os.environ[QUEUES_ENV])}


@pytest.mark.parametrize("chosen", [None, "4"])
def test_a_worker_starts_cuda_with_one_work_queue_unless_the_user_chose(monkeypatch, forked, chosen):
    """The driver makes contexts one at a time and each queue costs it time: a worker asks for one,
    and a value the user set reaches the worker unchanged (the parent's own environment untouched)."""
    if chosen is None:
        monkeypatch.delenv(QUEUES_ENV, raising=False)
    else:
        monkeypatch.setenv(QUEUES_ENV, chosen)
    pool = LocalWorkers("cpu", 1, work_queues)
    try:
        pool.wait_ready()
        parts = pool.run([], bar=types.SimpleNamespace(update=lambda n: None))
    finally:
        pool.close()
    assert parts["queues"] == float(chosen or WORKER_QUEUES)
    assert os.environ.get(QUEUES_ENV) == chosen


def test_cuda_started_sees_torch_warp_and_a_loaded_driver(monkeypatch):
    """Workers are forked only where nothing may have started CUDA in this process."""
    from types import SimpleNamespace

    from acoustic_sim import devices
    from acoustic_sim.datasets import workers

    monkeypatch.setattr(devices, "_cuda_driver_loaded", lambda: False)
    monkeypatch.setattr(devices, "_warp_runtime", lambda: None)
    monkeypatch.setitem(sys.modules, "torch", SimpleNamespace(cuda=SimpleNamespace(is_initialized=lambda: False)))
    assert not devices.cuda_started()
    monkeypatch.setattr(devices, "_warp_runtime", lambda: SimpleNamespace(cuda_devices=[]))  # Warp up, no GPU
    assert not devices.cuda_started()
    for runtime in (SimpleNamespace(cuda_devices=["cuda:0"]), devices._UNKNOWN):
        monkeypatch.setattr(devices, "_warp_runtime", lambda r=runtime: r)
        assert devices.cuda_started()
    monkeypatch.setattr(devices, "_warp_runtime", lambda: None)
    monkeypatch.setitem(sys.modules, "torch", SimpleNamespace(cuda=SimpleNamespace(is_initialized=lambda: True)))
    assert devices.cuda_started()
    monkeypatch.delitem(sys.modules, "torch")
    monkeypatch.setattr(devices, "_cuda_driver_loaded", lambda: True)  # e.g. torch.cuda.is_available()
    assert devices.cuda_started() and workers.start_method() == "spawn"
    monkeypatch.setenv(workers.START_ENV, "fork")
    assert workers.start_method() == "fork"
    monkeypatch.setenv(workers.START_ENV, "thread")
    with pytest.raises(ValueError, match="fork or spawn"):
        workers.start_method()
