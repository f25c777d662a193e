"""Warp device names from users, checked before any work starts.

Warp's own errors for a missing GPU come from deep inside a launch, after output folders exist and
progress bars are drawn; here the name is checked against what this machine has.
"""

from __future__ import annotations

import re

_NAME = re.compile(r"cpu|cuda(:\d+)?")


def check_device_name(name: str, *, allow_auto: bool = False) -> str:
    """Return `name` if it is a Warp device name ("cpu", "cuda", "cuda:i"; "auto" when allowed),
    else raise ValueError. Starts nothing: a parent that forks workers checks names with it."""
    if allow_auto and name == "auto":
        return name
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        choices = "auto, cpu, cuda or cuda:i" if allow_auto else "cpu, cuda or cuda:i"
        raise ValueError(f"device {name!r} is not a Warp device: use {choices}")
    return name


def check_device(name: str, *, allow_auto: bool = False) -> str:
    """Return `name` if Warp can run on it here ("cpu", "cuda", "cuda:i"; "auto" when allowed),
    else raise ValueError naming what this machine has."""
    import warp as wp

    if check_device_name(name, allow_auto=allow_auto) == "auto":
        return name
    quiet_warp()
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


_voice: bool | None = None  # quiet or not: the first quiet_warp call's choice

VERBOSE_ENV = "SONAR2LIDAR_WARP_VERBOSE"
"""Set to 1 to see Warp's own messages (start-up banner, module compiles and loads, a missing CUDA
driver) from library code and every command; the package keeps them off otherwise."""


def warp_messages_wanted() -> bool:
    """Whether the environment asks for Warp's messages (SONAR2LIDAR_WARP_VERBOSE=1)."""
    import os

    return os.environ.get(VERBOSE_ENV, "").strip().lower() not in ("", "0", "false", "no")


def quiet_warp(quiet: bool = True, *, start: bool = True) -> None:
    """Warp's start-up banner, per-module compile/load lines and missing-driver notice off
    (warnings and errors stay), unless SONAR2LIDAR_WARP_VERBOSE=1; the one place the package sets
    Warp's logging. The first call in a process decides, so a command's `--verbose` holds for the
    library code it runs; library code calls it (through `warp_device`) before it first touches
    Warp, so the package is quiet by default. `start` starts Warp now (with the driver notice
    caught); `start=False` only sets the voice, for a parent that will fork worker processes and
    so must not start CUDA itself."""
    global _voice
    import warp as wp

    if _voice is None:
        _voice = quiet and not warp_messages_wanted()
        if _voice:
            wp.config.quiet = True
            wp.config.log_level = wp.LOG_WARNING
    runtime = _warp_runtime()
    if start and _voice and (runtime is None or runtime is _UNKNOWN):  # wp.init is idempotent; the catch is not free
        _init_without_driver_notice(wp)


def warp_device(device=None):
    """`wp.get_device(device)` (None: Warp's default device), with Warp started the package's way
    first (quiet_warp): how library code reaches Warp, so that a script that only builds a Sonar
    prints nothing of Warp's."""
    import warp as wp

    quiet_warp()
    found = wp.get_device(device)
    if found.is_cuda and found.alias not in _pools_set:
        _pools_set.add(found.alias)
        _keep_freed_gpu_memory(found)
    return found


def current_in_thread(device) -> None:
    """Make `device`'s CUDA context this thread's current one (a no-op for the CPU): the
    initializer of a thread that works for a GPU. A thread with no context of its own makes CUDA's
    runtime start device 0's on its first call: each `generate` worker of cuda:1 held a second
    context on cuda:0 (518 MiB), and its first episode took ~1.5 s longer, the GPU idle meanwhile
    (two H100s, benchmarks/results/multi_gpu/session37)."""
    device = warp_device(device)
    if device.is_cuda:
        device.make_current()


