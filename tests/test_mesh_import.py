"""Mesh import: up axis and unit from the format or checked against a building (a Y-up file, a
millimetre file), handedness kept, material names of OBJ/GLB/PLY files mapped to ours and reported.

Files are written here from their specifications (OBJ text, glTF binary by hand, PLY text), so
that neither trimesh's exporters nor our reader define what the file holds.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import warnings

import numpy as np
import pytest
import trimesh

import scenes
from acoustic_sim.cli import main
from scenes.mesh_import import load
from tests.gltf_files import gltf_document, gltf_text

ROOM = (8.0, 6.0, 2.5)  # x forward, y left, z up [m]
PILLAR = (1.5, 4.5)  # (x, y) of a 0.4 m square pillar: on the left when facing +x (y > 3)


def room_z_up() -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """The room's shell (0..ROOM) and its pillar, z up, closed boxes with outward normals."""
    shell = trimesh.creation.box(extents=ROOM)
    shell.apply_translation(np.array(ROOM) / 2)
    pillar = trimesh.creation.box(extents=(0.4, 0.4, ROOM[2]))
    pillar.apply_translation((*PILLAR, ROOM[2] / 2))
    return shell, pillar


def as_y_up(points: np.ndarray) -> np.ndarray:
    """Z-up (forward x, left y, up z) points in a right-handed Y-up file. There up is +Y; facing
    +X, left is up x forward = Y x X = -Z; so X = x, Y = z, Z = -y."""
    x, y, z = np.asarray(points, dtype=np.float64).T
    return np.stack([x, z, -y], axis=1)


def obj_text(parts: list[tuple[str, np.ndarray, np.ndarray]]) -> str:
    """OBJ of (directive line or "", vertices, triangles) parts, one vertex list, 1-based indices."""
    lines, offset = [], 1
    for directive, vertices, faces in parts:
        lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices).tolist()]
        lines += [directive] if directive else []
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in faces]
        offset += len(vertices)
    return "\n".join(lines) + "\n"


def write_glb(path, primitives: list[tuple[str, np.ndarray, np.ndarray]]) -> None:
    """A glTF 2.0 binary (GLB) by the specification: one mesh whose primitives are (material name,
    positions (N, 3), triangles (M, 3)), one node, one scene."""
    doc, blob = gltf_document(primitives)
    text = gltf_text(doc)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(blob), b"BIN\0") + blob
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)


def imported(source, **kwargs):
    """load(...) with the warnings it gives: (scene, report, [warning texts])."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene, report = load(source, **kwargs)
    return scene, report, [str(w.message) for w in caught]


def face_materials(scene: scenes.Scene) -> np.ndarray:
    return np.array([scene.materials[i].name for i in scene.face_material])


def assert_upright_room(scene: scenes.Scene) -> None:
    """The z-up room: the pillar stands on the left (nearer the wall at largest y: facing +x, +y is
    left), still a closed box of positive volume (a mirror turns its faces inside out), and the
    room spans 0..ROOM exactly."""
    lo, hi = scene.mesh.bounds
    centres = scene.mesh.triangles_center
    pillar_at = lo[:2] + np.array([PILLAR[0], ROOM[1] - PILLAR[1]])  # the pillar if y were mirrored in the room
    mirrored = np.hypot(*(centres[:, :2] - pillar_at).T) < 0.3
    near = np.hypot(centres[:, 0] - lo[0] - PILLAR[0], centres[:, 1] - lo[1] - PILLAR[1]) < 0.3
    assert not mirrored.any() and near.sum() == 12, "the pillar is not on the left"
    assert hi[2] - lo[2] == pytest.approx(ROOM[2]), "the height is not along z"
    pillar = trimesh.Trimesh(scene.mesh.vertices, scene.mesh.faces[near])
    assert pillar.volume == pytest.approx(0.4 * 0.4 * ROOM[2], rel=1e-5), "the pillar is inside out"
    np.testing.assert_allclose(scene.mesh.bounds, [[0, 0, 0], ROOM], atol=1e-6)


def test_gltf_is_y_up_by_specification_and_keeps_its_handedness(tmp_path):
    """A hand-written GLB of the room, Y up: read without options it stands upright, the pillar
    still on the left, no warning; the report names glTF's specification for the axis and unit."""
    shell, pillar = room_z_up()
    parts = [
        ("Wall paint", as_y_up(shell.vertices), shell.faces),
        ("Steel pillar", as_y_up(pillar.vertices), pillar.faces),
    ]
    write_glb(tmp_path / "room.glb", parts)
    as_read = trimesh.load(tmp_path / "room.glb").to_geometry()  # trimesh itself does not turn glTF
    np.testing.assert_allclose(as_read.bounds, [[0, 0, -ROOM[1]], [ROOM[0], ROOM[2], 0]], atol=1e-6)
    scene, report, said = imported(tmp_path / "room.glb")
    assert_upright_room(scene)
    assert said == []
    assert (report.up, report.units) == ("y", "m") and "glTF" in report.up_reason and "glTF" in report.units_reason
    assert np.allclose(report.size_m, ROOM)


