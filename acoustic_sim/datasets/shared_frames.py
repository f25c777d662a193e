"""A full shard's arrays handed to a writer process through shared memory instead of a pipe.

A rendering process hands each full shard to a helper process that compresses and writes it. Sent
as it is, the shard is pickled, pushed through a pipe and unpickled: ~32 MB for a `paper` shard of
250 frames, copied four times. On the two-GPU host that cost ~16 % of all busy CPU time (py-spy over
a 10-worker run, benchmarks/results/multi_gpu/session30). Here the arrays are copied once, into a
file of the memory file system (/dev/shm) that the helper maps; only its name and layout travel.
"""

from __future__ import annotations

import glob
import itertools
import mmap
import os
import secrets
from dataclasses import dataclass, field

import numpy as np

from .shards import ShardFrames

FOLDER = "/dev/shm"  # Linux's memory file system: pages shared by every process that maps the file
ALIGN = 64  # each array starts on a cache line
PREFIX = "sonar2lidar-"  # then the sending process's id: what `sweep` finds after it died
ARRAYS = ("energyscape", "lidar_ranges", "lidar_image", "pose", "time", "episode", "scenario", "signals")
_COUNT = itertools.count()


@dataclass
class SharedFrames:
    """A ShardFrames whose arrays lie in one shared-memory file (`share`), read back as views by
    the writer (`open`); the sender removes the file once the write is over (`release`). Echo
    arrivals, small and ragged, travel pickled beside it."""

    path: str
    layout: dict[str, tuple[int, str, tuple[int, ...]]]  # array -> (offset, dtype, shape)
    arrivals: list[dict] = field(default_factory=list)

    @classmethod
    def share(cls, frames: ShardFrames, folder: str = FOLDER) -> SharedFrames | None:
        """The frames copied into a new shared-memory file, each list of arrays joined into one;
        None where there is no such file system or no room in it (the caller sends them pickled)."""
        lists = {name: [np.asarray(p) for p in parts] for name in ARRAYS if (parts := getattr(frames, name))}
        layout, size = {}, 0
        for name, parts in lists.items():  # each list joined in place in the file: one copy, not two
            dtype = np.result_type(*parts)
            shape = (sum(len(p) for p in parts), *parts[0].shape[1:])
            layout[name] = (size, dtype.str, shape)
            size += -(-int(np.prod(shape)) * dtype.itemsize // ALIGN) * ALIGN
        path = os.path.join(folder, f"{PREFIX}{os.getpid()}-{next(_COUNT)}-{secrets.token_hex(4)}")
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        except OSError:
            return None
        # Written by the system, part after part at its place: a full file system fails a write
        # (ENOSPC), where touching a mapped page it cannot provide kills the process (SIGBUS), and
        # no page is faulted in here (copying into a map of the file faulted in each of a paper
        # shard's ~8,300 pages: 23 against 11 ms a shard on the 2-core CPU).
        try:
            for name, parts in lists.items():
                offset, dtype, _ = layout[name]
                for part in parts:
                    data = memoryview(np.ascontiguousarray(part, dtype)).cast("B")
                    while data:  # a write may take less than all (large writes, signals)
                        written = os.pwrite(fd, data, offset)
                        data, offset = data[written:], offset + written
            os.ftruncate(fd, max(size, 1))  # the last array's padding: the reader maps the whole layout
        except OSError:
            os.unlink(path)
            return None
        finally:
            os.close(fd)
        return cls(path, layout, frames.arrivals)

    def open(self) -> ShardFrames:
        """The frames as views into the file, mapped here; the file's name is removed at once (the
        mapping lives on), so that nothing is left behind if either process dies from now on."""
        with open(self.path, "r+b") as file:
            memory = mmap.mmap(file.fileno(), 0)
        os.unlink(self.path)
        frames = ShardFrames(arrivals=self.arrivals)
        for name, (offset, dtype, shape) in self.layout.items():
            count = int(np.prod(shape))
            getattr(frames, name).append(np.frombuffer(memory, np.dtype(dtype), count, offset).reshape(shape))
        return frames

    def release(self) -> None:
        """Remove the file if the writer never opened it (a write cancelled or failed before)."""
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass


def sweep(pids, folder: str = FOLDER) -> int:
    """Remove the shared files that processes `pids` (rendering workers that have ended) left
    behind: one killed between handing a shard over and its writer opening it leaves that shard's
    file in memory until the machine restarts. Returns how many were removed."""
    removed = 0
    for pid in pids:
        for name in glob.glob(os.path.join(glob.escape(folder), f"{PREFIX}{int(pid)}-*")):
            try:
                os.unlink(name)
                removed += 1
            except FileNotFoundError:
                pass
    return removed
