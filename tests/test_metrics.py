"""learn.metrics against independent answers: scikit-image's SSIM, hand-computed tiny images,
and numpy brute force. Torch only (no Warp); `--device cuda:0` runs them on a GPU."""

import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy import ndimage
from skimage.metrics import structural_similarity

from learn import metrics
from learn.metrics import (
    CALIBRATION_THRESHOLDS,
    chamfer_distance,
    first_return_ranges,
    first_return_sweep,
    image_metrics,
    image_points,
    mse,
    occupancy_iou,
    peak_range_mae,
    predicted_ranges,
    scan_f1_sweep,
    scan_metrics,
    scan_scores,
    ssim,
)

INF = math.inf


@pytest.fixture(scope="module")
def dev(request):
    """The torch device named by `--device` (default cpu)."""
    name = request.config.getoption("--device")
    if name.startswith("cuda") and not torch.cuda.is_available():
        pytest.fail(f"torch has no CUDA device for --device {name}")
    return torch.device(name)


def t(x, dev, dtype=torch.float32):
    return torch.as_tensor(np.asarray(x), dtype=dtype, device=dev)


def f64(x, dev):
    return t(x, dev, torch.float64)


def skimage_ssim(pred: np.ndarray, target: np.ndarray, **kw) -> np.ndarray:
    return np.array([structural_similarity(b, a, **kw) for a, b in zip(pred, target, strict=True)])


def test_learn_metrics_never_imports_warp():
    """`import learn.metrics` (and the learn package) pulls in neither warp nor acoustic_sim."""
    code = "import sys, learn.metrics; assert not {'warp', 'acoustic_sim'} & set(sys.modules), sorted(sys.modules)"
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("shape", [(240, 181), (37, 50)])
def test_ssim_equals_skimage(dev, shape):
    """A batch of 5: two random pairs, a sparse 0/1 label vs its blur, identical images (SSIM = 1),
    and an all-zero prediction vs the label; each equals skimage's structural_similarity
    (data_range 1, win_size 7, uniform window, sample covariance) to 1e-6."""
    rng = np.random.default_rng(0)
    label = np.zeros(shape)
    label[rng.integers(0, shape[0], shape[1]), np.arange(shape[1])] = 1.0  # one return per column
    blurred = np.clip(ndimage.gaussian_filter(label, 1.5) * 4, 0, 1)
    rand = rng.random((4, *shape))
    pred = np.stack([rand[0], rand[1], blurred, label, np.zeros(shape)])
    target = np.stack([rand[2], rand[3], label, label, label])
    got = ssim(t(pred, dev), t(target, dev))
    want = skimage_ssim(pred, target, data_range=1.0, win_size=7)
    assert got.shape == (5,) and got.dtype == torch.float64
    np.testing.assert_allclose(got.cpu().numpy(), want, atol=1e-6)
    assert abs(got[3].item() - 1.0) < 1e-12


def test_ssim_other_window_and_range(dev):
    """win_size 11 and data_range 2 on images in [0, 2] also equal skimage, float64 inputs."""
    rng = np.random.default_rng(1)
    pred, target = 2 * rng.random((2, 3, 30, 41))
    got = ssim(f64(pred, dev), f64(target, dev), data_range=2.0, win_size=11)
    np.testing.assert_allclose(got.cpu().numpy(), skimage_ssim(pred, target, data_range=2.0, win_size=11), atol=1e-6)


def test_ssim_is_differentiable(dev):
    """The SSIM gradient matches finite differences (fast gradcheck, float64, 2 images of 9 x 10)."""
    rng = np.random.default_rng(2)
    pred = t(rng.random((2, 9, 10)), dev, torch.float64).requires_grad_()
    target = t(rng.random((2, 9, 10)), dev, torch.float64)
    assert torch.autograd.gradcheck(lambda p: ssim(p, target), (pred,), fast_mode=True)
    loss = 1 - ssim(pred.float(), target.float()).mean()  # float32 input, as in training
    loss.backward()
    assert pred.grad is not None and torch.isfinite(pred.grad).all()


