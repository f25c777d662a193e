"""Image sources of high order in rooms of planar polygons (float64 numpy): beam tracing proposes
image sources, a walk back from the receiver keeps those with a valid, unoccluded path. The
reference for specular paths of orders beyond what trying every plane sequence can reach
(`image_sources.specular_paths`).
"""

import numpy as np

from .image_sources import concave_edge

SLACK_M = 1e-6  # [m] how far outside a beam a polygon may lie and still count as inside it
SAME_M = 1e-6  # [m] image sources (and the source) closer than this are one point


class Polygons:
    """The planes' polygons stacked for vectorised segment tests (P polygons of at most m
    vertices; shorter ones repeat their last vertex): owning plane (P,), unit normals (P, 3),
    offsets (P,), and per edge the in-plane inward normal (P, m, 3) and its offset (P, m)."""

    def __init__(self, planes):
        self.planes = planes
        pairs = [(k, poly) for k, plane in enumerate(planes) for poly in plane.polygons]
        most = max(len(poly) for _, poly in pairs)
        vertices = np.array([np.vstack([poly, np.repeat(poly[-1:], most - len(poly), axis=0)]) for _, poly in pairs])
        self.owner = np.array([k for k, _ in pairs])
        self.normal = np.array([planes[k].normal for k in self.owner])
        self.offset = np.array([planes[k].offset for k in self.owner])
        # (edge x (point - vertex)) . normal = (normal x edge) . point - (normal x edge) . vertex
        self.edge_normal = np.cross(self.normal[:, None], np.roll(vertices, -1, axis=1) - vertices)
        self.edge_offset = np.einsum("pmi,pmi->pm", self.edge_normal, vertices)

    def _inside(self, points, which, tol=1e-7):
        """Whether points (n, 3), each on the plane of polygon which[i], lie inside it (boundary
        included), (n,)."""
        side = np.einsum("pmi,pi->pm", self.edge_normal[which], points) - self.edge_offset[which]
        return (side >= -tol).all(axis=1) | (side <= tol).all(axis=1)

    def holding(self, point):
        """Planes with a polygon that holds `point` (on its plane within 1e-9 m)."""
        on = np.flatnonzero(np.abs(self.normal @ point - self.offset) < 1e-9)
        return set(self.owner[on[self._inside(np.broadcast_to(point, (len(on), 3)), on)]].tolist())

    def crossings(self, a, b, tol=1e-7):
        """(t, plane index) of every polygon the open segment a + t (b - a), tol < t < 1 - tol,
        passes through, nearest first."""
        denom = self.normal @ (b - a)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.offset - self.normal @ a) / denom
        near = np.flatnonzero((np.abs(denom) >= 1e-15) & (tol < t) & (t < 1 - tol))
        near = near[self._inside(a + t[near, None] * (b - a), near)]
        near = near[np.argsort(t[near], kind="stable")]
        return list(zip(t[near].tolist(), self.owner[near].tolist(), strict=True))


def mirror(point, plane):
    return point - 2 * (plane.normal @ point - plane.offset) * plane.normal


def clip(polygon, normals, offsets):
    """The part of convex polygon (k, 3) where normals . x >= offsets - SLACK_M for every half-space
    (normals (c, 3), offsets (c,)), by Sutherland-Hodgman; (0, 3) if none."""
    for normal, offset in zip(normals, offsets, strict=True):
        inside = polygon @ normal - offset + SLACK_M
        if inside.min() >= 0:
            continue
        if inside.max() < 0:
            return polygon[:0]
        after = np.concatenate((inside[1:], inside[:1]))
        crossing = (inside >= 0) != (after >= 0)
        share = inside / np.where(crossing, inside - after, 1.0)
        # Each vertex inside, then where its edge crosses the boundary: (k, 2) in polygon order.
        edges = np.concatenate((polygon[1:], polygon[:1])) - polygon
        points = np.concatenate((polygon, polygon + edges * share[:, None]), axis=1).reshape(-1, 3)
        polygon = points[np.column_stack((inside >= 0, crossing)).ravel()]
    return polygon


def hull_on_plane(points, normal):
    """Convex hull (m, 3), in order, of points lying on the plane with unit `normal` (m = 2 if they
    lie on a line)."""
    flat = np.delete(points, np.argmax(np.abs(normal)), axis=1).tolist()  # a projection keeps the hull
    order = sorted(range(len(points)), key=lambda i: flat[i])

    def half(indices):  # Andrew's monotone chain
        chain = []
        for i in indices:
            while len(chain) >= 2:
                (ax, ay), (bx, by), (cx, cy) = flat[chain[-2]], flat[chain[-1]], flat[i]
                if (bx - ax) * (cy - ay) - (by - ay) * (cx - ax) > 0:  # no tolerance: it could drop a corner
                    break
                chain.pop()
            chain.append(i)
        return chain[:-1]

    ring = half(order) + half(order[::-1])
    return points[ring] if len(ring) >= 3 else points[[order[0], order[-1]]]


def beam_cuts(apex, window, plane):
    """Half-spaces (normals (c, 3), offsets (c,)) bounding the beam from `apex` through convex
    `window` (k, 3) on `plane`, beyond it: the window's plane, and one plane through the apex per
    window edge. An edge whose plane does not keep the whole window on one side (a tiny edge of
    rounding noise) gives no cut: a cut left out only widens the beam."""
    a = window - apex
    b = np.concatenate((a[1:], a[:1]))
    normals = np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=1,
    )
    size = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    normals = normals[size > 0] / size[size > 0, None]
    side = a @ normals.T  # (window vertices, cuts)
    inwards, outwards = (side >= -SLACK_M).all(axis=0), (side <= SLACK_M).all(axis=0)
    # A degenerate window (a segment) keeps both sides of its edge: a thin slab.
    normals = np.vstack([plane.normal, normals[inwards], -normals[outwards & ~inwards]])
    return normals, np.r_[plane.offset, normals[1:] @ apex]


