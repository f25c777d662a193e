"""Microphone signal synthesis: fractional-delay impulses, then FFT convolution with the call per absorption node."""

import functools

import warp as wp

from .common import NOISE_UNIFORM, complex_mul

# Impulses are summed as 64-bit fixed point: integer atomics add in any order to the same bits,
# so signals are reproducible on the GPU as well. 2^-32 resolution, range +-2^31.
FIXED_POINT_SCALE = wp.constant(4294967296.0)  # 2^32 [fixed-point units per unit amplitude]
# An absorption node's FFT spans this many blocks (block B = FFT size / NODE_BLOCKS samples): one
# block before the node, its impulses up to one block either side, and room for the call.
NODE_BLOCKS = wp.constant(4)


@wp.func
def echo_taps(
    length: float,
    amplitude: float,
    gain: float,
    mic_delay: float,
    samples_per_m: float,
    absorption_per_m: float,
    taps: wp.array2d[float],
):
    """Where an echo of path `length` [m] lands on a microphone: the sample of its first tap, the
    row of the fractional-delay table below its fraction and the weight of the row above, and
    its fixed-point scale."""
    delay = length * samples_per_m + mic_delay
    first = int(wp.floor(delay))
    position = (delay - float(first)) * float(taps.shape[0] - 1)
    i = wp.min(int(position), taps.shape[0] - 2)
    scale = amplitude * gain * wp.exp(-absorption_per_m * length) * FIXED_POINT_SCALE
    return first - taps.shape[1] // 2 + 1, i, position - float(i), scale


@wp.func
def tap_weight(taps: wp.array2d[float], i: int, v: float, j: int) -> float:
    """Tap j of the filter between table rows i and i + 1 (weight v)."""
    return (1.0 - v) * taps[i, j] + v * taps[i + 1, j]


@wp.func
def tap_value(taps: wp.array2d[float], i: int, v: float, j: int, scale: float) -> wp.int64:
    """Tap j of the filter between table rows i and i + 1 (weight v), fixed point."""
    return wp.int64(tap_weight(taps, i, v, j) * scale)


