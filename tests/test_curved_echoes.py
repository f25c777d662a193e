"""Small round reflectors echo from every side: the first-order specular echo off a sphere or a
cylinder is found at every pose (rays alone hit a facet that faces the sensor only by luck) at
the delay Fermat's principle gives on the true surface, with the textbook strength."""

import numpy as np
import pytest

import scenes
from acoustic_sim import Sonar, SonarConfig, TracerConfig
from acoustic_sim.engine.paths import KIND_SPECULAR
from scenes.scene import assemble, cylinder_mesh, room_shell, sphere_mesh
from scenes.surfaces import with_surfaces

ROOM = (9.0, 9.0, 3.0)  # poses up to 4 m from its middle stay inside
SPHERE_CENTRE, SPHERE_RADIUS = np.array([4.5, 4.5, 1.0]), 0.01  # a 2 cm ball
POLE_AXIS, POLE_RADIUS, POLE_TOP = np.array([4.5, 4.5]), 0.015, 2.0  # a 3 cm pole, floor to 2 m
SONAR = SonarConfig.ertis()
SAMPLE_M = SONAR.atmosphere.speed_of_sound / SONAR.chirp.sample_rate_hz  # path length of one sample


def room_with(*parts):
    shell = room_shell(ROOM)
    base = [(shell["floor"], "floor"), (shell["walls"], "painted_wall"), (shell["ceiling"], "painted_wall")]
    return assemble([*base, *parts], name="test_room")


def poses_around(centre_xy, count, seed, heights):
    """Poses 0.5-4 m from a vertical line through centre_xy, facing it within +-60 deg."""
    rng = np.random.default_rng(seed)
    distance = rng.uniform(0.5, 4.0, count)
    bearing = rng.uniform(0, 2 * np.pi, count)
    xy = centre_xy + distance[:, None] * np.c_[np.cos(bearing), np.sin(bearing)]
    yaw = bearing + np.pi + rng.uniform(-np.pi / 3, np.pi / 3, count)
    return scenes.poses(xy, yaw, rng.uniform(*heights, count))


def emitter_and_receiver(pose):
    return (pose @ np.r_[SONAR.emitter_m, 1.0])[:3], pose[:3, 3]


UNIT = np.random.default_rng(0).normal(size=(100_000, 3))
UNIT /= np.linalg.norm(UNIT, axis=1, keepdims=True)  # ~0.011 rad apart: path error ~1e-6 m at 1 cm


def shortest_path(e, r, points):
    """Fermat: the specular path is the shortest emitter -> surface -> receiver path; brute force
    over dense points of the surface (no use of the simulator's reflection-point solver)."""
    return (np.linalg.norm(points - e, axis=-1) + np.linalg.norm(points - r, axis=-1)).min()


def sphere_points(centre, radius):
    return centre + radius * UNIT


def cylinder_points(axis_xy, radius):
    """The side of a vertical cylinder on a 0.5 deg x 5 mm grid."""
    phi, z = np.meshgrid(np.linspace(0, 2 * np.pi, 720), np.linspace(0, POLE_TOP, 400))
    return np.stack([axis_xy[0] + radius * np.cos(phi), axis_xy[1] + radius * np.sin(phi), z], axis=-1).reshape(-1, 3)


@pytest.fixture(scope="module")
def small_reflectors(device):
    """200 poses around each reflector, alone in the middle of an empty room, traced with the
    default 20,000 rays (secondary bounces and scattering, off here, do not change which
    first-order echoes are found and would cost CPU minutes)."""
    ball = room_with((sphere_mesh(SPHERE_CENTRE, SPHERE_RADIUS), "metal"))
    pole = room_with((cylinder_mesh(*POLE_AXIS, POLE_RADIUS, 0.0, POLE_TOP), "metal"))
    around_ball = poses_around(SPHERE_CENTRE[:2], 200, 1, (0.9, 1.1))  # the ball at sensor height +-0.1 m
    around_pole = poses_around(POLE_AXIS, 200, 2, (0.15, 1.8))
    sonar = Sonar(SONAR, TracerConfig(max_bounces=0, scattering=False), device=device)
    return sonar.trace(ball, around_ball), around_ball, sonar.trace(pole, around_pole), around_pole


@pytest.mark.parametrize("target", ["sphere", "pole"])
def test_first_order_echo_of_a_small_reflector_at_every_pose(small_reflectors, target):
    """>= 99 % of the poses (here all) have a first-order specular arrival whose path equals the
    shortest path over the true surface within one sample."""
    arrivals, poses = small_reflectors[:2] if target == "sphere" else small_reflectors[2:]
    surface = (
        sphere_points(SPHERE_CENTRE, SPHERE_RADIUS) if target == "sphere" else cylinder_points(POLE_AXIS, POLE_RADIUS)
    )
    found = []
    for i, pose in enumerate(poses):
        want = shortest_path(*emitter_and_receiver(pose), surface)
        echoes = arrivals.for_pose(i)
        first = echoes.select((echoes.kind == KIND_SPECULAR) & (echoes.order == 1))
        found.append(np.abs(first.length_m - want).min(initial=np.inf) <= SAMPLE_M)
    assert np.mean(found) >= 0.99, f"{np.sum(found)} of {len(found)} poses"


