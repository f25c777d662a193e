"""`learn predict --png` on data with and without LiDAR truth, and the lines `predict` ends with.

Data without truth (a .npy of energyscapes, an MCAP bag, a recording imported without a LiDAR:
labels empty everywhere) is drawn as the predicted scan alone, with no "false" and no truth in
the legend and a title that says why; data with truth keeps its truth panel and its hits and
false returns. The drawn figure is read back through its artists (titles, legend texts, the
scattered points), against scans computed here with numpy.
"""

from __future__ import annotations

import shutil
import subprocess
import sys

import h5py
import matplotlib.pyplot as plt
import numpy as np
import pytest

import learn.plots
from clitools import counted
from learn import PRETRAINED_CHECKPOINT
from learn.plots import examples_figure
from learn.predict import PredictionRun, prediction_summary, run_predict
from learn.stream_predict import run_predict_stream

RANGE_M = np.linspace(0.21, 4.99, 60)  # a coarse grid: the drawing is what is tested
AZIMUTH_RAD = np.deg2rad(np.linspace(-90.0, 90.0, 31))
THRESHOLD = 0.4


def _ring(r_m: float) -> np.ndarray:
    """(R, A) 0/1 image of a ring at range r_m [m]: in every column the cell nearest r_m."""
    image = np.zeros((len(RANGE_M), len(AZIMUTH_RAD)))
    image[np.abs(RANGE_M - r_m).argmin()] = 1.0
    return image


def _first_returns(image: np.ndarray, level: float) -> np.ndarray:
    """Per column the range [m] of the nearest cell >= level, inf where none is."""
    hit = image >= level
    return np.where(hit.any(axis=0), RANGE_M[hit.argmax(axis=0)], np.inf)


def _rows(truth: bool) -> list[dict]:
    """Two rows, each column a return: a ring at 2 m predicted one 0.08 m bin farther (every
    return within 0.10 m), a ring at 3 m predicted at 1 m (every return false), over noise below
    the threshold; truth None where `truth` is False."""
    rng = np.random.default_rng(0)
    rows = []
    for i, (true_m, seen_m) in enumerate(((2.0, 2.0 + (RANGE_M[1] - RANGE_M[0])), (3.0, 1.0))):
        pred = 0.9 * _ring(seen_m) + 0.3 * rng.random((len(RANGE_M), len(AZIMUTH_RAD)))
        rows.append(
            {
                "title": f"frame {i}",
                "sonar": rng.random(pred.shape),
                "truth": _ring(true_m) if truth else None,
                "pred": np.clip(pred, 0, 1),
            }
        )
    return rows


def _drawn_examples(rows: list[dict]) -> list[dict]:
    """`_drawn` of the examples figure of `rows`, the figure closed after."""
    fig = examples_figure(rows, RANGE_M, AZIMUTH_RAD, threshold=THRESHOLD)
    try:
        return _drawn(fig)
    finally:
        plt.close(fig)


def _drawn(fig) -> list[dict]:
    """Per row of the figure: its title, its axes' titles, and its top view's legend texts and
    scattered points {label: (N, 2) y, x [m]}."""
    rows = []
    for sub in fig.subfigs:
        top = next(ax for ax in sub.axes if ax.get_title().startswith("top view"))
        points = {c.get_label(): np.asarray(c.get_offsets()) for c in top.collections}
        rows.append(
            {
                "title": sub._suptitle.get_text(),
                "axes": [ax.get_title() for ax in sub.axes if ax.get_title()],
                "legend": [t.get_text() for t in top.get_legend().get_texts()],
                "points": points,
            }
        )
    return rows


def _xy(ranges: np.ndarray) -> np.ndarray:
    """(N, 2) y, x [m] of a scan's returns as the top view places them (y left, x ahead)."""
    keep = np.isfinite(ranges)
    return np.c_[ranges[keep] * np.sin(AZIMUTH_RAD[keep]), ranges[keep] * np.cos(AZIMUTH_RAD[keep])]


