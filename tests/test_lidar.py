"""LiDAR against independent references: Open3D/Embree ray casts and analytic box-room distances."""

import dataclasses

import numpy as np
import pytest
import trimesh

import acoustic_sim as sim
import scenes
from scenes.scene import assemble, box_mesh

from .reference.raycast import first_hits, lidar_reference

HOKUYO = sim.LidarConfig.hokuyo_ust20lx()


def random_rigid(rng: np.random.Generator, count: int, low, high) -> np.ndarray:
    """Random rotations (QR of Gaussian matrices) at uniform positions, (count, 4, 4)."""
    q, r = np.linalg.qr(rng.normal(size=(count, 3, 3)))
    q *= np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    out = np.tile(np.eye(4), (count, 1, 1))
    out[:, :3, :3] = q
    out[:, :3, 3] = rng.uniform(low, high, size=(count, 3))
    return out


def assert_matches_reference(got: np.ndarray, ref: np.ndarray) -> None:
    """Identical hit/miss on >= 99.99 % of rays, and |range error| <= 1e-4 m where both hit."""
    same = np.isinf(got) == np.isinf(ref)
    assert same.mean() >= 0.9999, f"hit/miss differs on {int((~same).sum())} of {same.size} rays"
    both = np.isfinite(got) & np.isfinite(ref)
    err = np.abs(got[both] - ref[both])
    assert err.max() <= 1e-4, f"max range error {err.max():.3g} m"


def test_matches_open3d_on_random_meshes(device):
    """Triangle soup + noisy sphere, 20 random rigid poses x 1024 beams in all directions
    (20,480 rays, over 1,000 hits and 1,000 misses each): ranges equal Open3D's to 1e-4 m."""
    rng = np.random.default_rng(0)
    corners = rng.uniform(-2, 2, size=(400, 1, 3)) + rng.normal(scale=0.4, size=(400, 3, 3))
    soup = trimesh.Trimesh(corners.reshape(-1, 3), np.arange(1200).reshape(-1, 3), process=False)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    sphere.vertices += rng.normal(scale=0.03, size=sphere.vertices.shape)
    config = sim.LidarConfig(
        azimuth_min_deg=-180,
        azimuth_max_deg=179,
        azimuth_count=64,
        elevation_min_deg=-80,
        elevation_max_deg=80,
        elevation_count=16,
        range_min_m=0.0,
        range_max_m=100.0,
        rate_hz=10.0,
    )
    lidar = sim.Lidar(config, device=device)
    for mesh in (soup, sphere):
        scene = scenes.from_mesh(mesh)
        poses = random_rigid(rng, 20, -2.5, 2.5)
        got = lidar.scan(scene, poses)
        ref = lidar_reference(scene, poses, config)
        assert np.isinf(ref).sum() > 1000 and np.isfinite(ref).sum() > 1000  # both hits and misses
        assert_matches_reference(got, ref)


BUILT = {
    "box_room": lambda: scenes.box_room(),
    "corridor_few": lambda: scenes.corridor(reflectors="few"),
    "corridor_many": lambda: scenes.corridor(reflectors="many", seed=3),
    "office_low": lambda: scenes.office(seed=1, clutter="low"),
    "office_high": lambda: scenes.office(seed=2, clutter="high"),
    "random_world": lambda: scenes.random_world(seed=4),
    "svg": lambda: scenes.from_svg(
        '<svg xmlns="http://www.w3.org/2000/svg"><rect x="0" y="0" width="800" height="500"/>'
        '<circle cx="300" cy="200" r="40"/><path d="M 500 100 Q 650 250 500 400"/></svg>'
    ),
}


@pytest.mark.parametrize("name", sorted(BUILT))
def test_matches_open3d_on_every_builder(device, name):
    """Hokuyo scans along a trajectory (inside) and from outside the scene (misses): 10+ poses x
    1081 beams per scene equal Open3D's first hits, glass left out, 0.06-20 m limits applied."""
    scene = BUILT[name]()
    inside = scenes.trajectory(scene, frames=10, speed=0.5, seed=1)
    corner = scene.mesh.bounds[0] - (3.0, 3.0, -1.0)
    outside = np.stack([scenes.pose(*corner[:2], yaw, corner[2]) for yaw in (0.8, 2.5)])
    poses = np.concatenate([inside, outside])
    got = sim.Lidar(HOKUYO, device=device).scan(scene, poses)
    ref = lidar_reference(scene, poses, HOKUYO)
    assert np.isinf(ref).sum() > 100 and np.isfinite(ref).sum() > 5000
    assert_matches_reference(got, ref)


