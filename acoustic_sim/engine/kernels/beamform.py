"""Energyscape processing: complex baseband, matched filter and delay-and-sum per frequency, envelope."""

import functools

import warp as wp

from .common import complex_mul

# Floor under the peak an image is divided by, and under a value before its logarithm: no 0 / 0
# and no log(0) for an empty image (far below any float32 energy that matters; 10^-30 = -600 dB).
NONZERO_FLOOR = wp.constant(1.0e-30)


@wp.kernel(enable_backward=False)
def demodulate(
    # in
    signals: wp.array3d[float],
    samples: int,
    taps: wp.array[wp.vec2f],
    cycles_per_output: wp.float64,
    decimation: int,
    # out
    baseband_out: wp.array2d[wp.vec2f],
):
    """One thread per (ping, microphone, baseband sample); dim = (pings, mics, baseband length).

    x_bb[k] = exp(-2 pi i f0 D k / fs) sum_j taps[j] x[D k + j - J], with taps[j] = h[j]
    exp(-2 pi i f0 (j - J) / fs) the zero-phase low-pass h shifted to f0: the analytic signal
    around f0, moved to 0 Hz and decimated by D; zero past the recording.
    """
    p, m, k = wp.tid()
    half = taps.shape[0] // 2
    start = k * decimation - half
    acc = wp.vec2f(0.0, 0.0)
    if start < samples:
        for j in range(taps.shape[0]):
            n = start + j
            if n >= 0 and n < samples:
                acc = acc + taps[j] * signals[p, m, n]
    # Phase of the carrier at sample D k, reduced to one turn in double precision.
    turns = cycles_per_output * wp.float64(k)
    phase = -2.0 * wp.pi * float(turns - wp.floor(turns))
    baseband_out[p * signals.shape[1] + m, k] = complex_mul(acc, wp.vec2f(wp.cos(phase), wp.sin(phase)))


@functools.cache
def forward_fft(size: int):
    """Tiled in-place FFT of the rows of a (rows, size) vec2f array; launch_tiled(dim=[rows])."""

    @wp.kernel(enable_backward=False, module="unique")
    def fft_rows(
        # in-out: each row is replaced by its FFT
        rows_inout: wp.array2d[wp.vec2f],
    ):
        i = wp.tid()
        t = wp.tile_load(rows_inout, shape=(1, size), offset=(i, 0))
        wp.tile_fft(t)
        wp.tile_store(rows_inout, t, offset=(i, 0))

    return fft_rows


@functools.cache
def inverse_fft_magnitude(size: int):
    """Tiled inverse FFT of the rows of a (rows, size) vec2f array, keeping scale * |x|;
    launch_tiled(dim=[rows])."""

    @wp.func
    def magnitude(z: wp.vec2f) -> float:
        return wp.length(z)

    @wp.kernel(enable_backward=False, module="unique")
    def ifft_rows(
        # in
        rows: wp.array2d[wp.vec2f],
        # out
        magnitude_out: wp.array2d[float],
    ):
        i = wp.tid()
        t = wp.tile_load(rows, shape=(1, size), offset=(i, 0))
        wp.tile_ifft(t)
        wp.tile_store(magnitude_out, wp.tile_map(magnitude, t), offset=(i, 0))

    return ifft_rows


@wp.func
def steering_phase(frequency: float, delay: float) -> float:
    """-2 pi f tau [rad], the turns reduced before the trigonometry: f tau reaches a few turns."""
    turns = frequency * delay
    return -2.0 * wp.pi * (turns - wp.floor(turns))


@functools.cache
def delay_and_sum(mics: int):
    """Kernel for arrays of `mics` microphones: matched filter and delay-and-sum per frequency.

    One thread per (look direction, band bin), dim = (looks, band bins), looping over pings so
    that its steering weights are computed once:
    beams[p * looks + l, bin] = conj(C(f)) / M sum_m X[p * M + m, bin] exp(-2 pi i f tau_lm),
    with f the bin's true frequency and tau_lm = (m . u_l) / c. Bins off the band stay untouched.
    """
    Weights = wp.types.vector(length=mics, dtype=float)

    @wp.kernel(enable_backward=False, module="unique")
    def beamform(
        # in
        spectra: wp.array2d[wp.vec2f],
        band_bin: wp.array[wp.int32],
        band_hz: wp.array[float],
        matched: wp.array[wp.vec2f],
        delays: wp.array2d[float],
        pings: int,
        # out
        beams_out: wp.array2d[wp.vec2f],
    ):
        look, f = wp.tid()
        looks = delays.shape[0]
        frequency = band_hz[f]
        column = band_bin[f]
        re = Weights()
        im = Weights()
        for m in range(mics):
            phase = steering_phase(frequency, delays[look, m])
            re[m] = wp.cos(phase)
            im[m] = wp.sin(phase)
        weight = matched[f]
        for p in range(pings):
            sum_re = float(0.0)
            sum_im = float(0.0)
            for m in range(mics):
                x = spectra[p * mics + m, column]
                sum_re += x[0] * re[m] - x[1] * im[m]
                sum_im += x[0] * im[m] + x[1] * re[m]
            beams_out[p * looks + look, column] = complex_mul(wp.vec2f(sum_re, sum_im), weight)

    return beamform


