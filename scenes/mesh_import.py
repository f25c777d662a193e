"""A user's mesh file as a Scene, without surprises: its up axis and unit are taken from what the
format specifies (glTF: Y up, metres) or assumed (z up, metres) and checked against the size and
shape of a building; its material names (OBJ `usemtl`/groups, glTF/GLB and PLY material slots)
are mapped to our materials by a table and by name patterns; a report says what was done.

`load(path, up=, units=, materials=) -> (Scene, MeshImportReport)` is the one entry point
(`scenes.from_mesh` and the command line call it); `MeshImportReport.to_dict()` is its plain form.
"""

from __future__ import annotations

import dataclasses
import io
import os
import re
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import trimesh

from clitools.limits import available_memory_bytes, format_bytes, input_file

from .material_map import MappedName, check_material_table, map_names, read_material_table
from .materials import MATERIALS, Material
from .materials import material as preset
from .scene import Scene, SceneError, assemble
from .smooth_fit import fit_curved_surfaces

MESH_MEMORY_PER_FILE_BYTE = 32  # trimesh's arrays and our copies per byte of mesh file (8-20 measured: OBJ, STL, PLY)

UP_AXES = ("auto", "z", "y")
UNITS_M = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
"""Length of each file unit [m]."""
GLTF_SUFFIXES = (".gltf", ".glb")

Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""(x, y, z) of a Y-up file -> (x, -z, y): +90 deg about x, a proper rotation (det +1: nothing is
mirrored, a point on the left stays on the left). It undoes Blender's Y-up OBJ export and is what
Blender's glTF importer does."""

BUILDING_MAX_ACROSS_M = 1000.0  # a mesh wider than this is no building a robot maps: a unit mistake
BUILDING_MAX_HEIGHT_M = 100.0  # a room in centimetres is 250 m tall but may be under 1000 m across
BUILDING_MIN_ACROSS_M = 0.5  # smaller than the robot: not a room in metres
STOREYS_MAX_HEIGHT_M = 30.0  # a building of storeys is lower; a room in inches (8 x 6 x 2.4 m: 94.5 m tall) is not
SIDE_RATIO = 2.0  # height over width in y beyond which a glTF (Y-up by specification) written Z-up is suspected


@dataclasses.dataclass(frozen=True)
class MeshImportReport:
    """What `load` did with a mesh: frame, unit, and each file name's material.

    Attributes:
        source: The file, or None for a mesh given in Python.
        up: The file's up axis as used, "z" or "y"; `up_reason` says why.
        units: The file's unit as used (a key of UNITS_M); `units_reason` says why.
        size_m: The scene's extent along x, y, z after import [m].
        names: Every material name of the file in order of appearance, with its faces.
        unmapped: Names that neither the table nor a name pattern maps (they got the default).
        unused_keys: Table keys that matched no name of the file (a typo?).
        warnings: The warnings `load` gave.
        curved: The round surfaces fitted to its smooth patches (`smooth_fit`), one line each.
    """

    source: str | None
    up: str
    up_reason: str
    units: str
    units_reason: str
    size_m: tuple[float, float, float]
    names: tuple[MappedName, ...]
    unmapped: tuple[str, ...]
    unused_keys: tuple[str, ...]
    warnings: tuple[str, ...]
    curved: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        """The report as plain JSON-serialisable values."""
        return dataclasses.asdict(self)

    def text(self, *, max_names: int = 30) -> str:
        """Lines for a person: frame, unit, size, then one line a name (at most `max_names`)."""
        size = " x ".join(f"{s:.3g}" for s in self.size_m)
        lines = [
            f"mesh {self.source or '(given in Python)'}: {self.up} up ({self.up_reason}), "
            f"{self.units} ({self.units_reason}); {size} m"
        ]
        for entry in self.names[:max_names]:
            name = "(no name)" if entry.name is None else repr(entry.name)
            faces = f"{entry.faces} face" + ("" if entry.faces == 1 else "s")
            lines.append(f"  {name}: {faces} -> {entry.material} ({entry.rule})")
        if len(self.names) > max_names:
            lines.append(f"  ... and {len(self.names) - max_names} more names")
        if self.curved:
            shown = "; ".join(self.curved[:max_names]) + ("; ..." if len(self.curved) > max_names else "")
            lines.append(f"  round surfaces fitted, echoing off the true surface: {shown}")
        return "\n".join(lines)


