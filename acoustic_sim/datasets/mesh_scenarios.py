"""Suite scenarios made of a user's mesh file: where the file lies, what its bytes hash to, and the
scene it makes, loaded once per process.

A scenario names its mesh (and its material table) by a path relative to the suite file's folder.
`mesh_file` checks both when the suite is loaded, before anything is planned: they exist, load,
map to our materials, and leave a robot room to drive. Their bytes are hashed, so a dataset's plan
id changes with their content and never with where they lie; what a dataset records of them is
`MeshFile.to_json()` (file names and hashes, never a path of this machine).
"""

from __future__ import annotations

import hashlib
import json
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote

import scenes
from clitools.limits import regular_file
from scenes.mesh_import import UNITS_M, UP_AXES, MeshImportReport, load

MESH_BUILDER = "mesh"
"""A scenario's `builder` when its scene is a mesh file (it is no key of `scenes.BUILDERS`)."""
MESH_FIELDS = ("mesh", "materials", "up", "units")
"""A suite file's scenario fields that name a mesh file and say how to read it."""
NAMES_ONLY = ("file", "materials")
"""Keys of `MeshFile.to_json()` that name files rather than describe their content."""


@dataclass(frozen=True, kw_only=True)
class MeshFile:
    """A mesh file a scenario names, as found when its suite was loaded.

    Attributes:
        path: The file on this machine (absolute); loads it, never recorded.
        sha256: Hex SHA-256 of its content (`mesh_sha256`: a .gltf's with the files it references).
        up: The file's up axis as the scenario gives it ("auto", "z" or "y").
        units: The file's unit as the scenario gives it ("auto" or a key of UNITS_M).
        materials_path: Its material table (TOML, absolute) or None; never recorded.
        materials_sha256: Hex SHA-256 of the table's bytes, or None.
    """

    path: str
    sha256: str
    up: str = "auto"
    units: str = "auto"
    materials_path: str | None = None
    materials_sha256: str | None = None

    @property
    def name(self) -> str:
        return Path(self.path).name

    def to_json(self) -> dict:
        """What datasets record of the file: its name and hash, the table's, the frame and unit."""
        out = {"file": self.name, "sha256": self.sha256, "up": self.up, "units": self.units}
        if self.materials_path is not None:
            out |= {"materials": Path(self.materials_path).name, "materials_sha256": self.materials_sha256}
        return out


def file_sha256(path: str | Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def mesh_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a mesh file's content: its bytes, and for a .gltf also those of every file its
    `buffers[].uri` and `images[].uri` reference (in that order; `data:` URIs are in the .gltf
    already), since rewriting its .bin changes the geometry. Raises FileNotFoundError naming a
    referenced file that is missing."""
    path = Path(path)
    if path.suffix.lower() != ".gltf":
        return file_sha256(path)
    data = path.read_bytes()
    digest = hashlib.sha256(data)
    for field, uri in _gltf_uris(data):
        referenced = path.parent / unquote(uri)
        if not referenced.is_file():
            raise FileNotFoundError(
                f"glTF {path.name} references {uri!r} ({field}), which does not exist ({referenced}); keep the "
                "files a .gltf names beside it, or give the .glb that holds them"
            )
        digest.update(b"\0" + file_sha256(referenced).encode())  # one digest per file: lengths cannot blur
    return digest.hexdigest()


def _gltf_uris(data: bytes) -> list[tuple[str, str]]:
    """(field, uri) of each file a glTF's JSON references, buffers then images; [] where it is no
    JSON (the import refuses it, naming the cause)."""
    try:
        doc = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError):
        return []
    found = []
    for key in ("buffers", "images"):
        items = doc.get(key, []) if isinstance(doc, dict) else []
        for i, item in enumerate(items if isinstance(items, list) else []):
            uri = item.get("uri") if isinstance(item, dict) else None
            if isinstance(uri, str) and not uri.startswith("data:"):
                found.append((f"{key}[{i}].uri", uri))
    return found


def mesh_file(fields: dict, folder: Path, where: str) -> MeshFile:
    """The mesh of a scenario table's `fields` (mesh, materials, up, units; paths relative to
    `folder`), checked: the files exist and load, the table maps to our materials, a robot finds
    room to drive. Raises FileNotFoundError, ValueError or SceneError naming `where` and the field."""
    up, units = fields.get("up", "auto"), fields.get("units", "auto")
    if up not in UP_AXES:
        raise ValueError(f"{where} up: the mesh's up axis is one of {', '.join(UP_AXES)}, got {up!r}")
    if units != "auto" and units not in UNITS_M:
        raise ValueError(f"{where} units: the mesh's unit is auto or one of {', '.join(UNITS_M)}, got {units!r}")
    path = _found(fields["mesh"], folder, f"{where} mesh", "mesh file")
    table = (
        _found(fields["materials"], folder, f"{where} materials", "material table") if "materials" in fields else None
    )
    try:
        sha256 = mesh_sha256(path)
    except FileNotFoundError as err:
        raise FileNotFoundError(f"{where} mesh {fields['mesh']!r}: {err}") from None
    mesh = MeshFile(
        path=str(path),
        sha256=sha256,
        up=up,
        units=units,
        materials_path=None if table is None else str(table),
        materials_sha256=None if table is None else file_sha256(table),
    )
    here = f"{where} mesh {fields['mesh']!r}"
    scene, failure = None, None
    with warnings.catch_warnings(record=True) as said:  # unmapped names, a doubtful size: said with the field
        warnings.simplefilter("always")
        try:
            scene = mesh_scene(mesh, quiet=False)
        except (OSError, ValueError) as err:
            failure = err
    for warning in said:
        warnings.warn(f"{here}: {_as_fields(str(warning.message))}", stacklevel=3)
    if failure is not None:
        raise type(failure)(f"{here}: {_as_fields(str(failure))}") from None
    try:
        scenes.free_space(scene)  # as trajectory() maps it: the same clearance and robot height
    except scenes.SceneError as err:
        raise scenes.SceneError(
            f"{where} mesh {fields['mesh']!r}: no room for a robot to drive ({err}); robots drive on the mesh's "
            "lowest level, kept clear of everything up to 0.6 m: give a mesh whose floor has room enclosed by "
            "walls, or check its up axis and units"
        ) from None
    return mesh


def _as_fields(text: str) -> str:
    """The import's words for the render command's options, as a suite's fields."""
    text = re.sub(r"--(units|up) (\w+)", r'\1 = "\2"', text)  # TOML strings: up = "y"
    return text.replace("--materials TABLE.toml", 'materials = "TABLE.toml"')