def test_ssim_rejects_bad_windows(dev):
    with pytest.raises(ValueError):
        ssim(torch.zeros(1, 10, 10, device=dev), torch.zeros(1, 10, 10, device=dev), win_size=6)
    with pytest.raises(ValueError):
        ssim(torch.zeros(1, 5, 10, device=dev), torch.zeros(1, 5, 10, device=dev))


def test_mse_by_hand(dev):
    """[[0, 1], [1, 0.5]] vs [[0, 0], [1, 1]]: (0 + 1 + 0 + 0.25) / 4 = 0.3125; equal images: 0."""
    pred = t([[[0, 1], [1, 0.5]], [[0.2, 0.2], [0.2, 0.2]]], dev)
    target = t([[[0, 0], [1, 1]], [[0.2, 0.2], [0.2, 0.2]]], dev)
    got = mse(pred, target)
    assert got.shape == (2,)
    np.testing.assert_allclose(got.cpu().numpy(), [0.3125, 0.0], atol=1e-7)


# A 5 x 3 image: ranges 1.0 .. 3.0 m in 0.5 m bins, azimuth -90, 0, +90 deg.
RANGE_5 = [1.0, 1.5, 2.0, 2.5, 3.0]
AZIMUTH_3 = [-math.pi / 2, 0.0, math.pi / 2]


def test_first_return_ranges_by_hand(dev):
    """Column 0 has returns at rows 1 and 3 -> 1.5 m (the nearest), column 1 none -> inf,
    column 2 a cell of exactly 0.5 at row 4 -> 3.0 m; a threshold of 0.6 drops that one."""
    image = torch.zeros(1, 5, 3, device=dev)
    image[0, 1, 0] = image[0, 3, 0] = 1.0
    image[0, 4, 2] = 0.5
    got = first_return_ranges(image, f64(RANGE_5, dev))
    assert got.shape == (1, 3) and got.dtype == torch.float64
    assert got.cpu().tolist() == [[1.5, INF, 3.0]]
    assert first_return_ranges(image, RANGE_5, threshold=0.6).cpu().tolist() == [[1.5, INF, INF]]


def test_predicted_ranges_by_hand(dev):
    """Column 0 peaks (0.9) at row 2 -> 2.0 m although row 1 (0.6) is nearer; column 1's maximum
    0.45 at row 4 -> 3.0 m (no threshold: the peak counts whatever its value); column 2 is 0.5 at
    row 4 -> 3.0 m. The nearest cell >= 0.5 instead: 1.5 m, none, 3.0 m."""
    pred = t(
        [
            [
                [0.1, 0.40, 0.0],
                [0.6, 0.30, 0.0],
                [0.9, 0.20, 0.0],
                [0.0, 0.10, 0.0],
                [0.0, 0.45, 0.5],
            ]
        ],
        dev,
    )
    assert predicted_ranges(pred, f64(RANGE_5, dev)).cpu().tolist() == [[2.0, 3.0, 3.0]]
    assert first_return_ranges(pred, RANGE_5).cpu().tolist() == [[1.5, INF, 3.0]]


def test_peak_range_mae_by_hand(dev):
    """Ranges 0.21 .. 4.99 m in 2 cm bins, 4 beams. Image 0: label returns at rows 10, 20, none,
    5; prediction peaks at row 12 (0.04 m off), row 20 (exact), row 3 (no label return: not
    scored) and 0.3 at row 5 (exact: the peak counts whatever its value) -> (0.04 + 0 + 0) / 3.
    Image 1: same label, empty prediction: every column reads as the nearest bin (0.21 m) ->
    (0.2 + 0.4 + 0.1) / 3. Image 2: empty label -> nan."""
    range_m = 0.21 + 0.02 * np.arange(240)
    target = torch.zeros(3, 240, 4, device=dev)
    target[:2, 10, 0] = target[:2, 20, 1] = target[:2, 5, 3] = 1.0
    pred = torch.zeros(3, 240, 4, device=dev)
    pred[0, 12, 0], pred[0, 11, 0] = 0.9, 0.7
    pred[0, 20, 1] = 0.7
    pred[0, 3, 2] = 0.8
    pred[0, 5, 3] = 0.3
    got = peak_range_mae(pred, target, f64(range_m, dev))
    assert got.shape == (3,) and got.dtype == torch.float64
    np.testing.assert_allclose(got.cpu().numpy(), [0.04 / 3, 0.7 / 3, np.nan], atol=1e-12)