def load(
    source: trimesh.Trimesh | trimesh.Scene | str | os.PathLike,
    *,
    up: str = "auto",
    units: str = "auto",
    materials: str | os.PathLike | Mapping[str, str] | None = None,
    material: str | Material = "painted_wall",
    name: str = "mesh",
) -> tuple[Scene, MeshImportReport]:
    """A Scene from a mesh file (or a trimesh mesh or scene) and the report of the import.

    Args:
        source: A file trimesh reads (.obj, .glb/.gltf, .ply, .stl, ...) or a trimesh.Trimesh /
            trimesh.Scene (taken as z up, metres, unless `up`/`units` say otherwise).
        up: The file's up axis: "z", "y", or "auto" (glTF: y, by specification; other files:
            z, with a warning where the mesh is taller than it is deep in y, as a Y-up room is).
        units: The file's unit, a key of UNITS_M, or "auto" (metres; a file whose size is absurd
            for a building is refused, one taller than STOREYS_MAX_HEIGHT_M warned, each naming
            the units that would fit).
        materials: A TOML file with a `[materials]` table, or that table as a mapping: file name
            or glob (case-insensitive, first match in table order) -> one of MATERIALS.
        material: What faces get that the file names nothing, or whose names map to nothing.
        name: The scene's name.

    Raises:
        SceneError: the file cannot be read or used, its size is absurd for a building in the
            unit assumed, or the table names a material we do not have.
    """
    if up not in UP_AXES:
        raise SceneError(f"up (--up) must be one of {', '.join(UP_AXES)}; got {up!r}")
    if units != "auto" and units not in UNITS_M:
        raise SceneError(f"units (--units) must be auto or one of {', '.join(UNITS_M)}; got {units!r}")
    table = read_material_table(materials) if isinstance(materials, (str, os.PathLike)) else materials
    table = check_material_table(table or {}, where="material table")
    default = preset(material)
    path = os.fspath(source) if isinstance(source, (str, os.PathLike)) else None
    said = []
    parts = _read_parts(path, said) if path is not None else _given_parts(source)
    up, up_reason, units, units_reason = _frame(path, up, units)
    rotation = Y_UP_TO_Z_UP if up == "y" else np.eye(3)
    scale = UNITS_M[units]
    if up != "z" or scale != 1.0:
        parts = [(n, _transformed(m, rotation, scale)) for n, m in parts]
    if path is not None:  # a mesh given in Python is the caller's own frame: nothing to guess
        corners = np.concatenate([m.bounds for _, m in parts])
        size = corners.max(axis=0) - corners.min(axis=0)
        said += _check_size(path, size, units, units_reason, refuse=units_reason != "given")
        if up_reason != "given":
            said += _check_upright(path, size, up)
    names, by_material, unmapped, unused = map_names(parts, table, default)
    if unmapped:
        listed = ", ".join(map(repr, unmapped[:10])) + (f" and {len(unmapped) - 10} more" if len(unmapped) > 10 else "")
        said.append(
            f"{path or 'mesh'}: material names that map to none of ours got {default.name}: {listed}; map them in "
            f"a [materials] table (--materials TABLE.toml) to one of {', '.join(sorted(MATERIALS))}"
        )
    if unused:
        said.append(f"material table keys that match no name of {path or 'the mesh'}: {', '.join(map(repr, unused))}")
    for text in said:
        warnings.warn(text, stacklevel=2)
    params = {"source": path, "up": up, "units": units, "material": default.name, "material_table": dict(table)}
    scene = assemble(by_material, name=name, params=params, fit_curved=fit_curved_surfaces)
    report = MeshImportReport(
        source=path,
        up=up,
        up_reason=up_reason,
        units=units,
        units_reason=units_reason,
        size_m=tuple(float(s) for s in np.asarray(scene.mesh.extents)),
        names=tuple(names),
        unmapped=tuple(unmapped),
        unused_keys=tuple(unused),
        warnings=tuple(said),
        curved=tuple(_described(surface) for surface in scene.curved),
    )
    return scene, report