def sleeping_event(device):
    """A `wp.Event` on a GPU whose wait puts the waiting thread to sleep until the GPU reaches it
    (CUDA's blocking sync), where a wait on Warp's own events spins a core (CUDA's default in a
    process of one context): for threads whose wait is off the critical path. A `generate` worker's
    thread moving images to the host spun ~30 ms an episode (py-spy of `randomised` on an H100,
    multi_gpu/session37), while 12 workers kept ~80 % of two H100s' 32 cores busy (session38). Warp's
    constructor takes no flags: the event is made by its runtime (tests/test_warp_private.py)."""
    import warp as wp

    device = warp_device(device)
    flags = wp.Event.Flags.BLOCKING_SYNC | wp.Event.Flags.DISABLE_TIMING
    handle = _warp_runtime().core.wp_cuda_event_create(device.context, flags)
    if not handle:
        raise RuntimeError(f"CUDA could not create an event on {device}")
    event = wp.Event(device, cuda_event=handle)
    event.owner = True  # destroyed with the Event, as Warp's own are
    return event


POOL_ENV = "SONAR2LIDAR_CUDA_POOL"
"""keep (the default) or release: what a GPU's memory pool does with memory freed in this process."""
_pools_set: set[str] = set()  # the GPUs whose pool this process has set up


def env_choice(name: str, choices: tuple[str, ...]) -> str:
    """The environment variable `name`: one of `choices`, the first where it is unset; anything else is
    refused naming them."""
    import os

    chosen = os.environ.get(name, choices[0])
    if chosen not in choices:
        raise ValueError(f"{name}={chosen!r}: use {' or '.join(choices)}")
    return chosen


def cuda_pool() -> str:
    """SONAR2LIDAR_CUDA_POOL: "keep" (the pool holds what it has reserved, as torch's caching
    allocator does) or "release" (CUDA's default: freed memory goes back to the driver at every
    synchronize)."""
    return env_choice(POOL_ENV, ("keep", "release"))


def _keep_freed_gpu_memory(device) -> None:
    """Keep the memory Warp's arrays free on `device` in its pool (unless SONAR2LIDAR_CUDA_POOL=release).
    Every batch of pings allocates and frees its buffers, and each ping's results are copied back with a
    synchronize; with CUDA's default release threshold of 0 every synchronize hands the freed memory back
    to the driver and the next batch maps it again, driver calls that the processes sharing a host wait
    on each other for. A process keeps at most its own high-water mark."""
    import warp as wp

    if cuda_pool() == "keep" and device.is_mempool_enabled:
        wp.set_mempool_release_threshold(device, 2**64 - 1)


def warp_voice() -> bool:
    """Whether Warp is kept quiet in this process (the package's default until quiet_warp is called)."""
    return True if _voice is None else _voice


def cuda_started() -> bool:
    """Whether CUDA may have been started in this process: Warp or torch started it, or any
    library loaded the CUDA driver (a plain cuInit is enough). A process forked from one that has
    cannot use CUDA, so worker processes are spawned then. Unknown Warp internals count as
    started: spawning is always safe, only slower."""
    import sys

    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_initialized():
        return True
    if _cuda_driver_loaded():  # torch.cuda.is_available(), cupy, numba... (importing warp does not load it)
        return True
    if "warp" not in sys.modules:
        return False
    runtime = _warp_runtime()
    if runtime is _UNKNOWN:
        return True
    return runtime is not None and bool(getattr(runtime, "cuda_devices", True))


def _cuda_driver_loaded() -> bool:
    """Whether the CUDA driver library is mapped into this process (Linux; False where unknown)."""
    try:
        with open("/proc/self/maps") as maps:
            return any("libcuda.so" in line for line in maps)
    except OSError:
        return False


_UNKNOWN = "unknown"


def _warp_runtime():
    """Warp's runtime object once Warp has started in this process, None before; _UNKNOWN where a
    later Warp keeps it elsewhere than warp._src.context (1.19)."""
    import importlib

    try:
        return importlib.import_module("warp._src.context").runtime
    except (ImportError, AttributeError):
        return _UNKNOWN


def resolve_device(name: str, index: int = 0) -> str:
    """The Warp device worker `index` of a run uses: `name` checked (check_device), or for
    "auto" the GPUs in turn, the CPU where there is none."""
    import warp as wp

    if check_device_name(name, allow_auto=True) != "auto":
        return check_device(name)
    quiet_warp()
    gpus = wp.get_cuda_device_count()
    return f"cuda:{index % gpus}" if gpus else "cpu"


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
