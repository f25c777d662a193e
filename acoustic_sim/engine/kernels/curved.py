"""Specular echoes off curved surfaces (spheres, cylinders): solved on the surface itself."""

import warp as wp

from .common import add_count, lookup
from .paths import SURFACE_STEP

CURVED_SPHERE = wp.constant(0)  # curved surface kinds, as acoustic_sim.engine.scene.CURVED_KINDS
CURVED_STEPS = wp.constant(24)  # fixed-point steps towards a curved surface's reflection point


@wp.func
def bisecting_normal(centre: wp.vec3, radius: float, a: wp.vec3, b: wp.vec3) -> wp.vec3:
    """Unit normal of the point of a sphere (or, with centre, a and b in one plane through the
    origin, a circle) where a path from a to b reflects: there the normal bisects the directions
    to a and b. From the bisector seen from the centre, damped fixed-point steps: a plain step
    overshoots by about radius / h (h the distance to the surface) and diverges once h < radius;
    dividing the step by 1 + that gain (a Newton step on the linearised map) converges for every
    a, b outside the surface."""
    n = wp.normalize(wp.normalize(a - centre) + wp.normalize(b - centre))
    for _step in range(CURVED_STEPS):
        point = centre + radius * n
        to_a = a - point
        to_b = b - point
        da = wp.length(to_a)
        db = wp.length(to_b)
        to_a = to_a / da
        to_b = to_b / db
        gain = wp.max(0.5 * radius * (wp.dot(n, to_a) / da + wp.dot(n, to_b) / db), 0.0)
        n = wp.normalize(n + (wp.normalize(to_a + to_b) - n) / (1.0 + gain))
    return n


@wp.func
def reflected_radius(incident: float, added_curvature: float) -> float:
    """Radius of curvature of a wavefront from `incident` [m] away just after a reflection that
    adds `added_curvature` [1/m] in one principal direction (geometric optics)."""
    return 1.0 / (1.0 / incident + added_curvature)


@wp.kernel(enable_backward=False)
def curved_echoes(
    # in
    mesh: wp.uint64,
    kind: wp.array[wp.int32],
    centre: wp.array[wp.vec3],
    radius: wp.array[float],
    z_range: wp.array[wp.vec2],
    axis: wp.array[wp.vec3],
    gain: wp.array[float],
    poses: wp.array[wp.mat44],
    inverse_poses: wp.array[wp.mat44],
    emitter: wp.vec3,
    directivity: wp.array[float],
    emit_min_cosine: float,
    # out
    source_out: wp.array2d[wp.vec3],
    extra_out: wp.array2d[float],
    amplitude_out: wp.array2d[float],
    order_out: wp.array2d[wp.int32],
    ray_queries_out: wp.array[wp.int32],
):
    """First-order specular echo off each curved surface (sphere or cylinder) for each ping;
    dim = (pings, surfaces). Rays would find it only where a facet happens to face the sensor;
    here the reflection point is solved on the surface itself (for a cylinder in the plane square
    to its axis, its place along the axis from the unfolded path), both legs are checked
    unoccluded, and the amplitude follows geometric optics: sqrt(R (1 - s)) times the emitter's
    directivity times (1 / d1) sqrt(rho1 rho2 / ((rho1 + d2) (rho2 + d2))), with d1, d2 the legs
    and rho1, rho2 the reflected wavefront's principal radii (a sphere bends it in both directions, a cylinder only
    across its axis, for any incidence; a plane would give 1 / (d1 + d2)). Writes the reflection
    point (sensor frame) as the echo's source and d1 as the path before it, like a scattered
    arrival; order 1.
    """
    p, c = wp.tid()
    amplitude_out[p, c] = 0.0
    order_out[p, c] = 1
    pose = poses[p]
    inverse = inverse_poses[p]
    e = wp.transform_point(pose, emitter)
    r = wp.transform_point(pose, wp.vec3(0.0))
    o = centre[c]
    a = radius[c]
    sphere = kind[c] == CURVED_SPHERE
    if sphere:
        if wp.length(e - o) <= a or wp.length(r - o) <= a:
            return
        n = bisecting_normal(o, a, e, r)
        point = o + a * n
    else:
        u = axis[c]  # for a vertical axis (0, 0, 1) every product below is exact: x, y kept, z dropped
        e_along = wp.dot(e, u)
        r_along = wp.dot(r, u)
        flat_o = o - wp.dot(o, u) * u
        flat_e = e - e_along * u
        flat_r = r - r_along * u
        if wp.length(flat_e - flat_o) <= a or wp.length(flat_r - flat_o) <= a:
            return
        n = bisecting_normal(flat_o, a, flat_e, flat_r)
        foot = flat_o + a * n
        to_e = wp.length(flat_e - foot)
        z = e_along + (r_along - e_along) * to_e / (to_e + wp.length(flat_r - foot))
        if z <= z_range[c][0] or z >= z_range[c][1]:
            return
        point = foot + z * u
    d1 = wp.length(e - point)
    d2 = wp.length(r - point)
    cosine = wp.dot(n, e - point) / d1
    if cosine <= 0.0 or wp.dot(n, r - point) <= 0.0:
        return
    start = point + n * SURFACE_STEP
    queries = int(1)
    blocked = wp.mesh_query_ray_anyhit(mesh, start, wp.normalize(e - start), wp.length(e - start), -1)
    if not blocked:
        queries += 1
        blocked = wp.mesh_query_ray_anyhit(mesh, start, wp.normalize(r - start), wp.length(r - start), -1)
    add_count(ray_queries_out, p, queries)
    emit = wp.normalize(wp.transform_vector(inverse, point - e))
    if blocked or emit[0] < emit_min_cosine:  # a baffled emitter sends nothing backwards
        return
    if sphere:  # bends the front by 2 / (a cos) in the plane of incidence, 2 cos / a across it
        rho_1 = reflected_radius(d1, 2.0 / (a * cosine))
        rho_2 = reflected_radius(d1, 2.0 * cosine / a)
    else:
        # Curved only across its axis (tangent t): one principal direction gains 2/a weighted by
        # how t lies to the plane of incidence (cos phi), the other keeps the incident 1 / d1.
        tangent = wp.normalize(wp.cross(axis[c], n))
        incident = (point - e) / d1
        along = incident - wp.dot(incident, n) * n  # the plane of incidence's tangent direction
        cos_phi = float(1.0)
        if wp.length(along) > 1.0e-6:
            cos_phi = wp.dot(wp.normalize(along), tangent)
        sin2 = 1.0 - cos_phi * cos_phi
        rho_1 = reflected_radius(d1, 2.0 / a * (cos_phi * cos_phi / cosine + cosine * sin2))
        rho_2 = d1
    spreading = wp.sqrt(rho_1 * rho_2 / ((rho_1 + d2) * (rho_2 + d2))) / d1
    amplitude_out[p, c] = gain[c] * lookup(directivity, emit[0]) * spreading
    source_out[p, c] = wp.transform_point(inverse, point)
    extra_out[p, c] = d1
