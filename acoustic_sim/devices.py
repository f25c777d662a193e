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
        return name
    count = wp.get_cuda_device_count()
    if count == 0:
        raise ValueError(f"device {name!r}: Warp finds no CUDA GPU on this machine (driver missing?); use cpu")
    index = int(name.partition(":")[2] or 0)
    if index >= count:
        raise ValueError(f"device {name!r}: this machine has {count} CUDA GPU(s), cuda:0..cuda:{count - 1}")
    return name


def quiet_warp(quiet: bool = True) -> None:
    """Warp's start-up banner and per-module compile/load lines off (warnings and errors stay);
    the one place the package sets Warp's logging."""
    import warp as wp

    if quiet:
        wp.config.quiet = True
        wp.config.log_level = wp.LOG_WARNING
