"""Scene builders: box rooms, corridors, offices and the paper's random worlds of walls and cylinders."""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import trimesh

from .materials import Material
from .mesh_import import load
from .scene import Scene, SceneError, assemble, box_mesh, cylinder_mesh, room_shell

Part = tuple[trimesh.Trimesh, "str | Material"]


def _check_size(size: Sequence[float], minimum: Sequence[float]) -> np.ndarray:
    try:
        size = np.asarray(size, dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneError(f"size must be three finite numbers (x, y, z) in metres, got {size!r}") from None
    if size.shape != (3,) or not np.isfinite(size).all():
        raise SceneError(f"size must be three finite numbers (x, y, z) in metres, got {size!r}")
    if (size < minimum).any():
        raise SceneError(f"size {size.tolist()} m is too small; the minimum is {list(minimum)} m")
    return size


def _shell_parts(
    size: Sequence[float], wall: str | Material, floor: str | Material, ceiling: str | Material
) -> list[Part]:
    shell = room_shell(size)
    return [(shell["floor"], floor), (shell["walls"], wall), (shell["ceiling"], ceiling)]


class _Placer:
    """Rejection sampler for object footprints (circles) that keeps passages free for a robot.

    Two objects stay `passage` [m] apart, where each object brings its own passage and the
    smaller of the two applies: large furniture keeps robot-wide passages, small clutter may
    stand closer.
    """

    def __init__(self, rng: np.random.Generator, size: np.ndarray, passage: float):
        self.rng = rng
        self.size = size
        self.passage = passage
        self.placed: list[tuple[float, float, float, float]] = []
        self.skipped = 0

    def place(self, radius: float, *, wall_gap: float | None = None, passage: float | None = None, tries: int = 200):
        """Return (x, y) of a free spot for a footprint of `radius` [m], or None (and count a skip).

        Up to `tries` spots are drawn and the first free one is taken; they are drawn and checked
        all at once (an object that does not fit costs one array operation, not 200 loops, so
        thousands asked of a small room take seconds), and the generator is left where drawing
        them one by one up to the first free spot would leave it: the scenes are the same."""
        passage = self.passage if passage is None else passage
        wall_gap = passage if wall_gap is None else wall_gap
        lo, hi = radius + wall_gap, self.size[:2] - radius - wall_gap
        if (hi > lo).all():
            start = self.rng.bit_generator.state
            spots = self.rng.uniform(lo, hi, size=(tries, 2))  # the doubles `tries` calls would draw, in order
            free = np.ones(tries, dtype=bool)
            if self.placed:
                px, py, pr, pp = np.array(self.placed).T
                gap = radius + pr + np.minimum(passage, pp)
                free = (np.hypot(spots[:, :1] - px, spots[:, 1:] - py) > gap).all(axis=1)
            drawn = int(np.argmax(free)) + 1 if free.any() else tries
            self.rng.bit_generator.state = start
            self.rng.uniform(lo, hi, size=(drawn, 2))  # draw exactly what the one-by-one search drew
            if free.any():
                x, y = spots[drawn - 1]
                self.placed.append((x, y, radius, passage))
                return float(x), float(y)
        self.skipped += 1
        return None

    def warn_skipped(self, scene: str) -> None:
        if self.skipped:
            warnings.warn(
                f"{scene}: {self.skipped} objects did not fit with free passages and were left out", stacklevel=3
            )


def box_room(
    size: Sequence[float] = (6.0, 4.0, 3.0),
    *,
    wall: str | Material = "painted_wall",
    floor: str | Material = "floor",
    ceiling: str | Material = "painted_wall",
    seed: int = 0,
) -> Scene:
    """Empty shoebox room spanning (0, 0, 0) .. size [m], normals pointing inwards.

    It draws nothing; `seed` is accepted so that every builder is called alike."""
    size = _check_size(size, (0.5, 0.5, 0.5))
    return assemble(_shell_parts(size, wall, floor, ceiling), name="box_room", params={"size": size.tolist()})


def _door(x: float, side: int, width_y: float, *, width: float = 0.9, height: float = 2.1) -> list[Part]:
    """Door leaf recessed in a corridor wall plus a protruding frame (two jambs and a header).

    `side` is -1 for the wall at y = 0 and +1 for the wall at y = width_y.
    """
    wall_y = 0.0 if side < 0 else width_y
    inward = -side  # direction from the wall into the corridor
    frame_depth, frame_width = 0.04, 0.06
    leaf = box_mesh((x, wall_y + inward * 0.01, height / 2), (width, 0.04, height))
    parts: list[Part] = [(leaf, "wood")]
    y_frame = wall_y + inward * frame_depth / 2
    for dx in (-1, 1):
        jamb = box_mesh((x + dx * (width + frame_width) / 2, y_frame, height / 2), (frame_width, frame_depth, height))
        parts.append((jamb, "wood"))
    header = box_mesh((x, y_frame, height + frame_width / 2), (width + 2 * frame_width, frame_depth, frame_width))
    parts.append((header, "wood"))
    return parts


def _radiator(x: float, side: int, width_y: float, *, length: float = 1.0) -> list[Part]:
    """Ribbed panel radiator against a corridor wall: a flat body with vertical fins."""
    wall_y = 0.0 if side < 0 else width_y
    inward = -side
    body = box_mesh((x, wall_y + inward * 0.06, 0.45), (length, 0.04, 0.6))
    parts: list[Part] = [(body, "metal")]
    for fx in np.linspace(x - length / 2 + 0.05, x + length / 2 - 0.05, 10):
        parts.append((box_mesh((fx, wall_y + inward * 0.095, 0.45), (0.01, 0.03, 0.6)), "metal"))
    return parts


def corridor(
    length: float = 16.0,
    width: float = 2.0,
    height: float = 2.8,
    *,
    reflectors: str = "many",
    seed: int = 0,
) -> Scene:
    """Straight corridor along x with doors and, for `reflectors="many"`, edge-rich clutter.

    "few": plain walls with two flush doors. "many": door frames, pillars, ribbed radiators
    and skirting boards, the small features that echo ultrasound back to a sonar.
    """
    if reflectors not in ("few", "many"):
        raise SceneError(f"reflectors must be 'few' or 'many', got {reflectors!r}")
    size = _check_size((length, width, height), (3.0, 1.2, 2.2))
    rng = np.random.default_rng(seed)
    parts = _shell_parts(size, "painted_wall", "floor", "ceiling_tile")
    if reflectors == "few":
        for x, side in ((length * 0.3, -1), (length * 0.7, 1)):
            leaf = box_mesh((x, 0.005 if side < 0 else width - 0.005, 1.05), (0.9, 0.01, 2.1))
            parts.append((leaf, "wood"))
    else:
        door_x = np.arange(2.0, length - 1.0, 3.0) + rng.uniform(-0.4, 0.4, size=len(np.arange(2.0, length - 1.0, 3.0)))
        sides = np.where(np.arange(len(door_x)) % 2 == 0, -1, 1)
        for x, side in zip(door_x, sides, strict=True):
            parts += _door(float(x), int(side), width)
        for x in np.arange(4.5, length - 1.0, 5.0):
            for side in (-1, 1):
                y = 0.15 if side < 0 else width - 0.15
                parts.append((box_mesh((x, y, height / 2), (0.35, 0.3, height)), "painted_wall"))
        for x, side in zip(door_x[:-1] + 1.5, -sides[:-1], strict=True):
            parts += _radiator(float(x), int(side), width)
        for side in (-1, 1):
            y = 0.01 if side < 0 else width - 0.01
            parts.append((box_mesh((length / 2, y, 0.04), (length, 0.02, 0.08)), "wood"))
    return assemble(
        parts,
        name="corridor",
        params={
            "length": float(length),
            "width": float(width),
            "height": float(height),
            "reflectors": reflectors,
            "seed": seed,
        },
    )


_CLUTTER = {
    # desks, chairs, shelves, pillars, boxes, glass panels
    "low": (2, 2, 1, 0, 2, 0),
    "medium": (3, 3, 2, 1, 5, 1),
    "high": (3, 6, 3, 1, 12, 1),
}


def _desk(x: float, y: float, yaw: float) -> list[Part]:
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    parts: list[Part] = [(box_mesh((x, y, 0.735), (1.4, 0.7, 0.03), yaw), "wood")]
    for lx, ly in ((0.65, 0.3), (-0.65, 0.3), (0.65, -0.3), (-0.65, -0.3)):
        dx, dy = rot @ (lx, ly)
        parts.append((box_mesh((x + dx, y + dy, 0.36), (0.04, 0.04, 0.72), yaw), "metal"))
    return parts


def _chair(x: float, y: float, yaw: float) -> list[Part]:
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    parts: list[Part] = [(box_mesh((x, y, 0.46), (0.45, 0.45, 0.05), yaw), "fabric")]
    bx, by = rot @ (-0.21, 0.0)
    parts.append((box_mesh((x + bx, y + by, 0.75), (0.04, 0.45, 0.55), yaw), "fabric"))
    for lx, ly in ((0.19, 0.19), (-0.19, 0.19), (0.19, -0.19), (-0.19, -0.19)):
        dx, dy = rot @ (lx, ly)
        parts.append((cylinder_mesh(x + dx, y + dy, 0.015, 0.0, 0.44, sections=8), "metal"))
    return parts


def office(
    *,
    seed: int = 0,
    size: Sequence[float] = (8.0, 6.0, 3.0),
    clutter: str = "medium",
) -> Scene:
    """Office room with desks, chairs, shelves, pillars, boxes and a glass partition.

    `clutter` is "low", "medium" or "high"; object positions and orientations depend on
    `seed`. Objects keep ~0.8 m passages between them so a robot can drive through.
    """
    if clutter not in _CLUTTER:
        raise SceneError(f"clutter must be one of {sorted(_CLUTTER)}, got {clutter!r}")
    size = _check_size(size, (3.0, 3.0, 2.2))
    rng = np.random.default_rng(seed)
    placer = _Placer(rng, size, passage=0.8)
    parts = _shell_parts(size, "painted_wall", "floor", "ceiling_tile")
    desks, chairs, shelves, pillars, boxes, glass = _CLUTTER[clutter]

    def yaw() -> float:
        return float(rng.choice([0.0, np.pi / 2]) + rng.normal(0.0, 0.1))

    # Largest footprints first: they are the hardest to fit.
    for _ in range(desks):
        if (xy := placer.place(0.8, wall_gap=0.2)) is not None:
            parts += _desk(*xy, yaw())
    for _ in range(glass):
        if (xy := placer.place(0.7, wall_gap=0.5)) is not None:
            parts.append((box_mesh((*xy, 1.0), (1.2, 0.012, 2.0), yaw()), "glass"))
    for _ in range(pillars):
        if (xy := placer.place(0.3)) is not None:
            parts.append((box_mesh((*xy, size[2] / 2), (0.4, 0.4, size[2]), yaw()), "painted_wall"))
    for _ in range(shelves):
        if (xy := placer.place(0.45, wall_gap=0.05, passage=0.5)) is not None:
            parts.append((box_mesh((*xy, 0.9), (0.8, 0.35, 1.8), yaw()), "wood"))
    for _ in range(chairs):
        if (xy := placer.place(0.35, passage=0.15)) is not None:
            parts += _chair(*xy, float(rng.uniform(0, 2 * np.pi)))
    for _ in range(boxes):
        if (xy := placer.place(0.3, wall_gap=0.05, passage=0.05)) is not None:
            extents = rng.uniform((0.2, 0.2, 0.2), (0.5, 0.5, 0.6))
            parts.append((box_mesh((*xy, extents[2] / 2), extents, float(rng.uniform(0, np.pi))), "wood"))
    placer.warn_skipped("office")
    return assemble(parts, name="office", params={"seed": seed, "size": size.tolist(), "clutter": clutter})


def random_world(
    *,
    seed: int = 0,
    size: Sequence[float] = (10.0, 10.0, 3.0),
    wall_count: int | None = None,
    cylinder_count: int | None = None,
    object_scale: float = 1.0,
) -> Scene:
    """The paper's random worlds: free-standing walls and cylinders of random size and rotation.

    The 2D worlds of the paper are extruded to full-height 3D objects inside a closed room.
    Counts default to 3-7 walls and 3-8 cylinders; `object_scale` scales lengths and radii.
    """
    if not 0.1 <= object_scale <= 5.0:
        raise SceneError(f"object_scale must lie in [0.1, 5], got {object_scale}")
    size = _check_size(size, (3.0, 3.0, 1.0))
    rng = np.random.default_rng(seed)
    wall_count = int(rng.integers(3, 8)) if wall_count is None else wall_count
    cylinder_count = int(rng.integers(3, 9)) if cylinder_count is None else cylinder_count
    if wall_count < 0 or cylinder_count < 0:
        raise SceneError("wall_count and cylinder_count must be >= 0")
    placer = _Placer(rng, size, passage=0.8)
    parts = _shell_parts(size, "painted_wall", "floor", "painted_wall")
    for _ in range(wall_count):
        length = float(rng.uniform(1.0, 3.0) * object_scale)
        if (xy := placer.place(length / 2, wall_gap=0.8)) is not None:
            wall = box_mesh((*xy, size[2] / 2), (length, 0.1, size[2]), float(rng.uniform(0, np.pi)))
            parts.append((wall, "painted_wall"))
    for _ in range(cylinder_count):
        radius = float(rng.uniform(0.1, 0.5) * object_scale)
        if (xy := placer.place(radius)) is not None:
            parts.append(
                (
                    cylinder_mesh(*xy, radius, 0.0, size[2], sections=48),
                    str(rng.choice(["painted_wall", "metal", "wood"])),
                )
            )
    placer.warn_skipped("random_world")
    return assemble(
        parts,
        name="random_world",
        params={
            "seed": seed,
            "size": size.tolist(),
            "wall_count": wall_count,
            "cylinder_count": cylinder_count,
            "object_scale": object_scale,
        },
    )


def from_mesh(
    mesh: trimesh.Trimesh | trimesh.Scene | str | os.PathLike,
    *,
    up: str = "auto",
    units: str = "auto",
    materials: str | os.PathLike | Mapping[str, str] | None = None,
    material: str | Material = "painted_wall",
    name: str = "mesh",
    report: Callable[[str], object] | None = None,
) -> Scene:
    """Scene from any mesh trimesh loads (file path, Trimesh or trimesh Scene); the arguments are
    `scenes.mesh_import.load`'s, which also returns the import report as an object.

    The up axis and unit come from the format (glTF: Y up, metres) or are assumed (z up,
    metres) and checked against a building's size and shape; the file's material names are
    mapped to ours by `materials` (a TOML [materials] table, or a mapping of names or globs)
    and by name patterns ("floor", "glass", ...); faces left over get `material`. `report`, if
    given (e.g. print), is called with the import report's text: each name's material and faces.
    Degenerate faces are dropped with a warning; an empty or non-finite mesh raises SceneError.
    Smooth patches that approximate whole spheres or cylinders echo off the true surface
    (`scenes.smooth_fit`).
    """
    scene, done = load(mesh, up=up, units=units, materials=materials, material=material, name=name)
    if report is not None:
        report(done.text())
    return scene
