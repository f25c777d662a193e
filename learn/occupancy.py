"""The classical baseline beside the learned memory: a log-odds occupancy grid in the world frame.

Each frame's scan is integrated into a grid of cells fixed in the world (Moravec & Elfes 1985), with
the inverse sensor model of Thrun, Burgard & Fox (Probabilistic Robotics, ch. 9): along each beam the
cells before its return are made more likely free, the cells at the return (across the beam's width,
joined to the neighbouring beams' returns on the same surface) more likely occupied, each cell at
most once a frame, occupied before free. Log-odds add, so
evidence gathered a second ago stays when the wall is silent now, and a return that does not stay
put in the world (a multipath ghost) is worn away by the beams that later pass through it. The grid
is read out as a LiDAR scan from the current pose: each beam's first cell with log-odds > 0.

numpy only; poses are planar (x, y, yaw) of a level sensor (`learn.odometry.planar` reads them
from the shards' 4x4 sensor-to-world matrices). Azimuth 0 is the sensor's x axis (ahead), positive to the
left, as in the polar grid of `learn.metrics`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_JOIN_WIDTHS = 3.0
"""Neighbouring returns this many beam widths apart (or two cells) lie on one surface: a wall up
to 70 degrees off the beams' normal; a larger gap is a depth edge, left open."""

MAX_GRID_CELLS = 64_000_000
"""Most cells one episode's grid may have (256 MB of float32): a drive over 400 x 400 m at 5 cm."""


@dataclass(frozen=True, kw_only=True)
class GridConfig:
    """Cell size and the inverse sensor model's log-odds steps (log(p / (1 - p)) of a cell).

    The steps are OctoMap's (Hornung et al. 2013), taken from Thrun's model: one return makes a
    cell occupied (p 0.5 -> 0.7), three beams that pass through it make it free again, and a cell
    seen over and over saturates at `limit`, so it takes about nine beams through it to clear.

    Attributes:
        cell_m: Side of a square cell [m]. 0.05 m keeps the readout within half a cell of a wall
            along the cells' edges met square on, and about 1.5 cm nearer on average where the wall
            runs oblique to them (the first cell met is often one the wall only clips); the 0.10 m
            scan tolerance of `learn.scan` is two cells. A drive over 20 x 20 m (plus range) needs
            under 0.4 M cells.
        hit: Log-odds added to the cells at a return, > 0: 0.85 = p 0.7.
        miss: Log-odds added to the cells a returning beam passed through before its return
            (its echo came from beyond them), < 0: -0.4 = p 0.4.
        miss_no_return: Log-odds added along a beam with no return, to the range limit, <= 0.
            Half of `miss` by default: in a specular world silence is weak evidence of free space
            (a wall more than 30 degrees off its normal is mostly silent), so a saturated wall
            outlasts 17 silent beams through it and a single ghost return 4 (0 ignores silent
            beams, as many sonar grids do with max-range readings).
        limit: The log-odds stay in [-limit, limit], > 0: 3.5 = p 0.97, so that a cell can change
            its state after a few frames of contrary evidence however long it was seen.
    """

    cell_m: float = 0.05
    hit: float = 0.85
    miss: float = -0.4
    miss_no_return: float = -0.2
    limit: float = 3.5

    def __post_init__(self):
        for name in ("cell_m", "hit", "miss", "miss_no_return", "limit"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"GridConfig.{name} must be finite, got {getattr(self, name)}")
        if self.cell_m <= 0 or self.hit <= 0 or self.limit <= 0:
            raise ValueError(
                f"GridConfig.cell_m, hit and limit must be > 0, got {self.cell_m}, {self.hit}, {self.limit}"
            )
        if self.miss >= 0 or self.miss_no_return > 0:
            raise ValueError(
                f"GridConfig.miss must be < 0 and miss_no_return <= 0, got {self.miss}, {self.miss_no_return}"
            )


