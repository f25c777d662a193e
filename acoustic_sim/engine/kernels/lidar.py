"""LiDAR ray casting."""

import warp as wp

from .common import FAR_RAY_M, NOISE_GAUSSIAN, NOISE_UNIFORM

# Most see-through layers a beam passes before it is treated as a miss (glass panes have 2 faces).
MAX_TRANSPARENT_FACES = wp.constant(8)
# Step past a see-through face [m]; small against the 1e-4 m range accuracy we test for.
TRANSPARENT_STEP = wp.constant(1.0e-5)

# Largest deviation from a rigid transform that a pose may have (float32 round-off is ~1e-7).
POSE_TOLERANCE = 1.0e-4


@wp.kernel(enable_backward=False)
def pose_error(
    # in
    mesh: wp.uint64,
    poses: wp.array[wp.mat44],
    # out
    error_out: wp.array[float],
    behind_out: wp.array[wp.int32],
):
    """One thread per pose: max of |R^T R - I|, |det R - 1| (a mirror has det -1 yet R^T R = I) and
    |last row - (0, 0, 0, 1)|; inf if any entry is not finite. behind_out is 1 when most of six
    axis rays from the sensor hit the back of a face (inside a closed object, or outside the room),
    else 0. A vote, not the nearest face: an object standing on the floor has a bottom face that
    coincides with the floor, so the nearest face can be either. A sensor beyond a corner of the
    room sees no face along the axes and is not flagged."""
    p = wp.tid()
    m = poses[p]
    origin = wp.vec3(m[0, 3], m[1, 3], m[2, 3])
    back = int(0)
    front = int(0)
    for axis in range(3):
        for side in range(2):
            d = wp.vec3(0.0)
            d[axis] = float(2 * side - 1)
            hit = wp.mesh_query_ray(mesh, origin, d, FAR_RAY_M)
            if hit.result:
                if hit.sign < 0.0:
                    back += 1
                else:
                    front += 1
    behind_out[p] = wp.where(back > front, 1, 0)
    total = float(0.0)
    for i in range(4):
        for j in range(4):
            total = total + m[i, j]
    err = wp.max(wp.max(wp.abs(m[3, 0]), wp.abs(m[3, 1])), wp.max(wp.abs(m[3, 2]), wp.abs(m[3, 3] - 1.0)))
    for i in range(3):
        for j in range(i, 3):
            dot = m[0, i] * m[0, j] + m[1, i] * m[1, j] + m[2, i] * m[2, j]
            if i == j:
                dot = dot - 1.0
            err = wp.max(err, wp.abs(dot))
    det = (
        m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
        - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
        + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])
    )
    err = wp.max(err, wp.abs(det - 1.0))
    if not wp.isfinite(total):
        err = wp.inf
    error_out[p] = err


@wp.func
def beam_ray(poses: wp.array[wp.mat44], beam_dirs: wp.array[wp.vec3], tid: int):
    """Origin and unit direction (world frame) of flat ray index pose * beam_count + beam."""
    beam_count = beam_dirs.shape[0]
    p = tid // beam_count
    pose = poses[p]
    direction = wp.normalize(wp.transform_vector(pose, beam_dirs[tid - p * beam_count]))
    return wp.transform_point(pose, wp.vec3(0.0)), direction


@wp.func
def write_return(
    tid: int, t: float, face: int, range_min: float, range_out: wp.array[float], face_out: wp.array[wp.int32]
):
    """A return at range t off `face` (-1: none); one before range_min is none too."""
    if face < 0 or t < range_min:
        range_out[tid] = wp.inf
        face_out[tid] = -1
    else:
        range_out[tid] = t
        face_out[tid] = face


@wp.kernel(enable_backward=False)
def lidar_scan(
    # in
    mesh: wp.uint64,
    face_transparent: wp.array[wp.uint8],
    poses: wp.array[wp.mat44],
    beam_dirs: wp.array[wp.vec3],
    range_min: float,
    range_max: float,
    # out
    range_out: wp.array[float],
    face_out: wp.array[wp.int32],
):
    """One thread per (pose, beam); launch with dim=pose_count * beam_count. Outputs are flat,
    index pose * beam_count + beam: 2D launches and 2D output arrays each cost ~12 % on an H100.

    Beams pass see-through faces; a miss, or a return outside [range_min, range_max], gives
    range inf and face -1. Scenes without see-through faces take `lidar_scan_opaque`.
    """
    tid = wp.tid()
    origin, direction = beam_ray(poses, beam_dirs, tid)
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
    write_return(tid, t, face, range_min, range_out, face_out)


@wp.kernel(enable_backward=False)
def lidar_scan_opaque(
    # in
    mesh: wp.uint64,
    poses: wp.array[wp.mat44],
    beam_dirs: wp.array[wp.vec3],
    range_min: float,
    range_max: float,
    # out
    range_out: wp.array[float],
    face_out: wp.array[wp.int32],
):
    """`lidar_scan` for scenes without see-through faces: one BVH query a beam, no layer loop
    and no material lookup after it."""
    tid = wp.tid()
    origin, direction = beam_ray(poses, beam_dirs, tid)
    q = wp.mesh_query_ray(mesh, origin, direction, range_max)
    face = int(-1)
    if q.result:
        face = q.face
    write_return(tid, q.t, face, range_min, range_out, face_out)


@wp.kernel(enable_backward=False)
def lidar_noise(
    # in
    range_min: float,
    noise_kind: int,
    noise_m: float,
    dropout_probability: float,
    seed: int,
    # in-out: the scan's ranges and faces, changed in place
    range_inout: wp.array[float],
    face_inout: wp.array[wp.int32],
):
    """Range noise (`noise_kind`: NOISE_NONE, NOISE_GAUSSIAN or NOISE_UNIFORM, of standard deviation
    or half-width noise_m [m]) and dropouts on returns, in place; one thread per flat (pose, beam) index.

    A separate pass: the RNG code in the scan kernel costs it ~13 % even when noise is off.
    Draws come from a counter-based RNG keyed on (seed, index).
    """
    i = wp.tid()
    r = range_inout[i]
    if r == wp.inf:
        return
    rng = wp.rand_init(seed, i)
    if noise_kind == NOISE_GAUSSIAN:
        r = r + noise_m * wp.randn(rng)
    elif noise_kind == NOISE_UNIFORM:
        r = r + noise_m * (2.0 * wp.randf(rng) - 1.0)
    r = wp.max(r, range_min)
    if wp.randf(rng) < dropout_probability:
        r = wp.inf
        face_inout[i] = -1
    range_inout[i] = r
