"""Acoustic path tracing: rays discover specular reflection sequences, image sources make them exact."""

import warp as wp

from .common import FAR_RAY_M, add_count, claim_slot

MAX_ORDER = wp.constant(11)  # reflections per path: max_bounces <= 10 secondary bounces after the first
SequenceVec = wp.types.vector(length=MAX_ORDER, dtype=wp.int32)
TABLE_PROBES = wp.constant(32)  # linear probes before an insertion into a pose's sequence table gives up
HASH_SEED = wp.constant(wp.uint64(14695981039346656037))  # FNV-1a 64-bit offset basis
HASH_PRIME = wp.constant(wp.uint64(1099511628211))
SURFACE_STEP = wp.constant(1.0e-4)  # [m] step off a surface before the next query
PLANE_MATCH = wp.constant(2.0e-3)  # [m] how far a validation hit may lie from the image-source reflection point
EDGE_PROBE = wp.constant(1.0e-3)  # [m] probe distance that checks an edge point lies on a face of a plane
PARALLEL_LEG = wp.constant(1.0e-12)  # [m] |normal . leg| below which a leg runs along its plane: no reflection
LEG_SLACK = wp.constant(1.0e-6)  # [fraction of the leg] how far before a leg's start its reflection may lie
BAFFLE_SLACK = wp.constant(1.0e-6)  # [cosine] how far behind the emitter's baffle a path may leave it
RANK_SHIFT = wp.constant(wp.uint64(33))  # [bits] a sequence's rank is its hash >> 33: 31 bits, an int32 >= 0
RANK_NONE = 2**31 - 1  # image rank of an unclaimed slot, where the host starts them (int32 max: no rank is higher)


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
) -> int:
    """Diffuse rain: the Lambert-scattered share of a hit that reaches the receiver unoccluded,
    appended to the ping's echoes (hit point in the sensor frame, path before it, amplitude) at
    slot count_inout[p], which it increments. Returns the number of ray queries made (0 or 1)."""
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
    Adds the number of BVH ray queries made to `ray_queries_out[pose]` (for benchmarks).
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
        scattering = face_scattering[q.face]
        if near_sharp_edge(face_sharp_edges[q.face], face_altitudes[q.face], q.u, q.v, edge_width):
            scattering = 1.0
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


@wp.func
def plane_face_at(mesh: wp.uint64, point: wp.vec3, front: wp.vec3) -> int:
    """The face of the plane with unit normal `front` (towards the path) that `point` lies on, or
    -1: a probe from EDGE_PROBE in front of it, back along the normal, must hit at that distance."""
    q = wp.mesh_query_ray(mesh, point + front * EDGE_PROBE, -front, 2.0 * EDGE_PROBE)
    if not q.result or wp.abs(q.t - EDGE_PROBE) >= 0.5 * EDGE_PROBE:
        return -1
    return q.face


@wp.func
def on_plane(point: wp.vec3, normal: wp.vec3, offset: float) -> bool:
    """Whether `point` lies within PLANE_MATCH of the plane."""
    return wp.abs(wp.dot(normal, point) - offset) < PLANE_MATCH


@wp.func
def lookup(table: wp.array[float], x: float) -> float:
    """Table of a function over [0, 1] at equal steps, interpolated linearly at x (clamped)."""
    position = wp.clamp(x, 0.0, 1.0) * float(table.shape[0] - 1)
    i = wp.min(int(position), table.shape[0] - 2)
    w = position - float(i)
    return (1.0 - w) * table[i] + w * table[i + 1]


