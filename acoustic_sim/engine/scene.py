"""Device copies of scenes: one Warp BVH per (scene, device), built once and reused."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import warp as wp

from scenes import Scene

from ..devices import warp_device
from ..user_warning import warn_user


@dataclass
class WarpScene:
    """A scene's mesh and per-face material arrays on one Warp device."""

    mesh: wp.Mesh
    face_lidar_transparent: wp.array  # uint8 (face_count,)
    lidar_sees_through: bool  # any face transparent to the LiDAR
    face_plane: wp.array  # int32 (face_count,): coplanar faces of one orientation share a plane
    plane_normal: wp.array  # vec3 (plane_count,), unit, as the faces' winding gives
    plane_offset: wp.array  # float (plane_count,): n . x = offset on the plane [m]
    face_reflection: wp.array  # float (face_count,): energy reflection coefficient
    face_scattering: wp.array  # float (face_count,): scattered fraction of the reflected energy
    face_sharp_edges: wp.array  # uint8 (face_count,): bit k set = the edge opposite vertex k is sharp
    face_altitudes: wp.array  # vec3 (face_count,): distance from vertex k to its opposite edge [m]
    plane_curved: wp.array  # uint8 (plane_count,): 1 = a facet of a curved surface, no mirror of its own
    curved: CurvedArrays  # the curved surfaces the facets approximate (`scenes.CurvedSurface`)
    mesh_hash: int
    _lidar_mesh: wp.Mesh | None = None

    @property
    def lidar_mesh(self) -> wp.Mesh:
        """The same triangles in a BVH of LIDAR_BVH_LEAF_SIZE leaves, for the LiDAR's beams (built
        on first use: a scene the LiDAR never scans with many rays costs no second tree)."""
        if self._lidar_mesh is None:
            self._lidar_mesh = wp.Mesh(
                points=self.mesh.points,
                indices=self.mesh.indices,
                bvh_constructor=BVH_CONSTRUCTOR,
                bvh_leaf_size=LIDAR_BVH_LEAF_SIZE,
            )
        return self._lidar_mesh

    @property
    def has_lidar_mesh(self) -> bool:
        return self._lidar_mesh is not None


CURVED_KINDS = ("sphere", "cylinder")  # curved_kind values 0, 1


@dataclass
class CurvedArrays:
    """A scene's curved surfaces on the device, (count,) arrays."""

    kind: wp.array  # int32, index into CURVED_KINDS
    centre: wp.array  # vec3 [m]: sphere centre, or a point on the cylinder's axis
    radius: wp.array  # float [m]
    z_range: wp.array  # vec2 [m]: the cylinder's extent along its axis (axis . x)
    axis: wp.array  # vec3, unit: the cylinder's axis
    gain: wp.array  # float: specular pressure reflection factor sqrt(R (1 - s)) of its material
    face: np.ndarray  # int32, on the host: the face whose material `gain` is (its echoes' `Arrivals.faces`)

    @property
    def count(self) -> int:
        return self.kind.shape[0]


def curved_arrays(scene: Scene) -> dict[str, np.ndarray]:
    """Host arrays of `scene.curved` (see CurvedArrays). Each surface reflects with the material
    most of its faces have (`scene.face_curved` names only a cylinder's side faces, not its caps)."""
    reflection = scene.material_table("acoustic_reflection")
    scattering = scene.material_table("acoustic_scattering")
    gain, chosen = [], []
    for k in range(len(scene.curved)):
        faces = np.flatnonzero(scene.face_curved == k)
        most = np.bincount(scene.face_material[faces]).argmax() if len(faces) else 0
        face = faces[scene.face_material[faces] == most][0] if len(faces) else 0
        gain.append(np.sqrt(reflection[face] * (1.0 - scattering[face])))
        chosen.append(face)
    curved = scene.curved
    return {
        "kind": np.array([CURVED_KINDS.index(c.kind) for c in curved], dtype=np.int32),
        "centre": np.array([c.centre for c in curved], dtype=np.float32).reshape(-1, 3),
        "radius": np.array([c.radius for c in curved], dtype=np.float32),
        "z_range": np.array([c.z_range for c in curved], dtype=np.float32).reshape(-1, 2),
        "axis": np.array([c.axis for c in curved], dtype=np.float32).reshape(-1, 3),
        "gain": np.array(gain, dtype=np.float32),
        "face": np.array(chosen, dtype=np.int32),
    }


