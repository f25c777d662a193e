"""learn.plots: the pictures read back pixel by pixel against the data they draw."""

import numpy as np

from learn.plots import _first_return, plot_curves, plot_examples
from tests.pictures import axes_frames, colormap_value, distances, legend_boxes, near, points_of, read_rgb

RANGE_M = np.linspace(0.21, 4.99, 120)  # coarser than the real 240 x 181 grid, to keep the test fast
AZIMUTH_RAD = np.deg2rad(np.linspace(-90.0, 90.0, 91))


def _wall(x_m: float) -> np.ndarray:
    """(R, A) 0/1 image of a wall at x = x_m [m] ahead: one cell per column at range x_m / cos(a)."""
    image = np.zeros((len(RANGE_M), len(AZIMUTH_RAD)))
    r = x_m / np.cos(AZIMUTH_RAD)
    cols = np.flatnonzero(r < RANGE_M[-1])
    image[np.abs(RANGE_M[:, None] - r[cols]).argmin(axis=0), cols] = 1.0
    return image


def test_first_return_is_nearest_cell_at_threshold():
    """Column 0: cells at 1 m (0.4) and 2 m (0.9) -> 2 m at 0.5; column 1 empty -> inf."""
    range_m = np.array([1.0, 2.0, 3.0])
    image = np.array([[0.4, 0.0], [0.9, 0.0], [1.0, 0.2]])
    np.testing.assert_array_equal(_first_return(image, range_m, 0.5), [2.0, np.inf])
    np.testing.assert_array_equal(_first_return(image, range_m, 0.3), [1.0, np.inf])


def _examples(rng):
    """Four rows: walls at 1.5, 2.5 and 3.5 m predicted on the spot, one range bin off, or not at
    all, and a prediction (a wall at 4 m, three bins off, its top wrapped round to 0.2 m) where
    the truth is empty."""
    rows = []
    for i, x_m in enumerate((1.5, 2.5, 3.5, 4.0)):
        truth = _wall(x_m) if i != 3 else np.zeros((len(RANGE_M), len(AZIMUTH_RAD)))
        pred = np.clip(np.roll(_wall(x_m), i, axis=0) * 0.9 + 0.1 * rng.random(truth.shape), 0, 1)
        rows.append(
            {
                "title": f"scene {i}",
                "sonar": rng.random(truth.shape),
                "truth": truth,
                "pred": np.zeros_like(truth) if i == 2 else pred,
                "caption": f"scan_f1 0.{i}",
            }
        )
    return rows


def _edge_shift(image, box):
    """Where the sonar panel's cell edges lie against the frame's nominal grid [px] (x, y): its random
    cells show every edge. Matplotlib places an image to a fraction of a pixel of its axes' frame,
    and a cell is only 2 px wide here."""
    inner = image[box.top + 5 : box.bottom - 4, box.left + 5 : box.right - 4]
    shifts = []
    for axis, count, start, size in (
        (1, len(AZIMUTH_RAD), box.left + 5, box.width),
        (0, len(RANGE_M), box.top + 5, box.height),
    ):
        changes = np.abs(np.diff(inner, axis=axis)).max(axis=(1 - axis, 2)) > 0.01
        edges = np.flatnonzero(changes) + 0.5 + start  # between pixels i and i + 1
        origin, step = (box.left, box.top)[1 - axis], size / count
        assert len(edges) >= 0.85 * count, "the panel does not show the image's cells"
        shifts.append(float(np.median(edges - origin - np.rint((edges - origin) / step) * step)))
    return shifts


