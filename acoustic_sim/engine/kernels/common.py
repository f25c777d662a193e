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
