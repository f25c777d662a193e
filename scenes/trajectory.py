"""Ground-robot trajectories: free space from slices of the scene, geodesic routes, smooth paths."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage.graph import MCP_Geometric

from clitools.limits import check_memory

from .scene import Scene, SceneError


def pose(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    """4x4 float64 sensor-to-world transform for a sensor at (x, y, z) [m] heading `yaw` [rad]."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, z], [0.0, 0.0, 0.0, 1.0]])


def poses(xy: np.ndarray, yaw: np.ndarray, z: float | np.ndarray = 0.0) -> np.ndarray:
    """Batched `pose`: xy (N, 2) [m], yaw (N,) [rad] -> (N, 4, 4)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)
    out = np.zeros((len(xy), 4, 4))
    out[:, 0, 0] = out[:, 1, 1] = np.cos(yaw)
    out[:, 1, 0] = np.sin(yaw)
    out[:, 0, 1] = -out[:, 1, 0]
    out[:, 2, 2] = out[:, 3, 3] = 1.0
    out[:, :2, 3] = xy
    out[:, 2, 3] = z
    return out


@dataclass(frozen=True)
class FreeSpace:
    """2D map of where a ground robot fits.

    Attributes:
        origin: World (x, y) [m] of the centre of cell [0, 0].
        cell_m: Cell size [m].
        distance_m: Distance from each cell centre to the nearest obstacle [m], shape (nx, ny).
        reachable: Cells of the chosen free region, shape (nx, ny).
        clearance_m: Clearance the map was made for [m].
        segments: The obstacle cross-sections the map was rasterised from, (S, 2, 2) [m].
    """

    origin: np.ndarray
    cell_m: float
    distance_m: np.ndarray
    reachable: np.ndarray
    clearance_m: float
    segments: np.ndarray

    def to_world(self, ij: np.ndarray) -> np.ndarray:
        return self.origin + np.asarray(ij, dtype=np.float64) * self.cell_m

    def to_cell(self, xy: np.ndarray) -> np.ndarray:
        return (np.asarray(xy) - self.origin) / self.cell_m

    def distance_at(self, xy: np.ndarray) -> np.ndarray:
        """Bilinear distance to the nearest obstacle at world points (N, 2) [m]."""
        ij = self.to_cell(np.asarray(xy).reshape(-1, 2)).T
        return ndimage.map_coordinates(self.distance_m, ij, order=1, mode="nearest")


def obstacle_segments(scene: Scene, heights: np.ndarray) -> np.ndarray:
    """Cross-sections of the scene at the given heights above the floor: 2D segments (S, 2, 2) [m]."""
    return np.concatenate([scene.section(h)[0] for h in heights])


def free_space(
    scene: Scene,
    *,
    clearance: float = 0.35,
    robot_height: float = 0.6,
    cell: float = 0.05,
) -> FreeSpace:
    """Where a robot of radius `clearance` [m] and height `robot_height` [m] can drive.

    Obstacles are the scene's cross-sections between 5 cm above the floor and the robot's
    height (so a robot may pass under a desk top but not through its legs). The free region is
    the largest connected one enclosed by obstacles; if nothing encloses the robot (an open
    scene), the largest region inside the scene's footprint is used.
    """
    if (
        not (clearance > 0 and robot_height > 0.05 and cell > 0)
        or not np.isfinite([clearance, robot_height, cell]).all()
    ):
        raise SceneError("clearance and cell must be finite and > 0 and robot_height > 0.05 m")
    segments = obstacle_segments(scene, np.linspace(0.05, robot_height, 4))
    if len(segments) == 0:
        raise SceneError(
            f"{scene.name}: no obstacles between the floor and {robot_height} m; cannot tell where a robot may drive"
        )
    lo = scene.mesh.bounds[0, :2] - 2 * cell
    hi = scene.mesh.bounds[1, :2] + 2 * cell
    size = np.ceil((hi - lo) / cell) + 1  # float: an int64 product overflows for huge scenes or tiny cells
    if not np.isfinite(size).all() or float(np.prod(size)) > 25_000_000:
        raise SceneError(
            f"{scene.name}: footprint {hi - lo} m is too large for a {cell} m grid "
            f"({float(np.prod(size)):.3g} cells, at most 2.5e7)"
        )
    shape = size.astype(int)
    # Rasterise every segment densely enough that no cell along it is skipped.
    a, b = segments[:, 0], segments[:, 1]
    steps = np.ceil(np.linalg.norm(b - a, axis=1) / (0.5 * cell)).astype(int) + 1
    try:  # 48 bytes a point: its t, owner, position and cell (float64, int64)
        check_memory(
            float(steps.sum()) * 48,
            what=f"{scene.name}: rasterising {len(segments):,} wall segments",
            advice="give a scene with fewer walls",
        )
    except ValueError as err:
        raise SceneError(str(err)) from None
    owner = np.repeat(np.arange(len(segments)), steps)
    t = _unit_steps(steps, owner)
    pts = a[owner] + t[:, None] * (b[owner] - a[owner])
    ij = np.clip(np.rint((pts - lo) / cell).astype(int), 0, shape - 1)
    occupied = np.zeros(shape, dtype=bool)
    occupied[ij[:, 0], ij[:, 1]] = True
    distance = ndimage.distance_transform_edt(~occupied) * cell
    # 1.5 cells of margin cover the rasterisation error of the distance field.
    free = distance >= clearance + 1.5 * cell
    labels, count = ndimage.label(free)
    if count == 0:
        raise SceneError(f"{scene.name}: no free space for a robot with {clearance} m clearance")
    sizes = ndimage.sum(free, labels, index=np.arange(1, count + 1))
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    enclosed = [k for k in range(1, count + 1) if k not in border]
    if enclosed:
        best = max(enclosed, key=lambda k: sizes[k - 1])
        reachable = labels == best
    else:  # open scene: keep to the footprint of the scene (the grid is padded by 2 cells)
        inside = np.zeros(shape, dtype=bool)
        inside[3:-3, 3:-3] = True
        labels, count = ndimage.label(free & inside)
        if count == 0:
            raise SceneError(f"{scene.name}: no free space for a robot with {clearance} m clearance")
        sizes = ndimage.sum(free, labels, index=np.arange(1, count + 1))
        reachable = labels == 1 + int(np.argmax(sizes))
    return FreeSpace(
        origin=lo, cell_m=cell, distance_m=distance, reachable=reachable, clearance_m=clearance, segments=segments
    )


def _unit_steps(steps: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """`np.linspace(0, 1, n)` for each n of `steps`, concatenated (`owner`: each point's segment):
    the same values bit for bit (i times 1 / (n - 1), the last exactly 1), in one pass instead of
    a call per segment (a few thousand segments a scene: most of `free_space`'s time)."""
    first = np.cumsum(steps) - steps
    index = np.arange(len(owner)) - first[owner]
    step = 1.0 / np.maximum(steps - 1, 1)
    t = index * step[owner]
    t[(first + steps - 1)[steps > 1]] = 1.0
    return t


def clears(points: np.ndarray, space: FreeSpace, clearance: float) -> bool:
    """Whether every point (N, 2) lies at least `clearance` [m] from the exact cross-sections.

    The distance field answers for points far from the walls: an occupied cell lies within 0.96
    cell of every wall point (samples every half cell, rounded to a centre) and a bilinear read
    averages centres within 1.42 cells, so the field overstates a distance by less than 2.4 cells.
    Points nearer than that margin (and any off the grid) get the exact distance."""
    margin = 3.0 * space.cell_m
    cells = space.to_cell(points)
    inside = ((cells >= 0) & (cells <= np.array(space.distance_m.shape) - 1)).all(axis=1)
    near = ~inside | (space.distance_at(points) < clearance + margin)
    return not near.any() or bool(distance_to_segments(points[near], space.segments).min() >= clearance)


def distance_to_segments(points: np.ndarray, segments: np.ndarray, *, chunk: int = 512) -> np.ndarray:
    """Exact distance [m] from 2D points (N, 2) to the nearest of 2D segments (S, 2, 2)."""
    a, ab = segments[:, 0], segments[:, 1] - segments[:, 0]
    ab2 = np.maximum((ab * ab).sum(axis=1), 1e-18)
    out = np.empty(len(points))
    for i in range(0, len(points), chunk):
        ap = points[i : i + chunk, None, :] - a[None]
        t = np.clip((ap * ab[None]).sum(axis=2) / ab2, 0.0, 1.0)
        d = ap - t[..., None] * ab[None]
        out[i : i + chunk] = np.sqrt((d * d).sum(axis=2).min(axis=1))
    return out


def _resample(points: np.ndarray, spacing: float) -> np.ndarray:
    """Points at equal arc-length `spacing` along a polyline (N, 2)."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    s = np.arange(0.0, arc[-1] + 1e-12, spacing)
    return np.column_stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])])


def _walk(points: np.ndarray, step: float, count: int) -> np.ndarray:
    """Up to `count` points along a polyline, each exactly `step` [m] (straight line) from the last.

    Unlike equal arc-length sampling, this keeps the robot's speed constant through corners.
    """
    out = [points[0]]
    current, start, k = points[0], points[0], 0
    while len(out) < count and k < len(points) - 1:
        end = points[k + 1]
        if np.linalg.norm(end - current) < step:
            k, start = k + 1, end
            continue
        # Far intersection of segment start..end with the circle of radius `step` around `current`.
        d, f = end - start, start - current
        a, b, c = d @ d, 2.0 * (f @ d), f @ f - step * step
        t = (-b + np.sqrt(max(b * b - 4.0 * a * c, 0.0))) / (2.0 * a)
        current = start = start + t * d
        out.append(current)
    return np.array(out)


def _drive(samples: np.ndarray, frames: int, max_turn: float) -> tuple[np.ndarray, np.ndarray]:
    """Frames along equally spaced path samples, heading along the path; where the heading
    changes by more than `max_turn` [rad] per frame the robot stops and turns on the spot."""
    ahead = np.diff(samples, axis=0)
    heading = np.arctan2(ahead[:, 1], ahead[:, 0])
    xy, yaw = [samples[0]], [heading[0]]
    for i in range(len(heading)):
        turn = float(np.angle(np.exp(1j * (heading[i] - yaw[-1]))))
        while abs(turn) > max_turn and len(xy) < frames:
            xy.append(xy[-1])
            yaw.append(yaw[-1] + np.sign(turn) * max_turn)
            turn -= np.sign(turn) * max_turn
        if len(xy) >= frames:
            break
        xy.append(samples[i + 1])
        yaw.append(yaw[-1] + turn)
    return np.array(xy[:frames]), np.array(yaw[:frames])


def trajectory(
    scene: Scene,
    *,
    frames: int = 100,
    dt: float = 0.1,
    speed: float = 0.3,
    clearance: float = 0.35,
    sensor_height: float = 0.3,
    robot_height: float = 0.6,
    turn_rate: float = 1.0,
    seed: int = 0,
) -> np.ndarray:
    """A smooth, collision-free ground-robot drive through the scene, sampled every `dt`.

    The robot drives at constant `speed` [m/s] along geodesic routes between random goals
    (preferring goals ahead, so it rarely turns back), smoothed over ~0.4 m, keeping at least
    `clearance` [m] from every obstacle below `robot_height` [m]. The sensor looks along the
    direction of travel at `sensor_height` [m] above the floor. Where the path reverses (dead
    ends), the robot stops and turns on the spot at no more than `turn_rate` [rad/s], as a
    differential-drive robot does.

    Returns:
        Sensor-to-world poses, shape (frames, 4, 4), float64.
    """
    if frames < 1:
        raise SceneError(f"frames must be >= 1, got {frames}")
    if not (dt > 0 and speed >= 0 and sensor_height >= 0):
        raise SceneError("dt must be > 0, speed and sensor_height >= 0")
    if not np.isfinite([dt, speed, sensor_height, speed * dt]).all():
        raise SceneError(f"dt, speed and sensor_height must be finite, got {dt}, {speed} and {sensor_height}")
    space = free_space(scene, clearance=clearance, robot_height=robot_height)
    rng = np.random.default_rng(seed)
    # Prefer cells with room around them for goals; the cost grows near obstacles so routes
    # keep to the middle of passages.
    # Routes keep an extra margin where the scene allows it, so that smoothing the corners
    # (which cuts them by a fraction of the smoothing length) cannot bring the robot closer
    # than `clearance`; the cost grows near obstacles so routes keep to the middle of passages.
    roomy = space.reachable
    for margin in (0.3, 0.15):
        candidate = space.reachable & (space.distance_m >= clearance + margin)
        if candidate.sum() >= 0.25 * space.reachable.sum():
            labels, _ = ndimage.label(candidate)
            roomy = labels == np.bincount(labels[candidate]).argmax()
            break
    cells = np.argwhere(roomy)
    weights = np.minimum(space.distance_m[roomy], 1.5)
    weights = weights / weights.sum()
    cost = np.where(roomy, 1.0 + 0.5 / np.maximum(space.distance_m, 1e-3), np.inf)
    router = MCP_Geometric(cost)

    need = (frames - 1) * speed * dt
    start = cells[rng.choice(len(cells), p=weights)]
    route = [start]
    length, heading = 0.0, rng.uniform(-np.pi, np.pi)
    for _ in range(1000):
        if length > 1.5 * need + 2.0:  # smoothing shortens the route a little
            break
        # A random goal at least 1 m away, preferably within 90 deg of the heading: sharp
        # reversals would leave cusps that no smoothing removes.
        candidates = cells[rng.choice(len(cells), size=256, p=weights)]
        delta = (candidates - route[-1]) * space.cell_m
        far = np.linalg.norm(delta, axis=1) > 1.0
        if not far.any():
            far[:] = True
        turn = np.abs(np.angle(np.exp(1j * (np.arctan2(delta[:, 1], delta[:, 0]) - heading))))
        ahead = far & (turn < np.pi / 2)
        goal = candidates[ahead][0] if ahead.any() else candidates[far][np.argmin(turn[far])]
        router.find_costs([tuple(route[-1])], [tuple(goal)])
        leg = np.array(router.traceback(tuple(goal)))
        if len(leg) < 2:
            continue
        route.extend(leg[1:])
        step = np.diff(leg[-min(len(leg), 10) :], axis=0).sum(axis=0)
        heading = float(np.arctan2(step[1], step[0]))
        length += float(np.linalg.norm(np.diff(leg, axis=0), axis=1).sum()) * space.cell_m
    path = space.to_world(np.array(route))

    for sigma_m in (0.4, 0.2, 0.1, 0.0):
        dense = _resample(path, space.cell_m / 2) if len(path) > 1 else path
        if sigma_m > 0 and len(dense) > 3:
            dense = ndimage.gaussian_filter1d(dense, sigma_m / (space.cell_m / 2), axis=0, mode="nearest")
        # Checked against the exact cross-sections, not the rasterised distance field.
        if clears(dense, space, clearance):
            break
    else:  # pragma: no cover - the unsmoothed route lies in cells that satisfy the clearance
        raise SceneError(f"{scene.name}: could not keep {clearance} m clearance along the route")

    if speed == 0 or len(dense) < 2:
        xy = np.repeat(dense[:1], frames, axis=0)
        yaw = np.full(frames, heading)
    else:
        walked = _walk(dense, speed * dt, frames + 1)
        if len(walked) < 2:  # no point of the route lies a step away: the step outgrows the scene
            raise SceneError(
                f"{scene.name}: a step of speed x dt = {speed * dt:.3g} m is longer than any route through the "
                "scene; give a lower speed or dt"
            )
        xy, yaw = _drive(walked, frames, turn_rate * dt)
        if len(xy) < frames:  # pragma: no cover - the route is built longer than needed
            raise SceneError(f"{scene.name}: route too short for {frames} frames")
    return poses(xy, yaw, scene.floor_z + sensor_height)