# The GPU's delay-and-sum (`delay_and_sum_tiles`): band bins a block takes (a warp's lanes), and the
# microphone rows of the pings it stages in shared memory at once.
TILE_BINS = 32
STAGE_PINGS = 4


@wp.func_native("WP_TILE_SYNC();")
def block_sync(): ...


@functools.cache
def delay_and_sum_tiles(mics: int, looks_per_block: int):
    """GPU kernel: `delay_and_sum` with a block per (tile of up to TILE_BINS band bins,
    `looks_per_block` look directions); launch_tiled(dim=[bin tiles, ceil(looks /
    looks_per_block)], block_dim=TILE_BINS * looks_per_block).

    Each thread keeps one (look, bin)'s steering weights in registers, as `delay_and_sum`'s do;
    the block stages STAGE_PINGS pings' spectra of its bins in shared memory at a time, so each
    is read from global memory once per block, not once per look (the one-thread-per-(look, bin)
    kernel read the batch's spectra 181 times over, ~30 GB per 256 pings). Tile t covers band
    bins tile_band[t] .. + tile_width[t] - 1, FFT columns tile_column[t] on (the band is one or
    two runs of columns). The same sums in the same order as `delay_and_sum`.
    """
    Weights = wp.types.vector(length=mics, dtype=float)
    rows = STAGE_PINGS * mics

    @wp.kernel(enable_backward=False, module="unique")
    def beamform_tiles(
        # in
        spectra: wp.array2d[wp.vec2f],
        tile_column: wp.array[wp.int32],
        tile_band: wp.array[wp.int32],
        tile_width: wp.array[wp.int32],
        band_hz: wp.array[float],
        matched: wp.array[wp.vec2f],
        delays: wp.array2d[float],
        pings: int,
        # out
        beams_out: wp.array2d[wp.vec2f],
    ):
        t, look_tile, lane = wp.tid()
        looks = delays.shape[0]
        k = lane % TILE_BINS
        look = look_tile * looks_per_block + lane // TILE_BINS
        live = k < tile_width[t] and look < looks
        f = tile_band[t] + wp.min(k, tile_width[t] - 1)
        frequency = band_hz[f]
        re = Weights()
        im = Weights()
        for m in range(wp.static(mics)):
            phase = steering_phase(frequency, delays[wp.min(look, looks - 1), m])
            re[m] = wp.cos(phase)
            im[m] = wp.sin(phase)
        weight = matched[f]
        column = tile_column[t] + k
        for first in range(0, pings, STAGE_PINGS):
            x = wp.tile_load(spectra, shape=(rows, TILE_BINS), offset=(first * mics, tile_column[t]), storage="shared")
            for q in range(wp.min(STAGE_PINGS, pings - first)):
                sum_re = float(0.0)
                sum_im = float(0.0)
                for m in range(wp.static(mics)):
                    z = x[q * mics + m, k]
                    sum_re += z[0] * re[m] - z[1] * im[m]
                    sum_im += z[0] * im[m] + z[1] * re[m]
                if live:
                    beams_out[(first + q) * looks + look, column] = complex_mul(wp.vec2f(sum_re, sum_im), weight)
            block_sync()  # every thread is done with this stage before the next overwrites it

    return beamform_tiles


@wp.func
def lowpass_at(x: float, valid: int, lowpass: wp.array[float]):
    """Where the low-passed envelope at sample position x comes from: the first sample k0 - half of
    the FIR's window at sample k0 = floor(x), the taps j_lo..j_hi - 1 of the window that fall on
    samples 0..valid - 1, and the interpolation weight w of sample k0 + 1. The value is
    sum_j e[k0 + j - half] ((1 - w) h[j] + w h[j - 1]) over those taps (h zero outside 0..L - 1): the
    FIR at k0 and at k0 + 1, interpolated linearly, in one pass without a bounds check a tap."""
    k0 = int(wp.floor(x))
    half = lowpass.shape[0] // 2
    first = k0 - half
    return first, wp.max(0, -first), wp.min(lowpass.shape[0] + 1, valid - first), x - float(k0)


@wp.func
def tap_before(lowpass: wp.array[float], j: int) -> float:
    """h[j - 1], zero for j = 0."""
    before = float(0.0)
    if j > 0:
        before = lowpass[j - 1]
    return before


@wp.func
def tap_at(lowpass: wp.array[float], j: int) -> float:
    """h[j], zero for j = L."""
    now = float(0.0)
    if j < lowpass.shape[0]:
        now = lowpass[j]
    return now


