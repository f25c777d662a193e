"""Device copies of scenes: one Warp BVH per (scene, device), built once and reused."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import warp as wp

from scenes import Scene


@dataclass
class WarpScene:
    """A scene's mesh and per-face material arrays on one Warp device."""

    mesh: wp.Mesh
    face_lidar_transparent: wp.array  # uint8 (face_count,)
    mesh_hash: int


_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def warp_scene(scene: Scene, device=None) -> WarpScene:
    """The Warp mesh of `scene` on `device`, built on first use and cached.

    The cache is keyed on the Scene object and checked against a hash of its mesh data, so an
    edited mesh is rebuilt rather than silently reused.
    """
    device = wp.get_device(device)
    per_device = _CACHE.setdefault(scene, {})
    mesh_hash = hash(scene.mesh)
    cached = per_device.get(device.alias)
    if cached is not None and cached.mesh_hash == mesh_hash:
        return cached
    vertices = np.ascontiguousarray(scene.mesh.vertices, dtype=np.float32)
    faces = np.ascontiguousarray(scene.mesh.faces, dtype=np.int32).reshape(-1)
    with wp.ScopedDevice(device):
        points = wp.array(vertices, dtype=wp.vec3)
        indices = wp.array(faces, dtype=wp.int32)
        built = WarpScene(
            # SAH: built on the CPU in ~60 ms for 85k triangles, but its tree casts ~35 % more
            # rays/s on an H100 than the LBVH Warp builds on GPUs by default.
            mesh=wp.Mesh(points=points, indices=indices, bvh_constructor="sah"),
            face_lidar_transparent=wp.array(scene.material_table("lidar_transparent").astype(np.uint8), dtype=wp.uint8),
            mesh_hash=mesh_hash,
        )
    per_device[device.alias] = built
    return built
