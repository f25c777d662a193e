"""3D scenes a robot drives through: meshes with per-face materials, builders and trajectories.

Pure numpy/trimesh: no simulation code lives here.
"""

from .builders import box_room, corridor, from_mesh, office, random_world
from .floor_plans import FLOOR_PLANS, floor_plan, polygon_room
from .materials import MATERIALS, Material, material
from .scene import CurvedSurface, Scene, SceneError
from .svg import from_svg
from .trajectory import FreeSpace, free_space, pose, poses, trajectory

REVISION = 3
"""Bumped whenever a builder makes other scenes from the same arguments, or the mesh import
(`mesh_import`, `material_map`, `smooth_fit`) another scene from the same file's bytes (a suite's
mesh scenario counts by the hash of its bytes); part of every dataset's plan id, so data made
before is never taken for data made after (2: floor and ceiling materials of room shells the
right way round; 3: cylinders carry their curved surface, which echoes specularly from every side)."""

BUILDERS = {
    "box_room": box_room,
    "corridor": corridor,
    "office": office,
    "random_world": random_world,
    "polygon_room": polygon_room,
}

__all__ = [
    "BUILDERS",
    "FLOOR_PLANS",
    "MATERIALS",
    "CurvedSurface",
    "FreeSpace",
    "Material",
    "Scene",
    "SceneError",
    "box_room",
    "corridor",
    "floor_plan",
    "free_space",
    "from_mesh",
    "from_svg",
    "material",
    "office",
    "polygon_room",
    "pose",
    "poses",
    "random_world",
    "trajectory",
]
