"""Acoustic path tracing: rays discover specular reflection sequences and rain scattered echoes
(`image_sources` makes the sequences exact)."""

import warp as wp

from .common import FAR_RAY_M, add_count, claim_slot

MAX_ORDER = wp.constant(11)  # reflections per path: max_bounces <= 10 secondary bounces after the first
SequenceVec = wp.types.vector(length=MAX_ORDER, dtype=wp.int32)
TABLE_PROBES = wp.constant(32)  # linear probes before an insertion into a pose's sequence table gives up
HASH_SEED = wp.constant(wp.uint64(14695981039346656037))  # FNV-1a 64-bit offset basis
HASH_PRIME = wp.constant(wp.uint64(1099511628211))
SURFACE_STEP = wp.constant(1.0e-4)  # [m] step off a surface before the next query


@wp.func
def mirror(x: wp.vec3, normal: wp.vec3, offset: float) -> wp.vec3:
    """Mirror point x in the plane normal . y = offset."""
    return x - 2.0 * (wp.dot(normal, x) - offset) * normal


@wp.func
def scattered_hit(
    mesh: wp.uint64,
    hit: wp.vec3,
    normal: wp.vec3,
    incoming: wp.vec3,
    receiver: wp.vec3,
    inverse: wp.mat44,
    travelled: float,
    energy: float,
    order: int,
    p: int,
    capacity: int,
    count_inout: wp.array[wp.int32],
    source_out: wp.array2d[wp.vec3],
    extra_out: wp.array2d[float],
    amplitude_out: wp.array2d[float],
    order_out: wp.array2d[wp.int32],
    ray_code: int,
    ray_out: wp.array2d[wp.int32],
) -> int:
    """Diffuse rain: the Lambert-scattered share of a hit that reaches the receiver unoccluded,
    appended to the ping's echoes (hit point in the sensor frame, path before it, amplitude) at
    slot count_inout[p], which it increments; `ray_code` goes to ray_out[p, slot] where ray_out
    has slots (it has none unless faces are recorded). Returns the number of ray queries made (0 or 1)."""
    if energy <= 0.0:
        return 0
    front = -normal * wp.sign(wp.dot(incoming, normal))  # normal on the side the ray came from
    to_receiver = receiver - hit
    distance = wp.length(to_receiver)
    direction = to_receiver / distance
    cosine = wp.dot(direction, front)
    if cosine <= 0.0:
        return 0
    start = hit + front * SURFACE_STEP
    # Only whether anything is in the way matters: any hit ends the search (no closest hit needed).
    if wp.mesh_query_ray_anyhit(mesh, start, wp.normalize(receiver - start), wp.length(receiver - start), -1):
        return 1
    slot = claim_slot(count_inout, p)
    if slot < capacity:
        source_out[p, slot] = wp.transform_point(inverse, hit)
        extra_out[p, slot] = travelled
        amplitude_out[p, slot] = wp.sqrt(energy * cosine / (wp.pi * distance * distance))
        order_out[p, slot] = order
        if slot < ray_out.shape[1]:
            ray_out[p, slot] = ray_code
    return 1


@wp.func
def near_sharp_edge(edges: wp.uint8, altitudes: wp.vec3, u: float, v: float, width: float) -> bool:
    """Whether barycentric point (u, v) of a face lies within `width` [m] of one of its sharp edges."""
    mask = int(edges)
    if mask == 0 or width <= 0.0:
        return False
    weights = wp.vec3(u, v, 1.0 - u - v)
    for k in range(3):
        if ((mask >> k) & 1) == 1 and weights[k] * altitudes[k] < width:
            return True
    return False