@wp.kernel(enable_backward=False)
def accumulate_echoes(
    # in
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
    lead: int,
    # out
    impulses_out: wp.array2d[wp.int64],
):
    """One thread per (ping, echo slot, microphone); launch with dim=(pings, slots, mics).

    The echo reaches microphone m after L = extra_length + |source - mic| metres plus the
    channel's `mic_delay` [samples]: its impulse is the band-limited fractional-delay filter
    `taps[fraction]` (linear between the rows of the table) scaled by the channel's gain and
    amplitude * exp(-absorption_per_m * L), added to row p * rows_per_ping + m at column
    lead + sample. Samples at or after `samples` are not recorded.
    """
    p, s, m = wp.tid()
    a = amplitude[p, s]
    if s >= count[p] or a == 0.0:
        return
    length = extra_length[p, s] + wp.length(source[p, s] - microphones[m])
    lowest, i, v, scale = echo_taps(length, a, mic_gain[m], mic_delay[m], samples_per_m, absorption_per_m, taps)
    row = p * (impulses_out.shape[0] // count.shape[0]) + m
    for j in range(taps.shape[1]):
        n = lowest + j
        if n >= 0 and n < samples:
            wp.atomic_add(impulses_out, row, lead + n, tap_value(taps, i, v, j, scale))


@wp.func_native("WP_TILE_SYNC();")
def block_sync(): ...


# The GPU sums a row's taps in 32-bit integers (half the shared memory of 64-bit, two blocks per
# SM: 0.68x the time at 100k rays on an H100, benchmarks/results/sonar_cuda_same_job/
# run6_row_sums_32bit/; the CPU keeps one 64-bit atomic per tap). Each stretch of STRETCH samples
# of a ping's rows gets its own power-of-two unit, the finest (at most the 2^-32 of the CPU's int64
# path) at which no sum there can reach 2^SUM_BITS: stretches that are quiet enough keep the int64
# path's bits, loud ones lose the bits below 2^-29 of their summed |amplitude|.
STRETCH = 1024
SUM_BITS = wp.constant(30)
FINEST_EXPONENT = wp.constant(32)  # 2^32 units per unit amplitude, FIXED_POINT_SCALE
# One launch of the GPU's kernels sums this many echo buffers (the tracer's specular, scattered
# and curved echoes): each launch zeroes and writes back whole rows, so one per buffer cost more
# than the echoes of the small ones.
BUFFERS_PER_LAUNCH = 3


@wp.struct
class EchoRows:
    """An `EchoBuffer` as a kernel argument: (pings, slots) echoes, `count` slots used per ping."""

    source: wp.array2d[wp.vec3]
    extra_length: wp.array2d[float]
    amplitude: wp.array2d[float]
    count: wp.array[wp.int32]


@wp.func
def used_slots(echoes: EchoRows, p: int) -> int:
    return wp.min(echoes.count[p], echoes.amplitude.shape[1])


# Blocks that share the bounds of a ping's stretches (`stretch_bounds`): one block per ping walked
# 300k echoes at 100k rays in ~1,000 dependent steps a thread (15 ms per 1,000 pings on an H100).
BOUND_SPLITS = 16
BOUND_BLOCK_DIM = 256


@functools.cache
def stretch_bounds(stretches: int):
    """Tiled kernel, `BOUND_SPLITS` blocks per ping (`wp.launch_tiled(dim=[pings, BOUND_SPLITS],
    block_dim=BOUND_BLOCK_DIM)`): adds to `bounds_inout` (zeroed first) the |amplitude| (fixed
    point, rounded up) of every echo of the three buffers to each of the `stretches` stretches of
    the ping's rows its taps can reach on any microphone, i.e. within `reach` samples of its
    arrival at the array's origin. Block k takes every BOUND_SPLITS-th run of block_dim slots;
    each thread sums its echoes in registers, the block adds the threads' sums in shared memory,
    then adds them to the bounds with one global atomic per stretch. Integer sums: the same
    bounds in any order."""
    Bins = wp.types.vector(length=stretches, dtype=wp.int64)

    @wp.func_native("wp::tile_atomic_add_value(&sums.data(wp::tile_coord(i)), value);")
    def shared_add(sums: wp.tile(dtype=wp.int64, shape=(stretches,)), i: int, value: wp.int64): ...

    @wp.func
    def add_bounds(own: Bins, echoes: EchoRows, p: int, first: int, step: int, samples_per_m: float, reach: float):
        for s in range(first, used_slots(echoes, p), step):
            a = wp.abs(echoes.amplitude[p, s])
            if a != 0.0:
                centre = (echoes.extra_length[p, s] + wp.length(echoes.source[p, s])) * samples_per_m
                low = wp.max(int(wp.floor((centre - reach) / float(STRETCH))), 0)
                high = wp.min(int(wp.floor((centre + reach) / float(STRETCH))), stretches - 1)
                units = wp.int64(a * FIXED_POINT_SCALE) + wp.int64(1)
                for b in range(low, high + 1):
                    own[b] = own[b] + units
        return own

    @wp.kernel(enable_backward=False, module="unique")
    def bound_stretches(
        # in
        first: EchoRows,
        second: EchoRows,
        third: EchoRows,
        samples_per_m: float,
        reach: float,
        # in-out: the bounds, zeroed before the launch
        bounds_inout: wp.array2d[wp.int64],
    ):
        p, part, lane = wp.tid()
        start = part * wp.block_dim() + lane
        step = BOUND_SPLITS * wp.block_dim()
        own = Bins()
        own = add_bounds(own, first, p, start, step, samples_per_m, reach)
        own = add_bounds(own, second, p, start, step, samples_per_m, reach)
        own = add_bounds(own, third, p, start, step, samples_per_m, reach)
        sums = wp.tile_zeros(shape=stretches, dtype=wp.int64, storage="shared")
        for b in range(stretches):
            if own[b] != wp.int64(0):
                shared_add(sums, b, own[b])
        block_sync()
        for b in range(lane, stretches, wp.block_dim()):
            if sums[b] != wp.int64(0):
                wp.atomic_add(bounds_inout, p, b, sums[b])

    return bound_stretches


@wp.kernel(enable_backward=False)
def stretch_exponents(
    # in
    bounds: wp.array2d[wp.int64],
    largest_gain_tap: float,
    # out
    exponents_out: wp.array2d[wp.int32],
):
    """One thread per (ping, stretch): k in [0, FINEST_EXPONENT], the unit of its sums being
    2^-k of unit amplitude, the largest with bound * largest_gain_tap * 2^k below 2^(SUM_BITS - 1)
    (a tap is at most the largest |gain| times the largest |filter tap|; air absorption only
    lowers it): no sum of the stretch can overflow 32 bits."""
    p, b = wp.tid()
    worst = float(bounds[p, b]) / FIXED_POINT_SCALE * largest_gain_tap
    k = FINEST_EXPONENT
    if worst > 0.0:
        k = wp.min(k, int(wp.floor(float(SUM_BITS) - wp.log2(worst))) - 1)
    exponents_out[p, b] = wp.int32(wp.max(k, 0))


@wp.func
def in_units(k: wp.int32) -> float:
    """FIXED_POINT_SCALE units to 2^k units: 2^(k - 32), exact."""
    return float(wp.int64(1) << wp.int64(k)) / FIXED_POINT_SCALE


@functools.cache
def row_accumulation(chunk: int, stretches: int, launch_bounds=None):
    """The GPU's `accumulate_echoes`, over three echo buffers at once: one block per (ping,
    microphone, `chunk` samples of its row); launch `wp.launch_tiled(dim=[pings, mics,
    ceil(samples / chunk)])`. `launch_bounds`: CUDA's (threads, blocks per SM), for benchmarks.

    The block owns its stretch of the row: its threads walk the ping's echo slots and add their
    taps, in the units of `stretch_exponents` (2^-k, k = exponents[p, n // STRETCH]), with 32-bit
    atomics in shared memory (chunk * 4 bytes), then add the sums to the impulses once, in
    FIXED_POINT_SCALE units (an exact shift), without global atomics. Integer sums: the same bits in any order.
    """

    @wp.func_native("wp::tile_atomic_add_value(&row.data(wp::tile_coord(i)), value);")
    def shared_add(row: wp.tile(dtype=wp.int32, shape=(chunk,)), i: int, value: wp.int32): ...

    @wp.func
    def add_taps(
        row: wp.tile(dtype=wp.int32, shape=(chunk,)),
        exponent: wp.tile(dtype=wp.int32, shape=(1, stretches)),
        echoes: EchoRows,
        p: int,
        lane: int,
        start: int,
        mic: wp.vec3,
        gain: float,
        delay: float,
        samples_per_m: float,
        absorption_per_m: float,
        taps: wp.array2d[float],
    ):
        for s in range(lane, used_slots(echoes, p), wp.block_dim()):
            a = echoes.amplitude[p, s]
            if a != 0.0:
                length = echoes.extra_length[p, s] + wp.length(echoes.source[p, s] - mic)
                lowest, i, v, scale = echo_taps(length, a, gain, delay, samples_per_m, absorption_per_m, taps)
                # The echo's taps lie in one stretch or two (b and b + 1): their scales in the
                # stretches' units (scale holds FIXED_POINT_SCALE; powers of two, exact)
                b = wp.min(wp.max(lowest, 0) // STRETCH, stretches - 1)
                next_start = (b + 1) * STRETCH
                before = scale * in_units(exponent[0, b])
                after = scale * in_units(exponent[0, wp.min(b + 1, stretches - 1)])
                for j in range(taps.shape[1]):
                    n = lowest + j
                    # Taps before sample 0 fall before chunk 0; those after the record, in the
                    # last chunk's tail, which the sums below leave out.
                    if n >= start and n < start + chunk:
                        tap = tap_weight(taps, i, v, j)
                        shared_add(row, n - start, wp.int32(tap * wp.where(n < next_start, before, after)))

    @wp.kernel(enable_backward=False, module="unique", launch_bounds=launch_bounds)
    def accumulate_rows(
        # in
        first: EchoRows,
        second: EchoRows,
        third: EchoRows,
        microphones: wp.array[wp.vec3],
        mic_gain: wp.array[float],
        mic_delay: wp.array[float],
        samples_per_m: float,
        absorption_per_m: float,
        taps: wp.array2d[float],
        samples: int,
        lead: int,
        exponents: wp.array2d[wp.int32],
        # in-out: the impulses the echoes are added to
        impulses_inout: wp.array2d[wp.int64],
    ):
        p, m, c, lane = wp.tid()
        row = wp.tile_zeros(shape=chunk, dtype=wp.int32, storage="shared")
        exponent = wp.tile_load(exponents, shape=(1, stretches), offset=(p, 0), storage="shared")
        start = c * chunk
        mic, gain, delay = microphones[m], mic_gain[m], mic_delay[m]
        add_taps(row, exponent, first, p, lane, start, mic, gain, delay, samples_per_m, absorption_per_m, taps)
        add_taps(row, exponent, second, p, lane, start, mic, gain, delay, samples_per_m, absorption_per_m, taps)
        add_taps(row, exponent, third, p, lane, start, mic, gain, delay, samples_per_m, absorption_per_m, taps)
        block_sync()
        out = p * (impulses_inout.shape[0] // exponents.shape[0]) + m
        for k in range(lane, wp.min(chunk, samples - start), wp.block_dim()):
            total = row[k]
            if total != 0:
                n = start + k
                shift = FINEST_EXPONENT - exponent[0, wp.min(n // STRETCH, stretches - 1)]
                impulses_inout[out, lead + n] = impulses_inout[out, lead + n] + (wp.int64(total) << wp.int64(shift))

    return accumulate_rows


@functools.cache
def node_convolution(size: int):
    """Tiled kernel: the impulses around each absorption node, convolved with that node's filter.

    Node k sits at sample k B (B = size / NODE_BLOCKS) and owns the impulses within B of it,
    weighted by a hat (so each impulse is shared linearly between its two nodes); its filter is
    the call with the air absorption of the path length at that time. Two microphones share one
    complex FFT (real and imaginary parts stay apart: the filters are real in time). Launch
    `wp.launch_tiled(dim=[pings * pairs, nodes])`; the results go to `overlap_nodes`.
    """

    @wp.func
    def hat_pair(even: wp.int64, odd: wp.int64, hat: float) -> wp.vec2f:
        return wp.vec2f(float(even) * hat, float(odd) * hat)

    @wp.kernel(enable_backward=False, module="unique")
    def convolve(
        # in
        impulses: wp.array2d[wp.int64],
        hat: wp.array2d[float],
        node_filters: wp.array2d[wp.vec2f],
        # out
        nodes_out: wp.array2d[wp.vec2f],
    ):
        pair, k = wp.tid()
        block = size // NODE_BLOCKS
        even = wp.tile_load(impulses, shape=(1, size), offset=(2 * pair, k * block))
        odd = wp.tile_load(impulses, shape=(1, size), offset=(2 * pair + 1, k * block))
        weights = wp.tile_load(hat, shape=(1, size), offset=(0, 0))
        x = wp.tile_map(hat_pair, even, odd, weights)
        wp.tile_fft(x)
        h = wp.tile_load(node_filters, shape=(1, size), offset=(k, 0))
        y = wp.tile_map(complex_mul, x, h)
        wp.tile_ifft(y)
        wp.tile_store(nodes_out, y, offset=(pair * node_filters.shape[0] + k, 0))

    return convolve


@wp.kernel(enable_backward=False)
def overlap_nodes(
    # in
    nodes: wp.array2d[wp.vec2f],
    node_count: int,
    block: int,
    # out
    signals_out: wp.array3d[float],
):
    """signals[p, m, n] = sum of the node outputs covering sample n; dim = signals.shape.

    Node k's output starts at sample (k - 1) * block and spans nodes.shape[1] samples
    (NODE_BLOCKS blocks); microphone m is the real (even m) or imaginary (odd m) part of pair m // 2.
    """
    p, m, n = wp.tid()
    pairs = (signals_out.shape[1] + 1) // 2
    row0 = (p * pairs + m // 2) * node_count
    j = n // block
    total = float(0.0)
    # Node k covers blocks k - 1 .. k + NODE_BLOCKS - 2, so nodes j - NODE_BLOCKS + 2 .. j + 1
    # reach block j (the loop starts one node early; the bounds check skips it).
    for k in range(wp.max(j - (NODE_BLOCKS - 1), 0), wp.min(j + 2, node_count)):
        local = n - (k - 1) * block
        if local >= 0 and local < nodes.shape[1]:
            z = nodes[row0 + k, local]
            total += z[m % 2]
    signals_out[p, m, n] = total


# Threads that share one row's maximum (`peak_magnitude`): one atomic per thread on the ping's peak,
# not one per sample (52 M atomics on 100 addresses took 5.6 ms of a 21 ms paper-suite episode
# on an H100).
PEAK_LANES = 256


@wp.kernel(enable_backward=False)
def peak_magnitude(
    # in
    signals: wp.array3d[float],
    # out
    peak_out: wp.array[float],
):
    """peak_out[p] = max |signals[p]| (peak_out zeroed first); dim = (pings, mics, PEAK_LANES),
    lane k taking samples k, k + PEAK_LANES, ... (neighbouring lanes read neighbouring samples)."""
    p, m, lane = wp.tid()
    largest = float(0.0)
    for n in range(lane, signals.shape[2], PEAK_LANES):
        largest = wp.max(largest, wp.abs(signals[p, m, n]))
    wp.atomic_max(peak_out, p, largest)


@wp.kernel(enable_backward=False)
def add_noise(
    # in
    peak: wp.array[float],
    seeds: wp.array[wp.int32],
    relative_std: float,
    noise_kind: int,
    # in-out: the signals the noise is added to
    signals_inout: wp.array3d[float],
):
    """White noise of standard deviation relative_std * peak[p], uniform for noise_kind
    NOISE_UNIFORM, else Gaussian; dim = signals.shape.

    Each ping draws from its own seed, so a ping's noise does not depend on the batch it is in.
    """
    p, m, n = wp.tid()
    state = wp.rand_init(seeds[p], m * signals_inout.shape[2] + n)
    std = relative_std * peak[p]
    if noise_kind == NOISE_UNIFORM:
        value = std * wp.sqrt(3.0) * wp.randf(state, -1.0, 1.0)  # uniform on [-1, 1] has std 1 / sqrt(3)
    else:
        value = std * wp.randn(state)
    signals_inout[p, m, n] = signals_inout[p, m, n] + value
