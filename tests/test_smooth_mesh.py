"""Round objects in any mesh echo off their true surface: a 2 cm ball and a 3 cm pole made by
`trimesh.creation` (not our builders), loaded through `scenes.from_mesh` as a Trimesh and from an
OBJ file, give their first-order specular echo within one sample of Fermat's shortest path over
the true surface, as strong as geometric optics says; boxes, prisms of 12 sides or fewer, parts
of round things, hollows and other shapes stay faceted (`scenes.smooth_fit`)."""

import dataclasses

import numpy as np
import pytest
import trimesh

import scenes
from acoustic_sim import Sonar, SonarConfig, TracerConfig
from acoustic_sim.engine.paths import KIND_SPECULAR
from scenes.scene import assemble
from scenes.smooth_fit import fit_curved_surfaces
from tests.test_curved_echoes import poses_around

ROOM = np.array([9.0, 9.0, 3.0])
BALL_CENTRE, BALL_RADIUS = np.array([4.5, 4.5, 1.0]), 0.01  # a 2 cm ball
POLE_XY, POLE_RADIUS, POLE_TOP = np.array([4.5, 4.5]), 0.015, 2.0  # a 3 cm pole, floor to 2 m
PIPE_CENTRE, PIPE_RADIUS, PIPE_LENGTH = np.array([4.5, 4.5, 1.2]), 0.05, 3.0  # a 10 cm pipe ...
PIPE_AXIS = np.array([1.0, 0.4, 0.3]) / np.linalg.norm([1.0, 0.4, 0.3])  # ... 16 deg off horizontal
SONAR = SonarConfig.ertis()
SAMPLE_M = SONAR.atmosphere.speed_of_sound / SONAR.chirp.sample_rate_hz  # path length of one sample
TRACER = TracerConfig(max_bounces=0, scattering=False, ray_count=1_000)  # round echoes need no rays
LOADS = ("trimesh", "obj")


def box_room() -> trimesh.Trimesh:
    """The inside of a ROOM-sized box: normals into the room."""
    box = trimesh.creation.box(extents=ROOM)
    box.apply_translation(ROOM / 2)
    return trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)


def ball() -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=BALL_RADIUS)
    return mesh.apply_translation(BALL_CENTRE)


def pole(sections: int = 32) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=POLE_RADIUS, height=POLE_TOP, sections=sections).apply_translation(
        (*POLE_XY, POLE_TOP / 2)
    )


def pipe() -> trimesh.Trimesh:
    transform = trimesh.geometry.align_vectors((0.0, 0.0, 1.0), PIPE_AXIS)
    transform[:3, 3] = PIPE_CENTRE
    return trimesh.creation.cylinder(radius=PIPE_RADIUS, height=PIPE_LENGTH, sections=48, transform=transform)


def loaded(objects: trimesh.Trimesh, how: str, folder) -> scenes.Scene:
    """`objects` in the box room, through `from_mesh` as one Trimesh or from an OBJ file."""
    mesh = trimesh.util.concatenate([box_room(), objects])
    if how == "trimesh":
        return scenes.from_mesh(mesh)
    path = folder / f"room_{len(mesh.faces)}.obj"
    mesh.export(path)
    return scenes.from_mesh(path)


def poses_beside_pipe(count, seed):
    """Poses 0.4-2.5 m from the pipe's axis, beside its middle 1.6 m, facing it within +-60 deg."""
    rng = np.random.default_rng(seed)
    across = np.cross(PIPE_AXIS, (0.0, 0.0, 1.0))
    across /= np.linalg.norm(across)
    side = rng.choice([-1.0, 1.0], count)
    spot = (
        PIPE_CENTRE
        + rng.uniform(-0.8, 0.8, count)[:, None] * PIPE_AXIS
        + (side * rng.uniform(0.4, 2.5, count))[:, None] * across
    )
    yaw = np.arctan2(-side * across[1], -side * across[0]) + rng.uniform(-np.pi / 3, np.pi / 3, count)
    return scenes.poses(spot[:, :2], yaw, spot[:, 2] + rng.uniform(-0.2, 0.2, count))


