"""Image-source checks of the sequences the rays discovered (`paths.discover_sequences`), and one
echo per image source: the exact specular path of each sequence, its sound or silence."""

import warp as wp

from .common import add_count, lookup
from .paths import HASH_SEED, SURFACE_STEP, TABLE_PROBES, mirror

PLANE_MATCH = wp.constant(2.0e-3)  # [m] how far a validation hit may lie from the image-source reflection point
EDGE_PROBE = wp.constant(1.0e-3)  # [m] probe distance that checks an edge point lies on a face of a plane
PARALLEL_LEG = wp.constant(1.0e-12)  # [m] |normal . leg| below which a leg runs along its plane: no reflection
LEG_SLACK = wp.constant(1.0e-6)  # [fraction of the leg] how far before a leg's start its reflection may lie
RANK_SHIFT = wp.constant(wp.uint64(33))  # [bits] a sequence's rank is its hash >> 33: 31 bits, an int32 >= 0
RANK_NONE = 2**31 - 1  # image rank of an unclaimed slot, where the host starts them (int32 max: no rank is higher)


@wp.func
def plane_face_at(mesh: wp.uint64, point: wp.vec3, front: wp.vec3) -> int:
    """The face of the plane with unit normal `front` (towards the path) that `point` lies on, or
    -1: a probe from EDGE_PROBE in front of it, back along the normal, must hit at that distance."""
    q = wp.mesh_query_ray(mesh, point + front * EDGE_PROBE, -front, 2.0 * EDGE_PROBE)
    if not q.result or wp.abs(q.t - EDGE_PROBE) >= 0.5 * EDGE_PROBE:
        return -1
    return q.face


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
    plane_curved: wp.array[wp.uint8],
    directivity: wp.array[float],
    emit_min_cosine: float,
    # in-out: each slot's plane sequence, replaced by the faces its path reflects off
    table_planes: wp.array3d[wp.int32],
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
    reaches the emitter unoccluded, leaving it at a cosine from its axis of at least
    `emit_min_cosine` (a baffled emitter's: just below 0). Outputs are in the sensor frame: the
    image source [m], the direction the echo arrives from and the last reflection point. The
    amplitude (0 where invalid) is the product of the specular pressure reflection factors
    sqrt(R (1 - s)) along the path, R and s those of the face of each plane the path reflects
    off, times the emitter's directivity towards the path (table over the cosine from its axis,
    -1..1), over the path length. Each reflection's entry of `table_planes` becomes that face once
    it is checked (the planes before it are all a later check reads), so a valid slot's row holds
    the faces of its path in order: what a path's amplitude owes to each surface. Adds its BVH ray
    queries to `ray_queries_out[pose]`. A sequence through a facet of a curved surface
    (`plane_curved`) is left out: `kernels.curved.curved_echoes` reflects off the surface itself.
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
        face = int(-1)
        if distance < PLANE_MATCH:
            # Reflects where the previous reflection did: on the edge where two planes meet (the
            # corner reflector case), if that edge point also lies on a face of this plane.
            face = plane_face_at(mesh, point, normal * side)
            queries += 1
            if face < 0:
                valid = 0
                break
        else:
            direction = (point - x) / distance
            q = wp.mesh_query_ray(mesh, x + direction * SURFACE_STEP, direction, distance + PLANE_MATCH)
            queries += 1
            # The first thing the leg meets must be at the reflection point, on a face of this
            # plane; where two planes meet, the face hit may belong to the other one.
            if not q.result:
                valid = 0
                break
            if wp.abs(q.t + SURFACE_STEP - distance) > PLANE_MATCH:
                valid = 0
                break
            face = q.face
            if face_plane[face] != plane:
                face = plane_face_at(mesh, point, normal * side)
                queries += 1
                if face < 0:
                    valid = 0
                    break
            if back == 0:
                arrival = direction
                last_point = point
            x = point
        gain = gain * wp.sqrt(face_reflection[face] * (1.0 - face_scattering[face]))
        table_planes[p, s, j] = face
    if valid == 1:
        leg = source - x
        distance = wp.length(leg)
        direction = leg / distance
        emit = wp.normalize(wp.transform_vector(inverse, -direction))
        blocked = wp.mesh_query_ray_anyhit(
            mesh, x + direction * SURFACE_STEP, direction, distance - 2.0 * SURFACE_STEP, -1
        )
        queries += 1
        # A baffled emitter (the sensor's y-z plane) sends nothing backwards.
        if not blocked and emit[0] >= emit_min_cosine:
            amplitude_out[p, s] = gain * lookup(directivity, emit[0]) / wp.length(image - receiver)
            image_out[p, s] = wp.transform_point(inverse, image)
            arrival_dir_out[p, s] = wp.normalize(wp.transform_vector(inverse, arrival))
            last_point_out[p, s] = wp.transform_point(inverse, last_point)
    add_count(ray_queries_out, p, queries)


IMAGE_GRID = wp.constant(1.0e-4)  # [m] image sources closer than this are one echo


@wp.func
def mix64(z: wp.uint64) -> wp.uint64:
    """SplitMix64's finaliser: every input bit reaches every output bit."""
    z = (z ^ (z >> wp.uint64(30))) * wp.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> wp.uint64(27))) * wp.uint64(0x94D049BB133111EB)
    return z ^ (z >> wp.uint64(31))


@wp.func
def image_key(order: int, image: wp.vec3) -> wp.uint64:
    """A hash of (order, image rounded to IMAGE_GRID). Each coordinate is mixed in fully: with
    FNV's xor-and-multiply on whole words, (x, y, z) and (-x, -y, z) shared a key for a quarter of
    all cells (the sign's high bits never reach the low ones), so one of two distinct image
    sources mirrored through the sensor's z axis was dropped as the other's duplicate."""
    key = mix64(HASH_SEED ^ wp.uint64(order))
    for k in range(3):
        cell = wp.int64(wp.round(image[k] / IMAGE_GRID))
        key = mix64(key ^ wp.uint64(cell))
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