def test_scan_scores_by_hand(dev):
    """Eight beams, predicted / true range [m] (inf = no return), tolerance 0.10 m:
    0: 1.00 / 1.05 true positive (0.05); 1: 2.00 / 2.30 wrong range (both return, 0.30 off);
    2: none / 1.00 missed; 3: 3.00 / none false; 4: none / none correct empty;
    5: 1.50 / 1.50 true positive (0); 6: 4.00 / 4.08 true positive (0.08); 7: none / 2.00 missed.
    TP 3 of 5 predicted and 6 true returns: F1 2 * 3 / 11, precision 3/5, recall 3/6, beam
    accuracy (3 + 1) / 8, range error of TP (0.05 + 0 + 0.08) / 3, missed 2/6, wrong range 1/6
    (beam 1; with recall and missed it makes 1), false 1 of the 2
    empty beams, no return on 3 of 8 beams. At 0.05 m (inclusive) beam 6 drops out: TP 2."""
    pred = f64([[1.00, 2.00, INF, 3.00, INF, 1.50, 4.00, INF]], dev)
    true = f64([[1.05, 2.30, 1.00, INF, INF, 1.50, 4.08, 2.00]], dev)
    got = scan_scores(pred, true, tolerance_m=0.10)
    want = {
        "scan_f1": 6 / 11,
        "beam_accuracy": 4 / 8,
        "return_precision": 3 / 5,
        "return_recall": 3 / 6,
        "range_mae_tp_m": 0.13 / 3,
        "missed": 2 / 6,
        "wrong_range": 1 / 6,
        "false": 1 / 2,
        "no_return": 3 / 8,
    }
    assert list(got) == list(want) and all(v.shape == (1,) and v.dtype == torch.float64 for v in got.values())
    for k, v in want.items():
        np.testing.assert_allclose(got[k].item(), v, atol=1e-12, err_msg=k)
    tight = scan_scores(pred, true, tolerance_m=0.05)
    np.testing.assert_allclose(
        [tight[k].item() for k in ("scan_f1", "return_precision", "return_recall", "range_mae_tp_m")],
        [4 / 11, 2 / 5, 2 / 6, 0.05 / 2],
        atol=1e-12,
    )


def test_scan_scores_when_a_side_is_empty(dev):
    """Scans of 3 beams. Both empty: they agree, every ratio is 1, nothing missed or false, no
    true positive so no range error (nan). Empty prediction on returns: 0 everywhere, all
    missed. Returns on an empty label: 0, all false."""
    pred = f64([[INF] * 3, [INF] * 3, [1.0, 2.0, INF]], dev)
    true = f64([[INF] * 3, [1.0, 2.0, 3.0], [INF] * 3], dev)
    got = {k: v.cpu().numpy() for k, v in scan_scores(pred, true, tolerance_m=0.1).items()}
    np.testing.assert_allclose(got["scan_f1"], [1, 0, 0])
    np.testing.assert_allclose(got["return_precision"], [1, 0, 0])
    np.testing.assert_allclose(got["return_recall"], [1, 0, 0])
    np.testing.assert_allclose(got["beam_accuracy"], [1, 0, 1 / 3])
    np.testing.assert_allclose(got["missed"], [0, 1, 0])
    np.testing.assert_allclose(got["false"], [0, 0, 2 / 3])
    np.testing.assert_allclose(got["no_return"], [1, 1, 1 / 3])
    assert np.isnan(got["range_mae_tp_m"]).all()