def on_axis_amplitude(scene, target_xy, distance, radius, device, height=1.0):
    """Amplitude of the first-order specular echo off a round reflector of `radius` whose axis
    (or centre) is `distance` [m] ahead of the sensor (looking along +x)."""
    sonar = Sonar(SONAR, TracerConfig(scattering=False, max_bounces=0), device=device)
    x, y = target_xy[0] - distance, target_xy[1]
    pose = scenes.pose(x, y, 0.0, height - SONAR.emitter_m[2] / 2)  # the ball halfway between emitter and array
    echoes = sonar.trace(scene, pose[None]).for_pose(0)
    first = echoes.select((echoes.kind == KIND_SPECULAR) & (echoes.order == 1))
    nearest = np.argmin(np.abs(first.length_m - 2 * (distance - radius)))
    assert abs(first.length_m[nearest] - 2 * (distance - radius)) < 5e-3  # its echo (bistatic), not the floor's
    return first.amplitude[nearest]


def test_sphere_and_cylinder_echo_strengths_follow_geometric_optics(device):
    """A rigid sphere (ka >> 1) returns a / (2 d) of the incident pressure at its centre's range
    d: amplitude a / (2 d^2) re 1 m (within 5 % at d >= 0.5 m, a = 1 cm); a long cylinder's echo
    falls as d^-1.5, between a sphere's d^-2 and a wall's d^-1."""
    gain = np.sqrt(scenes.material("metal").acoustic_reflection * (1 - scenes.material("metal").acoustic_scattering))
    ball = room_with((sphere_mesh(SPHERE_CENTRE, SPHERE_RADIUS), "metal"))
    for d in (0.5, 1.0, 2.0):
        got = on_axis_amplitude(ball, SPHERE_CENTRE, d, SPHERE_RADIUS, device) / gain
        assert got == pytest.approx(SPHERE_RADIUS / (2 * d * d), rel=0.05)
    pole = room_with((cylinder_mesh(*POLE_AXIS, POLE_RADIUS, 0.0, POLE_TOP), "metal"))
    near, far = (on_axis_amplitude(pole, POLE_AXIS, d, POLE_RADIUS, device) for d in (1.0, 2.0))
    assert near / far == pytest.approx(2**1.5, rel=0.05)


def test_a_faceted_pole_echoes_once(device):
    """An octagonal chair leg faced flat on: its facet would mirror the call too (7.6 mm nearer
    than the round surface): only the curved surface's echo is kept."""
    leg = room_with((cylinder_mesh(*POLE_AXIS, 0.1, 0.0, POLE_TOP, sections=8), "metal"))
    sonar = Sonar(SONAR, TracerConfig(), device=device)
    facet_normal_yaw = np.pi / 8  # trimesh's octagon has a facet facing this way
    pose = scenes.pose(*(POLE_AXIS + 1.5 * np.array([np.cos(facet_normal_yaw), np.sin(facet_normal_yaw)])), 0.0, 1.0)
    pose[:3, :3] = scenes.pose(0, 0, facet_normal_yaw + np.pi)[:3, :3]
    echoes = sonar.trace(leg, pose[None]).for_pose(0)
    first = echoes.select((echoes.kind == KIND_SPECULAR) & (echoes.order == 1))
    near_leg = np.abs(first.length_m - 2 * (1.5 - 0.1)) < 0.05
    assert near_leg.sum() == 1, first.length_m[near_leg]


def test_scenes_remember_the_round_surfaces_behind_their_facets():
    """Builders pass each cylinder's surface through `assemble`: its side faces point to it, its
    caps stay flat mirrors; a scene with new materials (`with_surfaces`) keeps them."""
    world = scenes.random_world(seed=3, cylinder_count=4, wall_count=0)
    assert len(world.curved) == 4 and all(c.kind == "cylinder" for c in world.curved)
    normals_z = np.abs(world.mesh.face_normals[:, 2])
    assert (normals_z[world.face_curved >= 0] < 1e-6).all()
    assert np.bincount(world.face_curved[world.face_curved >= 0]).tolist() == [96] * 4  # 48 sections x 2
    for k, c in enumerate(world.curved):  # every side vertex lies on its circle
        sides = world.mesh.triangles[world.face_curved == k].reshape(-1, 3)
        np.testing.assert_allclose(np.linalg.norm(sides[:, :2] - c.centre[:2], axis=1), c.radius, rtol=1e-9)
    redrawn = with_surfaces(world, {"objects": {"reflection": 0.6}})
    assert redrawn.curved == world.curved and np.array_equal(redrawn.face_curved, world.face_curved)


def tilted(pose, pitch, roll):
    """`pose` with its sensor pitched and rolled (radians) about its own y and x axes."""
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    turn = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    out = pose.copy()
    out[:3, :3] = pose[:3, :3] @ turn
    return out


