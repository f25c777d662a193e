"""Issue 42's first question: what would make the recording's echo accumulation cheaper on a GPU?

    python benchmarks/bench_record_kernels.py --device cuda:0 --rays 20000,100000

`accumulate_rows` (one block per ping and microphone, each echo's 4 fractional-delay taps added
with 64-bit integer atomics in 128 KB of shared memory) is 68 % of the recording at 20k rays and
90 % at 100k (`results/sonar_profile_cuda.md`). This times it beside variants that keep its
layout and change one thing each, on the echoes of one batch of 256 office pings (3 bounces):

- `int64` the kernel before issue 42 (its sums, 2^32 units, 128 KB rows);
- `package` what `acoustic_sim` runs now (`Recorder.impulses`' GPU path: the units of each
  1,024-sample stretch, then 32-bit sums in the finest unit each stretch allows, the tracer's three
  echo buffers in one launch, as `Sonar.simulate` hands them over, compiled for two blocks of 1,024
  threads per SM: CUDA launch bounds, at most 32 registers a thread); `package_one_block` the same
  kernel without launch bounds (55 registers: one block per SM), `package_512` for three blocks of 512;
- `int32` 32-bit fixed point scaled per ping (2^30 over the ping's summed |amplitude| x gain x
  largest tap, so no sum can overflow): half the shared memory, so two blocks of 1,024 threads
  fit an SM where one fits now; integer sums, so still the same bits in any order;
- `int32_half` the same with rows of 8,192 samples (two blocks per row, 32 KB each);
- `float32` float atomics (order-dependent bits: a reference for what integers cost, not a
  candidate for datasets that must be reproducible).

Each variant's sums are checked against the int64 kernel's (largest difference over the ping's
peak), so a fast variant that is wrong says so. Medians of --repeats launches after one warm-up.
Writes record_kernels_<device>.json and .md under --out. (No `from __future__ import annotations`
here: Warp reads the kernels' tile annotations, which name closure variables, as live objects.)
"""

import argparse
import functools
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import acoustic_sim as sim  # noqa: E402
from acoustic_sim.engine import signals  # noqa: E402
from acoustic_sim.engine.kernels import signals as kernels  # noqa: E402
from acoustic_sim.engine.kernels.signals import block_sync  # noqa: E402
from benchmarks.bench_lidar import load_office, random_poses  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402

VARIANTS = ("int64", "package", "package_one_block", "package_512", "int32", "int32_half", "float32")
# The package's row kernel as compiled for each package variant: (CUDA launch bounds, threads a block).
PACKAGE_LAUNCHES = {
    "package": (signals.ROW_LAUNCH_BOUNDS, signals.ROW_BLOCK_DIM),
    "package_one_block": (None, 1024),
    "package_512": ((512, 3), 512),
}
FIXED = kernels.FIXED_POINT_SCALE  # echo_taps' scale: 2^32 units per unit amplitude
TO_PING_UNITS = wp.constant(1.0 / FIXED)


@functools.cache
def scaled_rows(chunk: int, dtype):
    """`kernels.row_accumulation` with `dtype` sums in shared memory and a per-ping scale (the
    fixed-point units of one unit amplitude for that ping)."""

    @wp.func_native("wp::tile_atomic_add_value(&row.data(wp::tile_coord(i)), value);")
    def shared_add(row: wp.tile(dtype=dtype, shape=(chunk,)), i: int, value: dtype): ...

    @wp.kernel(enable_backward=False, module="unique")
    def accumulate_scaled(
        source: wp.array2d[wp.vec3],
        extra_length: wp.array2d[float],
        amplitude: wp.array2d[float],
        count: wp.array[wp.int32],
        microphones: wp.array[wp.vec3],
        mic_gain: wp.array[float],
        mic_delay: wp.array[float],
        samples_per_m: float,
        absorption_per_m: float,
        taps: wp.array2d[float],
        samples: int,
        ping_scale: wp.array[float],
        sums_out: wp.array2d[dtype],
    ):
        p, m, c, lane = wp.tid()
        threads = wp.block_dim()
        row = wp.tile_zeros(shape=chunk, dtype=dtype, storage="shared")
        start = c * chunk
        mic = microphones[m]
        units = ping_scale[p] * TO_PING_UNITS  # echo_taps scales by 2^32
        for s in range(lane, wp.min(count[p], amplitude.shape[1]), threads):
            a = amplitude[p, s]
            if a != 0.0:
                length = extra_length[p, s] + wp.length(source[p, s] - mic)
                lowest, i, v, scale = kernels.echo_taps(
                    length, a, mic_gain[m], mic_delay[m], samples_per_m, absorption_per_m, taps
                )
                for j in range(taps.shape[1]):
                    n = lowest + j
                    if n >= start and n < start + chunk:
                        value = kernels.tap_weight(taps, i, v, j) * scale * units
                        shared_add(row, n - start, dtype(value))
        block_sync()
        out = p * microphones.shape[0] + m
        for k in range(lane, wp.min(chunk, samples - start), threads):
            sums_out[out, start + k] = row[k]

    return accumulate_scaled


