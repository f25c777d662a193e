"""`generate` and the simulator's CLI refuse bad output folders and names before they write
anything, with one `error:` line (the trace only with --debug)."""

import ctypes
import dataclasses
import subprocess
import sys

import pytest

from acoustic_sim.cli import main
from acoustic_sim.datasets.generate import generate
from acoustic_sim.datasets.shards import DatasetError
from acoustic_sim.datasets.suites import SUITES, Physics


def cli_error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def test_generate_never_writes_into_a_foreign_folder(tmp_path, capsys):
    """A folder with the user's own files and no plan.json is refused and left as it was; so is a
    file given as --out."""
    (tmp_path / "README.md").write_text("my notes")
    with pytest.raises(DatasetError, match="not a dataset folder"):
        generate(SUITES["tiny"], tmp_path, frames=3, device="cpu", progress=False)
    assert [p.name for p in tmp_path.iterdir()] == ["README.md"] and (tmp_path / "README.md").read_text() == "my notes"
    argv = ["generate", "--suite", "tiny", "--frames", "3", "--out", str(tmp_path / "README.md"), "--device", "cpu"]
    assert "is a file" in cli_error(capsys, argv)


@pytest.mark.parametrize("name", ["../escape", "/abs", "a/b", ".hidden", "..", "x\\y"])
def test_variant_names_cannot_leave_the_output_folder(name):
    with pytest.raises(ValueError, match="variant name"):
        dataclasses.replace(SUITES["tiny"], variants={name: Physics(), "ok": Physics()})


def test_zero_shards_is_refused_not_replaced_by_the_default(tmp_path, capsys):
    argv = ["generate", "--suite", "tiny", "--frames", "3", "--shards", "0", "--out", str(tmp_path / "z")]
    assert "shards must lie in 1..1" in cli_error(capsys, argv)
    assert not (tmp_path / "z").exists()


def test_cli_errors_are_one_line_and_debug_shows_the_trace(tmp_path, capsys):
    """A missing mesh file: one line from `render`; in a subprocess with --debug the trace appears."""
    argv = ["render", "--mesh", str(tmp_path / "missing.obj"), "--out", str(tmp_path / "m.png")]
    assert "missing.obj" in cli_error(capsys, argv)
    done = subprocess.run(
        [sys.executable, "-m", "acoustic_sim", "generate", "--suite", "nope", "--out", str(tmp_path / "n")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2 and "Traceback" not in done.stderr and "unknown suite" in done.stderr
    done = subprocess.run(
        [sys.executable, "-m", "acoustic_sim", "render", *argv[1:], "--debug"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode != 0 and "Traceback" in done.stderr


def test_cpu_refused_by_a_warp_build_without_a_cpu_compiler(monkeypatch, tmp_path):
    """A GPU-only Warp build (as on some lent GPU machines) cannot compile CPU kernels: `--device
    cpu` says so before any work, instead of an AttributeError from inside Warp's compiler."""
    import warp as wp

    monkeypatch.setattr(wp, "is_cpu_available", lambda: False)
    with pytest.raises(ValueError, match="cannot compile CPU kernels"):
        generate(SUITES["tiny"], tmp_path / "out", frames=3, device="cpu", progress=False)
    assert not (tmp_path / "out").exists()


def test_how_workers_wait_for_their_gpu_is_spin_or_block(monkeypatch):
    """SONAR2LIDAR_CUDA_WAIT: CUDA's spinning default unless set; "block" asks the driver for
    sleeping waits (and a driver that keeps its default is refused); anything else is refused
    naming the two."""
    from acoustic_sim.datasets import workers

    monkeypatch.delenv(workers.WAIT_ENV, raising=False)
    assert workers.cuda_wait() == "spin"
    workers._set_cuda_wait(0)  # spin: the driver is not touched (none here)
    monkeypatch.setenv(workers.WAIT_ENV, "sleep")
    with pytest.raises(ValueError, match="use spin or block"):
        workers.cuda_wait()

    asked = []

    class Driver:  # keeps its default flags whatever it is asked
        def __init__(self, name):
            assert name == "libcuda.so.1"

        def cuInit(self, flags):
            return 0

        def cuDevicePrimaryCtxSetFlags(self, ordinal, flags):
            asked.append((ordinal, flags))
            return 0

        def cuDevicePrimaryCtxGetState(self, ordinal, flags, active):
            return 0

    monkeypatch.setenv(workers.WAIT_ENV, "block")
    monkeypatch.setattr(ctypes, "CDLL", Driver)
    with pytest.raises(RuntimeError, match="refused"):
        workers._set_cuda_wait(1)
    assert asked == [(1, workers.CU_CTX_SCHED_BLOCKING_SYNC)]


def test_a_gpus_pool_keeps_freed_memory_unless_told_to_release(monkeypatch):
    """SONAR2LIDAR_CUDA_POOL: by default a GPU's pool keeps what the engine frees (release threshold
    at its maximum), once per GPU and process; "release" leaves CUDA's default; a device without a
    pool is left alone; anything else is refused naming the two."""
    import types

    import warp as wp

    from acoustic_sim import devices

    set_to = []
    monkeypatch.setattr(wp, "set_mempool_release_threshold", lambda device, value: set_to.append((device.alias, value)))
    gpu = types.SimpleNamespace(alias="cuda:1", is_cuda=True, is_mempool_enabled=True)
    monkeypatch.setattr(wp, "get_device", lambda name=None: gpu)
    monkeypatch.setattr(devices, "_pools_set", set())
    monkeypatch.delenv(devices.POOL_ENV, raising=False)
    devices.warp_device("cuda:1")
    devices.warp_device("cuda:1")  # set once
    assert set_to == [("cuda:1", 2**64 - 1)]

    monkeypatch.setenv(devices.POOL_ENV, "release")
    devices._keep_freed_gpu_memory(gpu)
    devices._keep_freed_gpu_memory(types.SimpleNamespace(alias="cuda:2", is_cuda=True, is_mempool_enabled=False))
    monkeypatch.setenv(devices.POOL_ENV, "keep")
    devices._keep_freed_gpu_memory(types.SimpleNamespace(alias="cuda:2", is_cuda=True, is_mempool_enabled=False))
    assert len(set_to) == 1
    monkeypatch.setenv(devices.POOL_ENV, "hold")
    with pytest.raises(ValueError, match="use keep or release"):
        devices.cuda_pool()