def test_y_up_obj_is_warned_with_the_fix_and_up_y_stands_it_upright(tmp_path):
    """The room as a Y-up OBJ (as Blender writes it): read z up it is 6 m tall and 2.5 m wide, and
    the warning names --up y; with up="y" it is the room, pillar on the left, without a warning."""
    shell, pillar = room_z_up()
    path = tmp_path / "room.obj"
    path.write_text(
        obj_text([("", as_y_up(shell.vertices), shell.faces), ("", as_y_up(pillar.vertices), pillar.faces)])
    )
    scene, report, said = imported(path)
    np.testing.assert_allclose(scene.mesh.extents, (8.0, 2.5, 6.0), atol=1e-6)
    assert report.up == "z" and len(said) == 1 and "lying on its side" in said[0] and "--up y" in said[0]
    scene, report, said = imported(path, up="y")
    assert_upright_room(scene)
    assert said == [] and report.up_reason == "given"


def test_a_z_up_obj_gives_no_warning(tmp_path):
    """The same room written z up (as examples/building.obj is): read as it is, silently."""
    shell, pillar = room_z_up()
    path = tmp_path / "room.obj"
    path.write_text(obj_text([("", shell.vertices, shell.faces), ("", pillar.vertices, pillar.faces)]))
    scene, report, said = imported(path)
    assert_upright_room(scene)
    assert said == [] and (report.up, report.units) == ("z", "m") and report.up_reason.startswith("assumed")


@pytest.mark.parametrize(("unit", "metres"), [("mm", 1e-3), ("cm", 1e-2)])
def test_a_millimetre_or_centimetre_obj_is_refused_naming_its_unit(tmp_path, unit, metres):
    """The room in mm is 8000 m across, in cm 250 m tall: refused, the first fix named being the
    file's unit and the size it would give; with that unit the room is right to the micrometre."""
    shell, pillar = room_z_up()
    path = tmp_path / "room.obj"
    path.write_text(
        obj_text([("", shell.vertices / metres, shell.faces), ("", pillar.vertices / metres, pillar.faces)])
    )
    with pytest.raises(scenes.SceneError, match=rf"give --units {unit} \(it would be 8 x 6 x 2\.5 m\)"):
        load(path)
    scene, report, said = imported(path, units=unit)
    assert_upright_room(scene)
    assert said == [] and report.units == unit
    scene, _, said = imported(path, units="m")  # given, the unit is kept: a warning, no refusal
    assert scene.mesh.extents.max() > 250 and len(said) == 1 and f"--units {unit}" in said[0]


def test_a_6000_m_footprint_is_refused_naming_the_units_that_fit(tmp_path):
    """A plan-like mesh 6000 x 4000 m across and 30 m tall (under the height limit): refused for
    its width, the fixes named with the sizes they give."""
    path = tmp_path / "site.stl"
    trimesh.creation.box(extents=(6000.0, 4000.0, 30.0)).export(path)
    with pytest.raises(scenes.SceneError, match=r"6000 m across.*--units mm \(it would be 6 x 4 x 0\.03 m\)"):
        load(path)


def test_a_mesh_smaller_than_a_robot_is_warned(tmp_path):
    path = tmp_path / "toy.stl"
    trimesh.creation.box(extents=(0.3, 0.2, 0.1)).export(path)
    _, _, said = imported(path)
    assert len(said) == 1 and "smaller than a robot" in said[0]


