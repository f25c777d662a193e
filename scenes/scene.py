"""Scene: one triangle mesh, a material id per face and the material table."""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import trimesh

from .materials import Material, material


class SceneError(ValueError):
    """A scene or its input geometry cannot be used (empty, non-finite, degenerate, ...)."""


@dataclass(frozen=True)
class CurvedSurface:
    """The smooth convex surface that some faces of a scene approximate: a sphere, or a cylinder
    (vertical unless `axis` says otherwise). A flat facet reflects specularly only where it happens
    to face the sensor, so simulators take specular echoes off these from the surface itself;
    everything else (LiDAR, scattering, occlusion) uses the faces.

    Attributes:
        kind: "sphere" or "cylinder".
        centre: The sphere's centre, or a point on the cylinder's axis [m].
        radius: [m].
        z_range: The cylinder's extent along its axis: the range of axis . x over it [m] (z for a
            vertical one; a sphere ignores it).
        axis: The cylinder's unit axis direction (a sphere ignores it).
    """

    kind: str
    centre: tuple[float, float, float]
    radius: float
    z_range: tuple[float, float] = (0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        if self.kind not in ("sphere", "cylinder") or not self.radius > 0:
            raise SceneError(f"a curved surface is a sphere or a cylinder of radius > 0, got {self.kind} {self.radius}")
        if len(self.centre) != 3 or not np.isfinite([*self.centre, self.radius]).all():
            raise SceneError(f"a curved surface needs a finite centre (x, y, z) and radius, got {self.centre}")
        if self.kind == "cylinder" and not self.z_range[0] < self.z_range[1]:
            raise SceneError(f"a cylinder's z_range must run upwards, got {self.z_range}")
        if len(self.axis) != 3 or not abs(np.linalg.norm(self.axis) - 1.0) < 1e-6:
            raise SceneError(f"a curved surface's axis must be a unit vector (x, y, z), got {self.axis}")


@dataclass(eq=False)
class Scene:
    """A static 3D world: one triangle mesh whose faces each carry a material.

    Build scenes with the builders (`box_room`, `corridor`, `office`, `random_world`,
    `from_svg`, `from_mesh`) rather than by hand: they validate their input. The
    mesh is treated as immutable; simulators cache device copies of it.

    Attributes:
        mesh: Triangle mesh in the world frame [m], z up, floor at `mesh.bounds[0, 2]`.
        face_material: Index into `materials` for every face, shape (face_count,).
        materials: Material table.
        name: Builder name, e.g. "office".
        params: The builder's arguments (JSON-serialisable), so a scene can be described
            and rebuilt.
        curved: The smooth surfaces some faces approximate (`CurvedSurface`).
        face_curved: For every face, the index into `curved` of the surface it approximates,
            -1 for a flat face (a cylinder's caps are flat), shape (face_count,); default all -1.
    """

    mesh: trimesh.Trimesh
    face_material: np.ndarray
    materials: tuple[Material, ...]
    name: str = "scene"
    params: dict = field(default_factory=dict)
    curved: tuple[CurvedSurface, ...] = ()
    face_curved: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.face_material = np.ascontiguousarray(self.face_material, dtype=np.int32)
        if self.face_material.shape != (len(self.mesh.faces),):
            raise SceneError(f"face_material has shape {self.face_material.shape}, expected ({len(self.mesh.faces)},)")
        if self.face_curved is None:
            self.face_curved = np.full(len(self.mesh.faces), -1, dtype=np.int32)
        self.face_curved = np.ascontiguousarray(self.face_curved, dtype=np.int32)
        if (
            self.face_curved.shape != self.face_material.shape
            or not ((self.face_curved >= -1) & (self.face_curved < len(self.curved))).all()
        ):
            count = len(self.curved)
            raise SceneError(f"face_curved must give each face -1 or the index of one of {count} curved surfaces")
        if len(self.materials) == 0:
            raise SceneError("the material table is empty")
        bad = (self.face_material < 0) | (self.face_material >= len(self.materials))
        if bad.any():
            raise SceneError(f"{int(bad.sum())} faces have a material id outside 0..{len(self.materials) - 1}")

    @property
    def face_count(self) -> int:
        return len(self.mesh.faces)

    @property
    def floor_z(self) -> float:
        """Height of the lowest point of the scene [m]; trajectories drive on it."""
        return float(self.mesh.bounds[0, 2])

    def section(self, height: float) -> tuple[np.ndarray, np.ndarray]:
        """Horizontal cut `height` [m] above the floor: 2D segments (S, 2, 2) [m] and their faces (S,)."""
        lines, faces = trimesh.intersections.mesh_plane(
            self.mesh, plane_normal=(0.0, 0.0, 1.0), plane_origin=(0.0, 0.0, self.floor_z + height), return_faces=True
        )
        if len(lines) == 0:
            return np.zeros((0, 2, 2)), np.zeros(0, dtype=np.int64)
        return np.asarray(lines)[:, :, :2], np.asarray(faces, dtype=np.int64)

    def material_table(self, attribute: str) -> np.ndarray:
        """Per-face value of a material attribute, e.g. "acoustic_reflection", shape (face_count,)."""
        values = np.array([getattr(m, attribute) for m in self.materials])
        return values[self.face_material]

    def describe(self) -> str:
        """JSON description (builder, parameters, size, materials) for dataset files."""
        return json.dumps(
            {
                "name": self.name,
                "params": self.params,
                "faces": self.face_count,
                "bounds_m": np.round(self.mesh.bounds, 4).tolist(),
                "materials": [m.__dict__ for m in self.materials],
                "curved": len(self.curved),
            },
            sort_keys=True,
        )

    def __repr__(self) -> str:
        size = np.round(self.mesh.extents, 2).tolist()
        names = [m.name for m in self.materials]
        return f"Scene({self.name!r}, faces={self.face_count}, size_m={size}, materials={names})"


def clean_mesh(mesh: trimesh.Trimesh, *, what: str = "mesh") -> tuple[trimesh.Trimesh, np.ndarray]:
    """Validate a mesh and drop its degenerate faces; raise SceneError when nothing usable is left.

    Returns a new mesh (the input is not modified) with float64 vertices, and the boolean
    mask of the input faces that were kept.
    """
    if not isinstance(mesh, trimesh.Trimesh):
        raise SceneError(f"{what} is a {type(mesh).__name__}, expected a trimesh.Trimesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(faces) == 0 or len(vertices) == 0:
        raise SceneError(f"{what} is empty: it has {len(vertices)} vertices and {len(faces)} faces")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise SceneError(f"{what} has face indices outside 0..{len(vertices) - 1}")
    finite = np.isfinite(vertices).all(axis=1)
    if not finite.all():
        raise SceneError(f"{what} has {int((~finite).sum())} vertices with non-finite (NaN or inf) coordinates")
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    scale = max(float(np.ptp(vertices, axis=0).max()), 1e-9)
    keep = area > 1e-12 * scale * scale
    if not keep.any():
        raise SceneError(f"all {len(faces)} faces of {what} are degenerate (zero area)")
    if not keep.all():
        warnings.warn(f"{what}: dropped {int((~keep).sum())} degenerate faces", stacklevel=3)
    return trimesh.Trimesh(vertices=vertices, faces=faces[keep], process=False), keep


def assemble(
    parts: Iterable[tuple[trimesh.Trimesh, str | Material]],
    *,
    name: str,
    params: dict | None = None,
    fit_curved: Callable[[trimesh.Trimesh], tuple[list[CurvedSurface], np.ndarray]] | None = None,
) -> Scene:
    """Concatenate (mesh, material) parts into one Scene with a compact material table. A part
    made by `cylinder_mesh` or `sphere_mesh` brings its `CurvedSurface` along; `fit_curved`
    (meshes from elsewhere: `smooth_fit.fit_curved_surfaces`) finds those of every other part:
    (surfaces, per-face index into them or -1)."""
    table: list[Material] = []
    meshes: list[trimesh.Trimesh] = []
    ids: list[np.ndarray] = []
    curved: list[CurvedSurface] = []
    face_curved: list[np.ndarray] = []
    for mesh, mat in parts:
        mat = material(mat)
        if mat not in table:
            if any(m.name == mat.name for m in table):
                raise SceneError(f"two different materials are both named {mat.name!r}")
            table.append(mat)
        surface = mesh.metadata.get(CURVED_KEY) if isinstance(mesh, trimesh.Trimesh) else None
        mesh, _ = clean_mesh(mesh, what=f"{name} part")
        if surface:
            found, on_found = [surface], np.where(_surface_faces(mesh, surface), 0, -1)
            _check_on_surface(mesh, surface, on_found >= 0, f"{name} part")
        elif fit_curved:
            found, on_found = fit_curved(mesh)
        else:
            found, on_found = [], np.full(len(mesh.faces), -1)
        meshes.append(mesh)
        ids.append(np.full(len(mesh.faces), table.index(mat), dtype=np.int32))
        face_curved.append(np.where(on_found >= 0, on_found + len(curved), -1).astype(np.int32))
        curved.extend(found)
    if not meshes:
        raise SceneError(f"{name}: no geometry to build a scene from")
    combined = trimesh.util.concatenate(meshes)
    combined.merge_vertices()  # parts that share corners become one connected surface (faces keep their order)
    return Scene(
        combined,
        np.concatenate(ids),
        tuple(table),
        name=name,
        params=dict(params or {}),
        curved=tuple(curved),
        face_curved=np.concatenate(face_curved),
    )


_UNIT_BOX = trimesh.creation.box()  # trimesh's box: its vertex and face order, centred on 0


def box_mesh(center: Sequence[float], extents: Sequence[float], yaw: float = 0.0) -> trimesh.Trimesh:
    """Closed box with outward normals, rotated by `yaw` [rad] about z: `trimesh.creation.box`'s
    vertices and faces, bit for bit, without its transform's bookkeeping (0.47 ms a box against
    0.03; a paper episode's preparation 25.5-27.6 ms with trimesh's, 24.7 without, 2-core CPU)."""
    extents = np.asarray(extents, dtype=np.float64)
    if extents.shape != (3,):
        raise ValueError(f"a box needs 3 extents, got {extents.shape}")
    transform = trimesh.transformations.rotation_matrix(yaw, (0, 0, 1))
    transform[:3, 3] = center
    vertices = _UNIT_BOX.vertices * extents  # as trimesh: (corner - 0.5) * extents
    if np.abs(transform - np.eye(4)).max() >= 1e-8:  # trimesh's own test for an identity
        vertices = np.dot(transform, np.column_stack((vertices, np.ones(len(vertices)))).T).T[:, :3]
    return trimesh.Trimesh(np.ascontiguousarray(vertices), _UNIT_BOX.faces.copy(), process=False)


CURVED_KEY = "curved_surface"  # trimesh metadata of a part that approximates a CurvedSurface


def _surface_faces(mesh: trimesh.Trimesh, surface: CurvedSurface) -> np.ndarray:
    """Which faces of a part stand for its curved surface: all of a sphere's, a cylinder's sides
    (its caps stay flat mirrors)."""
    if surface.kind == "sphere":
        return np.ones(len(mesh.faces), dtype=bool)
    return np.abs(mesh.face_normals @ np.asarray(surface.axis)) <= 0.5


def _check_on_surface(mesh: trimesh.Trimesh, surface: CurvedSurface, faces: np.ndarray, what: str) -> None:
    """Refuse a part whose `faces` do not lie on the curved surface it carries: trimesh keeps the
    metadata through moves, scaling and concatenation, which would leave the echo behind."""
    centre, radius = np.asarray(surface.centre), surface.radius
    tolerance = 1e-6 * max(radius, 1.0)
    corners = mesh.vertices[mesh.faces[faces].reshape(-1)]
    if surface.kind == "sphere":
        off = np.abs(np.linalg.norm(corners - centre, axis=1) - radius)
    else:
        axis, along = np.asarray(surface.axis), (corners - centre) @ np.asarray(surface.axis)
        off = np.abs(np.linalg.norm(corners - centre - along[:, None] * axis, axis=1) - radius)
        z0, z1 = surface.z_range
        height = mesh.vertices @ axis
        off = np.r_[off, np.maximum(z0 - height, height - z1).clip(0)]
    if off.max(initial=0.0) > tolerance:
        raise SceneError(
            f"{what}: its vertices lie up to {off.max():.3g} m off the {surface.kind} it carries (moved, scaled "
            "or merged after cylinder_mesh/sphere_mesh?); make it with those at its final place, or drop "
            f"mesh.metadata[{CURVED_KEY!r}]"
        )


def cylinder_mesh(x: float, y: float, radius: float, z0: float, z1: float, *, sections: int = 32) -> trimesh.Trimesh:
    """Closed vertical cylinder from z0 to z1 [m] (it carries its `CurvedSurface` into `assemble`)."""
    transform = np.eye(4)
    transform[:3, 3] = (x, y, 0.5 * (z0 + z1))
    mesh = trimesh.creation.cylinder(radius=radius, height=z1 - z0, sections=sections, transform=transform)
    axis = (float(x), float(y), float(z0))
    mesh.metadata[CURVED_KEY] = CurvedSurface("cylinder", axis, float(radius), (float(z0), float(z1)))
    return mesh


def sphere_mesh(centre: Sequence[float], radius: float, *, subdivisions: int = 3) -> trimesh.Trimesh:
    """Sphere [m] (an icosphere; it carries its `CurvedSurface` into `assemble`)."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    mesh.apply_translation(centre)
    mesh.metadata[CURVED_KEY] = CurvedSurface("sphere", tuple(float(c) for c in centre), float(radius))
    return mesh


def room_shell(size: Sequence[float], *, origin: Sequence[float] = (0.0, 0.0, 0.0)) -> dict[str, trimesh.Trimesh]:
    """Inside of a box room with inward normals, split into "floor", "walls" and "ceiling".

    The room spans origin .. origin + size [m].
    """
    size = np.asarray(size, dtype=np.float64)
    box = box_mesh(np.asarray(origin) + size / 2, size)
    # Normals into the room: a new mesh with reversed faces. (Trimesh.invert keeps face normals
    # cached from before, which once put the floor's material on the ceiling and back.)
    shell = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)
    normals = shell.face_normals
    pick = {
        "floor": normals[:, 2] > 0.5,
        "ceiling": normals[:, 2] < -0.5,
        "walls": np.abs(normals[:, 2]) <= 0.5,
    }
    return {k: shell.submesh([np.flatnonzero(v)], append=True) for k, v in pick.items()}