def _described(surface) -> str:
    """A fitted sphere or cylinder in a few words [m]."""
    centre = ", ".join(f"{c:.3g}" for c in surface.centre)
    if surface.kind == "sphere":
        return f"sphere r {surface.radius:.3g} m at ({centre})"
    axis = ", ".join(f"{a:.3g}" for a in surface.axis)
    return f"cylinder r {surface.radius:.3g} m through ({centre}) along ({axis})"


def _frame(path: str | None, up: str, units: str) -> tuple[str, str, str, str]:
    """The up axis and unit to use, each with the reason: given, specified by the format, or assumed."""
    suffix = os.path.splitext(path)[1].lower() if path else ""
    gltf = suffix in GLTF_SUFFIXES
    what = f"{suffix} files have" if suffix else "a mesh given in Python has"
    up_reason = "glTF is Y-up by specification" if gltf else f"assumed: {what} no up axis"
    units_reason = "glTF is in metres by specification" if gltf else f"assumed: {what} no unit"
    if up != "auto":
        up_reason = "given"
    if units != "auto":
        units_reason = "given"
    return ("y" if gltf else "z") if up == "auto" else up, up_reason, "m" if units == "auto" else units, units_reason


def _check_size(path: str, size: np.ndarray, units: str, reason: str, *, refuse: bool) -> list[str]:
    """Refuse (or, with the unit given, warn about) a mesh too large for a building; with the unit
    assumed, warn about one taller than a building of storeys (a room in inches); warn about one
    smaller than a robot. Names the units that would give a building."""
    across, height = float(size.max()), float(size[2])
    shape = " x ".join(f"{s:.4g}" for s in size)
    fits = [u for u in _units_that_fit(size / UNITS_M[units]) if u[0] != units]
    advice = " or ".join(f"--units {u} (it would be {dims} m)" for u, dims in fits[:3])
    if across > BUILDING_MAX_ACROSS_M or height > BUILDING_MAX_HEIGHT_M:
        problem = f"{across:.4g} m across" if across > BUILDING_MAX_ACROSS_M else f"{height:.4g} m tall"
        text = (
            f"mesh {path} is {shape} m (x, y, z) read in {units} ({reason}): {problem}, too large for a building; "
            f"a file in other units? give {advice or 'its unit with --units'}"
        )
        if refuse:
            raise SceneError(f"{text}; --units {units} keeps it as it is")
        return [text]
    if refuse and height > STOREYS_MAX_HEIGHT_M:  # a hall or tower may be, so warned, not refused
        lower = [u for u in _units_that_fit(size / UNITS_M[units], max_height=STOREYS_MAX_HEIGHT_M) if u[0] != units]
        advice = " or ".join(f"--units {u} (it would be {dims} m)" for u, dims in lower[:3])
        return [
            f"mesh {path} is {shape} m (x, y, z) read in {units} ({reason}): {height:.4g} m tall, taller than a "
            f"building of storeys; a file in other units? give {advice or 'its unit with --units'}; "
            f"if it is that tall, give --units {units} to say so"
        ]
    if across < BUILDING_MIN_ACROSS_M:
        return [
            f"mesh {path} is {shape} m (x, y, z) read in {units} ({reason}): smaller than a robot, no room to "
            f"drive in; a file in other units? give {advice or 'it in metres'}"
        ]
    return []


def _units_that_fit(
    size_in_file_units: np.ndarray, *, max_height: float = BUILDING_MAX_HEIGHT_M
) -> list[tuple[str, str]]:
    """(unit, "x x y x z") for each unit that makes the mesh building-sized (at most `max_height`
    [m] tall), the most usual storey height (3 m) first."""
    fits = []
    for unit, metres in UNITS_M.items():
        size = size_in_file_units * metres
        if BUILDING_MIN_ACROSS_M <= size.max() <= BUILDING_MAX_ACROSS_M and size[2] <= max_height:
            fits.append((abs(np.log(max(size[2], 1e-3) / 3.0)), unit, " x ".join(f"{s:.4g}" for s in size)))
    return [(unit, dims) for _, unit, dims in sorted(fits)]