def emitter_and_receiver(pose):
    return (pose @ np.r_[SONAR.emitter_m, 1.0])[:3], pose[:3, 3]


def sphere_paths(poses, centre, radius):
    """Fermat: the specular path is the shortest emitter -> surface -> receiver path. Brute force
    over 100,000 points of the sphere, ~0.011 rad apart (path error ~1e-6 m at 1 cm); no use of
    the simulator's reflection-point solver."""
    unit = np.random.default_rng(0).normal(size=(100_000, 3))
    points = centre + radius * unit / np.linalg.norm(unit, axis=1, keepdims=True)
    return np.array([path_lengths(pose, points).min() for pose in poses])


def cylinder_paths(poses, base, axis, radius, length):
    """Fermat over the side of a cylinder from `base` along unit `axis`: brute force on a 1 deg x
    1 cm grid, then on a 0.02 deg x 0.2 mm grid around its best point (path error ~1e-7 m)."""
    first = np.cross(axis, (1.0, 0.0, 0.0) if abs(axis[0]) < 0.9 else (0.0, 1.0, 0.0))
    first /= np.linalg.norm(first)
    second = np.cross(axis, first)

    def side(phi, t):
        phi, t = np.meshgrid(phi, np.clip(t, 0.0, length))
        ring = radius * (np.cos(phi)[..., None] * first + np.sin(phi)[..., None] * second)
        return (base + ring + t[..., None] * axis).reshape(-1, 3), phi.reshape(-1), t.reshape(-1)

    coarse = side(np.deg2rad(np.arange(0.0, 360.0, 1.0)), np.arange(0.0, length + 0.01, 0.01))
    out = []
    for pose in poses:
        best = np.argmin(path_lengths(pose, coarse[0]))
        phi, t = coarse[1][best], coarse[2][best]
        fine = side(phi + np.deg2rad(np.arange(-1.0, 1.0, 0.02)), t + np.arange(-0.01, 0.01, 2e-4))
        out.append(path_lengths(pose, fine[0]).min())
    return np.array(out)


def path_lengths(pose, points):
    e, r = emitter_and_receiver(pose)
    return np.linalg.norm(points - e, axis=1) + np.linalg.norm(points - r, axis=1)


def first_order(arrivals, i):
    echoes = arrivals.for_pose(i)
    return echoes.select((echoes.kind == KIND_SPECULAR) & (echoes.order == 1))


def share_found(arrivals, want) -> float:
    """Fraction of poses with a first-order specular echo within one sample of `want` [m]."""
    found = [np.abs(first_order(arrivals, i).length_m - w).min(initial=np.inf) <= SAMPLE_M for i, w in enumerate(want)]
    return float(np.mean(found))


@pytest.fixture(scope="module")
def references():
    """Poses around each object and Fermat's path lengths for them, computed once for both loads."""
    around_ball = poses_around(BALL_CENTRE[:2], 200, 1, (0.9, 1.1))  # the ball at sensor height +-0.1 m
    around_pole = poses_around(POLE_XY, 200, 2, (0.15, 1.8))
    vertical = np.array([0.0, 0.0, 1.0])
    return {
        "ball": (around_ball, sphere_paths(around_ball, BALL_CENTRE, BALL_RADIUS)),
        "pole": (around_pole, cylinder_paths(around_pole, np.r_[POLE_XY, 0.0], vertical, POLE_RADIUS, POLE_TOP)),
    }


@pytest.mark.parametrize("how", LOADS)
def test_a_small_ball_and_pole_from_any_mesh_echo_at_fermats_delay(references, how, tmp_path, device):
    """200 poses around each: >= 99 % (before the fit: ~0 %) have a first-order specular echo
    within one sample (0.76 mm of path at 450 kHz) of the shortest path over the true surface."""
    sonar = Sonar(SONAR, TRACER, device=device)
    for name, objects in (("ball", ball()), ("pole", pole())):
        scene = loaded(objects, how, tmp_path)
        assert len(scene.curved) == 1, scene.curved
        poses, want = references[name]
        share = share_found(sonar.trace(scene, poses), want)
        assert share >= 0.99, f"{name} ({how}): {share:.1%} of the poses"


