"""Review fixes of the mesh import (issue 41): material names match by words, a table value must be
a string, a PLY's quads and n-gons keep their material slots, a .gltf's content hash covers the
files it references, and a dataset records what each mesh's names became.

Files are written here by hand from their specifications (PLY text, glTF JSON with its .bin), so
that neither trimesh's exporters nor our reader define what the file holds.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import scenes
from acoustic_sim.datasets import mesh_scenarios
from acoustic_sim.datasets.generate import SuiteRenderer
from acoustic_sim.datasets.plan import plan
from acoustic_sim.datasets.suites import load_suite, mesh_files
from scenes import mesh_import
from scenes.material_map import material_for, read_material_table

from .gltf_files import gltf_document
from .test_mesh_suite import SUITE, TABLE, room_parts, write_suite


@pytest.mark.parametrize(
    ("name", "material"),
    [
        ("Indoor_Wall", "painted_wall"),  # not wood: "door" is inside "Indoor", no word of it
        ("Outdoor_Floor", "floor"),
        ("Underground_concrete", "painted_wall"),  # not floor: "ground" is inside "Underground"
        ("Underground", None),
        ("Wall.001", "painted_wall"),
        ("FloorTiles", "floor"),  # camelCase splits
        ("GlassPane", "glass"),
        ("steel_beam", "metal"),
        ("Walls2", "painted_wall"),  # a word starting with the pattern; digits split
        ("flooring", "floor"),
        ("WINDOWS_north", "glass"),
        ("wooden_door", "wood"),
        ("BRICKWall", "brick"),  # capitals before a capitalised word: two words
    ],
)
def test_name_patterns_match_words_not_substrings(name, material):
    assert material_for(name, {})[0] == material


def test_a_list_in_the_table_is_refused_naming_file_and_key(tmp_path):
    """`Floor = ["floor"]` is refused as a list, naming the table file and the key (it was an
    unhashable-type TypeError naming neither)."""
    path = tmp_path / "table.toml"
    path.write_text('[materials]\nFloor = ["floor"]\n')
    with pytest.raises(scenes.SceneError, match=r"material table .*table\.toml: 'Floor' = \['floor'\] is a list"):
        read_material_table(path)


PLY_HEADER = (
    "ply\nformat ascii 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n"
    "element face {faces}\nproperty list uchar int vertex_indices\nproperty int material_index\nend_header\n"
)


def write_ply(path: Path, polygons: list[tuple[np.ndarray, int]]) -> None:
    """An ASCII PLY of (polygon corners (n, 3), material_index) rows, each polygon its own vertices."""
    points = np.concatenate([corners for corners, _ in polygons])
    rows, offset = [], 0
    for corners, index in polygons:
        rows.append(" ".join(map(str, [len(corners), *range(offset, offset + len(corners)), index])))
        offset += len(corners)
    body = "".join(f"{x} {y} {z}\n" for x, y, z in points) + "\n".join(rows) + "\n"
    path.write_text(PLY_HEADER.format(vertices=len(points), faces=len(polygons)) + body)


def polygon_at(x: float, corner_count: int) -> np.ndarray:
    """A convex polygon of `corner_count` corners in the plane y = 1, around (x, 1, 0.5), 0.5 m across."""
    angles = np.linspace(0.0, 2 * np.pi, corner_count, endpoint=False)
    return np.stack([x + 0.25 * np.cos(angles), np.ones(corner_count), 0.5 + 0.25 * np.sin(angles)], axis=1)


def test_ply_quads_and_ngons_keep_their_material_slots(tmp_path):
    """Faces: a quad at x = 0 (index 1), a triangle at x = 10 (index 0), a pentagon at x = 20
    (index 2), a quad at x = 30 (index 0): trimesh puts triangles first and splits each quad in
    two halves listed apart, so each triangle's slot is told by its centroid's x alone."""
    polygons = [(polygon_at(0.0, 4), 1), (polygon_at(10.0, 3), 0), (polygon_at(20.0, 5), 2), (polygon_at(30.0, 4), 0)]
    write_ply(tmp_path / "quads.ply", polygons)
    table = {"material_0": "metal", "material_1": "glass", "material_2": "wood"}
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        scene, report = mesh_import.load(tmp_path / "quads.ply", up="z", units="m", materials=table)
    assert report.warnings == () and not [w for w in said if "material_index" in str(w.message)]
    assert sorted((n.name, n.material, n.faces) for n in report.names) == [
        ("material_0", "metal", 1 + 2),
        ("material_1", "glass", 2),
        ("material_2", "wood", 3),
    ]
    got = np.array([scene.materials[i].name for i in scene.face_material])
    polygon = np.rint(scene.mesh.triangles_center[:, 0] / 10.0).astype(int)
    assert (got == np.array(["glass", "metal", "wood", "metal"])[polygon]).all(), (got, polygon)


def test_a_ply_slot_count_that_does_not_fit_is_in_the_report(tmp_path, monkeypatch):
    """Where the slots cannot be matched to the triangles (here: one too few), the import says so in
    the report's warnings as well as in a warning, and every face gets the default."""
    write_ply(tmp_path / "quad.ply", [(polygon_at(0.0, 4), 1)])
    real = mesh_import._polygon_of_triangle
    monkeypatch.setattr(mesh_import, "_polygon_of_triangle", lambda polygons: real(polygons)[:-1])
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        _, report = mesh_import.load(tmp_path / "quad.ply")
    assert [w for w in report.warnings if "material_index ignored: 1 values for 2 triangles" in w]
    assert [w for w in said if "material_index ignored" in str(w.message)]
    assert [(n.name, n.faces) for n in report.names] == [(None, 2)]