def test_box_room_analytic_distances(device):
    """6 x 4 x 3 m room, sensor at (1.5, 1.2, 0.8) yawed 0.3 rad: every beam of a 3D scan ends on
    the first box face along it, t = min over axes of (face - p) / d."""
    scene = scenes.box_room((6.0, 4.0, 3.0))
    config = sim.LidarConfig.multibeam_64x1024()
    pose = scenes.pose(1.5, 1.2, 0.3, 0.8)
    got = sim.Lidar(config, device=device).scan(scene, pose)[0]
    dirs = config.beam_directions() @ pose[:3, :3].T
    p = pose[:3, 3]
    with np.errstate(divide="ignore"):
        t = np.where(dirs > 0, (np.array([6.0, 4.0, 3.0]) - p) / dirs, -p / dirs)
    ref = np.where(t > 0, t, np.inf).min(axis=1)
    np.testing.assert_allclose(got, ref, atol=1e-4, rtol=0)


def test_range_limits_are_misses(device):
    """Sensor 3 cm from a wall: those returns are below the 0.06 m minimum and read inf."""
    scene = scenes.box_room((4.0, 4.0, 3.0))
    ranges = sim.Lidar(HOKUYO, device=device).scan(scene, scenes.pose(3.97, 2.0, 0.0, 1.0))[0]
    ahead = np.argmin(np.abs(HOKUYO.azimuth_rad))
    assert np.isinf(ranges[ahead])
    short = dataclasses.replace(HOKUYO, range_max_m=2.5)
    ranges = sim.Lidar(short, device=device).scan(scene, scenes.pose(0.5, 2.0, 0.0, 1.0))[0]
    assert np.isinf(ranges[ahead])  # wall at 3.5 m, beyond 2.5 m


def test_glass_is_transparent(device):
    """A glass pane 1 m ahead of a wall 3 m ahead: the LiDAR sees the wall; the same pane made of
    wood is seen at 1 m (minus half its 1.2 cm thickness)."""
    room = scenes.box_room((6.0, 4.0, 3.0)).mesh
    pane = box_mesh((2.0, 2.0, 1.5), (0.012, 3.0, 3.0))
    ahead = np.argmin(np.abs(HOKUYO.azimuth_rad))
    lidar = sim.Lidar(HOKUYO, device=device)
    pose = scenes.pose(1.0, 2.0, 0.0, 1.0)
    glass = assemble([(room, "painted_wall"), (pane, "glass")], name="glass")
    wood = assemble([(room, "painted_wall"), (pane, "wood")], name="wood")
    assert lidar.scan(glass, pose)[0, ahead] == pytest.approx(5.0, abs=1e-4)
    assert lidar.scan(wood, pose)[0, ahead] == pytest.approx(1.0 - 0.006, abs=1e-4)


@pytest.fixture(scope="module")
def clean_and_poses(device):
    scene = scenes.box_room((6.0, 4.0, 3.0))
    poses = scenes.trajectory(scene, frames=200, speed=0.1, seed=0)
    return scene, poses, sim.Lidar(HOKUYO, device=device).scan(scene, poses)


def test_gaussian_noise_statistics(device, clean_and_poses):
    """sigma = 1.2 cm Gaussian noise on 216k returns: mean ~0 (5 standard errors), std within 2 %,
    about 68.3 % within one sigma."""
    scene, poses, clean = clean_and_poses
    noisy = sim.Lidar(dataclasses.replace(HOKUYO, noise="gaussian", noise_m=0.012), device=device).scan(scene, poses)
    res = (noisy - clean).ravel()
    assert abs(res.mean()) < 5 * 0.012 / np.sqrt(res.size)
    assert res.std() == pytest.approx(0.012, rel=0.02)
    assert np.mean(np.abs(res) < 0.012) == pytest.approx(0.6827, abs=0.01)


def test_uniform_noise_and_dropout_statistics(device, clean_and_poses):
    """Uniform +-2 cm noise (as in the paper) stays inside its bounds with std a/sqrt(3) and a flat
    histogram; 20 % dropout removes 20 % of the returns."""
    scene, poses, clean = clean_and_poses
    cfg = dataclasses.replace(HOKUYO, noise="uniform", noise_m=0.02, dropout_probability=0.2)
    noisy = sim.Lidar(cfg, device=device).scan(scene, poses)
    dropped = np.isinf(noisy)
    n = dropped.size
    assert dropped.mean() == pytest.approx(0.2, abs=5 * np.sqrt(0.2 * 0.8 / n))
    res = (noisy - clean)[~dropped]
    assert np.abs(res).max() <= 0.02 + 1e-6
    assert res.std() == pytest.approx(0.02 / np.sqrt(3), rel=0.02)
    counts, _ = np.histogram(res, bins=10, range=(-0.02, 0.02))
    assert counts.min() > 0.9 * counts.mean()


