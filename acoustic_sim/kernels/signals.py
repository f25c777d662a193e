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
def echo_at_microphone(
    source: wp.vec3,
    extra_length: float,
    amplitude: float,
    microphone: wp.vec3,
    gain: float,
    channel_delay: float,
    samples_per_m: float,
    absorption_per_m: float,
    fractions: int,
):
    """(first sample, fraction row, weight of the next row, fixed-point scale) of one echo at one
    microphone: taps j land on samples first - taps / 2 + 1 + j."""
    length = extra_length + wp.length(source - microphone)
    delay = length * samples_per_m + channel_delay
    first = int(wp.floor(delay))
    position = (delay - float(first)) * float(fractions - 1)
    i = wp.min(int(position), fractions - 2)
    v = position - float(i)
    scale = amplitude * gain * wp.exp(-absorption_per_m * length) * FIXED_POINT_SCALE
    return first, i, v, scale


@wp.func
def tap_value(taps: wp.array2d[float], i: int, v: float, j: int, scale: float) -> wp.int64:
    return wp.int64(((1.0 - v) * taps[i, j] + v * taps[i + 1, j]) * scale)


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
    taps_per_thread: int,
    samples: int,
    lead: int,
    # out
    impulses_out: wp.array2d[wp.int64],
):
    """One thread per (ping, echo slot, microphone, group of `taps_per_thread` taps); launch with
    dim=(pings, slots, mics * taps / taps_per_thread).

    The echo reaches microphone m after L = extra_length + |source - mic| metres plus the
    channel's `mic_delay` [samples]: its impulse is the band-limited fractional-delay filter
    `taps[fraction]` (linear between the rows of the table) scaled by the channel's gain and
    amplitude * exp(-absorption_per_m * L), added to row p * rows_per_ping + m at column
    lead + sample. Samples at or after `samples` are not recorded.

    On a GPU the atomics bound this kernel: with one tap per thread a warp's adds land on 4
    microphones x 8 neighbouring samples (4 memory segments) instead of 32 microphone rows. On a
    CPU the arithmetic does: there a thread adds all the taps of one microphone.
    """
    p, s, k = wp.tid()
    a = amplitude[p, s]
    if s >= count[p] or a == 0.0:
        return
    groups = taps.shape[1] // taps_per_thread
    m = k // groups
    first, i, v, scale = echo_at_microphone(
        source[p, s], extra_length[p, s], a, microphones[m], mic_gain[m], mic_delay[m],
        samples_per_m, absorption_per_m, taps.shape[0],
    )  # fmt: skip
    row = p * (impulses_out.shape[0] // count.shape[0]) + m
    start = (k - m * groups) * taps_per_thread
    for j in range(start, start + taps_per_thread):
        n = first - taps.shape[1] // 2 + 1 + j
        if n >= 0 and n < samples:
            wp.atomic_add(impulses_out, row, lead + n, tap_value(taps, i, v, j, scale))


@wp.kernel(enable_backward=False)
def bin_echoes(
    # in
    source: wp.array2d[wp.vec3],
    extra_length: wp.array2d[float],
    amplitude: wp.array2d[float],
    count: wp.array[wp.int32],
    centre: wp.vec3,
    samples_per_m: float,
    block: int,
    silent_after: float,
    # out
    bin_out: wp.array2d[wp.int32],
    rank_out: wp.array2d[wp.int32],
    # in-out: echoes per (ping, bin), from zero
    bin_count_inout: wp.array2d[wp.int32],
):
    """Each echo's time bin (its delay to the array's centre // block samples) and its rank among
    the echoes of its bin; dim=(pings, slots). Empty slots and echoes that reach the centre after
    `silent_after` samples (and so no microphone within the recording) get bin -1."""
    p, s = wp.tid()
    delay = (extra_length[p, s] + wp.length(source[p, s] - centre)) * samples_per_m
    if s >= count[p] or amplitude[p, s] == 0.0 or delay >= silent_after:
        bin_out[p, s] = -1
        return
    b = wp.clamp(int(delay) // block, 0, bin_count_inout.shape[1] - 1)
    bin_out[p, s] = b
    rank_out[p, s] = wp.atomic_add(bin_count_inout, p, b, 1)


@wp.kernel(enable_backward=False)
def sort_echoes(
    # in
    bins: wp.array2d[wp.int32],
    rank: wp.array2d[wp.int32],
    bin_start: wp.array[wp.int32],
    # out
    order_out: wp.array[wp.int32],
):
    """order_out[bin_start[p * bins + b] + rank] = slot: the slots of each (ping, bin) together."""
    p, s = wp.tid()
    b = bins[p, s]
    if b >= 0:
        order_out[bin_start[p * (bin_start.shape[0] // bins.shape[0]) + b] + rank[p, s]] = s


@functools.cache
def binned_accumulation(mics: int, taps: int, block: int, margin: int):
    """Tiled kernel: the echoes of one (ping, time bin) summed in shared memory, then added once.

    A bin's echoes (`bin_echoes`, `sort_echoes`) reach every microphone within `margin` samples
    of the bin's `block`, so their taps land in a window of mics x (block + 2 margin) samples kept
    in shared memory; one cooperative scatter-add per echo places its mics x taps values, and the
    window then goes to the impulse rows with one global atomic per non-zero sample (a tap outside
    the window, never expected, goes there directly). Same 64-bit integers, same bits as
    `accumulate_echoes`. Launch `wp.launch_tiled(dim=[pings, bins], block_dim=mics * taps)`.
    """
    width = block + 2 * margin

    @wp.kernel(enable_backward=False, module="unique")
    def accumulate_binned(
        # in
        source: wp.array2d[wp.vec3],
        extra_length: wp.array2d[float],
        amplitude: wp.array2d[float],
        microphones: wp.array[wp.vec3],
        mic_gain: wp.array[float],
        mic_delay: wp.array[float],
        samples_per_m: float,
        absorption_per_m: float,
        tap_table: wp.array2d[float],
        samples: int,
        lead: int,
        bin_count: wp.array2d[wp.int32],
        bin_start: wp.array[wp.int32],
        order: wp.array[wp.int32],
        # out
        impulses_out: wp.array2d[wp.int64],
    ):
        p, b, lane = wp.tid()
        window = wp.tile_zeros(shape=(mics, width), dtype=wp.int64, storage="shared")
        start = b * block - margin  # the window's first sample
        row0 = p * (impulses_out.shape[0] // bin_count.shape[0])
        first_echo = bin_start[p * bin_count.shape[1] + b]
        for e in range(first_echo, first_echo + bin_count[p, b]):
            s = order[e]
            # On a GPU one pass (block_dim = mics * taps); a CPU runs one lane per block.
            for t in range(lane, mics * taps, wp.block_dim()):
                m = t // taps
                j = t - m * taps
                first, i, v, scale = echo_at_microphone(
                    source[p, s], extra_length[p, s], amplitude[p, s], microphones[m], mic_gain[m],
                    mic_delay[m], samples_per_m, absorption_per_m, tap_table.shape[0],
                )  # fmt: skip
                n = first - taps // 2 + 1 + j
                column = n - start
                value = tap_value(tap_table, i, v, j, scale)
                recorded = n >= 0 and n < samples
                inside = column >= 0 and column < width
                if recorded and not inside:
                    wp.atomic_add(impulses_out, row0 + m, lead + n, value)
                wp.tile_scatter_add(window, m, wp.where(inside, column, 0), value, recorded and inside)
        for t in range(lane, mics * width, wp.block_dim()):
            m = t // width
            column = t - m * width
            value = window[m, column]
            if value != wp.int64(0):
                wp.atomic_add(impulses_out, row0 + m, lead + start + column, value)

    return accumulate_binned


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


@wp.kernel(enable_backward=False)
def peak_magnitude(
    # in
    signals: wp.array3d[float],
    # out
    peak_out: wp.array[float],
):
    """peak_out[p] = max |signals[p]| (peak_out zeroed first); dim = signals.shape."""
    p, m, n = wp.tid()
    wp.atomic_max(peak_out, p, wp.abs(signals[p, m, n]))


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