def write_gltf(folder: Path, parts, *, binary_name: str = "room_buffer_0.bin", scale: float = 1.0) -> Path:
    """A glTF 2.0 (JSON) whose one buffer lies in `binary_name` beside it: one primitive a part of
    (material name, z-up mesh), written Y-up as the specification says, lengths times `scale`."""
    primitives = []
    for name, mesh in parts:
        x, y, z = (np.asarray(mesh.vertices) * scale).T
        primitives.append((name, np.stack([x, z, -y], axis=1), np.asarray(mesh.faces)))  # z-up -> Y-up (x, z, -y)
    doc, blob = gltf_document(primitives)
    doc["buffers"][0]["uri"] = binary_name
    (folder / binary_name).write_bytes(blob)
    path = folder / "room.gltf"
    path.write_text(json.dumps(doc))
    return path


def gltf_suite(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    write_gltf(folder, room_parts())
    (folder / "room_materials.toml").write_text(TABLE)
    path = folder / "suite.toml"
    path.write_text(SUITE.format(mesh="room.gltf", table="room_materials.toml").replace('up = "z"\nunits = "m"\n', ""))
    return path


def test_a_gltf_hash_covers_its_buffer_files(tmp_path, monkeypatch):
    """Rewriting the .gltf's .bin with the room 1.25 times larger (the .gltf itself unchanged)
    changes the mesh's hash and the plan id, and a worker holding the earlier plan refuses the file
    as changed; the .bin gone, the suite is refused naming it."""
    path = gltf_suite(tmp_path / "suite")
    mesh = load_suite(path).scenarios[0].mesh
    before = plan(load_suite(path), tmp_path / "out", frames=4)[0].plan_id
    (tmp_path / "larger").mkdir()
    write_gltf(tmp_path / "larger", room_parts(), scale=1.25)
    (tmp_path / "suite" / "room_buffer_0.bin").write_bytes((tmp_path / "larger" / "room_buffer_0.bin").read_bytes())
    scene, _ = mesh_import.load(tmp_path / "suite" / "room.gltf", materials=tmp_path / "suite" / "room_materials.toml")
    np.testing.assert_allclose(scene.mesh.extents, np.array([4.0, 3.0, 2.5]) * 1.25, rtol=1e-6)  # other geometry
    assert mesh_scenarios.mesh_sha256(mesh.path) != mesh.sha256
    assert plan(load_suite(path), tmp_path / "out", frames=4)[0].plan_id != before
    monkeypatch.setattr(mesh_scenarios, "_SCENES", {})
    with pytest.raises(ValueError, match="changed since its suite was loaded"):
        mesh_scenarios.mesh_scene(mesh)
    (tmp_path / "suite" / "room_buffer_0.bin").unlink()
    with pytest.raises(
        FileNotFoundError, match=r"scenarios\[0\].*room\.gltf.*'room_buffer_0\.bin' \(buffers\[0\]\.uri\)"
    ):
        load_suite(path)


def test_a_gltf_hash_covers_its_images_in_order_and_skips_data_uris(tmp_path):
    """A .gltf naming an image file and a buffer as a data: URI: its hash changes with the image's
    bytes, and equals SHA-256 over its own bytes then each referenced file's digest."""
    doc = {"asset": {"version": "2.0"}, "buffers": [{"uri": "data:application/octet-stream;base64,AAAA"}]}
    doc["images"] = [{"uri": "wall%20paint.png"}, {"bufferView": 0}]  # percent-encoded, as URIs are
    path = tmp_path / "textured.gltf"
    path.write_text(json.dumps(doc))
    (tmp_path / "wall paint.png").write_bytes(b"first")
    first = mesh_scenarios.mesh_sha256(path)
    expected = hashlib.sha256(path.read_bytes() + b"\0" + hashlib.sha256(b"first").hexdigest().encode())
    assert first == expected.hexdigest()
    (tmp_path / "wall paint.png").write_bytes(b"other")
    assert mesh_scenarios.mesh_sha256(path) != first


def test_a_dataset_records_what_each_mesh_name_became(tmp_path):
    """The manifest's fields and the card's table (`SuiteRenderer.describe`) list each material name
    of the room with its faces: floor (2 triangles) floor by name, walls (8) brick and crate (12)
    wood by the table, ceiling (2) ceiling_tile by name."""
    suite = load_suite(write_suite(tmp_path))
    about = SuiteRenderer(mesh_files(suite)).describe(plan(suite, tmp_path / "out", frames=4))
    mapped = about.fields["meshes"]["room"]["material_map"]
    assert [(m["name"], m["material"], m["faces"]) for m in mapped] == [
        ("floor", "floor", 2),
        ("walls", "brick", 8),
        ("ceiling", "ceiling_tile", 2),
        ("crate", "wood", 12),
    ]
    assert mapped[1]["rule"] == "table: 'walls'" and json.loads(json.dumps(mapped)) == mapped
    rows = dict(row for table in about.tables for row in table.rows)
    assert rows["room: `walls`"] == "brick (8 faces; table: 'walls')"
    assert rows["room: `ceiling`"].startswith("ceiling_tile (2 faces; name contains 'ceiling')")