@wp.kernel(enable_backward=False)
def discover_sequences(
    # in
    mesh: wp.uint64,
    face_plane: wp.array[wp.int32],
    poses: wp.array[wp.mat44],
    inverse_poses: wp.array[wp.mat44],
    emitter: wp.vec3,
    ray_dirs: wp.array[wp.vec3],
    max_order: int,
    face_reflection: wp.array[float],
    face_scattering: wp.array[float],
    face_sharp_edges: wp.array[wp.uint8],
    face_altitudes: wp.array[wp.vec3],
    edge_width: float,
    ray_energy: wp.array[float],
    scatter: int,
    # in-out: a pose's sequence table (keys, 0 = empty slot) and count of scattered arrivals,
    # read and claimed by atomics; both start at zero
    table_key_inout: wp.array2d[wp.uint64],
    scatter_count_inout: wp.array[wp.int32],
    # out
    table_order_out: wp.array2d[wp.int32],
    table_planes_out: wp.array3d[wp.int32],
    overflow_out: wp.array[wp.int32],
    scatter_source_out: wp.array2d[wp.vec3],
    scatter_extra_out: wp.array2d[float],
    scatter_amplitude_out: wp.array2d[float],
    scatter_order_out: wp.array2d[wp.int32],
    ray_queries_out: wp.array[wp.int32],
    # out where they have room (calibration; empty otherwise): the face of each hit of each ray, and per
    # scattered arrival its ray, -(ray + 1) where an edge band scattered it
    hit_faces_out: wp.array3d[wp.int32],
    scatter_ray_out: wp.array2d[wp.int32],
):
    """One thread per (pose, ray); launch with dim=pose_count * ray_count.

    Follows the ray's specular bounces and records every prefix of its plane sequence (orders
    1..max_order) once per pose in an open-addressing hash table keyed by the sequence hash;
    insertions that find no free slot within TABLE_PROBES are counted in `overflow_out[pose]`.
    Rays leave the emitter (sensor frame position `emitter`) along `ray_dirs` (sensor frame),
    each carrying `ray_energy` (squared pressure at 1 m times its solid angle).

    With `scatter` on, every hit also sends its scattered share (Lambert lobe, energy R s) to
    the receiver (sensor origin) along an unoccluded shadow ray and appends it to the pose's
    scattered arrivals: hit point (world), path length, energy at the receiver, order. Within
    `edge_width` of a sharp edge a face scatters everything it reflects: edges and corners echo.
    Adds the number of BVH ray queries made to `ray_queries_out[pose]` (for benchmarks). Where
    `hit_faces_out` has a row per ray, each hit's face goes to hit_faces_out[pose, ray, order - 1]
    and each scattered arrival's ray to `scatter_ray_out`: what the arrival owes to which faces.
    """
    tid = wp.tid()
    ray_count = ray_dirs.shape[0]
    p = tid // ray_count
    r = tid - p * ray_count
    pose = poses[p]
    origin = wp.transform_point(pose, emitter)
    direction = wp.normalize(wp.transform_vector(pose, ray_dirs[r]))
    mask = table_key_inout.shape[1] - 1
    planes = SequenceVec()
    key = HASH_SEED
    receiver = wp.transform_point(pose, wp.vec3(0.0))
    energy = ray_energy[r]
    travelled = float(0.0)
    capacity = scatter_source_out.shape[1]
    inverse = inverse_poses[p]
    queries = int(0)
    for k in range(max_order):
        q = wp.mesh_query_ray(mesh, origin, direction, FAR_RAY_M)
        queries += 1
        if not q.result:
            break
        travelled = travelled + q.t
        if r < hit_faces_out.shape[1]:
            hit_faces_out[p, r, k] = q.face
        scattering = face_scattering[q.face]
        ray_code = r
        if near_sharp_edge(face_sharp_edges[q.face], face_altitudes[q.face], q.u, q.v, edge_width):
            scattering = 1.0
            ray_code = -(r + 1)
        if scatter != 0:
            queries += scattered_hit(
                mesh,
                origin + direction * q.t,
                wp.normalize(q.normal),
                direction,
                receiver,
                inverse,
                travelled,
                energy * face_reflection[q.face] * scattering,
                k + 1,
                p,
                capacity,
                scatter_count_inout,
                scatter_source_out,
                scatter_extra_out,
                scatter_amplitude_out,
                scatter_order_out,
                ray_code,
                scatter_ray_out,
            )
        energy = energy * face_reflection[q.face] * (1.0 - scattering)
        plane = face_plane[q.face]
        planes[k] = plane
        key = (key ^ wp.uint64(plane + 1)) * HASH_PRIME
        slot = int(key & wp.uint64(mask))
        stored = int(0)
        for _probe in range(TABLE_PROBES):
            # Most rays find their sequence already stored: a plain read settles those without
            # an atomic on the pose's hottest slots (a slot, once claimed, never changes). End to
            # end on an H100 this measured 1.00-1.03x: the BVH walk, not the table, bounds it.
            old = table_key_inout[p, slot]
            if old == wp.uint64(0):
                old = wp.atomic_cas(table_key_inout, p, slot, wp.uint64(0), key)
            if old == wp.uint64(0):
                table_order_out[p, slot] = k + 1
                for j in range(k + 1):
                    table_planes_out[p, slot, j] = planes[j]
                stored = 1
                break
            if old == key:
                stored = 1
                break
            slot = (slot + 1) & mask
        if stored == 0:
            wp.atomic_add(overflow_out, p, 1)
        hit = origin + direction * q.t
        normal = wp.normalize(q.normal)
        side = wp.sign(wp.dot(direction, normal))
        direction = direction - 2.0 * wp.dot(direction, normal) * normal
        # Step off along the normal, to the side the ray came from (along the new direction, rays
        # near an edge can slip behind the next face and escape a closed room).
        origin = hit - normal * (side * SURFACE_STEP)
    add_count(ray_queries_out, p, queries)