def test_without_truth_the_picture_draws_the_predicted_scan_alone():
    """Rows without truth: panels sonar, prediction, top view (no truth panel); the row's title
    says the data holds no LiDAR truth; the top view's legend names the predicted scan with its
    count of returns and nothing "false" nor "truth"; its points are the prediction's first returns."""
    rows = _rows(truth=False)
    drawn = _drawn_examples(rows)
    for row, got in zip(rows, drawn, strict=True):
        want = _first_returns(row["pred"], THRESHOLD)
        assert "no LiDAR truth in this data" in got["title"], got["title"]
        assert got["axes"][:2] == ["sonar input", "prediction"] and "LiDAR truth" not in got["axes"], got["axes"]
        label = f"predicted scan ({counted(int(np.isfinite(want).sum()), 'return')})"
        assert got["legend"] == ["field of view", "robot, heading +x", label], got["legend"]
        assert not any("false" in text or "truth" in text for text in got["legend"]), got["legend"]
        np.testing.assert_allclose(got["points"][label], _xy(want), atol=1e-9)


def test_with_truth_the_picture_draws_it_and_marks_hits_and_false_returns():
    """Rows with truth: a truth panel, the truth's returns in black, each predicted return within
    0.10 m of its column's truth counted as such and the others as "off / false" (row 0: all 31
    columns, one 0.08 m bin off; row 1: none); no "no LiDAR truth" in the title."""
    rows = _rows(truth=True)
    drawn = _drawn_examples(rows)
    for row, got in zip(rows, drawn, strict=True):
        truth, pred = _first_returns(row["truth"], 0.5), _first_returns(row["pred"], THRESHOLD)
        with np.errstate(invalid="ignore"):
            near = np.abs(pred - truth) <= 0.10
        hits, off = np.where(near, pred, np.inf), np.where(near, np.inf, pred)
        assert "no LiDAR truth" not in got["title"] and "LiDAR truth" in got["axes"], (got["title"], got["axes"])
        within = f"predicted scan, within 0.10 m ({near.sum()})"
        false = f"predicted scan, off / false ({np.isfinite(off).sum()})"
        assert got["legend"] == ["field of view", "robot, heading +x", "LiDAR truth", within, false], got["legend"]
        for label, scan in (("LiDAR truth", truth), (within, hits), (false, off)):
            np.testing.assert_allclose(got["points"][label], _xy(scan).reshape(-1, 2), atol=1e-9)
    assert [int(t.rpartition("(")[2][:-1]) for t in drawn[0]["legend"][3:]] == [31, 0]  # the geometry's answer
    assert [int(t.rpartition("(")[2][:-1]) for t in drawn[1]["legend"][3:]] == [0, 31]


@pytest.fixture
def drawn_rows(monkeypatch):
    """The rows of every picture `predict` draws in the test, as `examples_figure` draws them."""
    pictures, real = [], learn.plots.examples_figure

    def keep(rows, *args, **kwargs):
        fig = real(rows, *args, **kwargs)
        pictures.append(_drawn(fig))
        return fig

    monkeypatch.setattr(learn.plots, "examples_figure", keep)
    return pictures


@pytest.fixture(scope="module")
def without_lidar(tiny_dataset, tmp_path_factory):
    """The tiny dataset as a recording imported without a LiDAR holds it: every label empty."""
    folder = tmp_path_factory.mktemp("without_lidar") / "data"
    shutil.copytree(tiny_dataset, folder)
    for shard in folder.glob("shard-*.h5"):
        with h5py.File(shard, "r+") as f:
            f["lidar/image"][...] = 0
            f["lidar/ranges"][...] = np.inf
    return folder


@pytest.mark.parametrize("streamed", [False, True], ids=["batch", "stream"])
def test_predict_draws_truth_exactly_where_the_data_holds_it(
    streamed, tiny_dataset, without_lidar, tmp_path, drawn_rows
):
    """`predict` (and `--stream`) with a picture: on the tiny dataset each row has its truth panel
    and "off / false" in its legend; on the same drives without LiDAR labels (batch only), and on
    their energyscapes as a .npy, no row has either, each says there is no truth, and what
    `predict` returns says so too."""
    run = run_predict_stream if streamed else run_predict
    energyscapes = tmp_path / "energyscapes.npy"
    with h5py.File(next(tiny_dataset.glob("shard-*.h5"))) as f:
        np.save(energyscapes, f["energyscape"][:8].astype(np.float32))
    inputs = {"dataset": tiny_dataset, "no lidar": without_lidar, "npy": energyscapes}
    if streamed:  # it reads a folder as the batch run does: the truth of one folder of each kind is enough
        del inputs["no lidar"]
    done = {}
    for name, source in inputs.items():
        done[name] = run(PRETRAINED_CHECKPOINT, source, tmp_path / f"{name}.npz", png=tmp_path / f"{name}.png")
        assert (tmp_path / f"{name}.png").stat().st_size > 0
    truth, *without = drawn_rows
    assert done["dataset"].lidar_truth and not any(done[name].lidar_truth for name in inputs if name != "dataset")
    assert len(truth) == 4
    for row in truth:
        assert "LiDAR truth" in row["axes"] and "LiDAR truth" in row["legend"], row
        assert any("off / false" in text for text in row["legend"]) and "no LiDAR truth" not in row["title"], row
    for picture in without:
        assert len(picture) >= 2
        for row in picture:
            assert "LiDAR truth" not in row["axes"] and "no LiDAR truth in this data" in row["title"], row
            assert not any("false" in text or "truth" in text for text in row["legend"]), row["legend"]


