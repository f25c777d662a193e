"""Local worker processes for `generate`: forked where that is safe, fed from one shared queue of
shard tasks.

A spawned worker starts a fresh interpreter and imports the package again (~4 s on the lent GPU
machine, trimesh and Warp most of it) before its first frame; a forked one starts with its
parent's imports and only starts Warp and its device. Forking is safe only while the parent has
not started CUDA (after a cuInit in the parent, CUDA fails in the child), so the parent of a
multi-worker run leaves Warp and CUDA to its workers: they check the device and report it back
before any file is written. SONAR2LIDAR_WORKER_START=spawn forces spawning (for a process where
some library this package cannot see has started CUDA).
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed

from ..devices import cpu_cores, cuda_started, env_choice, quiet_warp, resolve_device, warp_voice
from .helper_processes import keep_freed_memory
from .shared_frames import sweep

# A worker's work: (its tasks, read lazily; its device; on_frames(n)) -> seconds by part.
Work = Callable[[Iterable, str, Callable[[int], None]], dict]
START_ENV = "SONAR2LIDAR_WORKER_START"
WAIT_ENV = "SONAR2LIDAR_CUDA_WAIT"  # how a worker's CUDA context waits for its GPU: spin (CUDA's default) or block
CU_CTX_SCHED_BLOCKING_SYNC = 0x04
QUEUES_ENV = "CUDA_DEVICE_MAX_CONNECTIONS"  # the work queues a CUDA context makes on its GPU (8 by default)
# The driver makes contexts one process at a time, machine-wide, and each queue costs it time: 12
# workers starting at once over two H100s waited 1.30 s each for their contexts with 8 queues, 0.43 s
# with one, and rendered no slower with one (6 a GPU, or one alone, whose copies go on a second
# stream behind its work: benchmarks/results/multi_gpu/session40). A value the user set is kept.
WORKER_QUEUES = "1"
READY_TIMEOUT_S = 300.0  # a worker not up by then is stuck (a spawned one imports in ~4 s)


def start_method() -> str:
    """SONAR2LIDAR_WORKER_START if set; else 'fork' on Linux while CUDA may not have been started
    in this process, 'spawn' otherwise (macOS and Windows discourage or lack fork)."""
    chosen = os.environ.get(START_ENV, "")
    if chosen:
        if chosen not in ("fork", "spawn"):
            raise ValueError(f"{START_ENV}={chosen!r}: use fork or spawn")
        return chosen
    return "fork" if sys.platform.startswith("linux") and not cuda_started() else "spawn"


class LocalWorkers:
    """`count` worker processes on `device` ("auto" spreads them over the GPUs), started at once.
    `wait_ready()` blocks until each has Warp and its device up, raising a worker's error (a GPU
    this machine lacks, say); `run(tasks, bar)` hands them the tasks and returns the seconds by
    part summed over them, with each worker's "start-up" (launch to device ready). `close()` ends
    them: after their queued tasks, with `abort=True` after the task each is on, or with `now=True`
    too at once, wherever each is (Ctrl-C: a shard being written stays a `.tmp` for the caller to
    remove); call it before releasing what the tasks write under, such as the output lock. After a
    `run` that returned, every task is written: `close(wait=False)` lets the workers exit (a CUDA
    context's teardown, ~0.1 s each) while the caller goes on, and `join()` waits for them. Workers
    ignore Ctrl-C: the parent takes it and stops them."""

    def __init__(self, device: str, count: int, work: Work):
        self.count = count
        self.start_method = start_method()
        context = multiprocessing.get_context(self.start_method)
        self._tasks = context.Queue()  # each worker takes the next task when it is ready for one
        self._ready = context.Queue()  # each worker's device, once up (only workers put: no feeder thread here)
        self._counts = context.Queue()  # frames as the workers simulate them, for the parent's bar
        self._abort = context.Event()  # set: workers take no further task
        claimed = context.Value("i", 0)  # the next worker index (a Value: no queue feeder thread at the fork)
        init = (claimed, self._tasks, self._ready, self._counts, self._abort, os.getpid())
        init += (max(1, cpu_cores() // count), warp_voice(), self.start_method, time.time())
        self._pool = ProcessPoolExecutor(count, mp_context=context, initializer=_init_worker, initargs=init)
        self._closed = self._fed = False
        try:
            self._futures = [self._pool.submit(_serve, work, device) for _ in range(count)]
        except BaseException:
            self._pool.shutdown(wait=True, cancel_futures=True)
            raise
        self._pids = list(getattr(self._pool, "_processes", None) or {})  # forked at once: all are known

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> list[str]:
        """Each worker's device, once all are up; a worker's failure to start is raised here."""
        found, deadline = [], time.monotonic() + timeout_s
        while len(found) < self.count:
            try:
                found.append(self._ready.get(timeout=0.2))
                continue
            except queue.Empty:
                pass
            for future in self._futures:
                if future.done():
                    future.result()  # raises the worker's error (it ends only after reporting, or failing)
            if time.monotonic() > deadline:
                raise RuntimeError(
                    f"{self.count - len(found)} of {self.count} {self.start_method}ed worker processes did not start "
                    f"within {timeout_s:.0f} s; try {START_ENV}=spawn"
                )
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

    def close(self, *, abort: bool = False, now: bool = False, wait: bool = True) -> None:
        if self._closed:
            if wait:
                self.join()
            return
        self._closed = True
        if abort:
            self._abort.set()
            self._tasks.cancel_join_thread()  # tasks left in the pipe must not block this process's exit
        if abort and now:  # not after the shard each is on (minutes on a CPU): a rerun does those again
            running = getattr(self._pool, "_processes", None) or {}  # pid -> Process (CPython's executor)
            for process in list(running.values()):
                process.terminate()
        self._end_tasks()
        self._pool.shutdown(wait=wait, cancel_futures=True)
        if wait:
            sweep(self._pids)

    def join(self) -> None:
        """Wait until the worker processes of a closed pool have exited (and remove any shard a
        killed one left in shared memory)."""
        self._pool.shutdown(wait=True)
        sweep(self._pids)

    def _end_tasks(self) -> None:
        if not self._fed:
            self._fed = True
            for _ in range(self.count):
                self._tasks.put(None)


_INDEX = 0
_TASKS = _READY = _PROGRESS = _ABORT = None
_START = "spawn"
_LAUNCHED = 0.0  # time.time() when the parent started the workers


def _init_worker(claimed, tasks, ready, progress, abort, parent, cpu_threads, quiet, start, launched):
    global _INDEX, _TASKS, _READY, _PROGRESS, _ABORT, _START, _LAUNCHED
    with claimed.get_lock():
        _INDEX = claimed.value
        claimed.value += 1
    _TASKS, _READY, _PROGRESS, _ABORT, _START, _LAUNCHED = tasks, ready, progress, abort, start, launched
    keep_freed_memory()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole process group: the parent stops us
    quiet_warp(quiet, start=False)  # the parent's voice (a spawned worker would start with the default)
    os.environ["SONAR2LIDAR_CPU_THREADS"] = str(cpu_threads)  # the workers share the cores (devices.cpu_cores)
    os.environ.setdefault(QUEUES_ENV, WORKER_QUEUES)  # read by the driver when this process starts CUDA
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()


def _exit_with_parent(parent: int) -> None:
    """A worker whose parent died (even by SIGKILL) exits too, instead of simulating on for nobody."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _serve(work: Work, device: str) -> dict:
    """One worker's whole share: Warp and its device up (reported to the parent), then tasks from
    the shared queue until its None (or an abort), so that its own overlap of preparing,
    rendering and writing runs across all its tasks and the workers finish within about one task
    of each other."""
    import warp as wp

    quiet_warp()  # Warp up (quietly where the parent asked), before the device is checked
    if _START == "fork" and wp.get_cuda_device_count() == 0:
        _refuse_a_poisoned_cuda()  # else "auto" would fall back to the CPU and "cuda" blame the driver
    device = resolve_device(device, _INDEX)
    if device.startswith("cuda"):
        _set_cuda_wait(int(device.partition(":")[2] or 0))
    wp.get_device(device)
    started = time.time() - _LAUNCHED
    _READY.put(device)
    return work(_tasks_until_abort(), device, _PROGRESS.put) | {"start-up": started}


def cuda_wait() -> str:
    """SONAR2LIDAR_CUDA_WAIT: "spin" (CUDA's default for a process of one context: its waiting
    thread spins a core) or "block" (it sleeps until the GPU signals)."""
    return env_choice(WAIT_ENV, ("spin", "block"))


def _set_cuda_wait(ordinal: int) -> None:
    """Make this process's context on GPU `ordinal` wait as `cuda_wait()` says, before Warp
    creates it. Several workers share a GPU's time slices, so their threads wait often, and a
    spinning wait holds a host core (8.5 % of the busy CPU time of 10 workers on two H100s); yet
    sleeping measured no faster there (benchmarks/results/multi_gpu/session30), so CUDA's
    default stays the default."""
    if cuda_wait() == "spin":
        return
    import ctypes

    cuda = ctypes.CDLL("libcuda.so.1")
    flags, active = ctypes.c_uint(), ctypes.c_int()
    code = cuda.cuInit(0) or cuda.cuDevicePrimaryCtxSetFlags(ordinal, CU_CTX_SCHED_BLOCKING_SYNC)
    code = code or cuda.cuDevicePrimaryCtxGetState(ordinal, ctypes.byref(flags), ctypes.byref(active))
    if code or not flags.value & CU_CTX_SCHED_BLOCKING_SYNC:
        refused = f"error {code}, flags {flags.value}"
        raise RuntimeError(f"{WAIT_ENV}=block: the CUDA driver refused ({refused}) on GPU {ordinal}")


def _tasks_until_abort():
    while not _ABORT.is_set():
        task = _TASKS.get()
        if task is None:
            return
        yield task


def _refuse_a_poisoned_cuda() -> None:
    """Warp finds no GPU in this forked worker: say so loudly if that is because CUDA had been
    started in the parent (the driver then answers CUDA_ERROR_NOT_INITIALIZED), rather than run
    on the CPU or blame a missing driver."""
    import ctypes

    try:
        code = ctypes.CDLL("libcuda.so.1").cuInit(0)
    except OSError:
        return  # no driver on this machine: no GPU is the truth
    if code == 3:
        raise RuntimeError(
            "CUDA had been started in this process before generate forked its workers, so they cannot use it; "
            f"set {START_ENV}=spawn, or call generate before using the GPU"
        )


def _show_progress(counts, bar) -> None:
    """Move the bar by the frame counts the workers send, until None arrives."""
    for n in iter(counts.get, None):
        bar.update(n)
