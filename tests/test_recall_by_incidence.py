"""The incidence angle that benchmarks/recall_by_incidence.py reads off a true scan, against walls
whose angle to every beam is known in closed form."""

import numpy as np

from benchmarks.recall_by_incidence import incidence_deg

AZIMUTH = np.radians(np.arange(-90.0, 91.0))  # the paper grid's 181 beams


def wall_ranges(point, normal_deg):
    """Range of each beam to the infinite wall through `point` with unit normal at `normal_deg` (inf behind)."""
    normal = np.array([np.cos(np.radians(normal_deg)), np.sin(np.radians(normal_deg))])
    beams = np.stack([np.cos(AZIMUTH), np.sin(AZIMUTH)], axis=1)
    with np.errstate(divide="ignore"):
        r = (np.asarray(point) @ normal) / (beams @ normal)
    return np.where((r > 0) & (r < 5.0), r, np.inf)


def test_incidence_on_straight_walls_is_the_angle_to_their_normal():
    for point, normal_deg in (((2.0, 0.0), 0.0), ((2.0, 0.5), 25.0), ((0.5, 1.5), 70.0)):
        ranges = wall_ranges(point, normal_deg)
        got = incidence_deg(ranges[None], AZIMUTH)[0]
        expected = np.degrees(np.arccos(np.abs(np.cos(AZIMUTH - np.radians(normal_deg)))))
        seen = np.isfinite(got)
        assert seen.sum() > 60, (point, normal_deg)
        np.testing.assert_allclose(got[seen], expected[seen], atol=1e-6)
        assert not np.isfinite(got[~np.isfinite(ranges)]).any()  # no return, no angle


def test_no_angle_at_a_corner_or_the_grid_edge():
    """A corner where a wall 1.2 m away ends in front of one 3 m away: the beams whose neighbours
    lie on the other surface get no angle, nor do the two outermost beams on each side."""
    ranges = np.where(AZIMUTH < 0, wall_ranges((1.2, 0.0), 0.0), wall_ranges((3.0, 0.0), 0.0))
    got = incidence_deg(ranges[None], AZIMUTH)[0]
    assert np.isnan(got[88:92]).all() and np.isfinite(got[[86, 93]]).all()
    assert np.isnan(got[[0, 1, -2, -1]]).all()
