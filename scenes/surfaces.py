"""Surface classes of a scene (walls, floor, ceiling, objects) and per-class acoustic properties,
so that a suite can draw what walls, floors, ceilings and objects reflect, each on its own."""

from __future__ import annotations

import dataclasses

import numpy as np

from .scene import Scene

SURFACE_CLASSES = ("walls", "floor", "ceiling", "objects")
WALL_MATERIALS = ("painted_wall", "brick")
LEVEL_COS = 0.99  # a face whose normal is within ~8 deg of vertical is level
HEIGHT_TOL_M = 1e-3


def surface_classes(scene: Scene) -> np.ndarray:
    """Index into SURFACE_CLASSES for every face: level faces at the lowest point facing up are
    the floor, level faces at the highest point facing down the ceiling, other faces of wall
    materials (painted wall, brick) walls, and everything else objects."""
    mesh = scene.mesh
    up, height = mesh.face_normals[:, 2], mesh.triangles_center[:, 2]
    floor = (up > LEVEL_COS) & (height < scene.floor_z + HEIGHT_TOL_M)
    ceiling = (up < -LEVEL_COS) & (height > mesh.bounds[1, 2] - HEIGHT_TOL_M)
    names = np.array([m.name for m in scene.materials])[scene.face_material]
    classes = np.full(scene.face_count, SURFACE_CLASSES.index("objects"), dtype=np.int32)
    classes[np.isin(names, WALL_MATERIALS)] = SURFACE_CLASSES.index("walls")
    classes[floor] = SURFACE_CLASSES.index("floor")
    classes[ceiling] = SURFACE_CLASSES.index("ceiling")
    return classes


def with_surfaces(scene: Scene, acoustics: dict[str, dict[str, float]]) -> Scene:
    """A copy of `scene` whose surface classes reflect and scatter as given, e.g. {"walls":
    {"reflection": 0.8, "scattering": 0.3}}: the energy fractions `acoustic_reflection` and
    `acoustic_scattering` of every material on those faces. What a LiDAR sees is unchanged."""
    if unknown := set(acoustics) - set(SURFACE_CLASSES):
        raise ValueError(f"unknown surface classes {sorted(unknown)}; use {SURFACE_CLASSES}")
    classes = surface_classes(scene)
    pairs, face_material = np.unique(np.stack([scene.face_material, classes], axis=1), axis=0, return_inverse=True)
    table = []
    for material_id, class_id in pairs:
        material, name = scene.materials[material_id], SURFACE_CLASSES[class_id]
        values = acoustics.get(name, {})
        changes = {f"acoustic_{k}": float(v) for k, v in values.items()}
        table.append(dataclasses.replace(material, name=f"{material.name}:{name}", **changes))
    params = scene.params | {"surfaces": acoustics}
    return Scene(
        scene.mesh,
        face_material.reshape(-1),
        tuple(table),
        name=scene.name,
        params=params,
        curved=scene.curved,
        face_curved=scene.face_curved,
    )