def test_a_tilted_pipe_echoes_at_fermats_delay(device):
    """A 10 cm pipe 16 deg off horizontal (any axis, not only vertical ones): 100 poses beside
    it, every one within one sample of Fermat's path."""
    poses = poses_beside_pipe(100, 3)
    want = cylinder_paths(poses, PIPE_CENTRE - PIPE_LENGTH / 2 * PIPE_AXIS, PIPE_AXIS, PIPE_RADIUS, PIPE_LENGTH)
    arrivals = Sonar(SONAR, TRACER, device=device).trace(loaded(pipe(), "trimesh", None), poses)
    assert share_found(arrivals, want) == 1.0


def broadside_amplitude(scene, centre, across, distance, radius, device):
    """Amplitude of the first-order echo off a round object `distance` [m] from its centre (or
    axis) along the horizontal unit vector `across`, the sensor facing it, the object halfway
    between the emitter and the array in height."""
    yaw = np.arctan2(-across[1], -across[0])
    spot = centre[:2] + distance * across[:2]
    pose = scenes.pose(*spot, yaw, centre[2] - SONAR.emitter_m[2] / 2)
    first = first_order(Sonar(SONAR, TRACER, device=device).trace(scene, pose[None]), 0)
    nearest = np.argmin(np.abs(first.length_m - 2 * (distance - radius)))
    assert abs(first.length_m[nearest] - 2 * (distance - radius)) < 5e-3  # its echo (bistatic), not a wall's
    return first.amplitude[nearest]


def test_echo_strengths_follow_geometric_optics(device):
    """A rigid ball (ka >> 1) returns a / (2 d^2) re 1 m of its material's specular gain (within
    5 % at d >= 0.5 m); a long pipe's echo falls as d^-1.5, a tilted one as a vertical one."""
    wall = scenes.material("painted_wall")  # from_mesh's one material
    gain = np.sqrt(wall.acoustic_reflection * (1 - wall.acoustic_scattering))
    room = loaded(ball(), "trimesh", None)
    for d in (0.5, 1.0, 2.0):
        got = broadside_amplitude(room, BALL_CENTRE, np.array([-1.0, 0.0, 0.0]), d, BALL_RADIUS, device)
        assert got / gain == pytest.approx(BALL_RADIUS / (2 * d * d), rel=0.05)
    across = np.cross(PIPE_AXIS, (0.0, 0.0, 1.0))
    across /= np.linalg.norm(across)
    room = loaded(pipe(), "trimesh", None)
    near, far = (broadside_amplitude(room, PIPE_CENTRE, across, d, PIPE_RADIUS, device) for d in (1.0, 2.0))
    assert near / far == pytest.approx(2**1.5, rel=0.05)


def test_fitted_surfaces_are_the_true_ones(tmp_path):
    """The fit recovers what trimesh.creation was given: centre, radius, axis and extent (1e-6 m
    from the OBJ's 8 decimals), the ball's every face and the pole's and pipe's sides only."""
    for how in LOADS:
        scene = loaded(trimesh.util.concatenate([ball(), pole().apply_translation((2.0, 0.0, 0.0))]), how, tmp_path)
        sphere, cylinder = sorted(scene.curved, key=lambda c: c.kind, reverse=True)
        assert sphere.kind == "sphere" and cylinder.kind == "cylinder"
        np.testing.assert_allclose(sphere.centre, BALL_CENTRE, atol=1e-6)
        assert sphere.radius == pytest.approx(BALL_RADIUS, abs=1e-6)
        np.testing.assert_allclose(cylinder.centre, (POLE_XY[0] + 2.0, POLE_XY[1], 0.0), atol=1e-6)
        assert cylinder.radius == pytest.approx(POLE_RADIUS, abs=1e-6)
        np.testing.assert_allclose(cylinder.z_range, (0.0, POLE_TOP), atol=1e-6)
        assert cylinder.axis == (0.0, 0.0, 1.0)
        sides = np.abs(scene.mesh.face_normals[:, 2]) < 0.5
        counts = np.bincount(scene.face_curved + 1, minlength=3)
        assert counts[0] == 12 + 2 * 32 and sorted(counts[1:]) == [64, 1280]  # room, caps | sides, ball
        assert sides[scene.face_curved == scene.curved.index(cylinder)].all()
    (tilted,), faces = fit_curved_surfaces(pipe())
    np.testing.assert_allclose(np.abs(tilted.axis @ PIPE_AXIS), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.ptp(tilted.z_range), PIPE_LENGTH, atol=1e-9)
    axis_point = np.asarray(tilted.centre) - (np.asarray(tilted.centre) - PIPE_CENTRE) @ PIPE_AXIS * PIPE_AXIS
    np.testing.assert_allclose(axis_point, PIPE_CENTRE, atol=1e-9)
    assert tilted.radius == pytest.approx(PIPE_RADIUS, rel=1e-9) and (faces >= 0).sum() == 2 * 48