def _check_upright(path: str, size: np.ndarray, up: str) -> list[str]:
    """Warn where the mesh looks like a room lying on its side, the up axis not given. Read z up
    (assumed, as for OBJ), any mesh taller than it is deep in y: a Y-up room (as Blender writes
    OBJ) of any usual shape is, a room standing upright is not unless it is a narrow corridor
    along x. Read y up (glTF, by specification), a height over SIDE_RATIO times the width in y
    (y being the narrower horizontal extent): such a file was likely written Z-up."""
    ex, ey, ez = (float(s) for s in size)
    lying = ez > ey if up == "z" else ey <= ex and ez > SIDE_RATIO * ey
    if not lying:
        return []
    other = "y" if up == "z" else "z"
    why = (
        "as Blender writes OBJ by default"
        if other == "y"
        else "as some exporters write glTF, against its specification"
    )
    return [
        f"mesh {path} read {up} up is {ex:.4g} x {ey:.4g} x {ez:.4g} m (x, y, z): {ez:.4g} m tall and {ey:.4g} m "
        f"across in y, taller than it is deep, like a room lying on its side; if the file is {other.upper()}-up "
        f"({why}), give --up {other}; if it stands upright (a narrow corridor, a tall hall), give --up {up} to say so"
    ]


def _check_mesh_file(path: str) -> None:
    """A regular file (a FIFO or /dev/urandom would never end) whose mesh this machine can hold."""
    limit = available_memory_bytes() / MESH_MEMORY_PER_FILE_BYTE
    free = format_bytes(limit * MESH_MEMORY_PER_FILE_BYTE)
    why = f"loading a mesh takes up to {MESH_MEMORY_PER_FILE_BYTE} times its size in memory, and {free} are free"
    try:
        input_file(path, what="mesh file", max_bytes=limit, bound=why)
    except FileNotFoundError:
        raise SceneError(f"could not load a mesh from {path}: there is no such file") from None
    except (OSError, ValueError) as err:
        raise SceneError(str(err)) from None


Part = tuple[str | None, trimesh.Trimesh]  # a material name of the file (None: none) and its faces


def _read_parts(path: str, said: list[str]) -> list[Part]:
    """The triangles of mesh file `path`, in parts by material name (node transforms applied);
    warnings for the report go to `said`."""
    _check_mesh_file(path)
    try:
        if path.lower().endswith(".obj"):
            loaded, known = _load_obj(path)
        else:
            # process=False: trimesh's clean-up drops NaN vertices and their faces without a word;
            # clean_mesh refuses them instead (assemble merges duplicate vertices afterwards)
            loaded, known = trimesh.load(path, process=False), None
    except Exception as err:
        raise SceneError(
            f"could not load a mesh from {path} (trimesh: {type(err).__name__}: {str(err).strip()}); give a "
            "mesh file trimesh reads (.obj, .stl, .ply, .glb, .off, ...) whose suffix names its format"
        ) from err
    parts = _parts_of(loaded, known, said)
    if not parts:
        vertices = sum(len(g.vertices) for g in _geometries(loaded) if hasattr(g, "vertices"))
        raise SceneError(f"mesh file {path} holds no faces (trimesh read {vertices} vertices)")
    return parts


def _given_parts(source) -> list[Part]:
    if isinstance(source, trimesh.Scene):
        if parts := _parts_of(source, None, []):
            return parts
        raise SceneError("the trimesh.Scene given holds no faces")
    if not isinstance(source, trimesh.Trimesh):  # the message clean_mesh gives
        raise SceneError(f"mesh is a {type(source).__name__}, expected a trimesh.Trimesh")
    return [(None, source)]


OBJ_NAME = re.compile(r"^[ \t]*(usemtl|g|o)[ \t]+(\S[^\r\n]*?)[ \t]*\r?$", re.MULTILINE)
OBJ_COMMENT = re.compile(r"^[ \t]*#[^\n]*", re.MULTILINE)
OBJ_NAMES_MTL = "names-of-this-file.mtl"


