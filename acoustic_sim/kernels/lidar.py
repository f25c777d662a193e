"""LiDAR ray casting."""

import warp as wp

# Most see-through layers a beam passes before it is treated as a miss (glass panes have 2 faces).
MAX_TRANSPARENT_FACES = 8
# Step past a see-through face [m]; small against the 1e-4 m range accuracy we test for.
TRANSPARENT_STEP = 1.0e-5

NOISE_NONE = 0
NOISE_GAUSSIAN = 1
NOISE_UNIFORM = 2


@wp.kernel(enable_backward=False)
def lidar_scan(
    # in
    mesh: wp.uint64,
    face_transparent: wp.array[wp.uint8],
    poses: wp.array[wp.mat44],
    beam_dirs: wp.array[wp.vec3],
    range_min: float,
    range_max: float,
    noise_kind: int,
    noise_m: float,
    dropout_probability: float,
    seed: int,
    # out
    range_out: wp.array2d[float],
    face_out: wp.array2d[wp.int32],
):
    """One thread per (pose, beam); launch with dim=(pose_count, beam_count).

    Beams pass see-through faces; a miss, or a return outside [range_min, range_max], gives
    range inf and face -1. Noise and dropout draw from a counter-based RNG keyed on (seed, thread).
    """
    p, b = wp.tid()
    pose = poses[p]
    origin = wp.transform_point(pose, wp.vec3(0.0))
    direction = wp.normalize(wp.transform_vector(pose, beam_dirs[b]))

    t = float(0.0)
    face = int(-1)
    for _layer in range(MAX_TRANSPARENT_FACES):
        q = wp.mesh_query_ray(mesh, origin + direction * t, direction, range_max - t)
        if not q.result:
            break
        t = t + q.t
        if face_transparent[q.face] == wp.uint8(0):
            face = q.face
            break
        t = t + TRANSPARENT_STEP

    r = wp.inf
    if face >= 0 and t >= range_min:
        r = t
        if noise_kind != NOISE_NONE or dropout_probability > 0.0:
            rng = wp.rand_init(seed, p * beam_dirs.shape[0] + b)
            if noise_kind == NOISE_GAUSSIAN:
                r = r + noise_m * wp.randn(rng)
            elif noise_kind == NOISE_UNIFORM:
                r = r + noise_m * (2.0 * wp.randf(rng) - 1.0)
            r = wp.max(r, range_min)
            if wp.randf(rng) < dropout_probability:
                r = wp.inf
    if r == wp.inf:
        face = -1
    range_out[p, b] = r
    face_out[p, b] = face