def band(i: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` triangles standing at x = 10 i .. 10 i + 1 (so each part's faces can be told apart)."""
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1]], dtype=float)
    vertices = np.concatenate([corners + np.array([10.0 * i, 1.0 + k, 0.0]) for k in range(count)])
    return vertices, np.arange(3 * count).reshape(count, 3)


def assert_faces_by_band(scene: scenes.Scene, expected: list[str]) -> None:
    """Every face in band i (x = 10 i .. 10 i + 1) got material expected[i]."""
    got = face_materials(scene)
    which = np.floor(scene.mesh.triangles_center[:, 0] / 10.0).astype(int)
    for i, name in enumerate(expected):
        assert (got[which == i] == name).all(), (i, name, got[which == i])


def test_obj_usemtl_names_map_by_table_then_patterns_and_are_reported(tmp_path):
    """An OBJ with groups and usemtl and no .mtl: its faces before any usemtl (1) keep the default;
    FloorTiles (2 + 1 faces in two runs) is floor by its name, Wall_North (3) brick by the table,
    Material.001 (1) maps to nothing: the default, named in a warning and in the report."""
    parts = [
        ("", *band(0, 1)),
        ("g room\nusemtl FloorTiles", *band(1, 2)),
        ("usemtl Wall_North", *band(2, 3)),
        ("usemtl Material.001", *band(3, 1)),
        ("g furniture\nusemtl FloorTiles", *band(1, 1)),
    ]
    path = tmp_path / "named.obj"
    path.write_text(obj_text(parts))
    scene, report, said = imported(path, materials={"wall_*": "brick", "Ceil*": "ceiling_tile"}, material="wood")
    assert [(n.name, n.material, n.faces) for n in report.names] == [
        (None, "wood", 1),
        ("FloorTiles", "floor", 3),
        ("Wall_North", "brick", 3),
        ("Material.001", "wood", 1),
    ]
    assert report.unmapped == ("Material.001",) and report.unused_keys == ("Ceil*",)
    assert_faces_by_band(scene, ["wood", "floor", "brick", "wood"])
    assert any("'Material.001'" in s and "got wood" in s for s in said)
    assert any("'Ceil*'" in s for s in said)
    assert "'Wall_North': 3 faces -> brick (table: 'wall_*')" in report.text()
    assert json.loads(json.dumps(report.to_dict()))["names"][1]["faces"] == 3


@pytest.mark.parametrize("directive", ["g", "o"])
def test_obj_groups_or_objects_name_the_faces_where_there_is_no_usemtl(tmp_path, directive):
    """Without usemtl the groups (or objects) name the faces: ceiling_01, glass door, sofa."""
    parts = [(f"{directive} ceiling_01", *band(0, 2)), (f"{directive} glass door", *band(1, 1))]
    parts.append((f"{directive} Sofa", *band(2, 2)))
    path = tmp_path / "groups.obj"
    path.write_text(obj_text(parts))
    scene, report, _ = imported(path)
    assert [(n.name, n.material, n.faces) for n in report.names] == [
        ("ceiling_01", "ceiling_tile", 2),
        ("glass door", "glass", 1),
        ("Sofa", "fabric", 2),
    ]
    assert_faces_by_band(scene, ["ceiling_tile", "glass", "fabric"])


def test_glb_material_slots_map_to_ours(tmp_path):
    """A GLB whose mesh has two primitives, materials "Concrete" (4 faces) and "Glass_pane"
    (2 faces): by name painted_wall and glass; a table entry turns the glass to metal."""
    slots = [("Concrete", *band(0, 4)), ("Glass_pane", *band(1, 2))]
    write_glb(tmp_path / "slots.glb", [(name, as_y_up(v), f) for name, v, f in slots])
    scene, report, said = imported(tmp_path / "slots.glb")
    assert said == []
    assert sorted((n.name, n.material, n.faces) for n in report.names) == [
        ("Concrete", "painted_wall", 4),
        ("Glass_pane", "glass", 2),
    ]
    assert_faces_by_band(scene, ["painted_wall", "glass"])
    scene, report, _ = imported(tmp_path / "slots.glb", materials={"glass_PANE": "metal"})
    assert_faces_by_band(scene, ["painted_wall", "metal"])


def test_ply_material_index_slots(tmp_path):
    """A PLY whose faces carry material_index 0, 1, 1: slots material_0 and material_1."""
    vertices, faces = band(0, 1)
    more, more_faces = band(1, 2)
    points = np.concatenate([vertices, more])
    rows = [(f, 0) for f in faces] + [(f + 3, 1) for f in more_faces]
    header = "ply\nformat ascii 1.0\nelement vertex 9\nproperty float x\nproperty float y\nproperty float z\n"
    header += "element face 3\nproperty list uchar int vertex_indices\nproperty int material_index\nend_header\n"
    body = "".join(f"{x} {y} {z}\n" for x, y, z in points) + "".join(f"3 {a} {b} {c} {m}\n" for (a, b, c), m in rows)
    (tmp_path / "slots.ply").write_text(header + body)
    scene, report, _ = imported(tmp_path / "slots.ply", materials={"material_1": "metal"})
    assert [(n.name, n.material, n.faces) for n in report.names] == [
        ("material_0", "painted_wall", 1),
        ("material_1", "metal", 2),
    ]
    assert_faces_by_band(scene, ["painted_wall", "metal"])


@pytest.mark.parametrize(
    ("table", "message"),
    [
        (
            '[materials]\n"Floor*" = "concrete"\n',
            r"'Floor\*' = 'concrete' is not one of our materials; ours are brick,",
        ),
        ("[materials]\nMaterial.001 = 'wood'\n", r"'Material' holds a table; quote names with dots: \"Material\.001\""),
        ('[material]\nfloor = "floor"\n', r"must hold one \[materials\] table"),
        ("[materials\n", r"is not valid TOML"),
    ],
)
def test_a_bad_material_table_is_refused_naming_the_entry(tmp_path, table, message):
    (tmp_path / "table.toml").write_text(table)
    with pytest.raises(scenes.SceneError, match=message):
        scenes.from_mesh(trimesh.creation.box(), materials=tmp_path / "table.toml")


def test_a_mesh_given_in_python_is_taken_as_it_is():
    """A Trimesh from Python: z up, metres, vertices untouched, nothing warned; up/units convert it."""
    box = trimesh.creation.box(extents=(0.2, 0.1, 3.0))  # tall and thin: no file, so no guessing
    scene, report, said = imported(box)
    assert said == [] and np.allclose(scene.mesh.extents, (0.2, 0.1, 3.0))
    assert report.source is None and report.names[0].name is None
    scene, _, _ = imported(box, up="y", units="cm")
    assert np.allclose(scene.mesh.extents, (0.002, 0.03, 0.001))


def test_render_cli_prints_the_import_report(tmp_path, capsys, device):
    """render --mesh with --up y and --materials: the room is driven upright and the report printed."""
    shell, pillar = room_z_up()
    shell = trimesh.Trimesh(shell.vertices, shell.faces[:, ::-1])  # walls face into the room
    path = tmp_path / "room.obj"
    path.write_text(
        obj_text(
            [
                ("usemtl Paint", as_y_up(shell.vertices), shell.faces),
                ("usemtl Column", as_y_up(pillar.vertices), pillar.faces),
            ]
        )
    )
    (tmp_path / "table.toml").write_text('[materials]\nColumn = "metal"\n')
    argv = ["render", "--mesh", str(path), "--up", "y", "--materials", str(tmp_path / "table.toml")]
    assert main([*argv, "--frames", "5", "--device", device, "--out", str(tmp_path / "room.png")]) == 0
    out = capsys.readouterr().out
    assert "y up (given)" in out and "'Paint': 12 faces -> painted_wall (name contains 'paint')" in out
    assert "'Column': 12 faces -> metal (table: 'Column')" in out and "size_m=[8.0, 6.0, 2.5]" in out


def test_render_cli_refuses_a_millimetre_mesh_in_one_line(tmp_path):
    shell, _ = room_z_up()
    path = tmp_path / "room_mm.obj"
    path.write_text(obj_text([("", shell.vertices * 1000, shell.faces)]))
    command = [sys.executable, "-m", "acoustic_sim", "render", "--mesh", str(path), "--out", str(tmp_path / "m.png")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.startswith("error: ") and "--units mm (it would be 8 x 6 x 2.5 m)" in done.stderr