def echoes_of(rays: int, device, pings: int, seed: int):
    """One batch of office pings traced at `rays` rays and 3 bounces: the sonar, the echoes as one
    EchoBuffer, their count, the tracer's own buffers of the batch, and which pings they hold
    whole (the rest are traced again by `simulate`)."""
    sonar = sim.Sonar(sim.SonarConfig.ertis(), max_bounces=3, ray_count=rays, device=device)
    poses = random_poses(pings, seed)
    arrivals = sonar.trace(load_office(), poses, batch=pings)
    _, keep, traced = next(iter(sonar.tracer.traced(load_office(), poses, pings)))
    return sonar, signals.echo_buffer(arrivals, pings, device), len(arrivals), traced.buffers(), keep


def registers(kernel, device, block_dim: int) -> dict:
    """Registers and local (spilled) bytes per thread of a loaded CUDA kernel, from the driver."""
    import ctypes

    try:
        execs = [e for (_, dim), e in kernel.module.execs.items() if dim == block_dim]
        function = execs[0].get_kernel_hooks(kernel).forward
        cuda = ctypes.CDLL("libcuda.so.1")
        out = {}
        for name, attribute in (("registers", 4), ("local_bytes", 3)):  # CU_FUNC_ATTRIBUTE_NUM_REGS, _LOCAL_SIZE_BYTES
            value = ctypes.c_int()
            cuda.cuFuncGetAttribute(ctypes.byref(value), attribute, ctypes.c_void_p(int(function)))
            out[name] = value.value
        return out
    except (OSError, IndexError, AttributeError, TypeError) as error:  # a benchmark's side note, not its result
        return {"error": repr(error)}


def ping_scales(echoes, recorder, bits: int) -> np.ndarray:
    """Fixed-point units per unit amplitude, per ping, such that no sum of taps can reach 2^bits."""
    amp = np.abs(echoes.amplitude.numpy()).sum(axis=1)
    bound = amp * float(np.abs(recorder._mic_gain.numpy()).max()) * float(np.abs(recorder._taps.numpy()).max())
    return (2.0**bits / np.maximum(bound, 1e-30)).astype(np.float32)


