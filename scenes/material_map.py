"""A mesh file's material names (OBJ `usemtl` or groups, glTF/GLB and PLY slots) mapped to our
materials: by a table (TOML `[materials]`, name or glob -> ours) and then by name patterns."""

from __future__ import annotations

import dataclasses
import fnmatch
import os
import re
import tomllib
from collections.abc import Mapping

import numpy as np
import trimesh

from clitools.limits import input_file

from .materials import MATERIALS, Material
from .scene import SceneError

TABLE_MAX_BYTES = 1_000_000  # a material table is a few lines; a file a thousand times larger is not one

NAME_PATTERNS: tuple[tuple[str, tuple[str, ...]], ...] = (
    # substance words first ("steel door" is metal, "carpet floor" fabric), then the parts of a room
    ("glass", ("glass", "window", "glazing")),
    ("metal", ("metal", "steel", "alumin", "chrome", "brass", "copper", "zinc")),
    ("wood", ("wood", "timber", "plywood", "parquet", "door")),
    ("fabric", ("fabric", "cloth", "carpet", "curtain", "textile", "sofa", "cushion")),
    ("brick", ("brick", "stone", "masonry")),
    ("ceiling_tile", ("ceiling",)),
    ("floor", ("floor", "ground")),
    ("painted_wall", ("wall", "plaster", "paint", "concrete")),
)
"""Defaults for names a table does not map: (our material, word beginnings), first match wins. A
name matches where one of its words (`name_words`) equals a beginning or starts with it ("walls",
"flooring", "windows", "wooden"); a word inside another never matches ("door" is not in "Indoor",
"ground" not in "Underground"). No beginning starts common other words ("pane" would start "panel")."""

NAME_WORD = re.compile(r"[A-Z]+(?![a-z])|[A-Z]?[a-z]+")
"""A word of a name: a run of capitals not followed by a small letter (an acronym, "WALL"), or a
capital and the small letters after it, or small letters alone; digits and anything else split."""


def name_words(name: str) -> list[str]:
    """The lower-case words of a file's material name: split at anything not a letter (digits
    included) and where camelCase starts a word ("FloorTiles.001" -> ["floor", "tiles"])."""
    return [word.lower() for word in NAME_WORD.findall(name)]


@dataclasses.dataclass(frozen=True)
class MappedName:
    """One material name of the file: `name` (None: faces the file names nothing), the material
    its `faces` triangles got, and the `rule` that chose it."""

    name: str | None
    material: str
    faces: int
    rule: str


def read_material_table(path: str | os.PathLike) -> dict[str, str]:
    """The `[materials]` table of TOML file `path`: file name or glob -> one of MATERIALS.

    Example:

        [materials]
        "Floor*" = "floor"
        "Material.001" = "brick"   # quote names with dots (TOML reads a.b as a nested table)
        "*glass*" = "glass"
    """
    path = input_file(path, what="material table", max_bytes=TABLE_MAX_BYTES, bound="a material table is a few lines")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise SceneError(f"material table {path} is not text (UTF-8); give a TOML file") from None
    except tomllib.TOMLDecodeError as err:
        raise SceneError(f"material table {path} is not valid TOML: {err}") from None
    if set(data) != {"materials"} or not isinstance(data["materials"], dict):
        raise SceneError(
            f"material table {path} must hold one [materials] table (file name or glob = our material), "
            f"found {sorted(data) or 'nothing'}"
        )
    return check_material_table(data["materials"], where=f"material table {path}")


def check_material_table(table: Mapping[str, str], *, where: str) -> dict[str, str]:
    """`table` (file name or glob -> one of MATERIALS) as a dict; SceneError naming a bad entry."""
    if not isinstance(table, Mapping):
        raise SceneError(f"{where} must map file names or globs to our material names, got a {type(table).__name__}")
    ours = ", ".join(sorted(MATERIALS))
    for key, value in table.items():
        if not isinstance(key, str) or not key:
            raise SceneError(f"{where}: keys are file names or globs, got {key!r}")
        if isinstance(value, Mapping):  # TOML reads Floor.001 = "wood" as {"Floor": {"001": "wood"}}
            dotted = ".".join([key, *list(value)[:1]])
            raise SceneError(f'{where}: {key!r} holds a table; quote names with dots: "{dotted}" = ...')
        if not isinstance(value, str):  # a list or a number is no material name (and a list is unhashable)
            raise SceneError(
                f"{where}: {key!r} = {value!r} is a {type(value).__name__}; give one of our materials as a "
                f'string ({key!r} = "floor"); ours are {ours}'
            )
        if value not in MATERIALS:
            raise SceneError(f"{where}: {key!r} = {value!r} is not one of our materials; ours are {ours}")
    return dict(table)


def material_for(name: str, table: dict[str, str]) -> tuple[str | None, str, str | None]:
    """(our material or None, the rule, the table key used) for a file's material name."""
    low = name.lower()
    for key, ours in table.items():
        if low == key.lower() or fnmatch.fnmatchcase(low, key.lower()):
            return ours, f"table: {key!r}", key
    words = name_words(name)
    for ours, beginnings in NAME_PATTERNS:
        for beginning in beginnings:
            if any(word.startswith(beginning) for word in words):
                return ours, f"name contains {beginning!r}", None
    return None, "unmapped: the default", None


def map_names(parts: list[tuple[str | None, trimesh.Trimesh]], table: dict[str, str], default: Material):
    """Each name's material; the parts joined by material (for `assemble`); the unmapped names;
    the table keys no name matched."""
    faces: dict[str | None, int] = {}
    for name, mesh in parts:
        faces[name] = faces.get(name, 0) + len(mesh.faces)
    chosen, names, unmapped, used = {}, [], [], set()
    for name, count in faces.items():
        ours, rule, key = material_for(name, table) if name is not None else (None, "the default", None)
        used.add(key)
        if ours is None:
            unmapped += [] if name is None else [name]
        chosen[name] = default if ours is None else MATERIALS[ours]
        names.append(MappedName(name, chosen[name].name, count, rule))
    groups: dict[str, tuple[Material, list[trimesh.Trimesh]]] = {}
    for name, mesh in parts:
        groups.setdefault(chosen[name].name, (chosen[name], []))[1].append(mesh)
    joined = [(meshes[0] if len(meshes) == 1 else _joined(meshes), mat) for mat, meshes in groups.values()]
    return names, joined, unmapped, [k for k in table if k not in used]


def _joined(meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """One mesh of several (geometry only: materials are assigned per part)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    vertices = np.concatenate([np.asarray(m.vertices, dtype=np.float64) for m in meshes])
    faces = np.concatenate([np.asarray(m.faces) + o for m, o in zip(meshes, offsets, strict=True)])
    return trimesh.Trimesh(vertices, faces, process=False)
