"""Scene builders, SVG import, mesh import and the errors bad input must give."""

import warnings

import numpy as np
import pytest
import trimesh

import scenes
from scenes import SceneError

SVG_HEAD = '<svg xmlns="http://www.w3.org/2000/svg">'


@pytest.mark.parametrize(
    "build",
    [
        lambda seed: scenes.office(seed=seed),
        lambda seed: scenes.corridor(reflectors="many", seed=seed),
        lambda seed: scenes.random_world(seed=seed),
    ],
)
def test_builders_are_valid_and_seeded(build):
    """Finite geometry, a material for every face, same seed -> same mesh, new seed -> new mesh."""
    a, b, c = build(0), build(0), build(1)
    assert np.isfinite(a.mesh.vertices).all() and a.face_count > 12
    assert a.face_material.shape == (a.face_count,)
    assert set(np.unique(a.face_material)) == set(range(len(a.materials)))
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    assert a.mesh.vertices.shape != c.mesh.vertices.shape or not np.allclose(a.mesh.vertices, c.mesh.vertices)


def test_box_room_is_closed_with_inward_normals():
    """The 6 x 4 x 3 m shoebox is watertight, spans its size, and every normal points inside."""
    scene = scenes.box_room((6.0, 4.0, 3.0))
    assert scene.mesh.is_watertight
    np.testing.assert_allclose(scene.mesh.bounds, [[0, 0, 0], [6, 4, 3]])
    inward = (np.array([3.0, 2.0, 1.5]) - scene.mesh.triangles_center) * scene.mesh.face_normals
    assert (inward.sum(axis=1) > 0).all()
    names = {m.name for m in scene.materials}
    assert names == {"floor", "painted_wall"}


def test_reflector_counts_grow_with_clutter():
    """'many' corridors carry door frames, radiators and skirting: far more faces than 'few';
    a high-clutter office has more objects than a low-clutter one; offices have LiDAR-clear glass."""
    assert scenes.corridor(reflectors="many").face_count > 5 * scenes.corridor(reflectors="few").face_count
    assert scenes.office(clutter="high").face_count > scenes.office(clutter="low").face_count
    glass = [m for m in scenes.office(clutter="medium").materials if m.name == "glass"]
    assert glass and glass[0].lidar_transparent


def test_random_world_counts_and_scale():
    """Explicit counts give that many walls (12 faces) and cylinders (48 sides) when they fit."""
    scene = scenes.random_world(seed=2, wall_count=2, cylinder_count=3, object_scale=0.5)
    assert scene.face_count == 12 + 2 * 12 + 3 * (48 * 4)


def section_extent(scene, height=1.0):
    segments, _ = scene.section(height)
    pts = segments.reshape(-1, 2)
    return pts.min(axis=0), pts.max(axis=0)


def test_svg_line_becomes_a_wall():
    """A 200-unit line at scale 0.01 -> a 2 m wall (+ thickness at the ends), 0.1 m thick, 2.5 m high."""
    scene = scenes.from_svg(SVG_HEAD + '<line x1="0" y1="0" x2="200" y2="0"/></svg>', ceiling=False)
    walls = scene.mesh.submesh([np.flatnonzero(scene.face_material == 0)], append=True)
    np.testing.assert_allclose(walls.extents, [2.1, 0.1, 2.5], atol=1e-9)


def test_svg_rect_transform_and_circle():
    """A translated 400 x 300 rect -> a closed 4 x 3 m room outline; a circle of r = 50 -> a pillar
    of 0.5 m radius at its (flipped, shifted) centre; the group transform is applied."""
    svg = (
        SVG_HEAD + '<g transform="translate(100,50)"><rect x="0" y="0" width="400" height="300"/></g>'
        '<circle cx="200" cy="150" r="50"/></svg>'
    )
    scene = scenes.from_svg(svg, scale=0.01, wall_thickness=0.1)
    lo, hi = section_extent(scene)
    np.testing.assert_allclose(hi - lo, [4.1, 3.1], atol=1e-6)
    segments, faces = scene.section(1.0)
    pillar = scene.face_material[faces] == scene.materials.index(scenes.MATERIALS["painted_wall"])
    pts = segments.reshape(-1, 2)
    # The pillar centre: svg (200, 150) -> world (2.0, -1.5) minus the plan's lower-left corner.
    centre = np.array([2.0, -1.5]) - (np.array([1.0, -3.5]) - 0.1)
    radius = np.linalg.norm(pts - centre, axis=1)
    assert np.sum(np.abs(radius - 0.5) < 1e-6) >= 48 and pillar.any()