def _cells(image, box, values_at_cells, shift):
    """An (R, A) polar panel read back at its cells' centres (azimuth +left on the left, range up),
    through `values_at_cells` (pixels (R, A, 3) -> values (R, A))."""
    half_deg, half_m = 0.5 * np.rad2deg(AZIMUTH_RAD[1] - AZIMUTH_RAD[0]), 0.5 * (RANGE_M[1] - RANGE_M[0])
    az_edges = (np.rad2deg(AZIMUTH_RAD[-1]) + half_deg, np.rad2deg(AZIMUTH_RAD[0]) - half_deg)
    range_edges = (RANGE_M[0] - half_m, RANGE_M[-1] + half_m)
    az, r = np.meshgrid(np.rad2deg(AZIMUTH_RAD), RANGE_M)
    centres = box.to_pixels(az.ravel(), r.ravel(), az_edges, range_edges) + shift
    col, row = np.rint(centres).astype(int).T
    return values_at_cells(image[row, col].reshape(*az.shape, 3))


def _nearest_at(image: np.ndarray, level: float) -> np.ndarray:
    """Per column of an (R, A) image, the range [m] of the nearest cell >= level; inf if none."""
    hit = image >= level
    return np.where(hit.any(axis=0), RANGE_M[hit.argmax(axis=0)], np.inf)


def _check_top_view(image, box, row):
    """The top view (robot heading up, left on the left) draws the truth's first returns black,
    predicted ones green within 0.10 m of the truth's and red otherwise, each where its (range,
    azimuth) puts it: from the origin where the field of view's edges meet (a line at x = 0),
    scaled by the rings drawn every metre."""
    inside = box.inside(image.shape)
    fov = points_of(near(image, "0.5", 0.05) & inside)
    fov = fov[np.abs(fov[:, 1] - np.median(fov[:, 1])) <= 1]  # the horizontal line at x = 0, y from +5 to -5 m
    origin = np.array([fov[:, 0].mean(), np.median(fov[:, 1])])
    rough_per_m = np.ptp(fov[:, 0]) / (2 * RANGE_M[-1])  # the dashes may stop short of the line's ends
    ring_px = np.linalg.norm(points_of(near(image, "0.8", 0.03) & inside) - origin, axis=1)
    ring_m = np.rint(ring_px / rough_per_m)
    on_ring = (np.abs(ring_px / rough_per_m - ring_m) < 0.1) & (ring_m > 0)  # not a light edge of a marker
    assert all(np.sum(ring_m[on_ring] == k) > 20 for k in (1, 2, 3, 4))
    per_m = float(np.median(ring_px[on_ring] / ring_m[on_ring]))

    def to_pixels(r):
        keep = np.isfinite(r)
        a = AZIMUTH_RAD[keep]
        return origin + per_m * np.c_[-r[keep] * np.sin(a), -r[keep] * np.cos(a)]

    robot = points_of(near(image, "tab:blue", 0.1) & inside)
    marker_centre = (robot.min(axis=0) + robot.max(axis=0)) / 2
    assert np.linalg.norm(marker_centre - origin) < 2.0, "the robot is not at the scans' origin"
    truth_r, pred_r = _nearest_at(row["truth"], 0.5), _nearest_at(row["pred"], 0.4)
    with np.errstate(invalid="ignore"):  # inf - inf: no return on either side is no hit
        within = np.abs(pred_r - truth_r) <= 0.10
    drawn = {colour: points_of(near(image, colour, 0.12) & inside) for colour in ("black", "tab:green", "tab:red")}
    drawn["black"] = drawn["black"][distances(drawn["black"], robot) > 12]  # not the robot's outline
    want = {
        "black": to_pixels(truth_r),
        "tab:green": to_pixels(np.where(within, pred_r, np.inf)),
        "tab:red": to_pixels(np.where(within, np.inf, pred_r)),
    }
    predicted = np.concatenate([want["tab:green"], want["tab:red"]])
    visible = {  # the predicted points are drawn over the truth's
        "black": want["black"][distances(want["black"], predicted) > 5],
        "tab:green": want["tab:green"],
        "tab:red": want["tab:red"],
    }
    for colour, points in drawn.items():
        # A marker reaches 3 px from its point; the scale read off the rings is good to 1.5 px.
        assert distances(points, want[colour]).max(initial=0) <= 4.5, (row["title"], colour, "drawn off its return")
        assert distances(visible[colour], points).max(initial=0) <= 4.5, (row["title"], colour, "a return not drawn")
        assert len(points) > 0 or len(visible[colour]) == 0


