"""learn.occupancy: the log-odds grid on hand-made drives past one straight wall, checked against
ray-segment intersections in float64 (written here, independent of the grid); and the drive seen
from above (learn.plots)."""

import numpy as np
import pytest

from learn.occupancy import GridConfig, OccupancyGrid, occupancy_scans
from learn.odometry import planar
from learn.plots import plot_drive_from_above, world_points
from tests.pictures import axes_frames, near, read_rgb

AZIMUTH_RAD = np.deg2rad(np.linspace(-90.0, 90.0, 181))  # 1 degree apart, as the polar grid
RANGE_MAX_M = 4.0
CELL_M = GridConfig().cell_m
TOL_M = 1.5 * CELL_M
"""Readout vs truth: a cell's centre is within half a cell of the wall at normal incidence, and a
return's width (a degree) puts the wall up to 3 cm nearer at 50 degrees incidence at 3 m."""

YAW = 0.5  # [rad]: the wall runs oblique to the grid's cells, and a sign error in the yaw shows
START = np.array([0.31, -0.27])
NORMAL = np.array([np.cos(YAW), np.sin(YAW)])  # the sensor faces the wall along it
ALONG = np.array([-np.sin(YAW), np.cos(YAW)])
DISTANCE_M = 2.2
WALL = (START + DISTANCE_M * NORMAL - 1.5 * ALONG, START + DISTANCE_M * NORMAL + 1.5 * ALONG)
"""A 3 m wall 2.2 m ahead of the sensor's start, square to its heading; nothing else in the world."""


def cross(u, v):
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def wall_ranges(poses, wall=WALL, range_max_m=RANGE_MAX_M):
    """Range [m] along each beam from each pose to the wall segment, inf where a beam misses it
    within range_max_m: p + t d = a + s e with t = (a - p) x e / d x e, s = (a - p) x d / d x e."""
    a, b = (np.asarray(end, dtype=np.float64) for end in wall)
    heading = poses[:, 2:3] + AZIMUTH_RAD[None, :]
    d = np.stack([np.cos(heading), np.sin(heading)], axis=-1)  # (T, A, 2)
    w = a - poses[:, None, :2]
    den = cross(d, b - a)
    with np.errstate(divide="ignore", invalid="ignore"):
        t, s = cross(w, b - a) / den, cross(w, d) / den
    hit = (np.abs(den) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1) & (t <= range_max_m)
    return np.where(hit, t, np.inf)


def longer(wall, by_m=2 * CELL_M):
    """The wall segment lengthened by by_m at each end: where a readout may still find it (a
    return stands for its beam's width)."""
    a, b = (np.asarray(end, dtype=np.float64) for end in wall)
    unit = (b - a) / np.linalg.norm(b - a)
    return a - by_m * unit, b + by_m * unit


def drive_along_wall(frames=10, step_m=0.1):
    """Poses facing the wall square on, driving along it from START, step_m a frame, (frames, 3)."""
    xy = START + step_m * np.arange(frames)[:, None] * ALONG
    return np.c_[xy, np.full(frames, YAW)]


def turned_away(last_pose, frames=5, turn_deg=60.0, step_m=0.05):
    """After the drive: turned left by turn_deg, then driving on along the new heading, (frames, 3)."""
    yaw = last_pose[2] + np.deg2rad(turn_deg)
    xy = last_pose[:2] + step_m * np.arange(1, frames + 1)[:, None] * np.array([np.cos(yaw), np.sin(yaw)])
    return np.c_[xy, np.full(frames, yaw)]


def scans(ranges, poses, episode=None):
    episode = np.zeros(len(poses), dtype=int) if episode is None else episode
    return occupancy_scans(ranges, poses, episode, AZIMUTH_RAD, RANGE_MAX_M)


def assert_reads_wall(readout, truth, *, wall=WALL, pose=None):
    """Every beam that hits the wall reads it within TOL_M; every beam that misses it by more than
    two cells beyond its ends (from `pose`) reads nothing."""
    hits = np.isfinite(truth)
    assert hits.sum() >= 20
    error = np.abs(readout[hits] - truth[hits])
    assert error.max() <= TOL_M, f"wall read {error.max():.3f} m off (beam {AZIMUTH_RAD[hits][error.argmax()]:.2f})"
    clear = np.isinf(wall_ranges(pose[None], longer(wall))[0])
    assert np.isinf(readout[clear]).all(), "a wall read where there is none"


