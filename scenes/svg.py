"""SVG floor plans extruded to 3D: strokes become walls, circles and ellipses become pillars."""

from __future__ import annotations

import io
import itertools
import os
import re

import numpy as np
import svgelements as se
import trimesh

from clitools.limits import available_memory_bytes, check_memory, format_bytes, input_file

from .materials import Material
from .scene import Scene, SceneError, assemble, cylinder_mesh

_CURVE_SAMPLES_PER_M = 10  # straight wall pieces per metre of curved stroke
# Memory per unit, at the least (measured on a 1.2 MB polyline of 100k points: 140 MB to parse it
# and walk its strokes), so that a plan this machine cannot hold is refused before it is read.
_BYTES_PER_SVG_BYTE = 150  # svgelements' objects per byte of SVG text
_BYTES_PER_CURVE_SAMPLE = 64  # a sampled point of a curve: complex and float64 copies
_BYTES_PER_WALL = 4096  # a wall's box (8 vertices, 12 faces) through assemble's copies and the BVH
_BYTES_PER_PILLAR = 65536  # a 48-sided pillar: 192 faces, the same way


def _read_svg(source: str | os.PathLike | io.IOBase) -> se.SVG:
    """Parse an SVG given as a path, a file object or the SVG text itself."""
    try:
        if hasattr(source, "read"):
            text = source.read()
            text = text.decode() if isinstance(text, bytes) else text
        elif str(source).lstrip().startswith("<"):
            text = str(source)
        elif not os.path.exists(str(source)):
            raise SceneError(f"SVG file not found: {source}")
        else:
            _check_svg_file(source)
            with open(source, encoding="utf-8", errors="replace") as f:
                text = f.read()
        _refuse_non_finite(text)
        return se.SVG.parse(io.StringIO(text))
    except SceneError:
        raise
    except Exception as err:
        where = f"SVG {source}" if isinstance(source, str | os.PathLike) and len(str(source)) < 256 else "the SVG"
        raise SceneError(
            f"could not parse {where}: {err or type(err).__name__}; save it again as plain SVG (any drawing "
            "program can) and check that it opens in a browser"
        ) from err


def _check_svg_file(path: str | os.PathLike) -> None:
    """A regular file (a FIFO or /dev/urandom would never end) this machine can parse."""
    try:
        limit = available_memory_bytes() / _BYTES_PER_SVG_BYTE
        input_file(
            path,
            what="SVG floor plan",
            max_bytes=limit,
            bound=f"parsing it takes about {_BYTES_PER_SVG_BYTE} "
            "times its size in memory, and this machine has "
            f"{format_bytes(limit * _BYTES_PER_SVG_BYTE)} free",
        )
    except (OSError, ValueError) as err:
        raise SceneError(str(err)) from None


_NON_FINITE = re.compile(r"(?<![A-Za-z_])(nan|inf(inity)?)(?![A-Za-z_])", re.IGNORECASE)


def _refuse_non_finite(text: str) -> None:
    """svgelements reads "NaN" and "inf" in coordinates as 0 or drops the rest of a path, which
    silently moves or loses walls: refuse them, naming the attribute."""
    for match in re.finditer(r'([\w:-]+)\s*=\s*("[^"]*"|\'[^\']*\')', text):
        name, value = match.group(1), match.group(2)
        if (
            name not in ("id", "class", "style")
            and not name.startswith(("xmlns", "xlink"))
            and _NON_FINITE.search(value)
        ):
            raise SceneError(f"the SVG has a non-finite (NaN or inf) number in {name}={value}")


def _check_fits(needed: float, what: str) -> None:
    try:
        check_memory(needed, what=what, advice="check the SVG's size and --scene-arg scale (metres per SVG unit)")
    except ValueError as err:
        raise SceneError(str(err)) from None


def _strokes(shape: se.Shape, scale: float, what: str) -> list[np.ndarray]:
    """Polylines [SVG units] of a shape's outline; curves are sampled into short straight pieces."""
    lines: list[np.ndarray] = []
    current: list[complex] = []
    for seg in se.Path(shape).segments():
        if isinstance(seg, se.Move):
            if len(current) > 1:
                lines.append(np.array(current))
            current = [complex(seg.end)]
        elif isinstance(seg, (se.Line, se.Close)):
            if seg.start is None or seg.end is None:
                continue
            if not current:
                current = [complex(seg.start)]
            current.append(complex(seg.end))
        else:  # Bezier curves and arcs
            length = seg.length() * scale
            if not np.isfinite(length):
                raise SceneError(f"the SVG's {what} has a curve of non-finite length")
            n = max(2, int(np.ceil(length * _CURVE_SAMPLES_PER_M)) + 1)
            _check_fits(n * _BYTES_PER_CURVE_SAMPLE, f"the SVG's {what}: a curve of {length:,.0f} m in {n:,} pieces")
            pts = seg.npoint(np.linspace(0.0, 1.0, n))
            if not current:
                current = [complex(*pts[0])]
            current.extend(complex(x, y) for x, y in pts[1:])
    if len(current) > 1:
        lines.append(np.array(current))
    return [np.column_stack([line.real, line.imag]) for line in lines]