def test_a_triangle_soup_is_welded_first():
    """Every face with its own corners (as OBJ files with per-face normals load): the ball and
    the pole are still found, on all their faces."""
    mesh = trimesh.util.concatenate([ball(), pole().apply_translation((2.0, 0.0, 0.0))])
    soup = trimesh.Trimesh(mesh.triangles.reshape(-1, 3), np.arange(3 * len(mesh.faces)).reshape(-1, 3), process=False)
    surfaces, faces = fit_curved_surfaces(soup)
    assert sorted(c.kind for c in surfaces) == ["cylinder", "sphere"] and (faces >= 0).sum() == 1280 + 64


def test_a_rebuilt_random_world_finds_the_builders_pillars():
    """A random world's mesh alone (its metadata gone), through from_mesh: the same three
    48-sided pillars as the builder made, on the same faces; its room and walls stay flat."""
    world = scenes.random_world(seed=3, cylinder_count=3, wall_count=3)
    found = scenes.from_mesh(trimesh.Trimesh(world.mesh.vertices, world.mesh.faces, process=False))
    assert len(found.curved) == len(world.curved) == 3
    assert np.array_equal(found.face_curved, world.face_curved)
    for got, want in zip(found.curved, world.curved, strict=True):
        np.testing.assert_allclose(got.centre, want.centre, atol=1e-9)
        assert got.radius == pytest.approx(want.radius, rel=1e-9) and got.axis == want.axis
        np.testing.assert_allclose(got.z_range, want.z_range, atol=1e-9)


def test_boxes_stay_flat_and_box_rooms_unchanged():
    """A cube and a box room: no curved surface, and every array of the scene the same as
    assembled without the fit (so their edges, mirrors and echoes are as before)."""
    cube = trimesh.creation.box(extents=(0.5, 0.5, 0.5)).apply_translation((2.0, 2.0, 0.25))
    mesh = trimesh.util.concatenate([box_room(), cube])
    fitted = scenes.from_mesh(mesh)
    plain = assemble([(mesh, "painted_wall")], name="mesh", params=fitted.params)
    assert fitted.curved == () and (fitted.face_curved == -1).all()
    for got, want in ((fitted.mesh.vertices, plain.mesh.vertices), (fitted.mesh.faces, plain.mesh.faces)):
        assert np.array_equal(got, want)
    assert np.array_equal(fitted.face_material, plain.face_material) and fitted.describe() == plain.describe()


@pytest.mark.parametrize(("sections", "round_"), [(6, False), (8, False), (12, False), (13, True), (32, True)])
def test_prisms_of_twelve_sides_or_fewer_are_faceted_on_purpose(sections, round_):
    """The crease rule: faces turning by 30 deg or more at an edge are meant flat (a hexagonal
    column keeps its six mirrors); 13 sides or more make a round pole."""
    surfaces, faces = fit_curved_surfaces(pole(sections))
    assert len(surfaces) == int(round_)
    assert (faces >= 0).sum() == (2 * sections if round_ else 0)


def test_icosahedron_is_faceted_and_an_icosphere_round():
    """Same rule for spheres: an icosahedron turns by 42 deg at its edges, an icosphere of one
    subdivision by at most 22 deg."""
    assert fit_curved_surfaces(trimesh.creation.icosphere(subdivisions=0))[0] == []
    assert [c.kind for c in fit_curved_surfaces(trimesh.creation.icosphere(subdivisions=1))[0]] == ["sphere"]