def _room_scan(azimuth_rad: np.ndarray) -> np.ndarray:
    """Ranges [m] from a sensor at (1.0, 0.3) heading +x to the walls of the room
    x in [0, 5.5], y in [-1.2, 2.0] (behind the sensor: the wall at x = 0)."""
    c, s = np.cos(azimuth_rad), np.sin(azimuth_rad)
    with np.errstate(divide="ignore"):
        to_x = np.where(c > 1e-9, (5.5 - 1.0) / c, np.where(c < -1e-9, -1.0 / c, np.inf))
        to_y = np.where(s > 1e-9, (2.0 - 0.3) / s, np.where(s < -1e-9, (-1.2 - 0.3) / s, np.inf))
    return np.minimum(to_x, to_y)


def test_scan_f1_ranks_baselines_that_game_other_metrics(dev):
    """A room seen on the 240 x 181 grid. scan F1 at 0.10 m orders: the empty image and a faint copy
    of the truth (0.4 everywhere the truth is 1, below the 0.5 threshold) score 0; the truth
    shifted 0.2 m outwards scores 0 too (every return is off by more than the tolerance) but
    ~1 at 0.25 m; an echo-peak readout (the true wall on the 40 beams facing a wall within
    +-20 deg of its normal, where a specular echo returns, and a floor echo at 0.6 m on the others)
    lies strictly between; the truth scores 1. The faint copy is what the column-peak range error
    cannot see: it scores a perfect 0 there."""
    range_m = 0.21 + 0.02 * np.arange(240)
    azimuth_rad = np.deg2rad(np.arange(-90, 91))
    true_r = _room_scan(azimuth_rad)
    rows = np.searchsorted(range_m - 0.01, true_r) - 1
    inside = true_r < range_m[-1]
    truth = np.zeros((240, 181))
    truth[rows[inside], np.flatnonzero(inside)] = 1.0
    facing = np.abs(azimuth_rad) < np.deg2rad(20)  # the far wall's normal points at the sensor
    facing |= np.abs(azimuth_rad - np.pi / 2) < np.deg2rad(20)  # the left wall
    peak_rows = np.where(facing & inside, rows, np.searchsorted(range_m, 0.6))
    echo_peak = np.zeros((240, 181))
    echo_peak[peak_rows, np.arange(181)] = 1.0
    shifted = np.roll(truth, 10, axis=0)
    shifted[:10] = 0
    images = {"empty": np.zeros_like(truth), "faint": 0.4 * truth, "shifted": shifted}
    images |= {"echo peak": echo_peak, "truth": truth}
    pred = t(np.stack(list(images.values())), dev)
    target = t(np.broadcast_to(truth, pred.shape).copy(), dev)
    f1 = dict(zip(images, scan_metrics(pred, target, f64(range_m, dev))["scan_f1"].tolist(), strict=True))
    assert f1["empty"] == f1["faint"] == f1["shifted"] == 0.0
    assert 0.1 < f1["echo peak"] < 0.9 and f1["truth"] == 1.0
    loose = scan_metrics(pred, target, range_m, tolerance_m=0.25)["scan_f1"].tolist()
    assert loose[2] > 0.95 > loose[3]  # shifted by 0.2 m: within 0.25 m
    peak = peak_range_mae(pred, target, range_m).tolist()
    assert peak[1] == 0.0 and peak[0] > 1.0  # faint copy "perfect" by the column peak


