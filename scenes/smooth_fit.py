"""Round surfaces behind the facets of a loaded mesh: spheres and cylinders fitted on import.

A tessellated ball or pole has almost no facet that faces the sensor, so rays find its specular
echo only by luck; a `CurvedSurface` lets the tracer reflect off the true surface instead. The
builders know their round parts; for any other mesh (`from_mesh`) this module finds them:

1. Smooth patches: faces joined by edges where the surface turns by less than `crease_deg`
   (default 30 deg). So a prism of 13 or more sides is round, and one of 12 or fewer (a hexagonal
   column, an octagonal leg) is faceted on purpose and keeps its flat mirrors; an icosphere of one
   subdivision or more (22 deg) is round, an icosahedron (42 deg) is not.
2. A patch whose face normals all lie square to one direction is fitted as a cylinder around it,
   one whose normals spread in all directions as a sphere (least squares on its vertices).
3. The fit is kept only where it is tight and whole: every vertex within min(1 % of the radius,
   0.2 mm) of the surface; every face facing away from the centre or axis (convex: the inside of a
   round room or tank stays faceted, the tracer reflects only off the outside); the patch closing
   all the way round (a cylinder's side around its axis, a sphere in every direction), since the
   tracer reflects off the whole surface and part of one would echo from where nothing is.
4. Only objects: a radius above MAX_RADIUS_M (1 m) is not fitted. A round room, tank, silo or
   large pipe that a robot drives inside, modelled with its normals outward (as a Blender or
   `trimesh.creation` cylinder used as a room is), passes the convexity check, and fitted as a
   solid it would put the sensor inside it, where no echo is solved: its walls would go silent.
   Left faceted, its wide facets echo as flat mirrors, as they do for the inside of such a room.

Flat faces, sharp edges and every other shape (cones, tori, capsules, half pillars, fillets
joined smoothly to flat faces) stay as they are: faceted mirrors, as before.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .scene import CurvedSurface

CREASE_DEG = 30.0  # an edge turning this much or more is a crease: the faces on each side are not one round surface
FIT_RELATIVE = 0.01  # the most a vertex may lie off a fitted surface, as a fraction of its radius ...
FIT_ABSOLUTE_M = 2e-4  # ... and in metres: the echo's round trip errs by at most twice this (half a sample at 450 kHz)
CYLINDER_SPREAD = 0.05  # normals of a cylinder keep < 5 % of their weight along its axis (a sphere's: 1/3 each way)
ROUND_SPREAD = 0.1  # normals with < 10 % of their weight off one direction (flat, gently bent) close round nothing
MAX_RADIUS_M = 1.0  # round pillars, poles, pipes, balls are smaller; a round room or tank (seen from inside) larger
AXIS_SNAP = 1e-6  # an axis this close [rad] to x, y or z is taken as exactly that (vertical poles stay vertical)
_DIRECTIONS = 256  # directions a sphere's faces must all face within the crease angle


def fit_curved_surfaces(
    mesh: trimesh.Trimesh, *, crease_deg: float = CREASE_DEG
) -> tuple[list[CurvedSurface], np.ndarray]:
    """The spheres and cylinders that the smooth patches of `mesh` approximate.

    Args:
        mesh: Triangle mesh [m]; duplicate vertices (as OBJ files split them) are welded here to
            find which faces meet, the mesh itself is not changed.
        crease_deg: Faces meeting at an edge that turns less than this [deg] belong to one patch.

    Returns:
        The fitted surfaces, and for every face the index of its surface or -1 (flat, creased or
        not fitted), int32 shape (face_count,).
    """
    face_count = len(mesh.faces)
    face_surface = np.full(face_count, -1, dtype=np.int32)
    welded = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    welded.merge_vertices()  # keeps the order of the faces
    pairs = welded.face_adjacency[welded.face_adjacency_angles < np.deg2rad(crease_deg) - 1e-9]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(face_count, face_count))
    patch_count, patch = connected_components(graph, directed=False)
    # Plain arrays: trimesh checks each cached property against a hash of the whole mesh per access.
    faces = _Faces(welded.vertices, welded.faces, welded.face_normals, welded.area_faces, welded.triangles_center)
    by_patch = np.argsort(patch, kind="stable")
    starts = np.searchsorted(patch[by_patch], np.arange(patch_count + 1))
    surfaces: list[CurvedSurface] = []
    for candidate in _round_candidates(faces, patch, patch_count):
        members = by_patch[starts[candidate] : starts[candidate + 1]]
        surface = _fit_patch(faces, members, np.deg2rad(crease_deg))
        if surface is not None:
            face_surface[members] = len(surfaces)
            surfaces.append(surface)
    return surfaces, face_surface


class _Faces(NamedTuple):
    """A welded mesh as plain arrays [m]."""

    vertices: np.ndarray  # (V, 3)
    corners: np.ndarray  # (F, 3) vertex indices
    normals: np.ndarray  # (F, 3) unit
    areas: np.ndarray  # (F,) [m^2]
    centroids: np.ndarray  # (F, 3)


def _round_candidates(faces: _Faces, patch: np.ndarray, patch_count: int) -> np.ndarray:
    """Patches whose normals spread over more than one plane: only they can close around a centre
    or an axis (walls, box faces and every flat patch drop out here, in one array operation)."""
    scatter = np.zeros((patch_count, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            scatter[:, i, j] = scatter[:, j, i] = np.bincount(
                patch, weights=faces.areas * faces.normals[:, i] * faces.normals[:, j], minlength=patch_count
            )
    total = np.bincount(patch, weights=faces.areas, minlength=patch_count)
    middle = np.linalg.eigvalsh(scatter)[:, 1] / np.maximum(total, np.finfo(float).tiny)
    return np.flatnonzero(middle > ROUND_SPREAD)


def _fit_patch(faces: _Faces, members: np.ndarray, crease: float) -> CurvedSurface | None:
    """A sphere or cylinder that the faces `members` tightly and wholly approximate, or None."""
    normals = faces.normals[members]
    weight = faces.areas[members]
    spread, directions = np.linalg.eigh(np.einsum("f,fi,fj->ij", weight, normals, normals) / weight.sum())
    points = faces.vertices[np.unique(faces.corners[members])]
    centroids = faces.centroids[members]
    if spread[0] < CYLINDER_SPREAD:
        surface = _fit_cylinder(points, centroids, normals, _canonical_axis(directions[:, 0]), crease)
    else:
        surface = _fit_sphere(points, centroids, normals, crease)
    if surface is not None and surface.radius > MAX_RADIUS_M + FIT_ABSOLUTE_M:  # (a unit sphere is 1 m, within the fit)
        return None  # a room or tank to drive inside, whatever way its normals face: its facets stay mirrors
    return surface


def _fit_sphere(points: np.ndarray, centroids: np.ndarray, normals: np.ndarray, crease: float) -> CurvedSurface | None:
    centre, radius = _fit_round(points)
    distance = np.linalg.norm(points - centre, axis=1)
    outward = centroids - centre
    if not _tight(distance, radius) or not (np.einsum("fi,fi->f", normals, outward) > 0).all():
        return None
    gap, _ = cKDTree(normals).query(_fibonacci_sphere(_DIRECTIONS))  # chord to the nearest face normal
    if gap.max() > 2 * np.sin(crease / 2):
        return None  # a part of a sphere (a dome, a cap): some directions have no face within the crease angle
    return CurvedSurface("sphere", tuple(float(c) for c in centre), float(distance.max()))


def _fit_cylinder(
    points: np.ndarray, centroids: np.ndarray, normals: np.ndarray, axis: np.ndarray, crease: float
) -> CurvedSurface | None:
    across = _basis_across(axis)  # (2, 3): two unit vectors square to the axis
    circle_centre, radius = _fit_round(points @ across.T)
    distance = np.linalg.norm(points @ across.T - circle_centre, axis=1)
    outward = centroids @ across.T - circle_centre
    flat_normals = normals @ across.T
    if not _tight(distance, radius) or not (np.einsum("fi,fi->f", flat_normals, outward) > 0).all():
        return None
    azimuth = np.sort(np.arctan2(flat_normals[:, 1], flat_normals[:, 0]))
    if np.diff(azimuth, append=azimuth[0] + 2 * np.pi).max() >= crease:
        return None  # an arc, not all the way round (a half pillar against a wall, a rounded corner)
    height = points @ axis
    centre = circle_centre @ across + height.min() * axis
    return CurvedSurface(
        "cylinder",
        tuple(float(c) for c in centre),
        float(distance.max()),
        (float(height.min()), float(height.max())),
        tuple(float(c) for c in axis),
    )


def _fit_round(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares circle (2D points) or sphere (3D): |p - c|^2 = r^2 is linear in c and
    r^2 - |c|^2 (Kasa's fit); about the points' mean for conditioning. Returns (centre, radius)."""
    mean = points.mean(axis=0)
    local = points - mean
    system = np.c_[2 * local, np.ones(len(local))]
    solution = np.linalg.lstsq(system, (local * local).sum(axis=1), rcond=None)[0]
    centre = solution[:-1]
    return mean + centre, float(np.sqrt(max(solution[-1] + centre @ centre, 0.0)))