@wp.kernel(enable_backward=False)
def validate_sequences(
    # in
    mesh: wp.uint64,
    face_plane: wp.array[wp.int32],
    plane_normal: wp.array[wp.vec3],
    plane_offset: wp.array[float],
    face_reflection: wp.array[float],
    face_scattering: wp.array[float],
    poses: wp.array[wp.mat44],
    emitter: wp.vec3,
    table_key: wp.array2d[wp.uint64],
    table_order: wp.array2d[wp.int32],
    table_planes: wp.array3d[wp.int32],
    plane_curved: wp.array[wp.uint8],
    directivity: wp.array[float],
    # out
    amplitude_out: wp.array2d[float],
    image_out: wp.array2d[wp.vec3],
    arrival_dir_out: wp.array2d[wp.vec3],
    last_point_out: wp.array2d[wp.vec3],
    ray_queries_out: wp.array[wp.int32],
):
    """One thread per (pose, table slot); launch with dim=(pose_count, table_size).

    Exact image-source check of a discovered sequence: mirror the emitter in each plane, then
    walk back from the receiver (sensor origin) through the reflection points. Valid when every
    leg's first hit is at the expected reflection point (within PLANE_MATCH) and the last leg
    reaches the emitter unoccluded, leaving it forwards. Outputs are in the sensor frame: the
    image source [m], the direction the echo arrives from and the last reflection point. The
    amplitude (0 where invalid) is the product of the specular pressure reflection factors
    sqrt(R (1 - s)) along the path, times the emitter's directivity towards the path (table over
    the cosine from its axis, 0..1), over the path length. Adds its BVH ray queries to
    `ray_queries_out[pose]`. A sequence through a facet of a curved surface (`plane_curved`) is
    left out: `kernels.curved.curved_echoes` reflects off the surface itself.
    """
    p, s = wp.tid()
    amplitude_out[p, s] = 0.0
    if table_key[p, s] == wp.uint64(0):
        return
    order = table_order[p, s]
    for m in range(order):
        if plane_curved[table_planes[p, s, m]] != wp.uint8(0):
            return
    pose = poses[p]
    source = wp.transform_point(pose, emitter)
    receiver = wp.transform_point(pose, wp.vec3(0.0))
    inverse = wp.inverse(pose)

    image = source
    for m in range(order):
        plane = table_planes[p, s, m]
        image = mirror(image, plane_normal[plane], plane_offset[plane])

    x = receiver
    gain = float(1.0)
    face_gain = float(1.0)
    valid = int(1)
    arrival = wp.vec3(0.0)
    last_point = wp.vec3(0.0)
    queries = int(0)
    for back in range(order):
        j = order - 1 - back
        target = source
        for m in range(j + 1):
            plane_m = table_planes[p, s, m]
            target = mirror(target, plane_normal[plane_m], plane_offset[plane_m])
        plane = table_planes[p, s, j]
        normal = plane_normal[plane]
        leg = target - x
        denom = wp.dot(normal, leg)
        if wp.abs(denom) < PARALLEL_LEG:
            valid = 0
            break
        t = (plane_offset[plane] - wp.dot(normal, x)) / denom
        if t < -LEG_SLACK or t >= 1.0:
            valid = 0
            break
        point = x + leg * wp.max(t, 0.0)
        distance = wp.length(point - x)
        # The side of this plane the path reflects on: where the previous image lies.
        side = wp.sign(wp.dot(normal, mirror(target, normal, plane_offset[plane]) - point))
        if distance < PLANE_MATCH:
            # Reflects where the previous reflection did: on the edge where two planes meet (the
            # corner reflector case), if that edge point also lies on a face of this plane.
            face = plane_face_at(mesh, point, normal * side)
            queries += 1
            if face < 0:
                valid = 0
                break
            gain = gain * face_gain
        else:
            direction = (point - x) / distance
            q = wp.mesh_query_ray(mesh, x + direction * SURFACE_STEP, direction, distance + PLANE_MATCH)
            queries += 1
            face = q.face
            # The first thing the leg meets must be at the reflection point, on a face of this
            # plane; where two planes meet, the face hit may belong to the other one, and a leg
            # aimed exactly at their edge may slip between the two (a one-triangle BVH leaf of an
            # axis-aligned face is a flat box, whose test may miss a ray through its edge). A
            # miss is such a slip only where the path's next reflection lies on that edge too (a
            # corner reflector's); then nothing stood in its way, and the point must still lie on
            # a face of this plane. Elsewhere it means no face is there.
            slipped = False
            if not q.result:
                if j == 0:
                    valid = 0
                    break
                next_plane = table_planes[p, s, j - 1]
                if not on_plane(point, plane_normal[next_plane], plane_offset[next_plane]):
                    valid = 0
                    break
                slipped = True
            elif wp.abs(q.t + SURFACE_STEP - distance) > PLANE_MATCH:
                valid = 0
                break
            probe = slipped  # (not `slipped or face_plane[q.face] != plane`: Warp evaluates both sides)
            if not slipped:
                probe = face_plane[q.face] != plane
            if probe:
                face = plane_face_at(mesh, point, normal * side)
                queries += 1
                if face < 0:
                    valid = 0
                    break
            face_gain = wp.sqrt(face_reflection[face] * (1.0 - face_scattering[face]))
            gain = gain * face_gain
            if back == 0:
                arrival = direction
                last_point = point
            x = point
    if valid == 1:
        leg = source - x
        distance = wp.length(leg)
        direction = leg / distance
        emit = wp.normalize(wp.transform_vector(inverse, -direction))
        blocked = wp.mesh_query_ray_anyhit(
            mesh, x + direction * SURFACE_STEP, direction, distance - 2.0 * SURFACE_STEP, -1
        )
        queries += 1
        # The emitter is baffled in the sensor's y-z plane: nothing leaves it backwards.
        if not blocked and emit[0] >= -BAFFLE_SLACK:
            amplitude_out[p, s] = gain * lookup(directivity, emit[0]) / wp.length(image - receiver)
            image_out[p, s] = wp.transform_point(inverse, image)
            arrival_dir_out[p, s] = wp.normalize(wp.transform_vector(inverse, arrival))
            last_point_out[p, s] = wp.transform_point(inverse, last_point)
    add_count(ray_queries_out, p, queries)


