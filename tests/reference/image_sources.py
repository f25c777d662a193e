"""Image-source method for rooms of planar polygons (float64 numpy), as the independent reference
for the specular path tracer. Classic algorithm (Allen & Berkley; Borish for arbitrary polyhedra):
mirror the source in each plane of a sequence, then validate by walking back from the receiver.
"""

from dataclasses import dataclass
from itertools import product

import numpy as np


@dataclass(frozen=True)
class Plane:
    """A reflecting plane n . x = offset made of one or more convex polygons (each (k, 3)); it
    reflects on the side its normal points to."""

    normal: np.ndarray
    offset: float
    polygons: tuple


def plane_of(polygons) -> Plane:
    first = np.asarray(polygons[0], dtype=np.float64)
    normal = np.cross(first[1] - first[0], first[2] - first[0])
    normal /= np.linalg.norm(normal)
    return Plane(normal, float(normal @ first[0]), tuple(np.asarray(p, dtype=np.float64) for p in polygons))


def inside_convex(point, polygon, normal, tol=1e-7) -> bool:
    """Whether `point` (on the polygon's plane) lies in the convex polygon, boundary included."""
    edges = np.roll(polygon, -1, axis=0) - polygon
    side = np.einsum("ij,ij->i", np.cross(edges, point - polygon), np.broadcast_to(normal, edges.shape))
    return bool(np.all(side >= -tol) or np.all(side <= tol))


def concave_edge(a: Plane, b: Plane, point, tol=1e-9) -> bool:
    """Whether planes a and b meet at `point` in an inside corner: each one's polygon there lies in
    front of the other."""

    def polygon_at(plane):
        return next(poly for poly in plane.polygons if inside_convex(point, poly, plane.normal))

    try:
        ca, cb = polygon_at(a).mean(axis=0), polygon_at(b).mean(axis=0)
    except StopIteration:
        return False
    return bool(a.normal @ (cb - point) >= -tol and b.normal @ (ca - point) >= -tol)


def blocked(a, b, planes, tol=1e-7) -> bool:
    """Whether the open segment a-b passes through any polygon (touching at its ends excluded)."""
    d = b - a
    for plane in planes:
        denom = plane.normal @ d
        if abs(denom) < 1e-15:
            continue
        t = (plane.offset - plane.normal @ a) / denom
        if not tol < t < 1 - tol:
            continue
        point = a + t * d
        if any(inside_convex(point, poly, plane.normal) for poly in plane.polygons):
            return True
    return False


def specular_paths(planes, source, receiver, max_order, leaves=None):
    """All valid specular paths source -> planes -> receiver with 1..max_order reflections, trying
    every plane sequence (planes x (planes - 1) ** (order - 1): up to order 4 or 5;
    `beam_tracing.image_sources` finds the same paths at higher orders).

    Returns a list of (length [m], order, image (3,)), one per distinct image of each order (two
    sequences meeting at an edge between perpendicular planes give one path). `leaves(direction)`
    may reject paths by their direction at the source (e.g. a baffled emitter).
    """
    found = {}
    for order in range(1, max_order + 1):
        for seq in product(range(len(planes)), repeat=order):
            if any(seq[i] == seq[i + 1] for i in range(order - 1)):
                continue
            images = [np.asarray(source, dtype=np.float64)]
            for k in seq:
                p = planes[k]
                images.append(images[-1] - 2 * (p.normal @ images[-1] - p.offset) * p.normal)
            x, ok, points = np.asarray(receiver, dtype=np.float64), True, []
            for j in range(order, 0, -1):
                p = planes[seq[j - 1]]
                leg = images[j] - x
                denom = p.normal @ leg
                if abs(denom) < 1e-15:
                    ok = False
                    break
                t = (p.offset - p.normal @ x) / denom
                if not -1e-9 <= t < 1:
                    ok = False
                    break
                point = x + max(t, 0.0) * leg
                if not any(inside_convex(point, poly, p.normal) for poly in p.polygons):
                    ok = False
                    break
                # Walls reflect on their front (room) side only: the path must come from there.
                toward = x if np.linalg.norm(x - point) > 1e-9 else images[j - 1]
                if p.normal @ (toward - point) < -1e-9:
                    ok = False
                    break
                if j < order and np.linalg.norm(x - point) <= 1e-9 and not concave_edge(p, planes[seq[j]], point):
                    ok = False  # two reflections at one edge point happen in inside corners only
                    break
                if np.linalg.norm(point - x) > 1e-9 and blocked(x, point, planes):
                    ok = False
                    break
                points.append(point)
                x = point
            if not ok or blocked(x, np.asarray(source, dtype=np.float64), planes):
                continue
            if leaves is not None and not leaves(x - source):
                continue
            key = (order, *np.round(images[-1], 6))
            found.setdefault(key, (float(np.linalg.norm(images[-1] - receiver)), order, images[-1]))
    return sorted(found.values(), key=lambda v: (round(v[0], 6), v[1]))