def test_scan_reads_the_nearest_cell_at_the_threshold(dev):
    """A column with 0.6 at 1.5 m and 0.9 at 2.0 m returns at 1.5 m (the nearest cell >= 0.5,
    as a LiDAR's first return), not at the peak; at threshold 0.7 it returns at 2.0 m."""
    pred = torch.zeros(1, 5, 1, device=dev)
    pred[0, 1, 0], pred[0, 2, 0] = 0.6, 0.9
    target = torch.zeros(1, 5, 1, device=dev)
    target[0, 2, 0] = 1.0
    assert scan_metrics(pred, target, RANGE_5)["scan_f1"].item() == 0.0
    assert scan_metrics(pred, target, RANGE_5, threshold=0.7)["scan_f1"].item() == 1.0


def test_threshold_sweep_equals_scan_metrics_at_each_threshold(dev):
    """first_return_sweep and scan_f1_sweep (one binary search per threshold) equal
    first_return_ranges and scan_metrics evaluated threshold by threshold, on random images."""
    rng = np.random.default_rng(6)
    range_m = f64(0.21 + 0.02 * np.arange(60), dev)
    pred = t(rng.random((3, 60, 25)) ** 4, dev)
    target = t(rng.random((3, 60, 25)) < 0.03, dev)
    swept = first_return_sweep(pred, range_m, CALIBRATION_THRESHOLDS)
    f1 = scan_f1_sweep(pred, target, range_m)
    assert swept.shape == (19, 3, 25) and f1.shape == (19, 3)
    for i, thr in enumerate(CALIBRATION_THRESHOLDS):
        torch.testing.assert_close(swept[i], first_return_ranges(pred, range_m, threshold=thr))
        torch.testing.assert_close(f1[i], scan_metrics(pred, target, range_m, threshold=thr)["scan_f1"])
    assert len(set(f1[:, 0].tolist())) > 3  # the thresholds matter on these images


def test_image_points_by_hand(dev):
    """Cells (1 m, 0) -> (1, 0); (2 m, +90 deg) -> (0, 2) (left is +y); (3 m, -90 deg) -> (0, -3);
    an empty image gives a (0, 2) array."""
    image = torch.zeros(2, 5, 3, device=dev)
    image[0, 0, 1] = image[0, 2, 2] = image[0, 4, 0] = 1.0
    points = image_points(image, f64(RANGE_5, dev), f64(AZIMUTH_3, dev))
    assert len(points) == 2 and points[1].shape == (0, 2)
    np.testing.assert_allclose(points[0].cpu().numpy(), [[1, 0], [0, 2], [0, -3]], atol=1e-12)


def test_chamfer_by_hand(dev):
    """Image 0: single points at (1 m, 0) and (1.04 m, 0) -> 0.04 m.
    Image 1 (asymmetric): label (1 m, 0) = (1, 0); prediction (1 m, 0) and (1 m, +90 deg) = (0, 1):
    pred -> label distances 0 and sqrt 2, label -> pred 0: 0.5 * sqrt(2) / 2 = sqrt(2) / 4.
    Image 2: label (1.04 m, -90 deg) = (0, -1.04) and (1.08 m, 0) = (1.08, 0), prediction
    (1.02 m, 0): pred -> label 0.06, label -> pred (sqrt(1.02^2 + 1.04^2) + 0.06) / 2.
    Image 3: empty prediction -> the penalty 2 x 1.08 m (more than any two cells are apart)."""
    range_m = [1.0, 1.02, 1.04, 1.06, 1.08]
    target = torch.zeros(4, 5, 3, device=dev)
    pred = torch.zeros(4, 5, 3, device=dev)
    target[0, 2, 1] = pred[0, 0, 1] = 1.0
    target[1, 0, 1] = pred[1, 0, 1] = pred[1, 0, 2] = 1.0
    target[2, 2, 0] = target[2, 4, 1] = pred[2, 1, 1] = 1.0
    target[3, 0, 1] = 1.0
    pred[3, 0, 1] = 0.4  # below the threshold
    got = chamfer_distance(pred, target, f64(range_m, dev), f64(AZIMUTH_3, dev))
    want = [0.04, math.sqrt(2) / 4, 0.5 * (0.06 + (math.hypot(1.02, 1.04) + 0.06) / 2), 2.16]
    assert got.shape == (4,) and got.dtype == torch.float64
    np.testing.assert_allclose(got.cpu().numpy(), want, atol=1e-12)
    swapped = chamfer_distance(target, pred, range_m, AZIMUTH_3)
    np.testing.assert_allclose(swapped.cpu().numpy(), want, atol=1e-12)
    empty = torch.zeros(1, 5, 3, device=dev)
    assert chamfer_distance(empty, empty, range_m, AZIMUTH_3).item() == 0.0