def _largest_cross_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """max over all lags of |normalised cross-correlation| of two equal-length noise records."""
    a, b = (a - a.mean()) / a.std(), (b - b.mean()) / b.std()
    size = 1 << int(np.ceil(np.log2(2 * len(a))))
    xcorr = np.fft.irfft(np.fft.rfft(a, size) * np.conj(np.fft.rfft(b, size)), size)
    return float(np.abs(xcorr).max() / len(a))


def test_noise_is_seeded(device, clean_and_poses):
    """Same seed, same noise sequence; successive calls draw fresh noise; a call seed pins it.
    Fresh means independent, not merely different: the noise of three calls of a Lidar seeded 5,
    two of one seeded 6 (a neighbouring seed must not replay a shifted sequence) and of one pose
    scanned three times in one call (drawn per pose and beam, not per beam) are pairwise
    uncorrelated at every lag (|r| under 6 standard errors, 1 / sqrt(draws), where a replayed or
    shifted sequence gives 1); each is the configured 1 cm Gaussian around the clean ranges."""
    scene, poses, clean = clean_and_poses
    cfg = dataclasses.replace(HOKUYO, noise="gaussian", noise_m=0.01)
    a, b = sim.Lidar(cfg, device=device, seed=5), sim.Lidar(cfg, device=device, seed=5)
    first, second = a.scan(scene, poses[:3]), a.scan(scene, poses[:3])
    np.testing.assert_array_equal(first, b.scan(scene, poses[:3]))
    assert not np.array_equal(first, second)
    np.testing.assert_array_equal(a.scan(scene, poses[:3], seed=9), b.scan(scene, poses[:3], seed=9))

    third = a.scan(scene, poses[:3])
    neighbour = sim.Lidar(cfg, device=device, seed=6)
    draws = [first, second, third, neighbour.scan(scene, poses[:3]), neighbour.scan(scene, poses[:3])]
    noise = [(d - clean[:3]).astype(np.float64).ravel() for d in draws]
    same_pose = (sim.Lidar(cfg, device=device, seed=7).scan(scene, poses[[0, 0, 0]]) - clean[[0, 0, 0]]).astype(float)
    noise += list(same_pose)  # three rows of one pose, each its own draw
    for r in noise:
        assert abs(r.mean()) < 5 * 0.01 / np.sqrt(r.size) and r.std() == pytest.approx(0.01, rel=0.1)
    pairs = [(i, j) for i in range(len(noise)) for j in range(i + 1, len(noise)) if len(noise[i]) == len(noise[j])]
    for i, j in pairs:
        assert _largest_cross_correlation(noise[i], noise[j]) < 6 / np.sqrt(len(noise[i])), (i, j)


def test_lidar_image_hand_computed():
    """Beam at azimuth 0 with 1.0 m -> cell (40, 90); +1 deg at 0.215 m -> (0, 91); a beam at
    -45.25 deg rounds to -45 deg; beyond 5 m, below 0.2 m, outside +-90 deg or inf -> nothing."""
    ranges = np.full(HOKUYO.beam_count, np.inf)
    az = np.round(np.rad2deg(HOKUYO.azimuth_rad), 2)
    ranges[az == 0.0] = 1.0
    ranges[az == 1.0] = 0.215
    ranges[az == -45.25] = 4.999
    ranges[az == 30.0] = 5.01
    ranges[az == 31.0] = 0.19
    ranges[az == 100.0] = 2.0
    image = sim.lidar_image(ranges, HOKUYO)
    assert image.shape == (1, 240, 181)
    assert set(zip(*np.nonzero(image[0]), strict=True)) == {(40, 90), (0, 91), (239, 45)}
    assert image.dtype == np.float32 and image.max() == 1.0
    labels = sim.lidar_image(ranges, HOKUYO, dtype=np.uint8)  # as datasets store it
    assert labels.dtype == np.uint8 and np.array_equal(labels, image)