def beam_images(planes, source, max_order, forward=None, receiver=None):
    """Image sources (order, image (3,)) of 1..max_order reflections that a specular path from
    `source` may have: beam tracing (Heckbert and Hanrahan; Funkhouser et al.) without occlusion.

    A beam is an image source, the plane it was mirrored in last and its window there, the part
    of that plane's polygons the path can pass through. A child beam reflects in another plane
    whose polygons the beam reaches beyond the window (from their front); its window is the
    convex hull of what it reaches. Beams of one order with the same image and last plane (plane
    sequences that differ in the order of commuting reflections) merge, their windows hulled
    together. Hulls, merging, a SLACK_M margin and no occluders only widen beams, so every valid
    path's image is among those returned (`walk_back` checks each). `forward` (3,): only paths
    leaving the source into that half-space (a baffled emitter). `receiver` (3,): only images
    whose beam reaches it (a path's last leg runs inside its beam).
    """
    source = np.asarray(source, dtype=np.float64)
    polygons = [(k, poly) for k, plane in enumerate(planes) for poly in plane.polygons]
    vertices = np.concatenate([poly for _, poly in polygons])
    starts = np.cumsum([0] + [len(poly) for _, poly in polygons[:-1]])
    owner = np.array([k for k, _ in polygons])
    normals = np.array([plane.normal for plane in planes])
    offsets = np.array([plane.offset for plane in planes])
    cuts = (np.reshape(forward, (1, 3)), np.array([forward @ source])) if forward is not None else None
    beams, found = [(source, -1, cuts)], []
    for order in range(1, max_order + 1):
        children = {}  # (plane, image rounded) -> (image, [parts of the plane's polygons reached])
        for image, last, cuts in beams:
            usable = (normals[owner] @ image - offsets[owner] >= -SLACK_M) & (owner != last)
            cutting = np.zeros((len(polygons), 0), dtype=bool)  # (polygon, cut): cuts some of it off
            if cuts is not None:
                side = vertices @ cuts[0].T - cuts[1] + SLACK_M
                usable &= (np.maximum.reduceat(side, starts, axis=0) >= 0).all(axis=1)
                cutting = np.minimum.reduceat(side, starts, axis=0) < 0
            for i in np.flatnonzero(usable):
                part = polygons[i][1]
                if cutting[i].any():  # (a cut that keeps every vertex keeps all of the clipped part)
                    part = clip(part, cuts[0][cutting[i]], cuts[1][cutting[i]])
                if len(part):
                    k = owner[i]
                    apex = mirror(image, planes[k])
                    key = (k, *np.round(apex / SAME_M).astype(np.int64))
                    children.setdefault(key, (apex, []))[1].append(part)
        beams = []
        for (k, *_), (apex, parts) in children.items():
            cuts = beam_cuts(apex, hull_on_plane(np.concatenate(parts), planes[k].normal), planes[k])
            if receiver is None or np.all(cuts[0] @ receiver - cuts[1] >= -SLACK_M):
                found.append((order, apex))
            beams.append((apex, k, cuts))
    return found


def walk_back(polygons, image, order, source, receiver):
    """The direction (3,) a valid specular path with `order` reflections and image source `image`
    leaves `source` in, or None if there is no such path (`polygons`: the room's `Polygons`).

    From the receiver towards the image, the first polygon met (from its front) is where the path
    reflected last: mirror the image in its plane there and go on; after `order` reflections the
    image must be the source, reached unoccluded. Where a leg meets planes at one point (an edge),
    each is tried first; a second reflection at the same point only in an inside corner.
    """
    planes = polygons.planes

    def step(x, target, left, last):
        if left == 0:
            done = np.linalg.norm(target - source) < SAME_M and not polygons.crossings(x, source)
            return x - source if done else None
        options = []
        if last is not None:  # reflect again where the path just did: the corner of two planes
            for k in polygons.holding(x) - {last}:
                turned = mirror(target, planes[k])
                if concave_edge(planes[last], planes[k], x) and planes[k].normal @ (turned - x) >= -1e-9:
                    options.append((k, x))
        met = polygons.crossings(x, target)
        for t, k in met:
            point = x + t * (target - x)
            if t - met[0][0] < 1e-9 and planes[k].normal @ (x - point) >= -1e-9:
                options.append((k, point))
        for k, point in options:
            leaves = step(point, mirror(target, planes[k]), left - 1, k)
            if leaves is not None:
                return leaves
        return None

    return step(receiver, image, order, None)


def image_sources(planes, source, receiver, max_order, forward=None):
    """All valid specular paths source -> planes -> receiver with 1..max_order reflections:
    `beam_images` proposes, `walk_back` checks. `forward` (3,): the source radiates into that
    half-space only (a baffled emitter).

    Returns a list of (length [m], order, image (3,)) as `image_sources.specular_paths` does.
    """
    source, receiver = np.asarray(source, dtype=np.float64), np.asarray(receiver, dtype=np.float64)
    polygons = Polygons(planes)
    # One image may end beams of different last planes: check it once.
    candidates = {
        (order, *np.round(image / SAME_M).astype(np.int64)): (order, image)
        for order, image in beam_images(planes, source, max_order, forward, receiver)
    }
    found = []
    for order, image in candidates.values():
        leaves = walk_back(polygons, image, order, source, receiver)
        if leaves is not None and (forward is None or forward @ leaves >= -1e-6 * np.linalg.norm(leaves)):
            found.append((float(np.linalg.norm(image - receiver)), order, image))
    return sorted(found, key=lambda v: (round(v[0], 6), v[1]))
