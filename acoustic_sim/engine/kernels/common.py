"""What several kernel files share: the complex multiply of the FFT kernels, noise kind codes, ray length."""

import warp as wp

# Noise kinds as the kernels take them (config.NOISE_CODES maps the names to these codes).
NOISE_NONE = wp.constant(0)
NOISE_GAUSSIAN = wp.constant(1)
NOISE_UNIFORM = wp.constant(2)

FAR_RAY_M = wp.constant(1.0e6)  # [m] length of a ray that should hit whatever lies ahead of it


@wp.func
def complex_mul(a: wp.vec2f, b: wp.vec2f) -> wp.vec2f:
    """(a0 + i a1)(b0 + i b1) as (re, im)."""
    return wp.vec2f(a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0])


# Per-ping counters that every ray of a ping adds to (scattered echoes' slots, ray queries): the
# threads of a warp are neighbouring rays of one ping, so on GPUs the lanes that count into the
# same ping add once for all (an atomic per lane on one address serialises; CPUs add per thread).
@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    const unsigned active = __activemask();
    const unsigned group = __match_any_sync(active, i);
    const int leader = __ffs(group) - 1;
    const int lane = threadIdx.x & 31;
    int first = 0;
    if (lane == leader)
        first = atomicAdd(wp::address(counts, i), __popc(group));
    first = __shfl_sync(active, first, leader);
    return first + __popc(group & ((1u << lane) - 1u));
#else
    return wp::atomic_add(wp::address(counts, i), 1);
#endif
"""
)
def claim_slot(counts: wp.array[wp.int32], i: int) -> int:
    """counts[i] += 1, returning the value before: a slot of row i no other thread gets."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
    const unsigned active = __activemask();
    const unsigned group = __match_any_sync(active, i);
    const int total = __reduce_add_sync(group, value);
    if ((threadIdx.x & 31) == __ffs(group) - 1)
        atomicAdd(wp::address(counts, i), total);
#else
    wp::atomic_add(wp::address(counts, i), value);
#endif
"""
)
def add_count(counts: wp.array[wp.int32], i: int, value: int):
    """counts[i] += value."""
    ...


@wp.func
def lookup(table: wp.array[float], x: float) -> float:
    """Table of a function over [-1, 1] at equal steps, interpolated linearly at x (clamped)."""
    position = (wp.clamp(x, -1.0, 1.0) + 1.0) * 0.5 * float(table.shape[0] - 1)
    i = wp.min(int(position), table.shape[0] - 2)
    w = position - float(i)
    return (1.0 - w) * table[i] + w * table[i + 1]