def test_examples_draw_each_row_s_images_and_scans(tmp_path):
    """Four example rows (one empty prediction, one empty truth) read back from the PNG: each
    polar panel holds its row's image cell by cell (sonar through magma, truth and prediction
    through gray_r, 0..1), and the top view puts the first returns of truth and prediction where
    their (range, azimuth) says, green within 0.10 m of the truth, red otherwise."""
    rows = _examples(np.random.default_rng(0))
    image = read_rgb(plot_examples(rows, RANGE_M, AZIMUTH_RAD, tmp_path / "examples.png", threshold=0.4))
    frames = axes_frames(image)  # top to bottom: a row's top view starts lower than its polar panels
    assert len(frames) == 4 * len(rows)
    for i, row in enumerate(rows):
        sonar, truth, pred, top_view = sorted(frames[4 * i : 4 * i + 4], key=lambda box: box.left)

        def magma(pixels):
            value, distance = colormap_value(pixels, "magma")
            assert distance.max() < 0.03
            return value

        def gray_r(pixels):
            return 1.0 - pixels.mean(axis=-1)

        shift = _edge_shift(image, sonar)  # the same in every panel of the figure
        inner = np.s_[1:-1, 1:-1]  # a spine may cover the outermost cells
        for box, read, key in ((sonar, magma, "sonar"), (truth, gray_r, "truth"), (pred, gray_r, "pred")):
            error = np.abs(_cells(image, box, read, shift) - row[key])[inner]
            assert error.max() <= 2.5 / 255, (row["title"], key)  # a colour map has 256 colours
        _check_top_view(image, top_view, row)


HISTORY = [
    {"epoch": 1, "train_loss": 1.0, "val_scan_f1": 0.2, "val_threshold": 0.5},
    {"epoch": 2, "train_loss": 0.5, "val_scan_f1": 0.4, "val_missed": 0.3, "val_threshold": 0.45},
    {"epoch": 3, "train_loss": 0.4, "val_scan_f1": 0.5, "val_missed": 0.2, "val_chamfer_m": 0.3},
]
"""Three epochs with keys missing: no validation loss, `val_missed` from epoch 2, `val_threshold`
up to epoch 2, the Chamfer distance at epoch 3 only."""


def _trace(image, box):
    """A panel's first line (tab:blue) outside its legend, as {column: mean row} of its pixels."""
    line = near(image, "tab:blue", 0.1) & box.inside(image.shape)
    for legend in legend_boxes(image, box):
        line &= ~legend.inside(image.shape, inset=-2)
    rows, cols = np.nonzero(line)
    assert len(cols), "no line drawn"
    return {c: rows[cols == c].mean() for c in np.unique(cols)}