def test_points_in_world_frame_lie_on_walls(device):
    """World-frame end points of a 2D scan in a 6 x 4 m room lie on its four walls."""
    scene = scenes.box_room((6.0, 4.0, 3.0))
    pose = scenes.pose(2.0, 1.5, 1.0, 1.2)[None]
    ranges = sim.Lidar(HOKUYO, device=device).scan(scene, pose)
    points = sim.ranges_to_points(ranges, HOKUYO, pose)[0]
    on_wall = np.minimum.reduce(
        [np.abs(points[:, 0]), np.abs(points[:, 0] - 6), np.abs(points[:, 1]), np.abs(points[:, 1] - 4)]
    )
    assert np.all(on_wall < 1e-4)
    np.testing.assert_allclose(points[:, 2], 1.2, atol=1e-9)


def test_bad_poses_raise(device):
    lidar = sim.Lidar(HOKUYO, device=device)
    scene = scenes.box_room()
    with pytest.raises(ValueError, match="shape"):
        lidar.scan(scene, np.eye(3))
    with pytest.raises(ValueError, match="NaN"):
        lidar.scan(scene, np.full((4, 4), np.nan))
    moved = np.tile(np.eye(4), (3, 1, 1))
    moved[2, 0, 3] = np.inf
    with pytest.raises(ValueError, match="pose 2 contains NaN or inf"):
        lidar.scan(scene, moved)
    with pytest.raises(ValueError, match="rigid"):
        lidar.scan(scene, np.diag([2.0, 1.0, 1.0, 1.0]))
    sheared = np.eye(4)
    sheared[0, 1] = 0.01
    with pytest.raises(ValueError, match="pose 0 is not a rigid"):
        lidar.scan(scene, sheared)
    with pytest.raises(ValueError, match="rigid"):
        lidar.scan(scene, np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1.0]]))
    with pytest.raises(ValueError, match="empty"):
        lidar.scan(scene, np.zeros((0, 4, 4)))
    mirrored = np.diag([1.0, -1.0, 1.0, 1.0])  # orthonormal (R^T R = I) but det -1: left and right swap
    with pytest.raises(ValueError, match=r"pose 0 is not a rigid transform .*determinant -1"):
        lidar.scan(scene, mirrored)
    with pytest.raises(ValueError, match="determinant -1"):
        sim.Sonar(sim.SonarConfig.ertis(), device=device).trace(scene, mirrored)


def test_warp_mesh_built_once_and_rebuilt_after_edit(device):
    scene = scenes.box_room()
    first = sim.warp_scene(scene, device)
    assert sim.warp_scene(scene, device) is first
    scene.mesh.vertices = scene.mesh.vertices * 2.0
    assert sim.warp_scene(scene, device) is not first


