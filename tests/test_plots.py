import numpy as np

from learn.plots import _first_return, plot_curves, plot_examples

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


def test_plots_write_pngs(tmp_path):
    """Four example rows (one empty prediction, one empty truth) and a 3-epoch history with keys missing."""
    rng = np.random.default_rng(0)
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
    examples = plot_examples(rows, RANGE_M, AZIMUTH_RAD, tmp_path / "examples.png", threshold=0.4)
    history = [
        {"epoch": 1, "train_loss": 1.0, "val_scan_f1": 0.2, "val_threshold": 0.5},
        {"epoch": 2, "train_loss": 0.5, "val_scan_f1": 0.4, "val_missed": 0.3, "val_threshold": 0.45},
        {"epoch": 3, "train_loss": 0.4, "val_scan_f1": 0.5, "val_missed": 0.2, "val_chamfer_m": 0.3},
    ]
    curves = plot_curves(history, tmp_path / "curves.png", kept_epoch=3, monitor="scan_f1")
    bare = plot_curves(history, tmp_path / "bare.png")
    for png in (examples, curves, bare):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert png.stat().st_size > 20_000
