"""Local worker processes for `generate`: started first, forked where that is safe, fed from one
shared queue of shard tasks.

A spawned worker starts a fresh interpreter and imports the package again (~4 s on the lent GPU
machine, trimesh and Warp most of it) before its first frame; a forked one starts with its
parent's imports and only starts Warp and its device. Forking is safe while the parent has not
started CUDA (a child cannot use a CUDA context its parent made), so the parent of a multi-worker
run leaves CUDA to its workers: they check the device and report it back before any file is
written.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed

from .devices import cpu_cores, cuda_started, quiet_warp, resolve_device, warp_voice

# A worker's work: (its tasks, read lazily; its device; on_frames(n)) -> seconds by part.
Work = Callable[[Iterable, str, Callable[[int], None]], dict]


def start_method() -> str:
    """'fork' on Linux while this process has not started CUDA, else 'spawn' (macOS and Windows
    discourage or lack fork)."""
    return "fork" if sys.platform.startswith("linux") and not cuda_started() else "spawn"


class LocalWorkers:
    """`count` worker processes on `device` ("auto" spreads them over the GPUs), started at once so
    that their start-up runs beside the parent's planning. `devices()` waits until each has Warp
    and its device up, raising a worker's error (a GPU this machine lacks, say); `run(tasks, bar)`
    hands them the tasks and returns the seconds by part summed over them, with each worker's
    "start-up" (launch to device ready). Leaving the `with` block ends the workers, also when the
    run failed before handing them anything."""

    def __init__(self, device: str, count: int, work: Work):
        self.count = count
        self.start_method = start_method()
        context = multiprocessing.get_context(self.start_method)
        self._tasks = context.Queue()  # each worker takes the next task when it is ready for one
        self._ready = context.Queue()  # each worker's device, once up
        self._counts = context.Queue()  # frames as the workers simulate them, for the parent's bar
        indices = context.Queue()
        for i in range(count):
            indices.put(i)
        init = (indices, self._tasks, self._ready, self._counts, os.getpid(), max(1, cpu_cores() // count))
        init += (warp_voice(), time.time())
        self._pool = ProcessPoolExecutor(count, mp_context=context, initializer=_init_worker, initargs=init)
        self._futures = [self._pool.submit(_serve, work, device) for _ in range(count)]
        self._fed = False

    def devices(self) -> list[str]:
        """Each worker's device, once all are up; a worker's failure to start is raised here."""
        found = []
        while len(found) < self.count:
            try:
                found.append(self._ready.get(timeout=0.2))
            except queue.Empty:
                for future in self._futures:
                    if future.done():
                        future.result()  # raises the worker's error (it ends only after reporting, or failing)
        return sorted(found)

    def run(self, tasks: Iterable, bar) -> dict:
        reader = threading.Thread(target=_show_progress, args=(self._counts, bar), daemon=True)
        reader.start()
        for task in tasks:
            self._tasks.put(task)
        self._end_tasks()
        parts = {}
        try:
            for future in as_completed(self._futures):
                for part, seconds in future.result().items():
                    parts[part] = parts.get(part, 0.0) + seconds
        finally:
            self._counts.put(None)
            reader.join(timeout=5)
        return parts

    def _end_tasks(self) -> None:
        if not self._fed:
            self._fed = True
            for _ in range(self.count):
                self._tasks.put(None)

    def __enter__(self) -> LocalWorkers:
        return self

    def __exit__(self, *exc) -> None:
        self._end_tasks()  # workers still waiting for tasks end now
        self._pool.shutdown(wait=True, cancel_futures=True)


_INDEX = 0
_TASKS = _READY = _PROGRESS = None
_LAUNCHED = 0.0  # time.time() when the parent started the workers


def _init_worker(indices, tasks, ready, progress, parent: int, cpu_threads: int, quiet: bool, launched: float):
    global _INDEX, _TASKS, _READY, _PROGRESS, _LAUNCHED
    _INDEX = indices.get()
    _TASKS, _READY, _PROGRESS, _LAUNCHED = tasks, ready, progress, launched
    quiet_warp(quiet, start=False)  # the parent's voice (a spawned worker would start with the default)
    os.environ["SONAR2LIDAR_CPU_THREADS"] = str(cpu_threads)  # the workers share the cores (devices.cpu_cores)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()


def _exit_with_parent(parent: int) -> None:
    """A worker whose parent died (even by SIGKILL) exits too, instead of simulating on for nobody."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _serve(work: Work, device: str) -> dict:
    """One worker's whole share: Warp and its device up (reported to the parent), then tasks from
    the shared queue until its None, so that its own overlap of preparing, rendering and writing
    runs across all its tasks and the workers finish within about one task of each other."""
    import warp as wp

    device = resolve_device(device, _INDEX)  # starts Warp (quietly where asked) and checks the device
    wp.get_device(device)
    started = time.time() - _LAUNCHED
    _READY.put(device)
    return work(iter(_TASKS.get, None), device, _PROGRESS.put) | {"start-up": started}


def _show_progress(counts, bar) -> None:
    """Move the bar by the frame counts the workers send, until None arrives."""
    for n in iter(counts.get, None):
        bar.update(n)
