"""Trajectories: smooth, at the requested speed, clear of obstacles and inside free space.

Clearance is checked with Open3D horizontal rays against the 3D mesh, not with the 2D map the
planner used.
"""

import numpy as np
import pytest

import scenes
from scenes import SceneError

from .reference.raycast import first_hits

SCENES = {
    "box_room": lambda: scenes.box_room((5.0, 4.0, 2.5)),
    "corridor": lambda: scenes.corridor(reflectors="many", seed=1),
    "office": lambda: scenes.office(seed=0, clutter="high"),
    "random_world": lambda: scenes.random_world(seed=0),
}


def horizontal_clearance(scene, xy, heights, ray_count=720):
    """Shortest horizontal distance [m] from each point to the mesh, over rays at several heights."""
    angles = np.linspace(0, 2 * np.pi, ray_count, endpoint=False)
    dirs = np.c_[np.cos(angles), np.sin(angles), np.zeros(ray_count)]
    out = np.full(len(xy), np.inf)
    for h in heights:
        origins = np.repeat(np.c_[xy, np.full(len(xy), scene.floor_z + h)], ray_count, axis=0)
        t, _ = first_hits(scene.mesh.vertices, scene.mesh.faces, origins, np.tile(dirs, (len(xy), 1)))
        out = np.minimum(out, t.reshape(len(xy), ray_count).min(axis=1))
    return out


@pytest.mark.parametrize("name", sorted(SCENES))
def test_trajectory_is_clear_smooth_and_inside(name):
    """150 poses at 0.3 m/s, dt 0.1 s, clearance 0.35 m: every pose >= 0.35 m from any surface
    between 5 cm and 0.6 m (Open3D rays); steps of exactly 3 cm (or 0 when turning on the spot),
    turn rate <= 1 rad/s, heading along the motion, sensor at 0.3 m; and enclosed: every
    horizontal ray and the floor/ceiling rays hit."""
    scene = SCENES[name]()
    poses = scenes.trajectory(scene, frames=150, dt=0.1, speed=0.3, clearance=0.35, seed=2)
    assert poses.shape == (150, 4, 4)
    rot = poses[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
    np.testing.assert_allclose(poses[:, 2, 3], scene.floor_z + 0.3)
    xy = poses[:, :2, 3]
    steps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    moving = steps > 1e-9  # otherwise turning on the spot at a dead end
    np.testing.assert_allclose(steps[moving], 0.03, rtol=1e-9)
    assert moving.mean() > 0.8
    yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    assert np.abs(np.diff(yaw)).max() <= 1.0 * 0.1 + 1e-9
    heading = np.arctan2(*np.diff(xy, axis=0)[moving].T[::-1])
    lag = np.angle(np.exp(1j * (heading - yaw[1:][moving])))
    assert np.abs(lag).max() < 0.1  # the sensor looks where the robot drives
    clearance = horizontal_clearance(scene, xy, heights=np.linspace(0.05, 0.6, 6))
    assert clearance.min() >= 0.35 - 1e-3, f"closest approach {clearance.min():.3f} m"
    assert np.isfinite(clearance).all()  # enclosed: no horizontal ray escapes
    up_down = np.repeat(np.c_[xy, poses[:, 2, 3]], 2, axis=0)
    t, _ = first_hits(scene.mesh.vertices, scene.mesh.faces, up_down, np.tile([[0, 0, 1], [0, 0, -1]], (150, 1)))
    assert np.isfinite(t).all()


def test_trajectory_is_seeded():
    scene = scenes.office(seed=0)
    a = scenes.trajectory(scene, frames=30, seed=4)
    np.testing.assert_array_equal(a, scenes.trajectory(scene, frames=30, seed=4))
    assert not np.allclose(a, scenes.trajectory(scene, frames=30, seed=5))


def test_no_free_space_raises():
    """A 0.6 m wide room cannot hold a robot that needs 0.35 m on every side."""
    with pytest.raises(SceneError, match="no free space"):
        scenes.trajectory(scenes.box_room((0.6, 0.6, 2.0)), frames=5, clearance=0.35)


def test_bad_trajectory_arguments():
    room = scenes.box_room()
    with pytest.raises(SceneError, match="frames"):
        scenes.trajectory(room, frames=0)
    with pytest.raises(SceneError, match="dt"):
        scenes.trajectory(room, frames=5, dt=0.0)


def test_pose_helpers_agree():
    """pose() and poses() build the same rigid transforms; yaw 90 deg maps sensor x to world y."""
    batch = scenes.poses([[1.0, 2.0], [3.0, 4.0]], [np.pi / 2, 0.3], 0.5)
    np.testing.assert_allclose(batch[0], scenes.pose(1.0, 2.0, np.pi / 2, 0.5))
    np.testing.assert_allclose(batch[0][:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)


@pytest.mark.parametrize("cell", [1e-9, 1e-4, float("nan"), float("inf"), 0.0])
def test_free_space_refuses_grids_it_cannot_hold(cell):
    """A cell so small that the grid's size overflows int64 (1e-9 m: ~1e19 cells) or would need
    gigabytes, and non-finite cells, are refused with SceneError before anything is allocated."""
    room = scenes.box_room(size=(4.0, 3.0, 2.5))
    with pytest.raises(scenes.SceneError, match=r"too large|finite"):
        scenes.free_space(room, cell=cell)


def test_clearance_check_answers_as_the_exact_distance():
    """`clears` trusts the raster field only far from walls: over points scattered near and far
    from an office's walls, it answers as the exact point-to-segment distance does (points just
    either side of each clearance, where a field read without its margin would be wrong)."""
    from scenes.trajectory import clears, distance_to_segments

    space = scenes.free_space(scenes.office(seed=3, clutter="high"))
    rng = np.random.default_rng(0)
    corner = space.to_world(np.array(space.distance_m.shape) - 1)
    points = rng.uniform(space.origin - 0.2, corner + 0.2, (4000, 2))  # some off the grid, too
    exact = distance_to_segments(points, space.segments)
    for clearance in (0.3, 0.35, 0.45):
        edge = np.abs(exact - clearance) < 0.02  # the cases the margin is for
        assert edge.sum() > 20
        for picked in (exact >= clearance, exact >= clearance - 0.01, slice(None)):
            assert clears(points[picked], space, clearance) == bool(exact[picked].min() >= clearance)
        for i in np.flatnonzero(edge):  # one by one: each point's own answer
            assert clears(points[i : i + 1], space, clearance) == bool(exact[i] >= clearance)
        # the field alone (no margin) would pass some point that is too close
        field = space.distance_at(points)
        assert ((field >= clearance) & (exact < clearance)).any()


def test_raster_steps_are_linspace():
    from scenes.trajectory import _unit_steps

    steps = np.array([1, 2, 7, 1, 31, 3])
    owner = np.repeat(np.arange(len(steps)), steps)
    expected = np.concatenate([np.linspace(0.0, 1.0, n) for n in steps])
    np.testing.assert_array_equal(_unit_steps(steps, owner), expected)