def test_the_closing_lines_say_what_was_written():
    """The lines name the frames and windows, the threshold and whence it came, the elevations
    where more than one, and each file with what it holds (the picture: truth or none)."""
    run = PredictionRun(
        out="p.npz",
        png="p.png",
        mcap="p.mcap",
        frame=np.arange(2, 10),
        frames_per_window=5,
        beams=181,
        threshold=0.65,
        threshold_given=False,
        elevation_deg=(-20.0, 0.0, 20.0),
        lidar_truth=False,
        streamed=True,
    )
    lines = prediction_summary(run, "rec.npy", 1.25).splitlines()
    assert lines == [
        "wrote p.npz: LiDAR images and scans for 8 frames of rec.npy (label frames 2..9; 181 beams, return "
        "threshold 0.65, the checkpoint's calibrated one) in 1.2 s",
        "  read 8 windows of 5 frames (one per frame predicted) at elevations -20, 0, 20 deg",
        "wrote p.png: 4 predictions beside their sonar input (no LiDAR truth in this data: the predicted scans alone)",
        "wrote p.mcap: the scans as ROS 2 LaserScans on /scan_pred and the poses on /tf",
    ]
    given = PredictionRun(**{**run.__dict__, "threshold_given": True, "elevation_deg": (0.0,), "lidar_truth": True})
    lines = prediction_summary(given, "data", 1.0).splitlines()
    assert "return threshold 0.65, given with --threshold)" in lines[0] and "elevation" not in lines[1], lines
    assert lines[2] == "wrote p.png: 4 predictions beside their sonar input and LiDAR truth", lines


def test_the_command_line_shows_progress_and_ends_with_what_it_wrote(tmp_path):
    """`learn predict --png` on a .npy (8 frames, K = 5: 4 windows): a bar on stderr, then the
    lines on stdout, the picture's naming no truth; --quiet drops the bar and keeps the lines."""
    np.save(tmp_path / "rec.npy", np.random.default_rng(0).random((8, 240, 181), dtype=np.float32))
    command = [sys.executable, "-m", "learn", "predict", "--checkpoint", str(PRETRAINED_CHECKPOINT)]
    command += ["--input", str(tmp_path / "rec.npy"), "--threshold", "0.5"]
    outputs = ["--out", str(tmp_path / "p.npz"), "--png", str(tmp_path / "p.png")]
    done = subprocess.run([*command, *outputs], capture_output=True, text=True, timeout=300, check=True)
    lines = done.stdout.splitlines()
    assert "predicting:" in done.stderr and "writing:" in done.stderr, done.stderr
    assert lines[0].startswith(f"wrote {tmp_path / 'p.npz'}: LiDAR images and scans for 4 frames of "), lines
    assert "return threshold 0.50, given with --threshold)" in lines[0], lines
    assert lines[1:] == [
        "  read 4 windows of 5 frames (one per frame predicted)",
        f"wrote {tmp_path / 'p.png'}: 4 predictions beside their sonar input (no LiDAR truth in this data: the "
        "predicted scans alone)",
    ], lines
    quiet = [*command, "--out", str(tmp_path / "q.npz"), "--quiet"]
    quiet = subprocess.run(quiet, capture_output=True, text=True, timeout=300, check=True)
    assert quiet.stderr == "" and len(quiet.stdout.splitlines()) == 2, (quiet.stderr, quiet.stdout)