def test_svg_curved_path_and_polyline():
    """A quadratic curve is walled in short pieces; a polyline gives one wall per segment."""
    curve = scenes.from_svg(SVG_HEAD + '<path d="M 0 0 Q 100 100 200 0"/></svg>', ceiling=False)
    poly = scenes.from_svg(SVG_HEAD + '<polyline points="0,0 100,0 100,100"/></svg>', ceiling=False)
    assert curve.face_count - 2 >= 12 * 10  # >= 10 wall boxes of 12 faces, plus the floor
    assert poly.face_count == 2 * 12 + 2


@pytest.mark.parametrize(
    "svg, message",
    [
        (SVG_HEAD + '<text x="0" y="0">hello</text></svg>', "no usable shapes"),
        ("<svg><unclosed", "could not parse"),
        ("/nonexistent/plan.svg", "not found"),
    ],
)
def test_svg_errors(svg, message):
    with pytest.raises(SceneError, match=message):
        scenes.from_svg(svg)


def test_from_mesh_file_and_trimesh(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    path = tmp_path / "box.stl"
    box.export(path)
    scene = scenes.from_mesh(str(path), material="metal")
    assert scene.face_count == 12 and scene.materials[0].name == "metal"
    assert scenes.from_mesh(box).face_count == 12
    assert scenes.from_mesh(path).face_count == 12  # pathlib.Path too


def test_bad_meshes_raise_clear_errors():
    with pytest.raises(SceneError, match="empty"):
        scenes.from_mesh(trimesh.Trimesh())
    box = trimesh.creation.box()
    vertices = box.vertices.copy()
    vertices[0, 1] = np.nan
    with pytest.raises(SceneError, match="non-finite"):
        scenes.from_mesh(trimesh.Trimesh(vertices, box.faces, process=False))
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2], [0, 0, 1]], process=False)
    with pytest.raises(SceneError, match="degenerate"):
        scenes.from_mesh(flat)
    with pytest.raises(SceneError, match="could not load"):
        scenes.from_mesh("/nonexistent/mesh.obj")
    with pytest.raises(SceneError, match=r"trimesh\.Trimesh"):
        scenes.from_mesh(np.zeros((3, 3)))


