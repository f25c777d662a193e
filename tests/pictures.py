"""The pixels of a written figure, for tests that check what a picture shows against the data it
draws (not against a golden image): colours, the axes' frames, and maps from data to pixels.

A picture is read as float RGB (H, W, 3) in [0, 1], row 0 at the top. Axes are found by their
black frames; data coordinates are mapped to pixels through something the picture itself shows
(an image's known extent, or a room's walls), never through the plotting code's own limits.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import matplotlib.colors
import matplotlib.image
import numpy as np
from scipy.spatial import cKDTree

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def read_rgb(path: str | Path) -> np.ndarray:
    """A PNG's pixels, float RGB (H, W, 3) in [0, 1] (alpha dropped: figures are opaque)."""
    assert Path(path).read_bytes()[:8] == PNG_SIGNATURE, f"{path} is not a PNG"
    return matplotlib.image.imread(path)[..., :3].astype(np.float64)


def near(image: np.ndarray, colour, tol: float = 0.06) -> np.ndarray:
    """Pixels within `tol` (per channel) of a matplotlib colour ("tab:red", "0.25", (r, g, b)), (H, W) bool."""
    return np.abs(image - np.asarray(matplotlib.colors.to_rgb(colour))).max(axis=-1) <= tol


def colormap_value(image: np.ndarray, cmap: str) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel read back through a colour map: (value in [0, 1], RGB distance to that map's
    nearest colour), both (H, W); a pixel not drawn by the map is far from all of its colours."""
    table = matplotlib.colormaps[cmap](np.linspace(0.0, 1.0, 256))[:, :3]
    distance, index = cKDTree(table).query(image.reshape(-1, 3))
    return (index / 255.0).reshape(image.shape[:2]), distance.reshape(image.shape[:2])


def points_of(mask: np.ndarray) -> np.ndarray:
    """(col, row) pixel centres of a mask's set pixels, (n, 2) float."""
    rows, cols = np.nonzero(mask)
    return np.c_[cols, rows].astype(np.float64)


def distances(from_px: np.ndarray, to_px: np.ndarray) -> np.ndarray:
    """For each (col, row) of `from_px`, the distance [px] to the nearest of `to_px`; inf if none."""
    if len(from_px) == 0:
        return np.zeros(0)
    if len(to_px) == 0:
        return np.full(len(from_px), np.inf)
    return cKDTree(to_px).query(from_px)[0]


def densify(points: np.ndarray, step: float = 0.5) -> np.ndarray:
    """A polyline (n, 2) resampled so that neighbours lie at most `step` apart (same units)."""
    out = [points[:1]]
    for a, b in itertools.pairwise(points):
        count = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        out.append(a + (b - a) * np.linspace(0.0, 1.0, count + 1)[1:, None])
    return np.concatenate(out)


@dataclass(frozen=True)
class Box:
    """An axes' frame in pixels: rows top..bottom, columns left..right (the black spines)."""

    top: int
    bottom: int
    left: int
    right: int

    @property
    def width(self) -> int:
        return self.right - self.left

    @property
    def height(self) -> int:
        return self.bottom - self.top

    def inside(self, image_shape, inset: int = 3) -> np.ndarray:
        """(H, W) mask of the pixels inside the frame, `inset` pixels clear of the spines."""
        mask = np.zeros(image_shape[:2], dtype=bool)
        mask[self.top + inset : self.bottom - inset + 1, self.left + inset : self.right - inset + 1] = True
        return mask

    def to_pixels(self, x, y, xlim: tuple[float, float], ylim: tuple[float, float]) -> np.ndarray:
        """(col, row) of data points when the frame spans xlim left to right and ylim bottom to top."""
        col = self.left + (np.asarray(x, dtype=np.float64) - xlim[0]) / (xlim[1] - xlim[0]) * self.width
        row = self.bottom - (np.asarray(y, dtype=np.float64) - ylim[0]) / (ylim[1] - ylim[0]) * self.height
        return np.c_[col, row]