def shoebox_images(size, source, receiver, max_order, leaves=None):
    """Image sources of `source` in the box [0, size] (closed form) with 1..max_order reflections.

    Along axis i an image lies at 2 n L_i + (1 - 2 q) s_i (n integer, q in {0, 1}) after
    |2 n - q| reflections on that axis' walls; a path leaves the source along its arrival
    direction with each axis flipped once per reflection on it. In a box every image is valid
    and audible. Returns a list of (length [m], order, image (3,)) as `specular_paths` does.
    """
    size, source = np.asarray(size, dtype=np.float64), np.asarray(source, dtype=np.float64)
    receiver = np.asarray(receiver, dtype=np.float64)
    span = np.arange(-max_order, max_order + 1)
    n = np.stack(np.meshgrid(span, span, span, indexing="ij"), axis=-1).reshape(-1, 1, 3)
    q = np.array(list(product((0, 1), repeat=3)))[None]
    n, q = (np.broadcast_to(a, (len(n), 8, 3)).reshape(-1, 3) for a in (n, q))
    counts = np.abs(2 * n - q)
    keep = (counts.sum(axis=1) >= 1) & (counts.sum(axis=1) <= max_order)
    images = 2 * n[keep] * size + (1 - 2 * q[keep]) * source
    found = []
    for image, count in zip(images, counts[keep], strict=True):
        if leaves is None or leaves((receiver - image) * (-1.0) ** count):
            found.append((float(np.linalg.norm(image - receiver)), int(count.sum()), image))
    return sorted(found, key=lambda v: (round(v[0], 6), v[1]))


def box_planes(size):
    """The walls, floor and ceiling of the box [0, size] as planes with normals into the box."""
    planes = []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for at, sign in ((0.0, 1.0), (size[axis], -1.0)):
            corners = []
            for a, b in ((0, 0), (1, 0), (1, 1), (0, 1)):
                corner = np.zeros(3)
                corner[axis], corner[u], corner[v] = at, a * size[u], b * size[v]
                corners.append(corner)
            planes.append(plane_of([corners if sign > 0 else corners[::-1]]))
    return planes


def l_room(height=3.0):
    """Closed L-shaped room: the 6 x 5 m rectangle minus the notch [3, 6] x [2, 5], `height` m high.

    Returns the planes (walls, floor, ceiling; floor and ceiling each two rectangles) with normals
    pointing into the room.
    """
    outline = np.array([[0, 0], [6, 0], [6, 2], [3, 2], [3, 5], [0, 5]], dtype=np.float64)
    planes = []
    for a, b in zip(outline, np.roll(outline, -1, axis=0), strict=True):
        quad = [[*a, 0], [*a, height], [*b, height], [*b, 0]]  # counter-clockwise outline: normal inwards
        planes.append(plane_of([quad]))
    rects = [((0, 0), (6, 2)), ((0, 2), (3, 5))]
    floor = [[[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]] for (x0, y0), (x1, y1) in rects]
    ceiling = [[[x0, y0, height], [x0, y1, height], [x1, y1, height], [x1, y0, height]] for (x0, y0), (x1, y1) in rects]
    planes.append(plane_of(floor))
    planes.append(plane_of(ceiling))
    return planes


def planes_mesh(planes):
    """The planes' polygons as one triangle mesh (vertices (V, 3), faces (F, 3)), fan-triangulated."""
    vertices, faces = [], []
    for plane in planes:
        for poly in plane.polygons:
            base = len(vertices)
            vertices.extend(poly)
            faces.extend([base, base + i, base + i + 1] for i in range(1, len(poly) - 1))
    return np.array(vertices), np.array(faces)