@wp.kernel(enable_backward=False)
def envelope_on_grid(
    # in
    envelope: wp.array2d[float],
    valid: int,
    lowpass: wp.array[float],
    range_m: wp.array[float],
    samples_per_m: float,
    elevations: int,
    # out
    image_out: wp.array3d[float],
):
    """One thread per (ping x elevation, azimuth, range bin); dim = (image_out.shape[0],
    image_out.shape[2], image_out.shape[1]).

    The envelope of beam row (p * elevations + e) * azimuths + a, low-passed by the zero-phase FIR
    `lowpass` and interpolated linearly at range r (sample r * samples_per_m); samples at or past
    `valid` count as zero. Neighbouring threads take neighbouring range bins of one beam, so the
    FIR's many reads share cache lines (the one write per thread is what strides). The CPU's
    kernel; GPUs run `envelope_rows`, the same sums with the row staged in shared memory.
    """
    pe, a, r = wp.tid()
    row = pe * image_out.shape[2] + a
    first, low, high, w = lowpass_at(range_m[r] * samples_per_m, valid, lowpass)
    total = float(0.0)
    before = tap_before(lowpass, low)
    for j in range(low, high):
        now = tap_at(lowpass, j)
        total += envelope[row, first + j] * ((1.0 - w) * now + w * before)
        before = now
    image_out[pe, r, a] = total


@functools.cache
def envelope_rows(span: int):
    """GPU kernel: `envelope_on_grid` with one block per beam row;
    launch_tiled(dim=[image_out.shape[0] * image_out.shape[2]]).

    The envelope of beam row (p * elevations + e) * azimuths + a, low-passed by the zero-phase FIR
    `lowpass` and interpolated linearly at range r (sample r * samples_per_m), goes to
    image_out[p * elevations + e, r, a]; samples at or past `valid` (<= span) count as zero. The
    block stages the row's first `span` samples in shared memory once; its threads then take the
    range bins in turn and read their ~225-sample windows from there (neighbouring range bins are
    ~7 samples apart, so straight from global memory a warp's every read spanned several cache
    lines). Each bin's sums run in the same order, so the results are `envelope_on_grid`'s bits
    (tested on the CPU). GPUs only: on the CPU, Warp keeps shared tiles in one static buffer per
    module, which the threads of a CPU `Sonar.simulate` beamforming at once would share.
    """

    @wp.kernel(enable_backward=False, module="unique")
    def envelope_on_grid(
        # in
        envelope: wp.array2d[float],
        valid: int,
        lowpass: wp.array[float],
        range_m: wp.array[float],
        samples_per_m: float,
        # out
        image_out: wp.array3d[float],
    ):
        beam, lane = wp.tid()
        azimuths = image_out.shape[2]
        pe = beam // azimuths
        a = beam - pe * azimuths
        row = wp.tile_load(envelope, shape=(1, span), offset=(beam, 0), storage="shared")
        for r in range(lane, image_out.shape[1], wp.block_dim()):
            first, low, high, w = lowpass_at(range_m[r] * samples_per_m, valid, lowpass)
            total = float(0.0)
            before = tap_before(lowpass, low)
            for j in range(low, high):
                now = tap_at(lowpass, j)
                total += row[0, first + j] * ((1.0 - w) * now + w * before)
                before = now
            image_out[pe, r, a] = total

    return envelope_on_grid


PEAK_LANES = 256  # threads that share an image's maximum (`image_peak`): one atomic each, not one per cell


@wp.kernel(enable_backward=False)
def image_peak(
    # in
    images: wp.array3d[float],
    per_ping: int,
    # out
    peak_out: wp.array[float],
):
    """peak_out[p] = max of images[p * per_ping .. (p + 1) * per_ping) (peak_out zeroed first);
    dim = (images.shape[0], PEAK_LANES), lane k taking cells k, k + PEAK_LANES, ... of an image in
    row-major order."""
    i, lane = wp.tid()
    azimuths = images.shape[2]
    largest = float(-wp.inf)
    for k in range(lane, images.shape[1] * azimuths, PEAK_LANES):
        largest = wp.max(largest, images[i, k // azimuths, k % azimuths])
    wp.atomic_max(peak_out, i // per_ping, largest)


@wp.kernel(enable_backward=False)
def scale_images(
    # in
    peak: wp.array[float],
    per_ping: int,
    decibels: int,
    floor_db: float,
    # in-out: the images, scaled in place
    images_inout: wp.array3d[float],
):
    """Divide each ping's images by its peak; with `decibels`, 20 log10 of that, at least floor_db."""
    i, r, a = wp.tid()
    value = images_inout[i, r, a] / wp.max(peak[i // per_ping], NONZERO_FLOOR)
    if decibels != 0:
        value = wp.max(20.0 * wp.log10(wp.max(value, NONZERO_FLOOR)), floor_db)
    images_inout[i, r, a] = value


@wp.kernel(enable_backward=False)
def to_float16(
    # in
    values: wp.array[float],
    # out
    halves_out: wp.array[wp.float16],
):
    """halves_out[i] = values[i] rounded to the nearest float16 (ties to even, as numpy's cast)."""
    i = wp.tid()
    halves_out[i] = wp.float16(values[i])