def test_curves_follow_the_history(tmp_path):
    """The five panels of a 3-epoch history with keys missing, read back from the PNG: each line
    runs over the epochs that have its key, on one epoch axis for all panels, and through the
    history's values (the loss falls steeply, then less: epoch 2 lies 5/6 of the way down); the
    kept epoch's dashed line stands at epoch 3 on every panel, and on none without `kept_epoch`."""
    curves = read_rgb(plot_curves(HISTORY, tmp_path / "curves.png", kept_epoch=3, monitor="scan_f1"))
    bare = read_rgb(plot_curves(HISTORY, tmp_path / "bare.png"))
    panels = axes_frames(curves)
    assert len(panels) == len(axes_frames(bare)) == 5  # loss, scan F1, missed, range error, threshold
    loss, scan_f1, missed, chamfer, threshold = panels

    def ends(trace, box):  # the first and last columns of a line, as a share of its panel's width
        cols = np.array(sorted(trace))
        marker = 2  # a marker of 3 pt at 90 dpi reaches ~2 px beyond its point
        return (cols[0] + marker - box.left) / box.width, (cols[-1] - marker - box.left) / box.width

    first, last = ends(_trace(curves, loss), loss)  # epochs 1 and 3

    def share(epoch):  # where an epoch lies across a panel
        return first + (epoch - 1) * (last - first) / 2

    for box, (e0, e1) in [(scan_f1, (1, 3)), (missed, (2, 3)), (threshold, (1, 2))]:
        np.testing.assert_allclose(ends(_trace(curves, box), box), (share(e0), share(e1)), atol=3 / box.width)
    np.testing.assert_allclose(np.mean(ends(_trace(curves, chamfer), chamfer)), share(3), atol=3 / chamfer.width)

    def row_at(trace, box, epoch):
        col = round(box.left + share(epoch) * box.width)
        return np.mean([trace[c] for c in range(col - 1, col + 2) if c in trace])

    for box, key in [(loss, "train_loss"), (scan_f1, "val_scan_f1")]:
        trace = _trace(curves, box)
        value = {r["epoch"]: r[key] for r in HISTORY}
        top, bottom = row_at(trace, box, 1), row_at(trace, box, 3)
        expected = top + (bottom - top) * (value[2] - value[1]) / (value[3] - value[1])
        assert abs(row_at(trace, box, 2) - expected) <= 2.0, (key, row_at(trace, box, 2), expected)
        assert (bottom > top) == (value[3] < value[1])  # rows grow downwards
    missed_trace, threshold_trace = _trace(curves, missed), _trace(curves, threshold)
    assert row_at(missed_trace, missed, 3) > row_at(missed_trace, missed, 2)  # 0.3 -> 0.2: down
    assert row_at(threshold_trace, threshold, 2) > row_at(threshold_trace, threshold, 1)  # 0.5 -> 0.45

    for picture, kept in ((curves, True), (bare, False)):
        for box in axes_frames(picture):
            dashes = near(picture, "0.3", 0.05) & box.inside(picture.shape)
            for legend in legend_boxes(picture, box):
                dashes &= ~legend.inside(picture.shape, inset=-2)
            rows, cols = np.nonzero(dashes)
            if not kept:
                assert len(cols) == 0
                continue
            assert len(np.unique(rows)) > box.height / 3  # a dashed line from top to bottom
            assert np.abs((cols - box.left) / box.width - share(3)).max() <= 2 / box.width


def test_elevation_examples_draw_each_elevation_in_order(tmp_path):
    """Two rows of three elevations and two models: each row's sonar panels, left to right, hold
    its (E, R, A) slices in elevation order cell by cell, and one top view follows per model."""
    from learn.plots import plot_elevation_examples

    rng = np.random.default_rng(1)
    truth = np.where(np.abs(AZIMUTH_RAD) < 1.0, 2.0 / np.cos(AZIMUTH_RAD), np.inf)
    rows = [
        {
            "title": f"window {i}",
            "sonar": rng.random((3, len(RANGE_M), len(AZIMUTH_RAD))),
            "truth": truth,
            "scans": {"e1": truth + 0.3 * i, "e3": truth},
        }
        for i in range(2)
    ]
    out = plot_elevation_examples(rows, RANGE_M, AZIMUTH_RAD, [-20, 0, 20], tmp_path / "elevations.png")
    image = read_rgb(out)
    frames = axes_frames(image)
    assert len(frames) == 2 * (3 + 2)
    for i, row in enumerate(rows):
        panels = sorted(frames[5 * i : 5 * i + 5], key=lambda box: box.left)
        shift = _edge_shift(image, panels[0])
        for box, expected in zip(panels[:3], row["sonar"], strict=True):
            cells = _cells(image, box, lambda px: colormap_value(px, "magma")[0], shift)
            assert np.abs(cells - expected)[1:-1, 1:-1].max() <= 2.5 / 255, (row["title"], "elevation order")
