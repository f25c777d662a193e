"""benchmarks/heard_before.py on a hand-made drive past one wall, where geometry gives the answer.

The wall is the line y = 2 m; the sensor faces it (yaw 90 degrees) from x = 0 (frame 0), then
from x = -2 m (frame 1, the label frame). A frame meets the wall point (x, 2) at an incidence of
atan(|x - x_sensor| / 2), so it hears the points with |x - x_sensor| < 2 tan 30 degrees.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.heard_before import heard, world_points  # noqa: E402

AZIMUTH = np.linspace(-math.pi / 2, math.pi / 2, 721)  # 0.25 degrees: beams 1-5 cm apart on the wall
WALL_Y, MAX_RANGE = 2.0, 6.0
REACH = WALL_Y * math.tan(math.radians(30.0))  # how far along the wall a sensor hears [m]


def scan(pose: np.ndarray) -> np.ndarray:
    """Ranges [m] (A,) from a sensor at `pose` facing the wall y = WALL_Y (inf beyond MAX_RANGE)."""
    heading = pose[2] + AZIMUTH
    with np.errstate(divide="ignore"):
        r = (WALL_Y - pose[1]) / np.sin(heading)
    return np.where((r > 0) & (r <= MAX_RANGE), r, np.inf)


def drive(episode=(0, 0), first_y=0.0):
    """What the label frame (1) heard, and where its returns lie; frame 0's pose as odometry gives it at `first_y`."""
    pose = np.array([[0.0, first_y, math.pi / 2], [-2.0, 0.0, math.pi / 2]])
    ranges = np.stack([scan(np.array([0.0, 0.0, math.pi / 2])), scan(pose[1])])  # frame 0 sees the wall as it is
    sets = {"self": np.array([0]), "before": np.array([-1, 0])}
    found = heard(ranges, AZIMUTH, pose, np.array(episode), np.array([1]), sets)
    x = world_points(ranges[1:], AZIMUTH, pose[1:])[0, :, 0]  # where the label frame's returns lie
    return found, x


def clear_of_edges(x: np.ndarray) -> np.ndarray:
    """Returns away (> 0.15 m) from where hearing begins or ends, and from the scan's own ends."""
    edges = np.array([-2.0 - REACH, -2.0 + REACH, -REACH, REACH])
    return np.isfinite(x) & (np.abs(x[:, None] - edges).min(1) > 0.15) & (np.abs(x + 2.0) < 5.0)


def test_a_wall_heard_from_an_earlier_pose():
    """Heard by frame 1 exactly where it faces the wall; before, also where frame 0 faced it."""
    found, x = drive()
    keep = clear_of_edges(x)
    assert keep.sum() > 300
    own = np.abs(x + 2.0) < REACH
    np.testing.assert_array_equal(found["self"][0][keep], own[keep])
    np.testing.assert_array_equal(found["before"][0][keep], (own | (np.abs(x) < REACH))[keep])
    # the point facing frame 0 (x = 0), met at 45 degrees from frame 1: heard before, not by frame 1
    at_45 = np.argmin(np.abs(x))
    assert found["before"][0, at_45] and not found["self"][0, at_45]


def test_a_wrong_pose_or_another_drive_hears_nothing_more():
    """Frame 0 placed 0.5 m off the wall's line, or in another drive, adds nothing to what frame 1 hears."""
    for found, _ in (drive(first_y=-0.5), drive(episode=(0, 1))):
        np.testing.assert_array_equal(found["before"], found["self"])


def test_world_points_turn_left_with_azimuth():
    """Azimuth is positive to the left (learn.odometry): a sensor at (1, 0) facing +y sees a return 2 m
    away at azimuth +90 degrees at (-1, 0), and none where the beam has no return."""
    points = world_points(np.array([[2.0, np.inf]]), np.array([math.pi / 2, 0.0]), np.array([[1.0, 0.0, math.pi / 2]]))
    np.testing.assert_allclose(points[0, 0], [-1.0, 0.0], atol=1e-12)
    assert np.isinf(points[0, 1]).all()