def _load_obj(path: str) -> tuple[trimesh.Trimesh | trimesh.Scene, list[str]]:
    """An OBJ file loaded by trimesh, named by its `usemtl` names, else its groups (`g`), else its
    objects (`o`); and those names in order of appearance.

    trimesh keeps a `usemtl` name only where the file's .mtl defines it (often the .obj comes
    alone) and names no groups, so it is handed a material file defining every name, with the
    groups or objects written as `usemtl` where the file has no `usemtl`."""
    text = OBJ_COMMENT.sub("", Path(path).read_bytes().decode("utf-8", errors="replace"))
    found = OBJ_NAME.findall(text)
    kind = next((k for k in ("usemtl", "g", "o") if any(f[0] == k for f in found)), None)
    if kind is None:
        return trimesh.load(path, process=False), []
    names = list(dict.fromkeys(" ".join(n.split()) for k, n in found if k == kind))  # as trimesh's .mtl reader does

    def as_usemtl(match: re.Match) -> str:
        return f"usemtl {' '.join(match[2].split())}" if match[1] == kind else match[0]

    text = f"mtllib {OBJ_NAMES_MTL}\n" + OBJ_NAME.sub(as_usemtl, text)
    mtl = "".join(f"newmtl {n}\n" for n in sorted(names)).encode()
    data = io.BytesIO(text.encode())
    return trimesh.load(data, file_type="obj", resolver={OBJ_NAMES_MTL: mtl}, process=False), names


def _geometries(loaded) -> list:
    if isinstance(loaded, trimesh.Scene):
        return loaded.dump()  # copies with each node's transform applied
    return [loaded]


def _parts_of(loaded, known: list[str] | None, said: list[str]) -> list[Part]:
    """Parts by material name: glTF/GLB primitives by material, OBJ by `known` names, PLY faces by
    their `material_index` slot; geometries without a material name by their own name, if several.
    What the file's slots leave unsaid goes to `said`."""
    meshes = [g for g in _geometries(loaded) if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    parts = []
    for mesh in meshes:
        name = getattr(getattr(mesh.visual, "material", None), "name", None) or None
        if known is not None:
            name = name if name in known else None
        elif name is None and len(meshes) > 1:
            name = mesh.metadata.get("name")
        parts += _ply_slots(mesh, said) or [(name, mesh)]
    if known:  # trimesh gives an OBJ's materials last first
        order = {name: i for i, name in enumerate(known)}
        parts.sort(key=lambda part: order.get(part[0], -1))
    return parts


def _ply_slots(mesh: trimesh.Trimesh, said: list[str]) -> list[Part]:
    """A PLY's faces by their `material_index` property (named "material_<index>"); [] for others
    (a count that does not fit the triangles is said in `said`). trimesh keeps the PLY's raw
    elements in metadata["_ply_raw"]; a quad or n-gon's index goes to each of its triangles."""
    raw = mesh.metadata.get("_ply_raw", {}).get("face", {}).get("data", {})
    index = raw.get("material_index") if isinstance(raw, dict) else None
    if index is None:
        return []
    index = np.asarray(index).reshape(-1)
    polygons = next((raw[k] for k in ("vertex_indices", "vertex_index") if k in raw), None)
    if polygons is not None and len(polygons) == len(index):
        index = index[_polygon_of_triangle(polygons)]
    if len(index) != len(mesh.faces):
        said.append(f"PLY material_index ignored: {len(index)} values for {len(mesh.faces)} triangles")
        return []
    return [(f"material_{i}", mesh.submesh([np.flatnonzero(index == i)], append=True)) for i in np.unique(index)]


def _polygon_of_triangle(polygons) -> np.ndarray:
    """The polygon each triangle of trimesh's triangulation comes from, shape (triangle_count,).
    trimesh puts the triangles first, then the quads' first halves, then their second halves, then
    the n-gons' fans: triangulating polygons whose every vertex index is their own number gives
    that order without copying it."""
    own = [np.full(len(p), k) for k, p in enumerate(polygons)]
    return trimesh.geometry.triangulate_quads(own)[:, 0].astype(np.int64)


def _transformed(mesh: trimesh.Trimesh, rotation: np.ndarray, scale: float) -> trimesh.Trimesh:
    vertices = np.asarray(mesh.vertices, dtype=np.float64) @ rotation.T * scale
    return trimesh.Trimesh(vertices, np.asarray(mesh.faces), process=False)
