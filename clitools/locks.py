"""Folder locks: one process at a time writes a folder (a training run, a dataset).

The lock is an advisory `flock` on a file in the folder, held while the process lives: the kernel
releases it when the process ends in any way (exit, Ctrl-C, kill -9), so a lock file left behind
by a killed run is recognised as free by the next one and taken over, without guessing from
process ids (which the system reuses). The file says who holds it ("pid host command since"),
for the refusal's message, and is removed when the holder lets go.

Where `flock` does not exist (Windows) or the file system refuses it, the folder is used
unlocked after a warning that says so.
"""

from __future__ import annotations

import contextlib
import os
import socket
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None


class FolderLocked(OSError):
    """Another live process holds the folder's lock."""


@contextlib.contextmanager
def folder_lock(folder: str | Path, name: str, *, command: str, option: str = "--out") -> Iterator[Path]:
    """Hold `folder`/`name` while the block runs; yields the lock file's path.

    Args:
        folder: The folder (it must exist).
        name: The lock file's name in it, e.g. ".train.lock".
        command: Who takes it, for another process's refusal, e.g. "learn train".
        option: The command-line option that named the folder, for the refusal.

    Raises:
        FolderLocked: a live process holds the lock; its message names it and the folder.
    """
    path = Path(folder) / name
    fd = _take(path, option)
    if fd is None:
        yield path
        return
    since = time.strftime("%Y-%m-%d %H:%M:%S")
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()} {socket.gethostname()} {command} since {since}\n".encode())
    try:
        yield path
    finally:
        with contextlib.suppress(OSError):
            path.unlink()  # while still held, so no one locks the file that is going away
        os.close(fd)


def _take(path: Path, option: str) -> int | None:
    """The open, locked descriptor of `path`; None where locking is unavailable (after a warning)."""
    if fcntl is None:
        warnings.warn(f"this system has no flock: nothing keeps a second run out of {path.parent}", stacklevel=4)
        return None
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            holder = _holder(path)
            raise FolderLocked(
                f"{option} {path.parent} is in use by {holder}; wait for it to end or use another folder "
                f"(the lock {path.name} frees itself when that process ends)"
            ) from None
        except OSError as err:  # a file system without locks (some network mounts)
            os.close(fd)
            warnings.warn(f"cannot lock {path} ({err.strerror}): make sure no other run uses it", stacklevel=4)
            return None
        try:  # the holder before us may have removed the file between our open and our lock
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)


def _holder(path: Path) -> str:
    """Who holds the lock, as its file says ("pid 123 on host: learn train since ...")."""
    try:
        pid, host, what = [*path.read_text(errors="replace").strip().split(" ", 2), "", "", ""][:3]
    except OSError:
        return "another process"
    return f"pid {pid} on {host} ({what})" if pid else "another process"