def _found(value: str, folder: Path, where: str, what: str) -> Path:
    """`value` read from `folder` (an absolute path stays as it is), a regular file, made absolute."""
    path = (folder / value).absolute()
    try:
        return regular_file(path, what)
    except FileNotFoundError:
        raise FileNotFoundError(
            f"{where}: {what} {value!r} does not exist ({path}); a relative path is read from the suite file's folder"
        ) from None
    except (OSError, ValueError) as err:
        raise type(err)(f"{where}: {err}") from None


_SCENES: dict[MeshFile, tuple[scenes.Scene, MeshImportReport]] = {}
"""Meshes this process has loaded: a worker loads each once, whatever the number of episodes (a
forked one finds those its parent loaded with the suite)."""


def mesh_scene(mesh: MeshFile, *, quiet: bool = True) -> scenes.Scene:
    """The scene of `mesh`, loaded once per process; refused if the file's bytes no longer hash to
    what they did when the suite was loaded. `quiet` hides the import's warnings (said at load)."""
    return _loaded(mesh, quiet=quiet)[0]


def mesh_material_map(mesh: MeshFile) -> list[dict]:
    """What each material name of `mesh` became, in the file's order: name (None: faces the file
    names nothing), our material, its triangle count and the rule that chose it."""
    return [{"name": n.name, "material": n.material, "faces": n.faces, "rule": n.rule} for n in _loaded(mesh)[1].names]


def _loaded(mesh: MeshFile, *, quiet: bool = True) -> tuple[scenes.Scene, MeshImportReport]:
    if mesh in _SCENES:
        return _SCENES[mesh]
    for path, digest, content in (
        (mesh.path, mesh.sha256, mesh_sha256),
        (mesh.materials_path, mesh.materials_sha256, file_sha256),
    ):
        if path is not None and content(path) != digest:
            raise ValueError(
                f"{path} changed since its suite was loaded (its SHA-256 is no longer {digest[:12]}...); "
                "rerun generate to plan with the file as it is now"
            )
    with warnings.catch_warnings():
        if quiet:
            warnings.simplefilter("ignore")
        scene, report = load(mesh.path, up=mesh.up, units=mesh.units, materials=mesh.materials_path, name=mesh.name)
    used = {k: v for k, v in scene.params.items() if k != "source"}  # the frame as used; the source is a path
    scene.params = mesh.to_json() | used
    _SCENES[mesh] = scene, report
    return scene, report


def content_key(suite_json: dict) -> dict:
    """A suite's JSON without the names of its mesh files (their hashes stay): what decides a
    dataset's arrays, so that renaming a file (or moving it with its suite) keeps the plan id."""
    scenarios = [
        s | {"mesh": {k: v for k, v in s["mesh"].items() if k not in NAMES_ONLY}} if s.get("mesh") else s
        for s in suite_json["scenarios"]
    ]
    return suite_json | {"scenarios": scenarios}
