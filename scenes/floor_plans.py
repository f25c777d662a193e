"""Empty rooms with polygon floor plans (L, T, U, corridor junctions, irregular halls): the random
plans and the extruded room, whose inner wall surfaces lie exactly on the plan's edges."""

from __future__ import annotations

import numpy as np
import trimesh

from .materials import Material
from .scene import Scene, SceneError, assemble, box_mesh

FLOOR_PLANS = ("l_room", "t_room", "u_room", "junction", "hall")
WALL_THICKNESS_M = 0.1


def floor_plan(plan: str, rng: np.random.Generator) -> np.ndarray:
    """A random floor plan of the family `plan`: counter-clockwise corners (N, 2) [m] with the
    lower-left of its extent at the origin, at least ~1.6 m wide everywhere (room for a robot
    with 0.35 m clearance)."""
    u = rng.uniform
    if plan == "l_room":
        w, h = u(5.0, 9.0), u(4.0, 8.0)
        nw, nh = w * u(0.35, 0.6), h * u(0.35, 0.6)
        xy = [(0, 0), (w, 0), (w, h - nh), (w - nw, h - nh), (w - nw, h), (0, h)]
    elif plan == "t_room":
        w, bar, stem, length = u(7.0, 11.0), u(2.0, 3.0), u(2.0, 3.5), u(3.0, 5.0)
        x0 = (w - stem) / 2
        xy = [(x0, 0), (x0 + stem, 0), (x0 + stem, length), (w, length), (w, length + bar), (0, length + bar)]
        xy += [(0, length), (x0, length)]
    elif plan == "u_room":
        w, h, arm = u(7.0, 10.0), u(5.0, 8.0), u(2.0, 3.0)
        depth = h * u(0.4, 0.65)
        xy = [(0, 0), (w, 0), (w, h), (w - arm, h), (w - arm, h - depth), (arm, h - depth), (arm, h), (0, h)]
    elif plan == "junction":  # two corridors crossing, arms of random length
        width = u(1.6, 2.6)
        west, east, south, north = (u(3.0, 6.0) for _ in range(4))
        a, b = west, west + width  # x extent of the north-south corridor
        c, d = south, south + width  # y extent of the east-west corridor
        xy = [(a, 0), (b, 0), (b, c), (b + east, c), (b + east, d), (b, d), (b, d + north), (a, d + north)]
        xy += [(a, d), (0, d), (0, c), (a, c)]
    elif plan == "hall":  # an irregular convex polygon: no two walls parallel by design
        while True:
            count = int(rng.integers(5, 8))
            angle = np.sort(u(0.0, 2 * np.pi, count))
            radius = u(3.0, 5.0, count)
            xy = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)
            if _convex_with_long_walls(xy):
                break
    else:
        raise SceneError(f"unknown floor plan {plan!r}; use one of {FLOOR_PLANS}")
    xy = np.asarray(xy, dtype=np.float64)
    return xy - xy.min(axis=0)


def _convex_with_long_walls(xy: np.ndarray) -> bool:
    edges = np.roll(xy, -1, axis=0) - xy
    following = np.roll(edges, -1, axis=0)
    cross = edges[:, 0] * following[:, 1] - edges[:, 1] * following[:, 0]
    return bool((cross > 0).all() and (np.linalg.norm(edges, axis=1) > 1.5).all())


def polygon_room(
    plan: str = "l_room",
    *,
    corners: np.ndarray | None = None,
    height: float = 3.0,
    wall: str | Material = "painted_wall",
    floor: str | Material = "floor",
    ceiling: str | Material | None = "ceiling_tile",
    seed: int = 0,
) -> Scene:
    """An empty room: a floor plan (drawn from `seed` for the family `plan`, or the given
    counter-clockwise `corners` [m]) extruded to `height` [m], walls built outside the plan so
    their inner faces lie on its edges; `ceiling=None` leaves the room open to the sky."""
    if corners is None:
        corners = floor_plan(plan, np.random.default_rng(seed))
    corners = np.asarray(corners, dtype=np.float64)
    if corners.ndim != 2 or corners.shape[1] != 2 or len(corners) < 3 or not np.isfinite(corners).all():
        raise SceneError(f"corners must be (N >= 3, 2) finite metres, got shape {corners.shape}")
    if not (np.isfinite(height) and height >= 1.0):
        raise SceneError(f"height must be >= 1 m, got {height}")
    edges = np.roll(corners, -1, axis=0) - corners
    if 0.5 * np.sum(corners[:, 0] * np.roll(corners[:, 1], -1) - np.roll(corners[:, 0], -1) * corners[:, 1]) <= 0:
        raise SceneError("corners must run counter-clockwise (the room on their left)")
    before = np.roll(edges, 1, axis=0)  # the edge into each corner
    convex = before[:, 0] * edges[:, 1] - before[:, 1] * edges[:, 0] > 0  # a left turn, going counter-clockwise
    t = WALL_THICKNESS_M
    parts = []
    for i, (a, edge) in enumerate(zip(corners, edges, strict=True)):
        length = float(np.linalg.norm(edge))
        along, out = edge / length, np.array([edge[1], -edge[0]]) / length  # out: away from the room
        # Convex corners get the wall's end extended to close them; reflex ones must not poke into the room.
        start, end = (t if convex[i] else 0.0), (t if convex[(i + 1) % len(corners)] else 0.0)
        centre = a + along * (length + end - start) / 2 + out * t / 2
        yaw = float(np.arctan2(along[1], along[0]))
        parts.append((box_mesh((*centre, height / 2), (length + start + end, t, height), yaw), wall))
    lo, hi = corners.min(axis=0) - t, corners.max(axis=0) + t
    parts.append((_plane(lo, hi, 0.0, up=True), floor))
    if ceiling is not None:
        parts.append((_plane(lo, hi, height, up=False), ceiling))
    params = {"plan": plan, "corners": corners.round(4).tolist(), "height": float(height), "seed": seed}
    return assemble(parts, name="polygon_room", params=params | {"open": ceiling is None})


def _plane(lo: np.ndarray, hi: np.ndarray, z: float, *, up: bool) -> trimesh.Trimesh:
    (x0, y0), (x1, y1) = lo, hi
    vertices = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]]) if up else np.array([[0, 2, 1], [0, 3, 2]])
    return trimesh.Trimesh(vertices, faces, process=False)