def test_wall_square_on_reads_at_its_range():
    """Driving 1 m along the wall, facing it square on 2.2 m away (yaw 0.5 rad): after each frame
    the grid reads the wall on every beam that hits it (63-69 of 181, up to 47 degrees incidence)
    within 1.5 cells of the ray-segment intersection, and nothing beyond its ends."""
    poses = drive_along_wall()
    truth = wall_ranges(poses)
    readout = scans(truth, poses)
    for t in range(len(poses)):
        assert_reads_wall(readout[t], truth[t], pose=poses[t])


def test_wall_along_cell_edges_reads_its_cells_chord():
    """A wall along the cells' edges: world x = 2.51 m (1 cm into the cells from x = 2.50 to 2.55
    m), the sensor facing it square on (yaw 0) from x = 0.31 m, three frames along it. Each beam
    within 10 degrees of its normal stops in the wall's cell, at the middle of its chord through
    it: beyond x = 2.50 m and not beyond the cell's centre, x = 2.525 m."""
    poses = np.c_[np.full(3, 0.31), -0.27 + 0.1 * np.arange(3), np.zeros(3)]
    wall = ((2.51, -2.0), (2.51, 2.0))
    readout = scans(wall_ranges(poses, wall), poses)
    square = np.abs(AZIMUTH_RAD) <= np.deg2rad(10.0)
    x = poses[:, :1] + readout[:, square] * np.cos(AZIMUTH_RAD[square])
    assert x.min() > 2.50 and x.max() <= 2.525 + 1e-9, (x.min(), x.max())


def test_a_return_stands_for_its_beam_width():
    """One scan of a wall square on 3.6 m away, where beams a degree apart land 6.3 cm apart (more
    than a cell), then a frame without a scan 0.3 m along the wall and turned half a degree: its
    beams, between the first scan's, still read the wall (within 1.5 cells) on every beam that
    hits it."""
    wall = (START + 3.6 * NORMAL - 1.2 * ALONG, START + 3.6 * NORMAL + 1.2 * ALONG)
    poses = np.array([[*START, YAW], [*(START + 0.3 * ALONG), YAW + np.deg2rad(0.5)]])
    ranges = wall_ranges(poses[:1], wall)
    readout = scans(np.r_[ranges, np.full_like(ranges, np.nan)], poses)
    assert_reads_wall(readout[1], wall_ranges(poses[1:], wall)[0], wall=wall, pose=poses[1])


def test_a_wall_that_goes_clears_after_nine_frames():
    """Thirty frames hear the wall (its cells saturate at the limit, log-odds 3.5); then it is
    gone and the beams return a wall 1.3 m behind it: each frame takes 0.4 off its cells, so the
    readout keeps the old wall for 8 frames (3.5 - 8 x 0.4 = 0.3 > 0) and reads the far wall from
    the 9th on, on every beam that hits both."""
    poses = np.tile([*START, YAW], (45, 1))
    far = (WALL[0] + 1.3 * NORMAL, WALL[1] + 1.3 * NORMAL)
    near_truth, far_truth = wall_ranges(poses[:1])[0], wall_ranges(poses[:1], far)[0]
    ranges = np.r_[np.tile(near_truth, (30, 1)), np.tile(far_truth, (15, 1))]
    readout = scans(ranges, poses)
    both = np.isfinite(near_truth) & np.isfinite(far_truth)
    assert both.sum() > 40
    np.testing.assert_allclose(readout[: 30 + 8, both], np.broadcast_to(near_truth[both], (38, both.sum())), atol=TOL_M)
    np.testing.assert_allclose(readout[30 + 8 :, both], np.broadcast_to(far_truth[both], (7, both.sum())), atol=TOL_M)