def from_svg(
    source: str | os.PathLike | io.IOBase,
    *,
    scale: float = 0.01,
    wall_height: float = 2.5,
    wall_thickness: float = 0.1,
    wall: str | Material = "painted_wall",
    pillar: str | Material = "painted_wall",
    floor: str | Material = "floor",
    ceiling: bool = True,
) -> Scene:
    """Extrude a 2D SVG floor plan into a 3D scene.

    Lines, polylines, polygons, rectangles and paths (curves sampled at 10 pieces per metre)
    become walls of `wall_thickness` [m] centred on the stroke; circles and ellipses become
    solid vertical cylinders (pillars). A floor (and a ceiling) covers the drawing's extent.

    Args:
        source: SVG file path, file object, or the SVG text.
        scale: Metres per SVG user unit (default 1 unit = 1 cm).
        wall_height: Height of walls and pillars [m].
        wall_thickness: Wall thickness [m].

    The SVG y axis points down; it is flipped so the plan reads the same from above, and the
    plan is shifted so its lower-left corner lies at the origin.
    """
    if not (scale > 0 and wall_height > 0 and wall_thickness > 0):
        raise SceneError("scale, wall_height and wall_thickness must be positive")
    svg = _read_svg(source)
    flip = np.array([scale, -scale])
    walls: list[tuple[np.ndarray, np.ndarray]] = []
    pillars: list[tuple[np.ndarray, float, float, float]] = []
    for element in svg.elements():
        if not isinstance(element, se.Shape):
            continue
        what = f"<{type(element).__name__.lower()}{' id=' + repr(element.id) if element.id else ''}>"
        if isinstance(element, (se.Circle, se.Ellipse)):
            rx, ry = float(element.implicit_rx) * scale, float(element.implicit_ry) * scale
            center = np.array([element.implicit_center.x, element.implicit_center.y]) * flip
            if not np.isfinite([rx, ry, *center]).all():
                raise SceneError(f"the SVG's {what} has a non-finite (NaN or inf) centre or radius")
            if rx > 0 and ry > 0:
                pillars.append((center, rx, ry, -float(element.rotation)))
            continue
        for line in _strokes(element, scale, what):
            pts = line * flip
            if not np.isfinite(pts).all():
                raise SceneError(f"the SVG's {what} has non-finite (NaN or inf) coordinates")
            for a, b in itertools.pairwise(pts):
                if np.linalg.norm(b - a) > 1e-6:
                    walls.append((a, b))
    if not walls and not pillars:
        raise SceneError("the SVG holds no usable shapes (lines, polylines, polygons, rects, paths, circles)")
    _check_fits(
        len(walls) * _BYTES_PER_WALL + len(pillars) * _BYTES_PER_PILLAR,
        f"the SVG's {len(walls):,} wall pieces and {len(pillars):,} pillars",
    )

    ends = [p for w in walls for p in w] + [c + s * max(rx, ry) for c, rx, ry, _ in pillars for s in (-1, 1)]
    offset = np.min(ends, axis=0) - wall_thickness
    parts: list[tuple[trimesh.Trimesh, str | Material]] = []
    if walls:
        parts.append((_wall_boxes(np.array(walls) - offset, wall_thickness, wall_height), wall))
    for center, rx, ry, rotation in pillars:
        if np.isclose(rx, ry, rtol=1e-6):  # a round pillar: its specular echoes follow the curve
            parts.append((cylinder_mesh(*(center - offset), rx, 0.0, wall_height, sections=48), pillar))
            continue
        mesh = trimesh.creation.cylinder(radius=1.0, height=wall_height, sections=48)
        mesh.apply_scale((rx, ry, 1.0))
        transform = trimesh.transformations.rotation_matrix(rotation, (0, 0, 1))
        transform[:3, 3] = (*(center - offset), wall_height / 2)
        mesh.apply_transform(transform)
        parts.append((mesh, pillar))
    extent = np.max(np.array([p - offset for p in ends]), axis=0) + wall_thickness
    parts.append((_plane(extent, 0.0, up=True), floor))
    if ceiling:
        parts.append((_plane(extent, wall_height, up=False), "painted_wall"))
    return assemble(
        parts,
        name="svg",
        params={
            "source": source if isinstance(source, str) and len(source) < 256 else "<svg>",
            "scale": scale,
            "wall_height": wall_height,
            "wall_thickness": wall_thickness,
        },
    )


_BOX = trimesh.creation.box(extents=(1.0, 1.0, 1.0))  # the unit box every wall is made from


def _wall_boxes(ends: np.ndarray, thickness: float, height: float) -> trimesh.Trimesh:
    """One mesh of a box per wall, in the order given: along each wall from a to b (ends (N, 2, 2)
    [m]), extended by the thickness so that the corners where two walls meet are closed; the
    boxes `box_mesh` makes, built at once (a plan of 100k pieces takes a second, not minutes)."""
    a, b = ends[:, 0], ends[:, 1]
    along = b - a
    length = np.linalg.norm(along, axis=1)
    yaw = np.arctan2(along[:, 1], along[:, 0])
    size = np.stack([length + thickness, np.full_like(length, thickness), np.full_like(length, height)], axis=1)
    local = _BOX.vertices[None] * size[:, None]  # (N, 8, 3)
    cos, sin = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x = cos * local[..., 0] - sin * local[..., 1] + (a[:, 0] + b[:, 0])[:, None] / 2
    y = sin * local[..., 0] + cos * local[..., 1] + (a[:, 1] + b[:, 1])[:, None] / 2
    vertices = np.stack([x, y, local[..., 2] + height / 2], axis=-1).reshape(-1, 3)
    faces = (_BOX.faces[None] + 8 * np.arange(len(ends))[:, None, None]).reshape(-1, 3)
    return trimesh.Trimesh(vertices, faces, process=False)


def _plane(extent: np.ndarray, z: float, *, up: bool) -> trimesh.Trimesh:
    """Rectangle (0, 0) .. extent at height z, normal +z (up) or -z."""
    x, y = extent
    vertices = np.array([[0, 0, z], [x, 0, z], [x, y, z], [0, y, z]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]]) if up else np.array([[0, 2, 1], [0, 3, 2]])
    return trimesh.Trimesh(vertices, faces, process=False)
