"""The occupancy-grid baselines as `learn evaluate` scores them (`learn.grid_baselines`), on a
hand-made drive past one wall: the sensor faces it, hears it, then turns away in place and hears
nothing (a specular wall met edge-on is silent). The true scans come from a float64 ray-segment
intersection (tests/test_occupancy.py's `wall_ranges`)."""

import numpy as np
import torch

from learn.data import DataConfig, Frames, Windows
from learn.evaluate import ECHO_PEAK_LEVEL, echo_peak_predictor, score
from learn.grid_baselines import grid_predictors, scan_images
from tests.test_occupancy import ALONG, AZIMUTH_RAD, DISTANCE_M, NORMAL, START, YAW, wall_ranges

RANGE_M = np.linspace(0.05, 3.95, 40)  # 0.1 m bins


def _turn_away(frames_facing: int = 8, frames_turning: int = 12) -> tuple[Frames, np.ndarray]:
    """Frames facing the wall, then turning left 6 degrees a frame; energyscapes hold the wall's
    echo on beams within 10 degrees of its normal while the sensor faces it, nothing after."""
    yaw = np.r_[np.full(frames_facing, YAW), YAW + np.deg2rad(6.0) * np.arange(1, frames_turning + 1)]
    poses = np.c_[np.tile(START, (len(yaw), 1)), yaw]
    truth = wall_ranges(poses)
    labels = scan_images(truth, RANGE_M).astype(np.uint8)
    energy = np.zeros_like(labels, dtype=np.float16)
    heard = np.abs(AZIMUTH_RAD + (yaw[:, None] - YAW)) <= np.deg2rad(10)  # beams near the wall's normal
    energy[:frames_facing] = labels[:frames_facing] * heard[:frames_facing, None, :]
    frames = Frames(
        energy, labels, np.zeros(len(yaw), np.int64), np.zeros(len(yaw), np.int64), ["wall"],
        RANGE_M, AZIMUTH_RAD, {"folder": "a drive past one wall"}, poses,
    )  # fmt: skip
    return frames, truth


def _recall_at_range(images: torch.Tensor, truth: np.ndarray) -> float:
    """Share of the true returns read within one range bin."""
    got = np.where(images.numpy().max(axis=1) > 0.5, RANGE_M[images.numpy().argmax(axis=1)], np.inf)
    seen = np.isfinite(truth)
    return float((np.abs(got[seen] - truth[seen]) <= 0.1).mean())


def test_grids_keep_the_wall_after_the_sensor_turned_away_and_it_fell_silent():
    frames, truth = _turn_away()
    windows = Windows(frames, DataConfig(frames=1, label="last"), "cpu")
    indices = np.arange(len(windows))
    silent = indices[14:]  # 36 to 72 degrees away from the wall's normal, nothing heard
    half = DISTANCE_M * np.tan(np.deg2rad(9.5))  # the part of the wall that was heard
    centre = START + DISTANCE_M * NORMAL
    remembered = wall_ranges(frames.pose[silent], wall=(centre - half * ALONG, centre + half * ALONG))
    assert np.isfinite(remembered).sum() > 100  # the heard part stays in view after the turn

    def amnesiac(x):  # a model that reads the wall only where it is heard, as a K = 1 model would
        return (x[:, :, -1] >= ECHO_PEAK_LEVEL).float()

    grids = grid_predictors(windows, indices, {"heard": (amnesiac, 0.5, windows)}, ECHO_PEAK_LEVEL)
    assert set(grids) == {"occupancy grid (echo peak)", "occupancy grid (heard)"}
    peak = echo_peak_predictor(0)(windows.batch(silent)[0])[:, 0]
    assert _recall_at_range(peak, truth[silent]) == 0.0
    for name, images in grids.items():
        recall = _recall_at_range(images.by_window(silent)[:, 0], remembered)
        assert recall > 0.9, (name, recall)
        scores = score(images, windows, silent, threshold=0.5)  # as evaluate scores it, on the whole wall
        assert scores["return_precision"].mean() > 0.9 and scores["scan_f1"].mean() > 0.3, name


def test_grid_with_a_wrong_heading_misplaces_the_wall():
    """The same frames, the odometry reporting no turn: the grid puts the remembered wall where
    the sensor no longer looks at it."""
    frames, truth = _turn_away()
    frames.pose[:, 2] = YAW
    windows = Windows(frames, DataConfig(frames=1, label="last"), "cpu")
    grids = grid_predictors(windows, np.arange(len(windows)), {}, ECHO_PEAK_LEVEL)
    images = grids["occupancy grid (echo peak)"].by_window(np.arange(14, len(windows)))[:, 0]
    assert _recall_at_range(images, truth[14:]) < 0.1


def test_scan_images_put_each_return_in_its_bin():
    ranges = np.array([[0.05, 0.149, 0.151, 3.95, 4.0, np.inf]])
    image = scan_images(ranges, RANGE_M)
    bins = [int(image[0, :, a].argmax()) if image[0, :, a].any() else None for a in range(6)]
    assert bins == [0, 1, 1, 39, 39, None] and image.sum() == 5
