"""Independent ray-cast reference: Open3D's RaycastingScene (Intel Embree), float32 on the CPU.

Where Open3D is not installed (the GPU machine), embreex, a second Embree binding, stands in.
"""

import numpy as np

try:
    import open3d as o3d
except ImportError:
    o3d = None


def first_hits(vertices: np.ndarray, faces: np.ndarray, origins: np.ndarray, dirs: np.ndarray):
    """Distance to the first face hit along unit rays; inf on a miss. Returns (t (N,), face (N,))."""
    if o3d is None:
        return _first_hits_embreex(vertices, faces, origins, dirs)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(vertices, np.float32)), o3d.core.Tensor(np.asarray(faces, np.uint32))
    )
    rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(np.float64)
    face = hit["primitive_ids"].numpy().astype(np.int64)
    face[~np.isfinite(t)] = -1
    return t, face


def _first_hits_embreex(vertices, faces, origins, dirs):
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.asarray(vertices, np.float32)[np.asarray(faces)])
    out = scene.run(np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(dirs, np.float32), output=1)
    hit = out["geomID"] >= 0
    t = np.where(hit, out["tfar"], np.inf).astype(np.float64)
    return t, np.where(hit, out["primID"], -1).astype(np.int64)


def lidar_reference(scene, poses: np.ndarray, config) -> np.ndarray:
    """What an ideal LiDAR of `config` measures in `scene` from `poses`, by Open3D.

    See-through faces are left out of the reference mesh; returns outside the range limits are
    misses. Returns ranges (N, beam_count) with inf for misses.
    """
    opaque = ~scene.material_table("lidar_transparent").astype(bool)
    dirs_sensor = config.beam_directions()
    origins = np.repeat(poses[:, :3, 3], len(dirs_sensor), axis=0)
    dirs = np.einsum("nij,bj->nbi", poses[:, :3, :3], dirs_sensor).reshape(-1, 3)
    t, _ = first_hits(scene.mesh.vertices, scene.mesh.faces[opaque], origins, dirs)
    t[(t < config.range_min_m) | (t > config.range_max_m)] = np.inf
    return t.reshape(len(poses), -1)