def half(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The faces of `mesh` on the side x > 0."""
    return mesh.submesh([np.flatnonzero(mesh.triangles_center[:, 0] > 0)], append=True)


def test_parts_hollows_rough_and_other_shapes_stay_faceted():
    """Only whole, convex, tight spheres and cylinders are taken: half a pillar or half a ball
    would echo from where nothing is, a round room or tank (normals inward) is seen from inside,
    a ball 1 mm rough is no 0.2 mm sphere, and a cone, a torus and a capsule are neither."""
    pillar = trimesh.creation.cylinder(radius=0.3, height=2.0, sections=48)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    rough = sphere.copy()
    rough.vertices += np.random.default_rng(0).uniform(-1e-3, 1e-3, rough.vertices.shape)
    shapes = {
        "half pillar": half(pillar),
        "half ball": half(sphere),
        "round room": trimesh.Trimesh(pillar.vertices, pillar.faces[:, ::-1]),
        "hollow ball": trimesh.Trimesh(sphere.vertices, sphere.faces[:, ::-1]),
        "rough ball": rough,
        "cone": trimesh.creation.cone(radius=0.3, height=1.0, sections=48),
        "torus": trimesh.creation.torus(major_radius=0.5, minor_radius=0.1),
        "capsule": trimesh.creation.capsule(height=1.0, radius=0.2),
    }
    found = {name: fit_curved_surfaces(mesh)[0] for name, mesh in shapes.items()}
    assert all(surfaces == [] for surfaces in found.values()), found


def round_room() -> trimesh.Trimesh:
    """A round room 3 m in radius and 3 m tall around the box room's middle, 48 sides, modelled as
    a solid (normals outward, as trimesh.creation or Blender make a cylinder used as a room)."""
    return trimesh.creation.cylinder(radius=3.0, height=3.0, sections=48).apply_translation((4.5, 4.5, 1.5))


@pytest.mark.filterwarnings("ignore:.*lie behind the surfaces")  # its normals face out: seen from behind
def test_a_round_room_stays_faceted_and_its_walls_echo(device):
    """Round things over 1 m in radius are rooms or tanks driven inside: not fitted (as a solid the
    sensor would be inside it, its walls silent), the scene and its echoes those assembled without
    the fit, its wide facets mirrors at every pose. A 0.5 m pillar in it is still fitted."""
    room = round_room()
    fitted = scenes.from_mesh(room)
    plain = assemble([(room, "painted_wall")], name="mesh", params=fitted.params)
    assert fitted.curved == () and (fitted.face_curved == -1).all()
    assert np.array_equal(fitted.mesh.faces, plain.mesh.faces) and fitted.describe() == plain.describe()
    rng = np.random.default_rng(4)
    bearing, distance = rng.uniform(0, 2 * np.pi, 6), rng.uniform(0.0, 2.0, 6)
    xy = 4.5 + distance[:, None] * np.c_[np.cos(bearing), np.sin(bearing)]
    poses = scenes.poses(xy, rng.uniform(0, 2 * np.pi, 6), rng.uniform(0.2, 1.5, 6))
    sonar = Sonar(SONAR, TracerConfig(max_bounces=1, scattering=False, ray_count=1_000), device=device)
    got, want = sonar.trace(fitted, poses), sonar.trace(plain, poses)
    for field in dataclasses.fields(want):
        np.testing.assert_array_equal(getattr(got, field.name), getattr(want, field.name), err_msg=field.name)
    assert all(len(first_order(got, i)) >= 3 for i in range(len(poses)))  # floor, ceiling and a wall at least
    pillar = trimesh.creation.cylinder(radius=0.5, height=2.0, sections=48).apply_translation((5.5, 4.5, 1.0))
    (surface,) = scenes.from_mesh(trimesh.util.concatenate([room, pillar])).curved
    assert surface.kind == "cylinder" and surface.radius == pytest.approx(0.5, rel=1e-9)