def test_chamfer_matches_numpy_bruteforce(dev, monkeypatch):
    """Random images on the real grid (0.21 .. 4.99 m, -90 .. 90 deg): equal to a numpy float64
    all-pairs sweep, also when cdist runs in chunks of 500 points."""
    rng = np.random.default_rng(3)
    range_m = 0.21 + 0.02 * np.arange(240)
    azimuth_rad = np.deg2rad(np.arange(-90, 91))
    pred = rng.random((2, 240, 181)) ** 8  # 1 - 0.5 ** (1 / 8): 8 % of the cells >= 0.5
    target = (rng.random((2, 240, 181)) < 0.005).astype(float)

    def points(image, threshold):
        i, j = np.nonzero(image >= threshold)
        return np.stack([range_m[i] * np.cos(azimuth_rad[j]), range_m[i] * np.sin(azimuth_rad[j])], axis=1)

    want = []
    for p, q in zip(pred, target, strict=True):
        d = np.linalg.norm(points(p, 0.5)[:, None] - points(q, 0.5)[None], axis=-1)
        want.append(0.5 * (d.min(1).mean() + d.min(0).mean()))
    args = (f64(pred, dev), t(target, dev), f64(range_m, dev), f64(azimuth_rad, dev))
    np.testing.assert_allclose(chamfer_distance(*args).cpu().numpy(), want, rtol=1e-9)
    monkeypatch.setattr(metrics, "_CDIST_CHUNK", 500)
    np.testing.assert_allclose(chamfer_distance(*args).cpu().numpy(), want, rtol=1e-9)


def test_iou_by_hand(dev):
    """4 x 4, P = {(0,0), (1,1), (3,3)}, T = {(0,0), (2,1)}.
    t = 0: |P & T| = 1, |P | T| = 4 -> 1/4.
    t = 1: correct P = (0,0), (1,1) (next to both T cells); (3,3) is 2 cells from (2,1) -> 2 of 3;
    found T = both -> matched (2 + 2) / 2 = 2, union 2 + 1 + 0 = 3 -> 2/3.
    t = 2: every cell matched -> 1. Batch images 1 and 2: P empty -> 0; both empty -> 1 (they agree)."""
    pred = torch.zeros(3, 4, 4, device=dev)
    target = torch.zeros(3, 4, 4, device=dev)
    pred[0, 0, 0] = pred[0, 1, 1] = pred[0, 3, 3] = 0.7
    target[0, 0, 0] = target[0, 2, 1] = 1.0
    target[1, 2, 2] = 1.0
    pred[1, 2, 2] = 0.3  # below the threshold
    for tol, first in [(0, 1 / 4), (1, 2 / 3), (2, 1.0)]:
        got = occupancy_iou(pred, target, tolerance_cells=tol)
        assert got.shape == (3,) and got.dtype == torch.float64
        np.testing.assert_allclose(got.cpu().numpy(), [first, 0.0, 1.0], atol=1e-12)
        np.testing.assert_allclose(occupancy_iou(target, pred, tolerance_cells=tol).cpu().numpy()[0], first)
    assert occupancy_iou(pred, target, threshold=0.2)[1].item() == 1.0