def face_planes(scene: Scene, *, tolerance: float = 1e-5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group faces by their plane: (face_plane (F,), plane_normal (P, 3), plane_offset (P,)).

    Faces whose unit normals and offsets agree within `tolerance` (in metres for the offset)
    share a plane, so a wall split into triangles is one mirror for image sources. A facet of a
    curved surface never shares a plane with a flat face (its plane is no mirror: `plane_curved`).
    """
    normals = np.asarray(scene.mesh.face_normals, dtype=np.float64)
    offsets = np.einsum("ij,ij->i", normals, scene.mesh.triangles[:, 0])
    keys = np.rint(np.c_[normals, offsets] / tolerance).astype(np.int64)
    keys = np.c_[keys, scene.face_curved >= 0]
    _, first, face_plane = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return face_plane.reshape(-1).astype(np.int32), normals[first], offsets[first]


def face_edges(scene: Scene, *, sharp_deg: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """Sharp edges of every face: (bitmask (F,) uint8, altitudes (F, 3)).

    Bit k of a face's mask is set when the edge opposite its vertex k is sharp: on the mesh
    boundary, or where the neighbouring face turns by more than `sharp_deg`, unless both faces
    stand for the same curved surface (a seam of its tessellation, not an edge). Altitude k is
    the distance from vertex k to that edge, so a point with barycentric weight b_k lies b_k h_k
    from it.
    """
    mesh = scene.mesh
    count = len(mesh.vertices)
    edge_key = mesh.edges_unique[:, 0].astype(np.int64) * count + mesh.edges_unique[:, 1]
    sharp = np.ones(len(edge_key), dtype=bool)
    pairs = np.sort(mesh.face_adjacency_edges, axis=1).astype(np.int64)
    surface = scene.face_curved[mesh.face_adjacency]
    seam = (surface[:, 0] >= 0) & (surface[:, 0] == surface[:, 1])
    smooth = (mesh.face_adjacency_angles <= np.deg2rad(sharp_deg)) | seam
    order = np.argsort(edge_key)
    found = order[np.searchsorted(edge_key, pairs[smooth, 0] * count + pairs[smooth, 1], sorter=order)]
    sharp[found] = False
    mask = np.zeros(len(mesh.faces), dtype=np.uint8)
    for i in range(3):  # faces_unique_edges[:, i] joins vertices i and i + 1: opposite vertex i + 2
        mask |= (sharp[mesh.faces_unique_edges[:, i]].astype(np.uint8) << ((i + 2) % 3)).astype(np.uint8)
    tri = mesh.triangles
    double_area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    opposite = np.stack([np.linalg.norm(tri[:, (k + 2) % 3] - tri[:, (k + 1) % 3], axis=1) for k in range(3)], axis=1)
    return mask, double_area[:, None] / opposite


# The scenes' BVH: SAH is built on the CPU in ~60 ms for 85k triangles, but its tree casts ~35 %
# more rays/s on an H100 than the LBVH Warp builds on GPUs by default. Leaves of one triangle cast
# 1.15x the LiDAR's rays/s and made 1.05-1.17x the sonar's energyscapes/s on the office
# (benchmarks/results/sonar_cuda_same_job/run7_session25/), but a one-triangle leaf of an
# axis-aligned face is a flat box, whose test can miss a ray aimed exactly at its edge: image-source
# legs aimed at a corner are such rays, and a paper-suite dataset lost or changed echoes in a few
# frames (up to 16 % of a frame's peak; benchmarks/dataset_before_after.py). Four it stays.
BVH_CONSTRUCTOR = "sah"
BVH_LEAF_SIZE = 4  # triangles a leaf holds at most
# A scan of many beams (lidar.OWN_TREE_RAYS) goes through a tree of its own with one-triangle leaves:
# nothing aims them at edges, and they return the same ranges as through the four-triangle tree, to
# float32 rounding (tests/test_lidar.py), at 1.1-1.3x its rays/s (bench_lidar).
LIDAR_BVH_LEAF_SIZE = 1

_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

# Beyond this distance from the origin [m], float32 resolves 61 um or worse: comparable to the
# 0.1 mm the tracer steps off a surface, so rays start inside walls and ranges round coarsely.
FLOAT32_SAFE_M = 512.0


def warn_if_far(coordinates: np.ndarray, what: str) -> None:
    """Warn when `coordinates` [m] reach beyond FLOAT32_SAFE_M, naming the float32 spacing there."""
    coordinates = np.abs(np.asarray(coordinates, dtype=np.float64))
    far = float(coordinates[np.isfinite(coordinates)].max(initial=0.0))  # non-finite ones are refused elsewhere
    if far > FLOAT32_SAFE_M:
        warn_user(
            f"{what} reach {far:,.0f} m from the origin, where float32 (the GPU's precision) resolves only "
            f"{1e3 * float(np.spacing(np.float32(far))):.2g} mm: move them near the origin (subtract a local "
            "reference point) for sub-millimetre ranges"
        )


def warp_scene(scene: Scene, device=None) -> WarpScene:
    """The Warp mesh of `scene` on `device`, built on first use and cached.

    The cache is keyed on the Scene object and checked against a hash of its mesh data, so an
    edited mesh is rebuilt rather than silently reused.
    """
    device = warp_device(device)
    per_device = _CACHE.setdefault(scene, {})
    mesh_hash = hash(scene.mesh)
    cached = per_device.get(device.alias)
    if cached is not None and cached.mesh_hash == mesh_hash:
        return cached
    warn_if_far(scene.mesh.vertices, f"the vertices of {scene.name!r}")
    vertices = np.ascontiguousarray(scene.mesh.vertices, dtype=np.float32)
    faces = np.ascontiguousarray(scene.mesh.faces, dtype=np.int32).reshape(-1)
    face_plane, plane_normal, plane_offset = face_planes(scene)
    sharp_edges, altitudes = face_edges(scene)
    plane_curved = np.zeros(len(plane_offset), dtype=np.uint8)
    plane_curved[face_plane[scene.face_curved >= 0]] = 1
    curved = curved_arrays(scene)
    transparent = scene.material_table("lidar_transparent")
    with wp.ScopedDevice(device):
        points = wp.array(vertices, dtype=wp.vec3)
        indices = wp.array(faces, dtype=wp.int32)
        built = WarpScene(
            mesh=wp.Mesh(points=points, indices=indices, bvh_constructor=BVH_CONSTRUCTOR, bvh_leaf_size=BVH_LEAF_SIZE),
            face_lidar_transparent=wp.array(transparent.astype(np.uint8), dtype=wp.uint8),
            lidar_sees_through=bool(transparent.any()),
            face_plane=wp.array(face_plane, dtype=wp.int32),
            plane_normal=wp.array(plane_normal.astype(np.float32), dtype=wp.vec3),
            plane_offset=wp.array(plane_offset.astype(np.float32), dtype=float),
            face_reflection=wp.array(scene.material_table("acoustic_reflection").astype(np.float32), dtype=float),
            face_scattering=wp.array(scene.material_table("acoustic_scattering").astype(np.float32), dtype=float),
            face_sharp_edges=wp.array(sharp_edges, dtype=wp.uint8),
            face_altitudes=wp.array(altitudes.astype(np.float32), dtype=wp.vec3),
            plane_curved=wp.array(plane_curved, dtype=wp.uint8),
            curved=CurvedArrays(
                kind=wp.array(curved["kind"], dtype=wp.int32),
                centre=wp.array(curved["centre"], dtype=wp.vec3),
                radius=wp.array(curved["radius"], dtype=float),
                z_range=wp.array(curved["z_range"], dtype=wp.vec2),
                axis=wp.array(curved["axis"], dtype=wp.vec3),
                gain=wp.array(curved["gain"], dtype=float),
                face=curved["face"],
            ),
            mesh_hash=mesh_hash,
        )
    per_device[device.alias] = built
    return built