def run_variant(name, echoes, traced, recorder, pings, device, repeats):
    """(median seconds, row chunk, the sums as amplitudes (pings, mics, samples), the row kernel's
    registers) of one variant."""
    cfg = recorder.config
    mics, samples = cfg.microphone_count, cfg.record_samples
    shared = device.max_shared_memory_per_block if device.is_cuda else 64 * 1024
    if name in PACKAGE_LAUNCHES:  # Recorder.impulses' GPU path, on the tracer's buffers
        bounds, block_dim = PACKAGE_LAUNCHES[name]
        chunk = signals.row_chunk(samples, shared)
        kernel = kernels.row_accumulation(chunk, recorder._stretches, bounds)
        rows = recorder.echo_rows(traced, pings)
        impulses = wp.zeros((pings * 2 * ((mics + 1) // 2), recorder.nodes * recorder.block + recorder._size), wp.int64)
        inputs = [*rows, *recorder._tap_inputs()]
        times = []
        for _ in range(repeats + 1):
            impulses.zero_()
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            exponents = recorder.sum_exponents(rows, pings)
            wp.launch_tiled(
                kernel,
                dim=[pings, mics, -(-samples // chunk)],
                inputs=[*inputs, exponents],
                outputs=[impulses],
                block_dim=block_dim,
                device=device,
            )
            wp.synchronize_device(device)
            times.append(time.perf_counter() - t0)
        sums = impulses.numpy().astype(np.float64).reshape(pings, 2 * ((mics + 1) // 2), -1)
        sums = sums[:, :mics, recorder.block : recorder.block + samples] / FIXED
        return float(np.median(times[1:])), chunk, sums, registers(kernel, device, block_dim)
    common = [echoes.source, echoes.extra_length, echoes.amplitude, echoes.count, recorder._mics, recorder._mic_gain]
    common += [recorder._mic_delay, cfg.chirp.sample_rate_hz / cfg.atmosphere.speed_of_sound]
    common += [recorder._absorption_per_m, recorder._taps, samples]
    dtype = {"float32": wp.float32, "int64": wp.int64}.get(name, wp.int32)
    if name == "int64":  # the kernel before issue 42: 2^32 units, 128 KB rows
        chunk, units = signals.row_chunk(samples, shared, sample_bytes=8), np.full(pings, FIXED, np.float32)
    else:
        chunk = 8192 if name == "int32_half" else signals.row_chunk(samples, shared)
        units = ping_scales(echoes, recorder, 30) if dtype is wp.int32 else np.ones(pings, np.float32)
    out = wp.zeros((pings * mics, samples), dtype=dtype, device=device)
    kernel, inputs = scaled_rows(chunk, dtype), [*common, wp.array(units, dtype=float, device=device)]
    dim = [pings, mics, -(-samples // chunk)]
    times = []
    for _ in range(repeats + 1):
        out.zero_()
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        wp.launch_tiled(kernel, dim=dim, inputs=inputs, outputs=[out], block_dim=signals.ROW_BLOCK_DIM, device=device)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    sums = out.numpy().astype(np.float64).reshape(pings, mics, samples) / units[:, None, None]
    return float(np.median(times[1:])), chunk, sums, registers(kernel, device, signals.ROW_BLOCK_DIM)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--rays", default="20000,100000")
    parser.add_argument("--pings", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    if not device.is_cuda:
        print("note: the shared-memory kernels are the GPU's; on the CPU this checks their sums only")
        wp.config.enable_cpu_blocks = True  # their blocks' threads as cooperative fibers
    variants = args.variants.split(",")
    res = {"device": str(device), "device_name": device.name if device.is_cuda else "CPU", "warp": wp.__version__}
    res |= {"date": time.strftime("%Y-%m-%d"), "pings": args.pings, "repeats": args.repeats, "runs": {}}
    for rays in map(int, args.rays.split(",")):
        sonar, echoes, arrivals, traced, whole = echoes_of(rays, device, args.pings, seed=3)
        recorder = signals.recorder(sonar.config, True, str(device))
        reference, rows = None, {}
        for name in variants:
            seconds, chunk, amplitude, regs = run_variant(
                name, echoes, traced, recorder, args.pings, device, args.repeats
            )
            if reference is None:
                reference = amplitude
            peak = np.abs(reference).max(axis=(1, 2))[:, None, None]
            error = np.abs(amplitude - reference) / np.maximum(peak, 1e-30)
            error = float(error[whole].max())  # pings the tracer held whole (the rest it traces again)
            rows[name] = {"ms": 1e3 * seconds, "chunk": chunk, "max_error_over_peak": error, "kernel": regs}
            print(f"{rays:,} rays, {name}: {1e3 * seconds:.2f} ms (chunk {chunk}), error/peak {error:.1e}, {regs}")
        res["runs"][str(rays)] = {"echoes_per_ping": arrivals / args.pings, "variants": rows}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"record_kernels_{'cuda' if device.is_cuda else 'cpu'}"
    res = write_json(out / f"{stem}.json", res, device=str(device))
    lines = [
        f"# Echo accumulation variants on {res['device_name']} ({res['device']})",
        "",
        f"One batch of {args.pings} office pings, 3 bounces; milliseconds per launch, median of {args.repeats}; "
        "error = largest |difference from int64| over the ping's peak sample; the row kernel's registers a thread.",
        "",
        "| rays | echoes per ping | " + " | ".join(variants) + " |",
        "|---|---|" + "---|" * len(variants),
    ]
    for rays, run in res["runs"].items():
        cells = [
            f"{v['ms']:.2f} ms ({v['max_error_over_peak']:.0e}, {v['kernel'].get('registers', '?')} registers)"
            for v in run["variants"].values()
        ]
        lines.append(f"| {int(rays):,} | {run['echoes_per_ping']:,.0f} | " + " | ".join(cells) + " |")
    lines += ["", provenance_line(res["provenance"])]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
