"""SVG floor plans extruded to 3D: strokes become walls, circles and ellipses become pillars."""

from __future__ import annotations

import io
import itertools
import os
import re

import numpy as np
import svgelements as se
import trimesh

from .materials import Material
from .scene import Scene, SceneError, assemble, box_mesh, cylinder_mesh

_CURVE_SAMPLES_PER_M = 10  # straight wall pieces per metre of curved stroke


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
            with open(source, encoding="utf-8", errors="replace") as f:
                text = f.read()
        _refuse_non_finite(text)
        return se.SVG.parse(io.StringIO(text))
    except SceneError:
        raise
    except Exception as err:
        raise SceneError(f"could not parse SVG: {err}") from err


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


def _strokes(shape: se.Shape, scale: float) -> list[np.ndarray]:
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
            n = max(2, int(np.ceil(length * _CURVE_SAMPLES_PER_M)) + 1)
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
        for line in _strokes(element, scale):
            pts = line * flip
            if not np.isfinite(pts).all():
                raise SceneError(f"the SVG's {what} has non-finite (NaN or inf) coordinates")
            for a, b in itertools.pairwise(pts):
                if np.linalg.norm(b - a) > 1e-6:
                    walls.append((a, b))
    if not walls and not pillars:
        raise SceneError("the SVG holds no usable shapes (lines, polylines, polygons, rects, paths, circles)")

    ends = [p for w in walls for p in w] + [c + s * max(rx, ry) for c, rx, ry, _ in pillars for s in (-1, 1)]
    offset = np.min(ends, axis=0) - wall_thickness
    parts: list[tuple[trimesh.Trimesh, str | Material]] = []
    for a, b in walls:
        a, b = a - offset, b - offset
        length = float(np.linalg.norm(b - a))
        yaw = float(np.arctan2(*(b - a)[::-1]))
        # Extending by the thickness closes the corners where two walls meet.
        mesh = box_mesh((*(a + b) / 2, wall_height / 2), (length + wall_thickness, wall_thickness, wall_height), yaw)
        parts.append((mesh, wall))
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


def _plane(extent: np.ndarray, z: float, *, up: bool) -> trimesh.Trimesh:
    """Rectangle (0, 0) .. extent at height z, normal +z (up) or -z."""
    x, y = extent
    vertices = np.array([[0, 0, z], [x, 0, z], [x, y, z], [0, y, z]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]]) if up else np.array([[0, 2, 1], [0, 3, 2]])
    return trimesh.Trimesh(vertices, faces, process=False)
