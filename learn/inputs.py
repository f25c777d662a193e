"""Files the learner reads are untrusted: each is checked before it is opened or allocated for.

A FIFO or a device (`/dev/urandom`) blocks or never ends a read, so only regular files are opened
(checked with `stat`, which follows links). A header (an HDF5 dataset's shape, a `.npy` header, a
model's config) may claim more than the machine holds: the claim is compared with the memory
available before anything is allocated. JSON that does not parse names its file, line and column.
Every refusal is a ValueError or OSError naming the file (the CLI prints it as one `error:` line).
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import numpy as np


class TooLarge(ValueError):
    """An input that would need more memory than this machine has available."""


def file_kind(mode: int) -> str:
    """What a `stat` mode describes, in words ("a FIFO", "a folder", ...)."""
    kinds = (
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    )
    return next((name for test, name in kinds if test(mode)), "not a regular file")


def regular_file(path: str | Path, what: str) -> Path:
    """`path` when it is a regular file (after links); else FileNotFoundError or ValueError naming
    `what` ("checkpoint", "--input", ...) and what the path is instead."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} {path} does not exist") from None
    except OSError as err:
        raise OSError(f"{what} {path} cannot be read ({err.strerror})") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{what} {path} is {file_kind(mode)}, not a regular file: give the file itself")
    return path


def available_memory_bytes() -> int | None:
    """Memory this process can still allocate [bytes]: /proc/meminfo's MemAvailable, less where a
    cgroup (container) limit leaves less; None where neither can be read (no check is made then)."""
    found = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        try:
            found.append(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (OSError, ValueError, AttributeError):
            pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            found.append(int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text()))
    except (OSError, ValueError):
        pass
    return max(0, min(found)) if found else None


def size_text(nbytes: float) -> str:
    """Bytes in words: "1.3 GB", "512 MB", "24 kB"."""
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if nbytes >= scale:
            return f"{nbytes / scale:,.3g} {unit}"
    return f"{int(nbytes)} B"


def check_fits(nbytes: float, what: str, advice: str) -> None:
    """Refuse (TooLarge) when `what` needs more than the memory available, before it is allocated.

    Args:
        nbytes: Memory the input needs once read [bytes].
        what: The input and its size in words ("data/x: 1,000,000 frames of 240 x 181").
        advice: What to do instead.
    """
    available = available_memory_bytes()
    if available is not None and nbytes > available:
        raise TooLarge(
            f"{what} would need {size_text(nbytes)} of memory, more than the {size_text(available)} available "
            f"here: {advice}"
        )


def read_json(path: str | Path, what: str, advice: str) -> dict:
    """A JSON object from `path` (a regular file); any failure names the file (and the line and
    column of a syntax error) and says `advice`."""
    path = regular_file(path, what)
    check_fits(20 * path.stat().st_size, f"{what} {path} ({size_text(path.stat().st_size)} of JSON)", advice)
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise ValueError(
            f"{what} {path} is not valid JSON (line {err.lineno}, column {err.colno}: {err.msg}): {advice}"
        ) from None
    except UnicodeDecodeError:
        raise ValueError(f"{what} {path} is not UTF-8 text: {advice}") from None
    if not isinstance(record, dict):
        raise ValueError(f"{what} {path} holds a JSON {type(record).__name__}, not an object: {advice}")
    return record


def npy_header(path: str | Path, what: str) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) of a `.npy` file from its header, checked against the bytes the file holds
    (a header may claim any shape), without reading the array."""
    path = regular_file(path, what)
    with open(path, "rb") as stream:
        try:
            version = np.lib.format.read_magic(stream)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(stream)
        except (ValueError, OSError, SyntaxError) as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ValueError(f"{what} {path} is not a .npy file ({first}): save the array with numpy.save") from None
        offset = stream.tell()
    if dtype.hasobject:
        raise ValueError(
            f"{what} {path} holds Python objects (dtype {dtype}), which only pickle could load (refused): save a "
            "numeric array"
        )
    claimed = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
    held = path.stat().st_size - offset
    if held < claimed:
        raise ValueError(
            f"{what} {path} is truncated: its header says shape {shape} of {dtype} ({size_text(claimed)}), the file "
            f"holds {size_text(held)}: save it again"
        )
    return tuple(shape), dtype