def test_some_degenerate_faces_are_dropped_with_a_warning():
    box = trimesh.creation.box()
    faces = np.vstack([box.faces, [[0, 0, 1]]])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = scenes.from_mesh(trimesh.Trimesh(box.vertices, faces, process=False))
    assert scene.face_count == 12
    assert any("degenerate" in str(w.message) for w in caught)


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: scenes.box_room((0.1, 4.0, 3.0)), "too small"),
        (lambda: scenes.box_room((np.nan, 4.0, 3.0)), "finite"),
        (lambda: scenes.office(clutter="extreme"), "clutter"),
        (lambda: scenes.corridor(reflectors="lots"), "reflectors"),
        (lambda: scenes.random_world(object_scale=0.0), "object_scale"),
        (lambda: scenes.from_mesh(trimesh.creation.box(), material="unobtainium"), "unknown material"),
    ],
)
def test_bad_builder_arguments(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_describe_is_json_with_builder_params():
    import json

    info = json.loads(scenes.office(seed=3, clutter="low").describe())
    assert info["name"] == "office" and info["params"]["seed"] == 3 and info["params"]["clutter"] == "low"
    assert {m["name"] for m in info["materials"]} >= {"painted_wall", "wood"}


def test_random_world_warns_when_objects_do_not_fit():
    """Asking for 60 cylinders in a 3.5 x 3.5 m room: most cannot keep their passages free, and it
    says so (as office does) instead of silently building a sparser world."""
    with pytest.warns(UserWarning, match=r"random_world: \d+ objects did not fit"):
        scenes.random_world(size=(3.5, 3.5, 2.5), wall_count=0, cylinder_count=60, seed=1)


@pytest.mark.parametrize(
    "shape",
    ['<path d="M 10 10 L nan 20"/>', '<line x1="20" y1="20" x2="NaN" y2="40"/>', '<circle cx="inf" cy="50" r="5"/>'],
)
def test_svg_with_non_finite_coordinates_is_refused(shape, tmp_path):
    """A NaN or inf coordinate used to drop that wall silently; now it names the element."""
    path = tmp_path / "plan.svg"
    rect = '<rect x="0" y="0" width="100" height="100"/>'
    path.write_text(f'<svg xmlns="http://www.w3.org/2000/svg" width="100" height="100">{rect}{shape}</svg>')
    with pytest.raises(SceneError, match="non-finite"):
        scenes.from_svg(path, scale=0.05)


@pytest.mark.parametrize("build", [scenes.box_room, scenes.corridor, scenes.office, scenes.random_world])
def test_floor_material_lies_on_the_floor_and_ceiling_material_on_top(build):
    """Each shell material where it belongs: the floor's faces at the lowest point facing up,
    the ceiling's at the top facing down (once swapped by normals cached across Trimesh.invert)."""
    scene = build(seed=0)
    names = np.array([m.name for m in scene.materials])[scene.face_material]
    floor = names == "floor"
    assert floor.any() and np.allclose(scene.mesh.triangles_center[floor, 2], scene.floor_z)
    assert (scene.mesh.face_normals[floor, 2] > 0.99).all()
    top = scene.mesh.bounds[1, 2]
    ceiling = np.isclose(scene.mesh.triangles_center[:, 2], top) & (scene.mesh.face_normals[:, 2] < -0.99)
    expected = {"box_room": "painted_wall", "random_world": "painted_wall"}.get(scene.name, "ceiling_tile")
    assert ceiling.any() and set(names[ceiling]) == {expected}


def test_surface_classes_and_their_acoustics():
    """Walls, floor, ceiling and objects take their own reflection and scattering; the LiDAR's
    view of each material and the geometry stay as they were."""
    from scenes.surfaces import SURFACE_CLASSES, surface_classes, with_surfaces

    office = scenes.office(seed=0)
    classes = surface_classes(office)
    counts = {name: int((classes == i).sum()) for i, name in enumerate(SURFACE_CLASSES)}
    assert counts["floor"] == counts["ceiling"] == 2 and counts["walls"] >= 8 and counts["objects"] > 100
    drawn = {"walls": {"reflection": 0.6, "scattering": 0.4}, "floor": {"reflection": 0.5}, "objects": {}}
    changed = with_surfaces(office, drawn)
    reflection = changed.material_table("acoustic_reflection")
    scattering = changed.material_table("acoustic_scattering")
    assert (reflection[classes == 0] == 0.6).all() and (scattering[classes == 0] == 0.4).all()
    assert (reflection[classes == 1] == 0.5).all()
    before = office.material_table("acoustic_scattering")
    np.testing.assert_array_equal(scattering[classes != 0], before[classes != 0])
    lidar = changed.material_table("lidar_reflectivity")
    np.testing.assert_array_equal(lidar, office.material_table("lidar_reflectivity"))
    assert changed.mesh is office.mesh and changed.params["surfaces"] == drawn
    with pytest.raises(ValueError, match="unknown surface classes"):
        with_surfaces(office, {"roof": {"reflection": 0.5}})
    open_room = scenes.polygon_room("u_room", ceiling=None)
    assert (surface_classes(open_room) != SURFACE_CLASSES.index("ceiling")).all()


def test_box_mesh_is_trimeshs_box_bit_for_bit():
    """`box_mesh` builds trimesh's box without its transform's bookkeeping: the same vertices (every
    bit) and faces for boxes turned and moved, unturned at the origin, and flat; a scene's face
    order, and so every shard, stays as it was."""
    from scenes.scene import box_mesh

    rng = np.random.default_rng(0)
    for i in range(300):
        center = np.zeros(3) if i % 7 == 0 else rng.uniform(-5, 5, 3)
        extents = rng.uniform(0.01, 5, 3) * (1, 1, 1e-3 if i % 5 == 0 else 1)
        yaw = 0.0 if i % 3 == 0 else rng.uniform(-4, 4)
        transform = trimesh.transformations.rotation_matrix(yaw, (0, 0, 1))
        transform[:3, 3] = center
        theirs, ours = trimesh.creation.box(extents=extents, transform=transform), box_mesh(center, extents, yaw)
        assert np.array_equal(ours.vertices, theirs.vertices) and np.array_equal(ours.faces, theirs.faces), i
    with pytest.raises(ValueError, match="3 extents"):
        box_mesh((0, 0, 0), (1, 1))
