"""The parts of Warp outside its public API that the simulator relies on, named one by one, so that
a Warp upgrade fails here with a clear message rather than deep in a kernel or as a silent slowdown
(pyproject.toml pins warp-lang to the tested minor version; this says what to check before moving it).

- `warp._src.context.runtime` (read by `acoustic_sim.devices`): whether Warp has started CUDA, which
  decides whether worker processes may be forked. Where it is gone, workers are always spawned.
- `Device.make_current()` (called by `acoustic_sim.devices.current_in_thread`): makes a GPU's context
  current in the calling thread alone, where `wp.ScopedDevice` and `wp.set_device` also change the
  process's default device. Where it is gone, a worker thread of a process on GPU 1 opens a context
  on GPU 0 again (~0.5 GB and seconds at a multi-GPU run's start).
- `runtime.core.wp_cuda_event_create` with `wp.Event.Flags.BLOCKING_SYNC`, wrapped by `wp.Event(cuda_event=)`
  with `owner` set (`acoustic_sim.devices.sleeping_event`): an event whose wait sleeps, for the thread that
  moves a GPU's images to the host. Where it is gone, that thread's wait would spin a core again.
- C++ of Warp's native tile code called from `wp.func_native` snippets (the recorder's row kernel,
  acoustic_sim/engine/kernels/signals.py): the block barrier, atomic adds into a shared tile and tile
  coordinates. tests/test_record.py compiles and runs them; this test names them.
"""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import warp as wp

from acoustic_sim import devices

ROOT = Path(__file__).resolve().parents[1]
NATIVE_HEADERS = Path(wp.__file__).parent / "native"

NATIVE = {
    "WP_TILE_SYNC": r"#define WP_TILE_SYNC\b",  # the block's barrier, on CUDA and on CPU blocks
    "wp::tile_atomic_add_value": r"\btile_atomic_add_value\(T\* ptr, T value\)",
    "wp::tile_coord": r"\binline auto tile_coord\(int i\)",
    # an array element's address and the atomic add on it (the per-ping counters of kernels/common.py)
    "wp::address": r"\bT\* address\(const A<T>& buf, int i\)",
    "wp::atomic_add": r"\bT atomic_add\(T\* buf, T value\)",
    # a shared tile's storage, read and written at a coordinate: row.data(coord)
    ".data": r"struct Storage \{.*?T& operator\(\)\(typename Layout::Coord c\).*?Storage data;",
}
"""Native name used in a snippet -> the definition it needs in Warp's headers (a regex)."""


def native_snippets() -> list[str]:
    """The C++ source of every `wp.func_native(...)` in the simulator."""
    found = []
    for path in sorted((ROOT / "acoustic_sim").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "func_native":
                found.append(ast.literal_eval(node.args[0]))
    return found


def test_every_native_name_in_our_snippets_is_listed_here():
    """A new native call must be added to NATIVE (so that the check below covers it)."""
    snippets = native_snippets()
    assert len(snippets) >= 2, snippets
    used = {name for snippet in snippets for name in re.findall(r"wp::\w+|\bWP_\w+|\.\w+(?=\()", snippet)}
    assert used == set(NATIVE), f"native names in wp.func_native snippets: {sorted(used)}; listed: {sorted(NATIVE)}"


def test_warp_native_headers_define_what_our_snippets_call():
    headers = "\n".join(path.read_text() for path in sorted(NATIVE_HEADERS.glob("*.h")))
    assert headers, f"Warp {wp.__version__} keeps no native headers in {NATIVE_HEADERS}"
    missing = [name for name, pattern in NATIVE.items() if not re.search(pattern, headers, re.S)]
    assert not missing, (
        f"Warp {wp.__version__} no longer defines {missing} as acoustic_sim/engine/kernels/signals.py "
        "calls them in wp.func_native: rewrite those snippets or keep the pinned warp-lang"
    )


def test_warp_runtime_is_where_devices_reads_it():
    """After wp.init: warp._src.context.runtime exists and lists its CUDA devices (none on a CPU machine)."""
    wp.init()
    try:
        runtime = importlib.import_module("warp._src.context").runtime
    except (ImportError, AttributeError) as err:
        raise AssertionError(
            f"Warp {wp.__version__} moved its runtime ({err}): update acoustic_sim.devices._warp_runtime, "
            "without which worker processes are always spawned"
        ) from err
    assert isinstance(runtime.cuda_devices, list)
    assert devices._warp_runtime() is runtime


def test_a_device_can_be_made_current_in_one_thread():
    """Device.make_current exists and takes no argument (on a CPU machine current_in_thread does
    not call it: there is no context to make current)."""
    import inspect

    device_class = type(wp.get_device("cpu"))
    assert callable(getattr(device_class, "make_current", None)), (
        f"Warp {wp.__version__} has no Device.make_current: update acoustic_sim.devices.current_in_thread"
    )
    assert list(inspect.signature(device_class.make_current).parameters) == ["self"]
    devices.current_in_thread("cpu")  # a no-op on the CPU


def test_a_sleeping_event_is_made_by_warps_runtime():
    """The blocking-sync flag and the runtime's event constructor exist, and a wp.Event wraps a
    handle it is given, destroying it at the end where `owner` is set (as devices.sleeping_event does)."""
    import inspect

    wp.init()
    assert wp.Event.Flags.BLOCKING_SYNC == 1 and wp.Event.Flags.DISABLE_TIMING == 2  # cudaEventBlockingSync, ...
    runtime = devices._warp_runtime()
    assert callable(getattr(runtime.core, "wp_cuda_event_create", None)), (
        f"Warp {wp.__version__} has no runtime.core.wp_cuda_event_create: update acoustic_sim.devices.sleeping_event"
    )
    assert "cuda_event" in inspect.signature(wp.Event.__init__).parameters
    assert "self.owner" in inspect.getsource(wp.Event.__del__)


def test_a_thread_waiting_on_a_sleeping_event_leaves_its_core_idle(device):
    """Behind ~0.1-1 s of GPU work, a wait on devices.sleeping_event lasts until the work is done
    and takes a small share of its time on the CPU (a spinning wait takes all of it)."""
    import time

    import pytest

    if not wp.get_device(device).is_cuda:
        pytest.skip("needs a CUDA device (run with --device cuda:0)")

    @wp.kernel
    def busy(steps: int, out: wp.array(dtype=float)):
        x = wp.float32(0.0)  # a variable the loop may change (a literal stays constant in Warp)
        for _step in range(steps):
            x = x * 0.999999 + 1.0
        out[0] = x

    out = wp.zeros(1, dtype=float, device=device)
    wp.launch(busy, dim=1, inputs=[10, out], device=device)  # compiled and loaded
    wp.synchronize_device(device)
    event = devices.sleeping_event(device)
    wp.launch(busy, dim=1, inputs=[50_000_000, out], device=device)
    wp.get_stream(device).record_event(event)
    wall, cpu = time.perf_counter(), time.thread_time()
    wp.synchronize_event(event)
    wall, cpu = time.perf_counter() - wall, time.thread_time() - cpu
    assert event.is_complete and wall > 0.05, wall
    assert cpu < 0.2 * wall, (cpu, wall)