def _tight(distance: np.ndarray, radius: float) -> bool:
    """Every vertex near the fitted surface. The surface kept is the one through the outermost
    vertex, so no facet stands in front of it (the tracer checks both legs of the echo for
    occlusion from just above the surface, as for the builders' parts, whose facets are chords)."""
    return radius > 0 and np.abs(distance - radius).max() <= min(FIT_RELATIVE * radius, FIT_ABSOLUTE_M)


def _canonical_axis(axis: np.ndarray) -> np.ndarray:
    """`axis` with its largest component positive (a vertical axis points up), snapped onto x, y
    or z when within AXIS_SNAP of it."""
    largest = int(np.argmax(np.abs(axis)))
    axis = axis * np.sign(axis[largest])
    if np.linalg.norm(np.delete(axis, largest)) < AXIS_SNAP:
        axis = np.eye(3)[largest]
    return axis / np.linalg.norm(axis)


def _basis_across(axis: np.ndarray) -> np.ndarray:
    """Two orthonormal vectors square to the unit `axis`, shape (2, 3); for z they are x and y."""
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))] if abs(axis[2]) < 1 else np.array([1.0, 0.0, 0.0])
    first = helper - (helper @ axis) * axis
    first /= np.linalg.norm(first)
    return np.stack([first, np.cross(axis, first)])


def _fibonacci_sphere(count: int) -> np.ndarray:
    """`count` unit vectors spread evenly over the sphere, shape (count, 3)."""
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    phi = np.pi * (1 + 5**0.5) * k
    ring = np.sqrt(1 - z * z)
    return np.c_[ring * np.cos(phi), ring * np.sin(phi), z]