def test_iou_matches_numpy_bruteforce(dev):
    """Random sparse images, t = 0..3: the documented definition evaluated with explicit
    Chebyshev distances between cell indices in numpy; t = 0 is |P & T| / |P | T|."""
    rng = np.random.default_rng(4)
    pred = rng.random((3, 40, 30)) ** 6
    target = (rng.random((3, 40, 30)) < 0.03).astype(float)
    for tol in range(4):
        want = []
        for p, q in zip(pred >= 0.5, target >= 0.5, strict=True):
            ip, iq = np.argwhere(p), np.argwhere(q)
            cheb = np.abs(ip[:, None] - iq[None]).max(-1)
            correct, found = (cheb <= tol).any(1).sum(), (cheb <= tol).any(0).sum()
            matched = (correct + found) / 2
            want.append(matched / (matched + len(ip) - correct + len(iq) - found))
            if tol == 0:
                assert want[-1] == (p & q).sum() / (p | q).sum()
        got = occupancy_iou(t(pred, dev), t(target, dev), tolerance_cells=tol)
        np.testing.assert_allclose(got.cpu().numpy(), want, rtol=1e-12)


def test_image_metrics_on_a_batch(dev):
    """image_metrics returns every (B,) float64 metric, scan F1 first, each equal to its own
    function; a perfect prediction scores F1, beam accuracy, precision, recall, IoU and SSIM 1 and
    range errors, missed, false, Chamfer and MSE 0."""
    rng = np.random.default_rng(5)
    range_m = t(0.21 + 0.02 * np.arange(60), dev)
    azimuth_rad = t(np.deg2rad(np.arange(-20, 21)), dev)
    target = torch.zeros(4, 60, 41, device=dev)
    rows = torch.as_tensor(rng.integers(0, 60, (4, 41)), device=dev)
    target.scatter_(1, rows[:, None], 1.0)
    target[:, :, :5] = 0  # empty columns
    pred = (target + 0.3 * t(rng.random((4, 60, 41)), dev)).clamp(0, 1)
    pred[0] = target[0]
    got = image_metrics(pred, target, range_m, azimuth_rad, threshold=0.6)
    scan = ["scan_f1", "beam_accuracy", "return_precision", "return_recall", "range_mae_tp_m"]
    extra = [f"{k}_{cm}cm" for cm in (5, 25) for k in scan]
    others = ["missed", "wrong_range", "false", "no_return", "chamfer_m", "iou", *extra]
    others += ["mse", "ssim", "peak_range_mae_m"]
    assert list(got) == scan + others
    assert all(v.shape == (4,) and v.dtype == torch.float64 for v in got.values())
    want = scan_metrics(pred, target, range_m, threshold=0.6)
    want |= {f"{k}_25cm": v for k, v in scan_metrics(pred, target, range_m, threshold=0.6, tolerance_m=0.25).items()}
    want |= {
        "chamfer_m": chamfer_distance(pred, target, range_m, azimuth_rad, threshold=0.6),
        "iou": occupancy_iou(pred, target, threshold=0.6),
        "mse": mse(pred, target),
        "ssim": ssim(pred, target),
        "peak_range_mae_m": peak_range_mae(pred, target, range_m),
    }
    for k, v in want.items():
        if k in got:
            torch.testing.assert_close(got[k], v, equal_nan=True)
    perfect = {k: got[k][0].item() for k in got if not k.startswith("no_return")}
    ones = {k for k in perfect if k.split("_")[0] in ("scan", "beam", "return", "iou", "ssim")}
    assert perfect == {k: 1.0 if k in ones else 0.0 for k in perfect}
    tolerant = image_metrics(pred, target, range_m, azimuth_rad, iou_tolerance_cells=1)["iou"]
    torch.testing.assert_close(tolerant, occupancy_iou(pred, target, tolerance_cells=1))


def test_shape_mismatch_is_an_error(dev):
    with pytest.raises(ValueError):
        mse(torch.zeros(2, 5, 3, device=dev), torch.zeros(2, 5, 4, device=dev))
    with pytest.raises(ValueError):
        first_return_ranges(torch.zeros(2, 5, 3, device=dev), RANGE_5[:4])