def _runs(line: np.ndarray, covered: np.ndarray, min_length: int) -> list[tuple[int, int]]:
    """(first, last) index of each run of True in `line` at least `min_length` long, across gaps
    where something else is drawn (`covered`: markers over a spine), as long as half of it is True."""
    edges = np.flatnonzero(np.diff(np.r_[0, line.astype(np.int8), 0]))
    merged: list[list[int]] = []
    for a, b in zip(edges[::2], edges[1::2] - 1, strict=True):
        if merged and covered[merged[-1][1] + 1 : a].all():
            merged[-1][1] = b
        else:
            merged.append([a, b])
    return [(int(a), int(b)) for a, b in merged if b - a + 1 >= min_length and line[a : b + 1].mean() >= 0.5]


def axes_frames(image: np.ndarray, *, min_side: int = 40) -> list[Box]:
    """The black rectangular frames of the picture's axes (and of colour bars at least `min_side`
    wide), sorted top to bottom, then left to right. Tick marks may stick out of a corner."""
    return rectangles(image.max(axis=-1) < 0.15, image.min(axis=-1) > 0.85, min_side=min_side, tick=8, corner=2)


def legend_boxes(image: np.ndarray, box: Box) -> list[Box]:
    """The frames of legends drawn inside an axes' frame (matplotlib's light grey, rounded edges)."""
    edge = near(image, "0.8", 0.05) & box.inside(image.shape, inset=1)
    return rectangles(edge, image.min(axis=-1) > 0.85, min_side=15, tick=0, corner=6)


def rectangles(edge: np.ndarray, light: np.ndarray, *, min_side: int, tick: int, corner: int) -> list[Box]:
    """Rectangles drawn with `edge` pixels: two long rows and two long columns of them that span
    each other (a run may stick out of its corner by `tick` pixels, or stop `corner` pixels short
    of it), each with `light` pixels on its outer or inner side for most of its length; that tells
    an axes' spine from a dark row of an image drawn inside it."""
    height, width = edge.shape

    def lines(edge_lines, light_lines, count):
        found = []  # (index of the line, first, last)
        for i in range(1, count - 1):
            for a, b in _runs(edge_lines[i], ~light_lines[i], min_side):
                if max(light_lines[i - 1][a : b + 1].mean(), light_lines[i + 1][a : b + 1].mean()) > 0.5:
                    found.append((i, a, b))
        return found

    rows = lines(edge, light, height)
    cols = lines(edge.T, light.T, width)

    def spans(run, first, last):
        _, a, b = run
        return a - corner <= first <= a + tick and b - tick <= last <= b + corner

    boxes: list[Box] = []
    for i, (top, a, b) in enumerate(rows):
        for bottom, a2, b2 in rows[i + 1 :]:
            if bottom - top < min_side or min(b, b2) - max(a, a2) < min_side:
                continue
            sides = [c for c, y0, y1 in cols if max(a, a2) - tick - corner <= c <= min(b, b2) + tick + corner]
            sides = [c for c in sides if any(spans(run, top, bottom) for run in cols if run[0] == c)]
            if not sides:
                continue
            left, right = min(sides), max(sides)
            if right - left >= min_side and spans((top, a, b), left, right) and spans((bottom, a2, b2), left, right):
                box = Box(top, bottom, left, right)
                if not any(_overlap(box, o) for o in boxes):  # a line 2 px wide gives the rectangle twice
                    boxes.append(box)
    return sorted(boxes, key=lambda o: (o.top, o.left))


def _overlap(a: Box, b: Box) -> bool:
    return a.left < b.right and b.left < a.right and a.top < b.bottom and b.top < a.bottom


def outline(mask: np.ndarray, box: Box, *, share: float = 0.5) -> tuple[float, float, float, float]:
    """The outermost lines that `mask` draws across most of a frame (a room's outer walls):
    (left col, right col, top row, bottom row), each the centre of its line."""
    inside = mask & box.inside(mask.shape)

    def ends(counts: np.ndarray) -> tuple[float, float]:
        full = np.flatnonzero(counts >= share * counts.max())
        first = full[: np.argmax(np.diff(np.r_[full, full[-1] + 9]) > 1) + 1]  # the first contiguous group
        last = full[len(full) - np.argmax(np.diff(np.r_[full[0] - 9, full])[::-1] > 1) - 1 :]
        return float(first.mean()), float(last.mean())

    left, right = ends(inside.sum(axis=0))
    top, bottom = ends(inside.sum(axis=1))
    return left, right, top, bottom