def test_memory_keeps_a_wall_that_fell_silent():
    """Ten frames hear the wall; then the sensor turns 60 degrees left and drives on 0.25 m, its
    scans empty (silent, as a specular world leaves a wall met obliquely). The grid still reads
    the wall where the intersection from each new pose says (41-45 beams, -90 to -46 degrees);
    a grid fed only the empty scans (the heard frames without a scan: NaN) reads nothing."""
    heard = drive_along_wall()
    later = turned_away(heard[-1])
    poses = np.r_[heard, later]
    ranges = np.r_[wall_ranges(heard), np.full((len(later), len(AZIMUTH_RAD)), np.inf)]
    readout = scans(ranges, poses)
    truth = wall_ranges(later)
    for t in range(len(later)):
        assert_reads_wall(readout[len(heard) + t], truth[t], pose=later[t])
    ranges[: len(heard)] = np.nan
    assert np.isinf(scans(ranges, poses)[len(heard) :]).all()


def test_wrong_pose_puts_the_wall_elsewhere():
    """The memory drive again, the turned frames' yaw told 20 degrees off (odometry that lost the
    turn): from the true poses the wall's beams read it at most a quarter right (where the wall
    seen from the wrong pose crosses the true one), the median beam 3 tolerances off or not at
    all; told right, every beam reads it right."""
    heard = drive_along_wall()
    later = turned_away(heard[-1])
    ranges = np.r_[wall_ranges(heard), np.full((len(later), len(AZIMUTH_RAD)), np.inf)]
    truth = wall_ranges(later)
    hits = np.isfinite(truth)
    for yaw_error_deg in (0.0, 20.0):
        told = later + np.array([0.0, 0.0, np.deg2rad(yaw_error_deg)])
        readout = scans(ranges, np.r_[heard, told])[len(heard) :]
        with np.errstate(invalid="ignore"):  # inf - inf: a wall beam that reads nothing
            error = np.where(np.isfinite(readout), np.abs(readout - truth), np.inf)[hits]
        right = np.mean(error <= TOL_M)
        if yaw_error_deg == 0.0:
            assert right == 1.0, f"{right:.0%} of the wall read right from the true pose"
        else:
            assert right <= 0.25 and np.median(error) >= 3 * TOL_M, (right, np.median(error))


