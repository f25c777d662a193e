"""What this machine can hold, and input files checked before they are opened.

A FIFO, a device (`/dev/urandom`, also behind a symlink) or a file far larger than its kind ever
is would hang a reader or fill the memory; `input_file` refuses them by `stat`, before anything
opens them. A size a user asks for (frames, rays, samples, pings) is compared with the memory
(`available_memory_bytes`) or the disk (`free_disk_bytes`) it would take, before it is allocated:
`check_fits` refuses it with both figures.
"""

from __future__ import annotations

import os
import stat
import time
from pathlib import Path


class SizeError(ValueError):
    """A size beyond what this machine (or a kind of input file) can hold; the message gives the
    estimate and the limit."""


def format_bytes(count: float) -> str:
    """1536 -> '1.5 KB', 3.2e12 -> '3.2 TB' (powers of 1,000)."""
    for unit in ("bytes", "KB", "MB", "GB", "TB", "PB"):
        if abs(count) < 1000 or unit == "PB":
            return f"{count:,.0f} {unit}" if unit == "bytes" else f"{count:,.1f} {unit}"
        count /= 1000
    raise AssertionError("unreachable")


_MEMORY_READ: list[float] = [-1.0, 0.0]  # (time.monotonic() of the last reading, its bytes)


def available_memory_bytes() -> int:
    """Memory this process can still take [bytes]: Linux's MemAvailable, lowered to what a cgroup
    (a container's memory.max) leaves; the free pages elsewhere. Read at most once a second
    (configs check their sizes against it every time one is made)."""
    now = time.monotonic()
    if now - _MEMORY_READ[0] > 1.0:
        _MEMORY_READ[:] = now, _read_available_memory()
    return int(_MEMORY_READ[1])


def _read_available_memory() -> int:
    found = None
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    found = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    if found is None:
        try:
            found = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return 2**63 - 1  # unknown: refuse nothing on this ground
    cgroup = Path("/sys/fs/cgroup")
    try:
        limit = (cgroup / "memory.max").read_text().strip()
        if limit != "max":
            found = min(found, int(limit) - int((cgroup / "memory.current").read_text()))
    except (OSError, ValueError):
        pass
    return max(found, 0)


def free_disk_bytes(path: str | os.PathLike) -> int:
    """Free space [bytes] on the disk that holds `path` (or would: its nearest existing folder)."""
    here = Path(path).absolute()
    while not here.exists() and here != here.parent:
        here = here.parent
    try:
        import shutil

        return shutil.disk_usage(here).free
    except OSError:
        return 2**63 - 1  # unknown: refuse nothing on this ground


def check_fits(needed: float, *, available: float, what: str, room: str, advice: str) -> None:
    """Refuse `needed` bytes where only `available` are, with both figures: SizeError "WHAT needs
    N, more than the M ROOM; ADVICE".

    Args:
        needed: The estimate [bytes].
        available: What there is [bytes].
        what: What asks for it, with the size that decides it (e.g. "--frames 1,000,000,000").
        room: Where `available` is, as the message says it ("of memory free on this machine").
        advice: What to do instead.
    """
    if needed > available:
        raise SizeError(
            f"{what} needs {format_bytes(needed)}, more than the {format_bytes(available)} {room}; {advice}"
        )


def check_memory(needed: float, *, what: str, advice: str) -> None:
    """`check_fits` against the memory free now."""
    check_fits(
        needed, available=available_memory_bytes(), what=what, room="of memory free on this machine", advice=advice
    )


_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def file_kind(mode: int) -> str:
    """What a `stat` mode describes, in words ("a FIFO (named pipe)", "a folder", ...)."""
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def regular_file(path: str | os.PathLike, what: str) -> Path:
    """`path`, checked by `stat` before anything opens it: it exists and is a regular file (through
    any symlinks). FileNotFoundError, or ValueError naming `what` and what the path is instead."""
    path = Path(path)
    try:
        info = path.stat()  # follows symlinks: a link to /dev/urandom is a character device
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} {path} does not exist") from None
    except OSError as err:
        raise OSError(f"{what} {path} cannot be read ({err.strerror})") from None
    if not stat.S_ISREG(info.st_mode):
        target = f" (the symlink leads to {os.path.realpath(path)})" if path.is_symlink() else ""
        raise ValueError(
            f"{what} {path} is {file_kind(info.st_mode)}{target}, not a regular file: reading it could hang or "
            "never end; give a file on disk"
        )
    return path


def input_file(path: str | os.PathLike, *, what: str, max_bytes: float, bound: str = "") -> Path:
    """`path`, checked by `stat` before anything opens it: it exists, is a regular file (through
    any symlinks) and holds at most `max_bytes`.

    Args:
        path: The file as the user gave it.
        what: Its kind, as the messages name it ("SVG floor plan", "suite file").
        max_bytes: The most a file of this kind may hold [bytes].
        bound: Why that is the most (e.g. "what this machine's memory can parse"), for the message.

    Raises:
        FileNotFoundError: it does not exist.
        ValueError: it is a FIFO, device, socket or folder (SizeError: it is larger than `max_bytes`).
    """
    path = regular_file(path, what)
    info = path.stat()
    if info.st_size > max_bytes:
        why = f" ({bound})" if bound else ""
        raise SizeError(
            f"{what} {path} holds {format_bytes(info.st_size)}, over the limit of {format_bytes(max_bytes)} for "
            f"its kind{why}; is it the file you meant?"
        )
    return path
