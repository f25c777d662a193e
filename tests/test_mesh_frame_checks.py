"""The import's doubts about an assumed frame: every usual room written Y-up (Blender's OBJ) is
warned about when read z up, the same rooms written z up are not; a room in inches (94.5 m tall
read in metres) is warned about naming --units in, not refused. In a suite the same advice reads
as its fields (`up = "y"`, `units = "in"`)."""

from __future__ import annotations

import contextlib
import warnings

import numpy as np
import pytest
import trimesh

from acoustic_sim.datasets import mesh_scenarios
from scenes import SceneError

from .test_mesh_import import as_y_up, imported, obj_text

USUAL_ROOMS = [(8.0, 6.0, 3.0), (5.0, 5.0, 3.0), (4.0, 3.0, 2.5), (12.0, 5.0, 3.0)]  # x, y, z up [m]


def write_room(path, size, *, y_up: bool = False, metres: float = 1.0):
    """A closed box room of `size` (x, y, z up) [m] with its corner at the origin, as an OBJ in
    units of `metres`, written Y-up (as Blender does) or z up."""
    box = trimesh.creation.box(extents=size)
    box.apply_translation(np.asarray(size) / 2)
    vertices = as_y_up(box.vertices) if y_up else box.vertices
    path.write_text(obj_text([("", vertices / metres, box.faces)]))
    return path


@pytest.mark.parametrize("size", USUAL_ROOMS)
def test_a_y_up_room_read_z_up_is_warned_naming_both_fixes(tmp_path, size):
    """Written Y-up its height lies along the file's y: read z up it is taller than it is deep,
    one warning naming --up y (the fix) and --up z (to say it stands upright); the same room
    written z up gives none, and --up y stands the Y-up one upright without a word."""
    lying = write_room(tmp_path / "lying.obj", size, y_up=True)
    scene, report, said = imported(lying)
    np.testing.assert_allclose(scene.mesh.extents, (size[0], size[2], size[1]), atol=1e-6)
    assert report.up == "z" and len(said) == 1, said
    assert "--up y" in said[0] and "--up z" in said[0] and "lying on its side" in said[0]
    scene, _, said = imported(lying, up="y")
    np.testing.assert_allclose(scene.mesh.extents, size, atol=1e-6)
    assert said == []
    _, report, said = imported(write_room(tmp_path / "upright.obj", size))
    assert said == [] and report.up_reason.startswith("assumed")


def test_a_narrow_corridor_said_upright_is_not_warned(tmp_path):
    """A corridor 1.2 m wide in y and 2.5 m tall, z up: warned, --up z silences it."""
    path = write_room(tmp_path / "corridor.obj", (20.0, 1.2, 2.5))
    assert len(imported(path)[2]) == 1
    assert imported(path, up="z")[2] == []


def test_a_room_in_inches_is_warned_naming_inches_not_refused(tmp_path):
    """8 x 6 x 2.4 m in inches reads 315 x 236 x 94.5 m in metres (under the 100 m refusal):
    loaded, with one warning whose first fix is inches and the size they give; in inches it is
    the room, silently; with metres given, the tall hall is taken as said."""
    path = write_room(tmp_path / "room_in.obj", (8.0, 6.0, 2.4), metres=0.0254)
    scene, report, said = imported(path)
    np.testing.assert_allclose(scene.mesh.extents, np.array([8.0, 6.0, 2.4]) / 0.0254, rtol=1e-9)
    assert report.units == "m" and len(said) == 1, said
    assert "94.49 m tall" in said[0] and "give --units in (it would be 8 x 6 x 2.4 m)" in said[0]
    assert "--units m" in said[0]  # how to say it is that tall
    scene, _, said = imported(path, units="in")
    np.testing.assert_allclose(scene.mesh.extents, (8.0, 6.0, 2.4), atol=1e-6)
    assert said == []
    assert imported(path, units="m")[2] == []


def test_a_building_of_storeys_in_metres_is_not_warned(tmp_path):
    """A 40 x 30 x 28 m block of storeys, under the 30 m limit, in metres: silent."""
    assert imported(write_room(tmp_path / "block.obj", (40.0, 30.0, 28.0)))[2] == []


def test_a_suite_names_the_fixes_as_its_fields(tmp_path):
    """The same doubts about a suite's mesh name the suite's fields, TOML strings as written (the
    room in inches is then refused too: 315 x 236 m is too wide to map for driving)."""
    write_room(tmp_path / "lying.obj", (8.0, 6.0, 3.0), y_up=True)
    write_room(tmp_path / "room_in.obj", (8.0, 6.0, 2.4), metres=0.0254)
    for mesh, advice in (("lying.obj", 'give up = "y"'), ("room_in.obj", 'give units = "in" (it would be 8 x 6')):
        with warnings.catch_warnings(record=True) as caught, contextlib.suppress(SceneError):
            warnings.simplefilter("always")
            mesh_scenarios.mesh_file({"mesh": mesh}, tmp_path, "suite.toml scenario 'room'")
        said = [str(w.message) for w in caught]
        assert len(said) == 1 and advice in said[0] and "--" not in said[0], said
