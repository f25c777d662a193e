"""Which of a dataset's elevation beams a model reads: the rows of the elevations it asks for,
and those the data lacks (a model trained on three elevations needs data beamformed at them)."""

from __future__ import annotations

import numpy as np

MATCH_DEG = 1e-6  # elevations this close are one (they come through JSON and float32 alike)


def level_index(elevation_deg) -> int:
    """Index of the elevation [deg] nearest 0: the LiDAR's plane, the one a planar sonar images."""
    return int(np.argmin(np.abs(np.asarray(elevation_deg, dtype=np.float64))))


def elevation_rows(have_deg, want_deg) -> list[int]:
    """Where each elevation of `want_deg` lies among `have_deg` [deg] (see `missing_elevations`)."""
    have = np.asarray(have_deg, dtype=np.float64)
    return [int(np.argmin(np.abs(have - e))) for e in want_deg]


def missing_elevations(have_deg, want_deg) -> list[float]:
    """Those of `want_deg` [deg] that `have_deg` (a dataset's elevations) lacks."""
    have = np.asarray(have_deg, dtype=np.float64)
    return [float(e) for e in want_deg if np.abs(have - e).min() > MATCH_DEG]


def rows_to_hold(have_deg, want_deg) -> list[int]:
    """The rows of `have_deg` [deg] a reader of `want_deg` needs, in order (all of them where `want_deg` is None,
    or where the data lacks one of it: the reader then refuses, naming both)."""
    if want_deg is None or missing_elevations(have_deg, want_deg):
        return list(range(len(have_deg)))
    return sorted(set(elevation_rows(have_deg, want_deg)))