def test_moving_ghost_is_worn_away_and_the_wall_stays():
    """The sensor starts with its back to the wall and turns left 15 degrees a frame (creeping
    along the wall) until it faces it square on after 12 frames. On frames 0-8 the beams within 1
    degree of +80 degrees (space just come into view) return 1.2 m: a ghost at a new place in the
    world each frame, like multipath, on frames 5-8 in front of the wall. The grid shows each ghost
    when it appears (nothing contradicts it yet); the beams that later pass through it (returning
    the wall beyond, or nothing) free it, so at frame 12 the readout is the wall alone, on every
    beam that hits it."""
    frames = np.arange(13)
    xy = START + 0.03 * frames[:, None] * ALONG
    poses = np.c_[xy, YAW - np.pi + np.deg2rad(15.0) * frames]
    truth = wall_ranges(poses)
    ghost = (np.abs(AZIMUTH_RAD - np.deg2rad(80.0)) <= np.deg2rad(1.01))[None, :] & (frames <= 8)[:, None]
    ranges = np.where(ghost, 1.2, truth)
    readout = scans(ranges, poses)
    np.testing.assert_allclose(readout[ghost], 1.2, atol=TOL_M)
    assert np.isinf(truth[: len(poses) // 3]).all() and np.isfinite(truth[5:9][ghost[5:9]]).all()
    assert_reads_wall(readout[-1], truth[-1], pose=poses[-1])


def test_episodes_start_from_an_empty_grid():
    """Episode 7 hears the wall; episode 3, on the same poses right after, has no scans: it reads
    nothing, and episode 7 reads the same as alone (also when it comes second)."""
    poses = drive_along_wall()
    heard = wall_ranges(poses)
    silent = np.full_like(heard, np.nan)
    two = np.r_[poses, poses]
    episodes = np.repeat([7, 3], len(poses))
    readout = scans(np.r_[heard, silent], two, episodes)
    assert np.isinf(readout[len(poses) :]).all()
    alone = scans(heard, poses)
    np.testing.assert_array_equal(readout[: len(poses)], alone)
    np.testing.assert_array_equal(scans(np.r_[silent, heard], two, episodes)[len(poses) :], alone)


def test_a_frame_without_scan_adds_nothing():
    """The wall heard once, on frame 0; frames 1-9 along it have no scan (NaN). Each reads out
    exactly what a grid fed frame 0 alone reads from its pose, the wall within 1.5 cells: had the
    NaN frames counted as silent beams through it, its one hit (0.85) would be gone by frame 5."""
    poses = drive_along_wall()
    truth = wall_ranges(poses)
    ranges = np.full_like(truth, np.nan)
    ranges[0] = truth[0]
    readout = scans(ranges, poses)
    grid = OccupancyGrid.for_drive(poses, AZIMUTH_RAD, RANGE_MAX_M)
    grid.integrate(truth[0], poses[0])
    np.testing.assert_array_equal(readout, np.array([grid.readout(pose) for pose in poses]))
    hits = np.isfinite(truth[-1]) & np.isfinite(truth[0])  # the part of the wall frame 0 saw
    np.testing.assert_allclose(readout[-1, hits], truth[-1, hits], atol=TOL_M)


@pytest.mark.parametrize(
    "change, field",
    [
        (lambda r, p, e: (r, np.where(np.arange(len(p))[:, None] == 4, np.nan, p), e), "poses"),
        (lambda r, p, e: (np.where(np.arange(r.shape[1]) == 9, np.nan, r), p, e), "ranges"),
        (lambda r, p, e: (-r, p, e), "negative"),
        (lambda r, p, e: (r, p[:, :2], e), "poses"),
        (lambda r, p, e: (r, p, np.array([0, 0, 1, 1, 0, 0, 2, 2, 2, 2])), "episode 0"),
        (lambda r, p, e: (r, p, e + 0.5), "episode"),
        (lambda r, p, e: (r, p * [1e4, 1.0, 1.0], e), "cells"),
    ],
)
def test_refusals_name_what_is_wrong(change, field):
    """A NaN pose, a NaN on some beams of a frame, a negative range, a pose without yaw, an episode
    split in two runs, fractional episode ids, or a drive over 30 km (a grid of 10^8 cells,
    refused before it is allocated): a ValueError naming it."""
    poses = drive_along_wall()
    poses[:, 0] += np.arange(len(poses))  # a drive 9 m long, so that x 1e4 spans 90 km
    ranges, poses, episode = change(wall_ranges(poses), poses, np.zeros(len(poses), dtype=int))
    with pytest.raises(ValueError, match=field):
        scans(ranges, poses, episode)


def test_planar_poses_from_4x4():
    """A sensor at (1, 2, 0.5) turned 120 degrees left: x, y and yaw read back; the z row ignored."""
    yaw = np.deg2rad(120.0)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    m[:3, 3] = [1.0, 2.0, 0.5]
    np.testing.assert_allclose(planar(m[None]), [[1.0, 2.0, yaw]], atol=1e-12)


def test_world_points_by_hand():
    """Sensor at (1, 2) facing +y: a return 1 m ahead is at (1, 3), one 2 m to its left (+90
    degrees) at (-1, 2); a second frame at the origin facing +x puts 3 m at -90 degrees at
    (0, -3); no return (inf, NaN) gives no point."""
    azimuth = np.deg2rad([-90.0, 0.0, 90.0])
    ranges = np.array([[np.inf, 1.0, 2.0], [3.0, np.nan, np.inf]])
    poses = np.array([[1.0, 2.0, np.pi / 2], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(world_points(ranges, poses, azimuth), [[1, 3], [-1, 2], [0, -3]], atol=1e-12)


def test_drive_from_above_draws_each_set(tmp_path):
    """Three named sets over the wall drive: a PNG with three panels; the set without returns
    draws no black dots, the others do."""
    poses = drive_along_wall()
    truth = wall_ranges(poses)
    sets = {"truth": truth, "empty": np.full_like(truth, np.inf), "grid": scans(truth, poses)}
    image = read_rgb(plot_drive_from_above(sets, poses, AZIMUTH_RAD, tmp_path / "drive.png", title="wall"))
    panels = sorted(axes_frames(image), key=lambda box: box.left)
    assert len(panels) == 3
    dots = [(near(image, "black", 0.3) & box.inside(image.shape, inset=4)).sum() for box in panels]
    assert dots[0] > 50 and dots[2] > 50 and dots[1] == 0, dots