IMAGE_GRID = wp.constant(1.0e-4)  # [m] image sources closer than this are one echo


@wp.func
def image_key(order: int, image: wp.vec3) -> wp.uint64:
    key = (HASH_SEED ^ wp.uint64(order)) * HASH_PRIME
    for k in range(3):
        cell = wp.int64(wp.round(image[k] / IMAGE_GRID))
        key = (key ^ wp.uint64(cell)) * HASH_PRIME
    return wp.max(key, wp.uint64(1))


@wp.func
def image_slot(image_table: wp.array2d[wp.uint64], p: int, key: wp.uint64, insert: int) -> int:
    """Slot of `key` in ping p's image table (inserted if `insert`), -1 if absent or full."""
    mask = image_table.shape[1] - 1
    slot = int(key & wp.uint64(mask))
    for _probe in range(TABLE_PROBES):
        old = image_table[p, slot]
        if insert != 0 and old == wp.uint64(0):
            old = wp.atomic_cas(image_table, p, slot, wp.uint64(0), key)
            if old == wp.uint64(0):
                return slot
        if old == key:
            return slot
        if old == wp.uint64(0):
            return -1
        slot = (slot + 1) & mask
    return -1


@wp.func
def sequence_rank(key: wp.uint64) -> int:
    return int(key >> RANK_SHIFT)


@wp.kernel(enable_backward=False)
def claim_images(
    # in
    amplitude: wp.array2d[float],
    table_order: wp.array2d[wp.int32],
    image: wp.array2d[wp.vec3],
    table_key: wp.array2d[wp.uint64],
    # in-out: a ping's image table (keys, 0 = empty slot, claimed by atomics), starts at zero
    image_table_inout: wp.array2d[wp.uint64],
    # out
    image_rank_out: wp.array2d[wp.int32],
):
    """Valid paths register their image source (rounded) per ping; the lowest sequence rank wins
    (an atomic min into `image_rank_out`, which starts at RANK_NONE). dim = (pings, table size).

    Two orders of reflection in perpendicular planes give the same image source; where both
    validate, the path runs into the edge between the planes and is one echo, not two.
    """
    p, s = wp.tid()
    if amplitude[p, s] == 0.0:
        return
    slot = image_slot(image_table_inout, p, image_key(table_order[p, s], image[p, s]), 1)
    if slot >= 0:
        wp.atomic_min(image_rank_out, p, slot, sequence_rank(table_key[p, s]))


@wp.kernel(enable_backward=False)
def drop_duplicate_images(
    # in
    table_order: wp.array2d[wp.int32],
    image: wp.array2d[wp.vec3],
    table_key: wp.array2d[wp.uint64],
    image_table: wp.array2d[wp.uint64],
    image_rank: wp.array2d[wp.int32],
    # in-out: the paths' amplitudes, set to 0 where a path is dropped
    amplitude_inout: wp.array2d[float],
):
    """Silence every path whose image source another path with a lower rank claimed;
    dim = (pings, table size)."""
    p, s = wp.tid()
    if amplitude_inout[p, s] == 0.0:
        return
    slot = image_slot(image_table, p, image_key(table_order[p, s], image[p, s]), 0)
    if slot >= 0 and image_rank[p, slot] < sequence_rank(table_key[p, s]):
        amplitude_inout[p, s] = 0.0
