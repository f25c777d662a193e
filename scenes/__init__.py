"""3D scenes a robot drives through: meshes with per-face materials, builders and trajectories.

Pure numpy/trimesh: no simulation code lives here.
"""

from .builders import box_room, corridor, from_mesh, office, random_world
from .materials import MATERIALS, Material, material
from .scene import Scene, SceneError
from .svg import from_svg
from .trajectory import FreeSpace, free_space, pose, poses, trajectory

BUILDERS = {
    "box_room": box_room,
    "corridor": corridor,
    "office": office,
    "random_world": random_world,
}

__all__ = [
    "BUILDERS",
    "MATERIALS",
    "FreeSpace",
    "Material",
    "Scene",
    "SceneError",
    "box_room",
    "corridor",
    "free_space",
    "from_mesh",
    "from_svg",
    "material",
    "office",
    "pose",
    "poses",
    "random_world",
    "trajectory",
]
