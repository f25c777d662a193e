"""Poses the simulator cannot trust are warned about, never used silently: a sensor behind the
surface nearest to it (inside an object, outside the room) and coordinates so far from the origin
that float32 loses the tracer's precision. References are analytic: a box inside a box room."""

import re
import warnings

import numpy as np
import pytest

import acoustic_sim as sim
import scenes
from scenes.scene import assemble, box_mesh, room_shell

HOKUYO = sim.LidarConfig.hokuyo_ust20lx()
ROOM = (6.0, 4.0, 3.0)
BOX_CENTER, BOX_SIZE = np.array([4.0, 2.0, 0.5]), np.array([1.0, 1.2, 1.0])
BEHIND = re.compile(r"(\d+) of (\d+) poses \(first: pose (\d+)\) lie behind the surfaces")


def room_with_box(center=BOX_CENTER) -> scenes.Scene:
    """The room with a box standing on its floor (default) or floating at `center`."""
    parts = [(mesh, "painted_wall") for mesh in room_shell(ROOM).values()]
    return assemble([*parts, (box_mesh(center, BOX_SIZE), "wood")], name="room_with_box")


def at(points: np.ndarray) -> np.ndarray:
    poses = np.tile(np.eye(4), (len(points), 1, 1))
    poses[:, :3, 3] = points
    return poses


def behind_warnings(call) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        call()
    return [str(w.message) for w in caught if BEHIND.search(str(w.message))]


def test_poses_behind_a_surface_match_the_analytic_count(device):
    """300 random positions in and around the room: the warning counts exactly the ones inside the
    box or outside the room (analytic), and names the first of them. Positions beyond an edge or
    corner of the room (outside in two coordinates) see no face along the axes and are not judged:
    they are left out. The box floats 0.2 m above the floor here, so that no face coincides with
    another (below the floor, looking up, a box standing on it shows its front or its back)."""
    center = BOX_CENTER + np.array([0.0, 0.0, 0.2])
    rng = np.random.default_rng(4)
    points = rng.uniform((-1.0, -1.0, -1.0), (7.0, 5.0, 4.0), size=(400, 3))
    outside = (points < 0) | (points > ROOM)
    in_box = np.all(np.abs(points - center) < BOX_SIZE / 2, axis=1)
    gap = np.minimum(np.abs(points).min(axis=1), np.abs(points - ROOM).min(axis=1))
    gap = np.minimum(gap, np.abs(np.abs(points - center) - BOX_SIZE / 2).min(axis=1))
    judged = (gap > 0.01) & (outside.sum(axis=1) <= 1)  # a centimetre off every surface plane
    points, expected = points[judged], (outside.any(axis=1) | in_box)[judged]
    assert 20 < expected.sum() < len(points) - 20
    scene, lidar = room_with_box(center), sim.Lidar(HOKUYO, device=device)
    (message,) = behind_warnings(lambda: lidar.scan(scene, at(points)))
    count, total, first = map(int, BEHIND.search(message).groups())
    assert (count, total, first) == (int(expected.sum()), len(points), int(np.argmax(expected)))


def test_the_sonar_warns_as_well(device):
    """The sensor at the centre of a box standing on the floor, as far from its bottom face (which
    coincides with the floor) as from its sides: flagged."""
    scene = room_with_box()
    sonar = sim.Sonar(sim.SonarConfig.ertis(), max_bounces=1, ray_count=256, device=device)
    (message,) = behind_warnings(lambda: sonar.trace(scene, at(np.array([[1.0, 1.0, 0.3], BOX_CENTER]))))
    assert "1 of 2 poses (first: pose 1)" in message
    assert behind_warnings(lambda: sonar.trace(scene, at(np.array([[1.0, 1.0, 0.3]])))) == []


def test_the_sonar_names_poses_of_a_trajectory_not_of_a_batch(device):
    """Five poses traced two at a time, the fourth inside the box: one warning for the whole
    trajectory that names pose 3 of 5 (not pose 1 of its batch of 2), shown at the caller's line
    for the sonar's trace and simulate and the LiDAR alike; a mirror at pose 3 raises naming pose 3."""
    scene = room_with_box()
    sonar = sim.Sonar(sim.SonarConfig.ertis(), max_bounces=1, ray_count=256, device=device)
    poses = at(np.array([[1.0, 1.0, 0.3], [1.5, 1.0, 0.3], [2.0, 1.0, 0.3], BOX_CENTER, [1.0, 3.0, 0.3]]))
    lidar = sim.Lidar(HOKUYO, device=device)
    for call in (lambda: sonar.trace(scene, poses, batch=2), lambda: sonar.simulate(scene, poses, batch=2)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            call()
            lidar.scan(scene, poses)
        shown = [w for w in caught if BEHIND.search(str(w.message))]
        assert [w.filename for w in shown] == [__file__] * 2
        assert ["1 of 5 poses (first: pose 3)" in str(w.message) for w in shown] == [True, True]
    mirrored = poses.copy()
    mirrored[3, :3, :3] = np.diag([1.0, 1.0, -1.0])
    with pytest.raises(ValueError, match="pose 3 is not a rigid transform"):
        sonar.trace(scene, mirrored, batch=2)


@pytest.mark.parametrize("builder", sorted(scenes.BUILDERS))
def test_no_warning_along_the_trajectories_of_every_builder(builder, device):
    """Free-space trajectories through each builder's default scene are never flagged: the
    builders' surfaces face the space the robot drives in."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # e.g. random_world leaving objects out
        scene = scenes.BUILDERS[builder](seed=1) if builder == "random_world" else scenes.BUILDERS[builder]()
    poses = scenes.trajectory(scene, frames=60, seed=2)
    assert behind_warnings(lambda: sim.Lidar(HOKUYO, device=device).scan(scene, poses)) == []


def test_scenes_and_poses_far_from_the_origin_are_warned(device):
    """A room moved 100 km away (UTM-like coordinates): float32 resolves 7.8 mm there. The
    warnings are shown at the caller's line, whichever sensor reaches them."""
    far = room_with_box()
    far.mesh.apply_translation((100_000.0, 0.0, 0.0))
    pose = at(np.array([[100_001.0, 1.0, 0.3]]))
    with pytest.warns(UserWarning, match=r"vertices of 'room_with_box' reach 100,006 m .* only 7\.8 mm") as caught:
        sim.Lidar(HOKUYO, device=device).scan(far, pose)
    assert {w.filename for w in caught if "reach" in str(w.message)} == {__file__}
    with pytest.warns(UserWarning, match=r"sensor positions reach 100,001 m") as caught:
        sim.Sonar(sim.SonarConfig.ertis(), max_bounces=0, ray_count=64, device=device).trace(far, pose)
    assert {w.filename for w in caught if "reach" in str(w.message)} == {__file__}
    with pytest.warns(UserWarning, match=r"sensor positions reach 100,001 m"):
        sim.check_poses(pose)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim.check_poses(at(np.array([[500.0, 0.0, 0.0]])))  # within 512 m: no warning