def fermat_path(e, r, surface_point, start):
    """Shortest emitter -> surface -> receiver path over a smooth surface (Nelder-Mead from `start`)."""
    from scipy.optimize import minimize

    def length(uv):
        p = surface_point(*uv)
        return np.linalg.norm(p - e) + np.linalg.norm(p - r)

    return minimize(length, start, method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12}).fun


def test_close_to_a_large_round_object_the_echo_is_still_exact(device):
    """A 1 m pillar and a 1 m ball seen from 0.05-1 m off their surface, the sensor pitched and
    rolled up to 20 deg (the reflection point's solver must not diverge when the sensor is nearer
    than one radius): path within one sample of Fermat's shortest path on the true surface."""
    radius, centre = 0.5, np.array([4.5, 4.5, 1.2])
    ball = room_with((sphere_mesh(centre, radius, subdivisions=4), "metal"))
    pillar = room_with((cylinder_mesh(*centre[:2], radius, 0.0, 2.5, sections=96), "metal"))
    rng = np.random.default_rng(5)
    sonar = Sonar(SONAR, TracerConfig(max_bounces=0, scattering=False, ray_count=2_000), device=device)
    on_ball = lambda t, p: centre + radius * np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])  # noqa: E731
    on_pillar = lambda phi, z: np.array([*(centre[:2] + radius * np.array([np.cos(phi), np.sin(phi)])), z])  # noqa: E731
    for scene, on_surface in ((ball, on_ball), (pillar, on_pillar)):
        bearing = rng.uniform(0, 2 * np.pi, 20)
        gap = rng.uniform(0.05, 1.0, 20)
        xy = centre[:2] + (radius + gap)[:, None] * np.c_[np.cos(bearing), np.sin(bearing)]
        yaw = bearing + np.pi + rng.uniform(-0.5, 0.5, 20)
        poses = scenes.poses(xy, yaw, centre[2] + rng.uniform(-0.2, 0.2, 20))
        poses = np.stack([tilted(p, *rng.uniform(-0.35, 0.35, 2)) for p in poses])
        arrivals = sonar.trace(scene, poses)
        for i, pose in enumerate(poses):
            e, r = emitter_and_receiver(pose)
            facing = np.arctan2(*(r - centre)[1::-1])  # bearing of the sensor from the axis
            start = [np.arccos(np.clip((r - centre)[2] / np.linalg.norm(r - centre), -1, 1)), facing]
            want = fermat_path(e, r, on_surface, start if scene is ball else [facing, r[2]])
            echoes = arrivals.for_pose(i)
            first = echoes.select((echoes.kind == KIND_SPECULAR) & (echoes.order == 1))
            assert np.abs(first.length_m - want).min(initial=np.inf) <= SAMPLE_M, (scene.name, i, gap[i], want)


def test_a_moved_or_merged_round_part_is_refused():
    """trimesh keeps a part's metadata when it is moved or merged: `assemble` refuses a part whose
    faces left the surface it carries, rather than echo from where the surface used to be."""
    moved = sphere_mesh(SPHERE_CENTRE, SPHERE_RADIUS)
    moved.apply_translation((1.0, 0.0, 0.0))
    with pytest.raises(scenes.SceneError, match="off the sphere"):
        room_with((moved, "metal"))
    merged = cylinder_mesh(*POLE_AXIS, POLE_RADIUS, 0.0, POLE_TOP)
    merged = merged + scenes.scene.box_mesh((1.0, 1.0, 0.5), (0.2, 0.2, 0.2))
    with pytest.raises(scenes.SceneError, match="off the cylinder"):
        room_with((merged, "metal"))
    assert len(room_with((sphere_mesh(SPHERE_CENTRE, SPHERE_RADIUS), "metal")).curved) == 1


def test_a_wall_flush_with_a_pillar_facet_still_echoes(device):
    """A hexagonal pillar sunk into the wall y = 0 with one facet flush with it (same plane, same
    normal): the wall's mirror echo stays (a curved facet never shares the wall's plane)."""
    radius = 0.3
    pillar = cylinder_mesh(3.0, -radius * np.cos(np.pi / 6), radius, 0.0, 3.0, sections=6)
    room = assemble([*[(m, "painted_wall") for m in room_shell((6.0, 4.0, 3.0)).values()], (pillar, "metal")], name="r")
    facet = np.flatnonzero((room.face_curved >= 0) & (room.mesh.face_normals[:, 1] > 0.999))
    assert len(facet) and np.allclose(room.mesh.triangles[facet][..., 1], 0.0, atol=1e-9)  # flush with the wall
    sonar = Sonar(SONAR, TracerConfig(max_bounces=0, scattering=False), device=device)
    pose = scenes.pose(1.0, 1.5, -np.pi / 2, 1.5)  # looking at the wall, 2 m beside the pillar
    echoes = sonar.trace(room, pose[None]).for_pose(0)
    first = echoes.select((echoes.kind == KIND_SPECULAR) & (echoes.order == 1))
    wall = np.hypot(3.0, SONAR.emitter_m[2])  # emitter 1.5 m + array 1.5 m from the wall, 5 cm apart
    assert np.abs(first.length_m - wall).min() < 1e-3, first.length_m