def test_reference_agrees_with_float64_bruteforce():
    """Sanity of the reference itself: Open3D vs Moller-Trumbore in float64 on a small box."""
    box = trimesh.creation.box(extents=(2.0, 3.0, 4.0))
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(500, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = np.tile([0.1, -0.2, 0.3], (500, 1))
    t, _ = first_hits(box.vertices, box.faces, origins, dirs)
    tri = box.vertices[box.faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(dirs[:, None], e2[None])
    a = (e1[None] * h).sum(-1)
    s = origins[:, None] - tri[None, :, 0]
    u = (s * h).sum(-1) / a
    q = np.cross(s, e1[None])
    v = (dirs[:, None] * q).sum(-1) / a
    tt = (e2[None] * q).sum(-1) / a
    tt[(u < 0) | (v < 0) | (u + v > 1) | (tt <= 0)] = np.inf
    np.testing.assert_allclose(t, tt.min(axis=1), atol=1e-5)


def test_cpu_threads_split_the_poses_without_changing_a_range():
    """On the CPU the scan launch is split over threads by pose (3 uneven slices of 7 poses here):
    every range, face and noise draw equals the one-thread scan's, and a pose error still surfaces."""
    scene = scenes.BUILDERS["office"](seed=0)
    poses = scenes.trajectory(scene, frames=7, seed=1)
    config = sim.LidarConfig.hokuyo_ust20lx(noise="gaussian", dropout_probability=0.05)
    one = sim.Lidar(config, device="cpu", cpu_threads=1, seed=4).cast(scene, poses)
    three = sim.Lidar(config, device="cpu", cpu_threads=3, seed=4).cast(scene, poses)
    np.testing.assert_array_equal(one.range_m.numpy(), three.range_m.numpy())
    np.testing.assert_array_equal(one.face.numpy(), three.face.numpy())
    bad = poses.copy()
    bad[4, :3, 3] = np.nan
    with pytest.raises(ValueError):
        sim.Lidar(config, device="cpu", cpu_threads=3).scan(scene, bad)
    with pytest.raises(ValueError, match="cpu_threads"):
        sim.Lidar(config, device="cpu", cpu_threads=0)


def test_a_queued_scan_gives_the_scans_ranges_after_other_work(device):
    """`scan_begin` then other device work (another scene's scan) then `ranges()`: the ranges
    `scan` gives for the same poses and noise seed; a bad pose is refused at `ranges()`; the
    ranges of a scan whose buffers a later call took are refused, not returned overwritten."""
    lidar = sim.Lidar(dataclasses.replace(HOKUYO, noise="gaussian", noise_m=0.01), device=device)
    room, corridor = scenes.box_room((6.0, 4.0, 3.0)), scenes.corridor(reflectors="few")
    poses = np.stack([scenes.pose(2.0 + 0.1 * k, 1.5, 0.0, 1.0) for k in range(5)])
    expected = lidar.scan(room, poses, seed=3)
    pending = lidar.scan_begin(room, poses, seed=3)
    other = sim.Lidar(HOKUYO, device=device).scan(corridor, poses[:2])
    np.testing.assert_array_equal(pending.ranges(), expected)
    assert not np.array_equal(other, expected[:2])
    bad = poses.copy()
    bad[2, 0, 0] = 2.0  # not a rotation
    with pytest.raises(ValueError, match="pose 2 is not a rigid transform"):
        lidar.scan_begin(room, bad).ranges()
    first = lidar.scan_begin(room, poses, seed=3)
    lidar.scan_begin(room, poses[:3], seed=4)
    with pytest.raises(RuntimeError, match="reused this scan's buffers"):
        first.ranges()


@pytest.mark.parametrize("build", [lambda: scenes.office(seed=2, clutter="high"), lambda: scenes.random_world(seed=5)])
def test_the_beams_tree_of_one_triangle_leaves_returns_what_four_triangle_leaves_do(build, device, monkeypatch):
    """The LiDAR's own BVH (LIDAR_BVH_LEAF_SIZE) against one of the scene's leaf size: every beam
    hits or misses alike, and ranges agree to float32 rounding (a few units in the last place:
    another traversal order meets the same triangles). A tree that lost a face would fail."""
    from acoustic_sim.engine import lidar as lidar_module
    from acoustic_sim.engine import scene as scene_module

    assert scene_module.LIDAR_BVH_LEAF_SIZE != scene_module.BVH_LEAF_SIZE
    monkeypatch.setattr(lidar_module, "OWN_TREE_RAYS", 0)  # every scan through the LiDAR's tree
    config = dataclasses.replace(HOKUYO, range_max_m=30.0)
    got = []
    for leaf in (scene_module.LIDAR_BVH_LEAF_SIZE, scene_module.BVH_LEAF_SIZE):
        monkeypatch.setattr(scene_module, "LIDAR_BVH_LEAF_SIZE", leaf)
        scene = build()  # a scene object of its own: its device copy is built with this leaf size
        poses = scenes.trajectory(scene, frames=40, seed=3)
        got.append(sim.Lidar(config, device=device).scan(scene, poses))
    ones, fours = got
    assert np.isfinite(fours).mean() > 0.9
    np.testing.assert_array_equal(np.isinf(ones), np.isinf(fours))
    hit = np.isfinite(fours)
    np.testing.assert_allclose(ones[hit], fours[hit], rtol=5e-7, atol=0)


def test_only_a_scan_of_many_rays_builds_the_lidars_own_tree(device, monkeypatch):
    """A dataset episode's scan (100 poses) casts through the scene's tree; one of OWN_TREE_RAYS
    or more builds the LiDAR's tree, and returns the same ranges to float32 rounding."""
    from acoustic_sim.engine import lidar as lidar_module
    from acoustic_sim.engine.scene import warp_scene

    scene = scenes.box_room(seed=1)
    poses = scenes.trajectory(scene, frames=4, seed=0)
    lidar = sim.Lidar(HOKUYO, device=device)
    small = lidar.scan(scene, poses)
    assert not warp_scene(scene, device).has_lidar_mesh
    monkeypatch.setattr(lidar_module, "OWN_TREE_RAYS", len(poses) * HOKUYO.beam_count)
    large = lidar.scan(scene, poses)
    assert warp_scene(scene, device).has_lidar_mesh
    np.testing.assert_allclose(large, small, rtol=5e-7, atol=0)
