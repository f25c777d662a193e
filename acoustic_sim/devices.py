"""Warp device names from users, checked before any work starts.

Warp's own errors for a missing GPU come from deep inside a launch, after output folders exist and
progress bars are drawn; here the name is checked against what this machine has.
"""

from __future__ import annotations

import re

_NAME = re.compile(r"cpu|cuda(:\d+)?")


def check_device(name: str, *, allow_auto: bool = False) -> str:
    """Return `name` if Warp can run on it here ("cpu", "cuda", "cuda:i"; "auto" when allowed),
    else raise ValueError naming what this machine has."""
    import warp as wp

    if allow_auto and name == "auto":
        return name
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        choices = "auto, cpu, cuda or cuda:i" if allow_auto else "cpu, cuda or cuda:i"
        raise ValueError(f"device {name!r} is not a Warp device: use {choices}")
    if name == "cpu":
        if not wp.is_cpu_available():  # GPU-only builds: their kernel compile would fail on a None library
            raise ValueError(
                "device 'cpu': this Warp build cannot compile CPU kernels (its LLVM/Clang library is missing); "
                "use cuda or cuda:i, or install warp-lang from PyPI"
            )
        return name
    count = wp.get_cuda_device_count()
    if count == 0:
        raise ValueError(f"device {name!r}: Warp finds no CUDA GPU on this machine (driver missing?); use cpu")
    index = int(name.partition(":")[2] or 0)
    if index >= count:
        raise ValueError(f"device {name!r}: this machine has {count} CUDA GPU(s), cuda:0..cuda:{count - 1}")
    return name


_warp_voice_set = False


def quiet_warp(quiet: bool = True) -> None:
    """Warp's start-up banner, per-module compile/load lines and missing-driver notice off
    (warnings and errors stay); the one place the package sets Warp's logging. The first call in
    a process decides, so a command's `--verbose` holds for the library code it runs."""
    global _warp_voice_set
    if _warp_voice_set:
        return
    _warp_voice_set = True
    import warp as wp

    if quiet:
        wp.config.quiet = True
        wp.config.log_level = wp.LOG_WARNING
        _init_without_driver_notice(wp)


NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"
"""Warp's native start-up line on a machine without a GPU: news to nobody who runs on the CPU."""


def _init_without_driver_notice(wp) -> None:
    """Start Warp with its native messages (written to file descriptor 2, out of Python's reach)
    caught, and pass every one on except the missing-driver line."""
    import os
    import sys
    import tempfile

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as caught:
        os.dup2(caught.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        caught.seek(0)
        lines = caught.read().decode(errors="replace").splitlines()
    for line in lines:
        if NO_DRIVER not in line:
            print(line, file=sys.stderr)


def device_calls(device):
    """(wp.zeros, wp.empty, wp.launch, wp.launch_tiled) bound to `device`. Code that may run in
    worker threads names its device on every call: wp.ScopedDevice sets one process-wide
    default, which threads would race on."""
    import functools

    import warp as wp

    return tuple(functools.partial(f, device=device) for f in (wp.zeros, wp.empty, wp.launch, wp.launch_tiled))


def cpu_cores() -> int:
    """CPU cores this process may use (its affinity where the OS tells it, else the machine's);
    SONAR2LIDAR_CPU_THREADS overrides it (`generate` gives each of its workers a share)."""
    import os

    if os.environ.get("SONAR2LIDAR_CPU_THREADS", "").isdigit():
        return max(1, int(os.environ["SONAR2LIDAR_CPU_THREADS"]))
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1
