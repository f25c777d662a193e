"""The helper processes a rendering process forks for its host work (`runner.run_tasks`): each
holds the run's renderer from the fork, lives only as long as its rendering process, and keeps
freed memory for the next shard."""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
from concurrent.futures import ProcessPoolExecutor
from typing import Any

PR_SET_PDEATHSIG = 1  # Linux prctl: the signal a process gets when its parent dies
# glibc's malloc: how much freed memory a process keeps (M_TRIM_THRESHOLD: -1) and from what size a
# block is mapped apart, to go back to the system when freed (M_MMAP_THRESHOLD: -3, at most 32 MB).
# By default a shard's chunks and copies went back between shards and were page-faulted in again.
MALLOC_KEEP = {-1: 64 << 20, -3: 32 << 20}
# A helper's niceness above its rendering process's (0: the same): whether a rendering thread back
# from its GPU should get a core before a write with slack is for benchmarks/generate_load.py to measure.
HELPER_NICENESS_ENV = "SONAR2LIDAR_HELPER_NICENESS"


# A helper process's renderer, inherited from the rendering process at the fork: what it is sent
# with each call is None (a renderer may hold a user's meshes: pickled once per episode otherwise).
_RENDERER: Any = None


def helper_renderer(sent):
    """The renderer a call runs with: the one `sent`, or in a helper (sent None) the fork's."""
    return _RENDERER if sent is None else sent


class Helpers(ProcessPoolExecutor):
    """Forked helper processes that hold the renderer from the fork: calls leave it out."""

    def submit(self, fn, renderer, *args):
        return super().submit(fn, None, *args)


def helper_pool(count: int, renderer) -> Helpers:
    """`count` helper processes holding `renderer`, forked now (all at once: fork starts them on the first call)."""
    global _RENDERER
    _RENDERER = renderer
    fork = multiprocessing.get_context("fork")
    niceness = helper_niceness()  # checked here: a helper's error would only break the pool
    pool = Helpers(count, mp_context=fork, initializer=_init_helper, initargs=(os.getpid(), niceness))
    for started in [pool.submit(_started, None) for _ in range(count)]:
        started.result()
    return pool


def _started(_renderer) -> int:
    return os.getpid()


def keep_freed_memory() -> None:
    """Let this process's malloc keep up to 64 MB of freed memory instead of returning it at once,
    and serve blocks up to a shard's size from it (glibc only; a no-op elsewhere). Called in the
    processes generate starts, never in a caller's. Writing a shard in two threads page-faulted 8.6
    times a frame without it, 0.1 with it, on the 2-core CPU (tests/test_chunks.py)."""
    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)  # this process's C library, as for prctl below
    if mallopt is None:
        return
    for option, value in MALLOC_KEEP.items():
        mallopt(option, value)


def _init_helper(parent: int, niceness: int) -> None:
    """A helper ignores Ctrl-C (its rendering process is stopped by the parent) and dies at once
    with its rendering process (even one killed by SIGKILL), so that no helper goes on writing a
    shard that the parent, having stopped the run, is about to remove."""
    keep_freed_memory()
    os.nice(niceness)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # it died before the line above
        os._exit(1)


def helper_niceness() -> int:
    """SONAR2LIDAR_HELPER_NICENESS: how much less a helper's scheduling priority is than its
    rendering process's, 0 (the default) to 19."""
    chosen = os.environ.get(HELPER_NICENESS_ENV, "0")
    if not chosen.isdigit() or int(chosen) > 19:
        raise ValueError(f"{HELPER_NICENESS_ENV}={chosen!r}: use a whole number from 0 to 19")
    return int(chosen)