class OccupancyGrid:
    """One drive's log-odds grid: a fixed window of the world, prior log-odds 0 (unknown).

    Args:
        bounds_m: (x_min, y_min, x_max, y_max) [m] the grid must cover.
        azimuth_rad: Beam directions of the scans it takes and gives, shape (A,).
        range_max_m: Longest range [m] a beam integrates and reads out.
        config: Cell size and log-odds steps.
    """

    def __init__(self, bounds_m, azimuth_rad, range_max_m: float, config: GridConfig = GridConfig()):
        self.config = config
        self.azimuth_rad = np.asarray(azimuth_rad, dtype=np.float64)
        self.range_max_m = float(range_max_m)
        c = config.cell_m
        x_min, y_min, x_max, y_max = bounds_m
        # Cell edges on multiples of cell_m in the world, so a place falls in the same cell whatever the drive.
        self.origin_m = np.array([math.floor(x_min / c) * c, math.floor(y_min / c) * c])
        self.shape = (math.floor((x_max - self.origin_m[0]) / c) + 1, math.floor((y_max - self.origin_m[1]) / c) + 1)
        cells = self.shape[0] * self.shape[1]
        if cells > MAX_GRID_CELLS:
            raise ValueError(
                f"an occupancy grid over {x_max - x_min:.0f} x {y_max - y_min:.0f} m at GridConfig.cell_m = {c} m "
                f"needs {cells:,} cells, more than {MAX_GRID_CELLS:,}: use larger cells or split the episode"
            )
        self.log_odds = np.zeros(cells, dtype=np.float32)
        self._mark = np.zeros(cells, dtype=np.int8)  # which update a cell gets this frame (0 = none)
        self._beams_of: tuple | None = None
        # Samples along a beam every half cell meet every cell it crosses but corners (see _path_cells).
        self.step_m = 0.5 * c
        self.sample_range_m = self.step_m * np.arange(1, math.floor(self.range_max_m / self.step_m) + 1)
        # A return stands for its beam's width (Thrun's opening angle): the gap to its neighbours.
        self.beam_width_rad = np.abs(np.gradient(self.azimuth_rad)) if len(self.azimuth_rad) > 1 else np.zeros(1)
        longest = max(_JOIN_WIDTHS * self.range_max_m * float(self.beam_width_rad.max()), 2 * c)  # of a half
        self._along_half = np.linspace(0.0, 1.0, math.ceil(longest / self.step_m) + 1)[:, None]

    @classmethod
    def for_drive(cls, poses, azimuth_rad, range_max_m: float, config: GridConfig = GridConfig()) -> OccupancyGrid:
        """A grid sized to what a drive's scans can reach: its poses' extent plus `range_max_m` all round."""
        poses = np.asarray(poses, dtype=np.float64)
        reach = float(range_max_m) + 2 * config.cell_m
        lo, hi = poses[:, :2].min(axis=0) - reach, poses[:, :2].max(axis=0) + reach
        return cls((lo[0], lo[1], hi[0], hi[1]), azimuth_rad, range_max_m, config)

    def _path_cells(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cells paths cross: world points [m] (K, N), each path along axis 0, its points at most
        half a cell apart.

        A step between two points that changes both cell indices also cuts the corner of a third
        cell, the one beyond the cell edge it crosses first: without it a beam would slip through
        a wall one cell thick where two of its cells touch at a corner only.

        Returns:
            cells: Flat index of each point's cell, (K, N).
            corners: Flat index of the cell whose corner the step to point k cuts, -1 where none, (K, N).
            leave: Where the step to point k leaves that corner's cell, as a share of the step, (K, N).
        """
        ny = self.shape[1]
        fx, fy = (x - self.origin_m[0]) / self.config.cell_m, (y - self.origin_m[1]) / self.config.cell_m
        ix, iy = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
        if ix.size and (ix.min() < 0 or iy.min() < 0 or ix.max() >= self.shape[0] or iy.max() >= ny):
            raise ValueError("a scan reaches outside its occupancy grid: size the grid from the drive's poses")
        k, n = np.nonzero((ix[1:] != ix[:-1]) & (iy[1:] != iy[:-1]))
        here, before = (k + 1, n), (k, n)
        # Where the step crosses the x and the y cell edge, as shares of the step (both edges: no division by 0).
        at_x = (np.maximum(ix[here], ix[before]) - fx[before]) / (fx[here] - fx[before])
        at_y = (np.maximum(iy[here], iy[before]) - fy[before]) / (fy[here] - fy[before])
        corners = np.full(ix.shape, -1, dtype=np.int64)
        leave = np.ones(ix.shape)
        corners[here] = np.where(at_x < at_y, ix[here] * ny + iy[before], ix[before] * ny + iy[here])
        leave[here] = np.maximum(at_x, at_y)
        return ix * ny + iy, corners, leave

    def _beams(self, pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`_path_cells` of the beams from `pose` out to `range_max_m` (sampled every half cell), with
        the range [m] at which a beam leaves each corner cell instead of the share: (S, A) each.
        The last pose's are kept: a frame integrates and reads out from the same pose."""
        key = tuple(float(v) for v in pose[:3])
        if self._beams_of != key:
            heading = pose[2] + self.azimuth_rad
            r = self.sample_range_m[:, None]
            cells, corners, leave = self._path_cells(pose[0] + r * np.cos(heading), pose[1] + r * np.sin(heading))
            self._beams_of, self._beam_cells = key, (cells, corners, r - self.step_m * (1 - leave))
        return self._beam_cells

    def _surface(self, z: np.ndarray, hit: np.ndarray, pose) -> tuple[np.ndarray, np.ndarray]:
        """Points [m] on the surface each return stands for, (P, 2 * returns) x and y: from the
        return half-way to its neighbour's on each side where the two lie on one surface (within
        `_JOIN_WIDTHS` beam widths or two cells of each other), else out to its beam's edge at the
        same range. A wall met obliquely so stays where it is, not an arc in front of it."""
        heading = pose[2] + self.azimuth_rad
        reach = np.where(hit, z, 0.0)
        end_x, end_y = pose[0] + reach * np.cos(heading), pose[1] + reach * np.sin(heading)
        i = np.flatnonzero(hit)
        xs, ys = [], []
        for side in (-1, 1):
            j = np.clip(i + side, 0, len(z) - 1)
            gap = np.hypot(end_x[j] - end_x[i], end_y[j] - end_y[i])
            near = np.maximum(_JOIN_WIDTHS * z[i] * self.beam_width_rad[i], 2 * self.config.cell_m)
            join = (j != i) & hit[j] & (gap <= near)
            edge = heading[i] + side * 0.5 * self.beam_width_rad[i]
            far_x = np.where(join, 0.5 * (end_x[i] + end_x[j]), pose[0] + z[i] * np.cos(edge))
            far_y = np.where(join, 0.5 * (end_y[i] + end_y[j]), pose[1] + z[i] * np.sin(edge))
            xs.append(end_x[i] + self._along_half * (far_x - end_x[i]))
            ys.append(end_y[i] + self._along_half * (far_y - end_y[i]))
        return np.concatenate(xs, axis=1), np.concatenate(ys, axis=1)

    def integrate(self, ranges: np.ndarray, pose) -> None:
        """Add one scan's evidence.

        Args:
            ranges: Range [m] per beam, shape (A,); inf = no return (free to `range_max_m`); a
                return beyond `range_max_m` only frees the cells up to it. No NaN: a frame
                without a scan is not integrated at all.
            pose: Sensor pose (x [m], y [m], yaw [rad]) in the world.
        """
        cfg, z = self.config, np.asarray(ranges, dtype=np.float64)
        returned = np.isfinite(z)
        hit = returned & (z <= self.range_max_m)
        cells, corners, corner_leave_m = self._beams(pose)
        # Free up to a cell before the return: the return's own cell is never cleared by its beam.
        free_to = np.where(hit, z - cfg.cell_m, self.range_max_m)[None, :]
        passed = self.sample_range_m[:, None] <= free_to
        corner_passed = (corners >= 0) & (corner_leave_m <= free_to)
        free_strong = np.r_[cells[passed & returned], corners[corner_passed & returned]]
        free_weak = np.r_[cells[passed & ~returned], corners[corner_passed & ~returned]]
        surface, surface_corners, _ = self._path_cells(*self._surface(z, hit, pose))
        occupied = np.r_[surface.ravel(), surface_corners[surface_corners >= 0]]
        # Each cell once a frame, the strongest evidence winning: occupied over a miss over silence.
        updates = ((free_weak, cfg.miss_no_return, 1), (free_strong, cfg.miss, 2), (occupied, cfg.hit, 3))
        for cells, _, level in updates:
            self._mark[cells] = level
        for cells, step, level in updates:
            mine = cells[self._mark[cells] == level]
            self.log_odds[mine] = np.clip(self.log_odds[mine] + step, -cfg.limit, cfg.limit)
        for cells, _, _ in updates:
            self._mark[cells] = 0

    def readout(self, pose) -> np.ndarray:
        """The grid seen as a LiDAR scan from `pose`: per beam, the first cell with log-odds > 0.

        The range given is the middle of the beam's chord through that cell (its centre at normal
        incidence), at most `range_max_m`; every cell the beam crosses is looked at, corners
        included, so a wall one cell thick stops it.

        Args:
            pose: Sensor pose (x [m], y [m], yaw [rad]) in the world.

        Returns:
            Range [m] per beam, inf where no cell within `range_max_m` is occupied, float64, (A,).
        """
        cells, corners, _ = self._beams(pose)
        count, beams = cells.shape
        # First occupied cell along each beam: a corner cut on the step to sample k comes before sample k's cell.
        at_point, at_corner = self.log_odds[cells] > 0, (corners >= 0) & (self.log_odds[corners] > 0)
        k_point = np.where(at_point.any(axis=0), at_point.argmax(axis=0), count)
        k_corner = np.where(at_corner.any(axis=0), at_corner.argmax(axis=0), count)
        corner_first = k_corner <= k_point
        k = np.minimum(k_point, k_corner)
        seen = k < count
        k, beam = k[seen], np.arange(beams)[seen]
        first = np.where(corner_first[seen], corners[k, beam], cells[k, beam])
        c, heading = self.config.cell_m, pose[2] + self.azimuth_rad[seen]
        lo_x = self.origin_m[0] + c * (first // self.shape[1]) - pose[0]
        lo_y = self.origin_m[1] + c * (first % self.shape[1]) - pose[1]
        enter_x, leave_x = _slab(lo_x, lo_x + c, np.cos(heading))
        enter_y, leave_y = _slab(lo_y, lo_y + c, np.sin(heading))
        middle = 0.5 * (np.maximum(enter_x, enter_y) + np.minimum(leave_x, leave_y))
        out = np.full(len(self.azimuth_rad), np.inf)
        out[seen] = np.minimum(middle, self.range_max_m)
        return out


def _slab(lo: np.ndarray, hi: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters where a ray from 0 along d (one axis) is inside [lo, hi]: (enter, leave)."""
    parallel = np.abs(d) < 1e-12  # inside the slab all along (a sample of the ray lies in the cell)
    safe = np.where(parallel, 1.0, d)
    t0, t1 = lo / safe, hi / safe
    enter = np.where(parallel, -np.inf, np.minimum(t0, t1))
    leave = np.where(parallel, np.inf, np.maximum(t0, t1))
    return enter, leave


def occupancy_scans(
    ranges, poses, episode, azimuth_rad, range_max_m: float, config: GridConfig = GridConfig()
) -> np.ndarray:
    """Scans read out of an occupancy grid fed with a drive's scans and poses, frame by frame.

    A fresh grid per episode, in the world frame, sized to the episode's poses plus
    `range_max_m`. Frame t's scan is integrated, then the grid is read out from pose t: so frame
    t's readout holds frames 0..t of its episode.

    Args:
        ranges: Range [m] per frame and beam, shape (T, A); inf = no return on that beam (it saw
            free space to `range_max_m`); a frame all NaN = no scan that frame (nothing
            integrated, still read out), so scans can be fed for some frames only.
        poses: Planar sensor poses in the world, x [m], y [m], yaw [rad], float64, shape (T, 3).
        episode: Episode id per frame, ints, shape (T,); an episode's frames contiguous and in
            time order.
        azimuth_rad: Beam directions [rad], 0 = sensor x axis (ahead), positive left, shape (A,).
        range_max_m: Longest range [m] integrated and read out.
        config: Cell size and log-odds steps.

    Returns:
        Range [m] per frame and beam, inf where no occupied cell lies within `range_max_m`,
        float64, shape (T, A).

    Raises:
        ValueError: A shape that does not match, a NaN or infinite pose, a NaN in part of a
            frame's scan, a negative range, an episode in two separate runs of frames, a
            `range_max_m` that is not a positive number, or a grid beyond `MAX_GRID_CELLS`.
    """
    ranges, poses, episode, azimuth_rad = _checked(ranges, poses, episode, azimuth_rad, range_max_m)
    out = np.full(ranges.shape, np.inf)
    if not len(out):
        return out
    starts = np.flatnonzero(np.r_[True, episode[1:] != episode[:-1]])
    for start, stop in zip(starts, np.r_[starts[1:], len(episode)], strict=True):
        grid = OccupancyGrid.for_drive(poses[start:stop], azimuth_rad, range_max_m, config)
        for t in range(start, stop):
            if not np.isnan(ranges[t]).all():
                grid.integrate(ranges[t], poses[t])
            out[t] = grid.readout(poses[t])
    return out


def _checked(ranges, poses, episode, azimuth_rad, range_max_m):
    """The inputs of `occupancy_scans` as float64 / int64 arrays, refused with the field named."""
    ranges = np.asarray(ranges, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    azimuth_rad = np.asarray(azimuth_rad, dtype=np.float64)
    episode = np.asarray(episode)
    if ranges.ndim != 2:
        raise ValueError(f"ranges must have shape (frames, beams), got {ranges.shape}")
    frames, beams = ranges.shape
    for name, array, shape in (("poses", poses, (frames, 3)), ("episode", episode, (frames,))):
        if array.shape != shape:
            raise ValueError(f"{name} must have shape {shape} to match ranges {ranges.shape}, got {array.shape}")
    if azimuth_rad.shape != (beams,) or not np.isfinite(azimuth_rad).all():
        raise ValueError(f"azimuth_rad must be {beams} finite beam directions, got shape {azimuth_rad.shape}")
    if not (isinstance(range_max_m, int | float | np.number) and 0 < range_max_m < math.inf):
        raise ValueError(f"range_max_m must be a positive number of metres, got {range_max_m!r}")
    bad = np.flatnonzero(~np.isfinite(poses).all(axis=1))
    if len(bad):
        raise ValueError(f"poses of {len(bad)} frames are NaN or infinite (first: frame {bad[0]}): no odometry there")
    nan = np.isnan(ranges)
    partial = np.flatnonzero(nan.any(axis=1) & ~nan.all(axis=1))
    if len(partial):
        raise ValueError(
            f"ranges of {len(partial)} frames are NaN on some beams only (first: frame {partial[0]}): "
            "use inf for no return, or NaN on every beam for a frame without a scan"
        )
    if (ranges < 0).any():
        raise ValueError(f"ranges hold negative values (first: frame {np.argwhere(ranges < 0)[0, 0]})")
    if episode.dtype.kind not in "iu":
        raise ValueError(f"episode must be integer ids, got dtype {episode.dtype}")
    runs = episode[np.r_[True, episode[1:] != episode[:-1]][: len(episode)]]
    if len(np.unique(runs)) != len(runs):
        ids, counts = np.unique(runs, return_counts=True)
        raise ValueError(
            f"episode {ids[counts > 1][0]} has frames in separate runs: an episode's frames must be contiguous"
        )
    return ranges, poses, episode.astype(np.int64), azimuth_rad
