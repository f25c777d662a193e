"""Microphone signal synthesis: band-limited fractional-delay impulses."""

import warp as wp


@wp.func
def lanczos(x: float, half_width: float) -> float:
    """Windowed sinc sinc(x) sinc(x / a), zero for |x| >= a."""
    if wp.abs(x) >= half_width:
        return 0.0
    if wp.abs(x) < 1.0e-6:
        return 1.0
    px = wp.pi * x
    return half_width * wp.sin(px) * wp.sin(px / half_width) / (px * px)


@wp.kernel(enable_backward=False)
def accumulate_impulses(
    # in
    row_base: wp.array[wp.int32],
    source: wp.array[wp.vec3],
    extra_length: wp.array[float],
    amplitude: wp.array[float],
    microphones: wp.array[wp.vec3],
    samples_per_m: float,
    half_taps: int,
    # out
    impulses_out: wp.array2d[float],
):
    """One thread per (arrival, microphone); launch with dim=(arrival_count, microphone_count).

    Adds the arrival's impulse, delayed by (extra_length + |source - mic|) / c, to the row
    row_base[arrival] + mic of `impulses_out` as Lanczos-windowed sinc taps (exact fractional
    delay for band-limited signals). `samples_per_m` is sample_rate / c.
    """
    a, m = wp.tid()
    delay = (extra_length[a] + wp.length(source[a] - microphones[m])) * samples_per_m
    first = int(wp.floor(delay)) - half_taps + 1
    row = row_base[a] + m
    count = impulses_out.shape[1]
    for j in range(2 * half_taps):
        n = first + j
        if n >= 0 and n < count:
            wp.atomic_add(impulses_out, row, n, amplitude[a] * lanczos(delay - float(n), float(half_taps)))
