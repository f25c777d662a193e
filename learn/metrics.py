"""Metrics of predicted LiDAR images on the polar grid, per image: (B, R, A) tensors -> (B,).

Images are (range, azimuth) with bin centres `range_m` (R,) [m], ascending, and `azimuth_rad`
(A,) [rad], 0 ahead and positive to the left; cell (r, a) is the sensor-frame point
(r cos a, r sin a) (x forward, y left). Labels are 0/1 LiDAR images (1 where a return falls in
the cell); predictions are floats in [0, 1].

The primary metric reads a prediction as a LiDAR would (`learn.scan.scan_metrics`): each azimuth
column is a beam whose return is the nearest cell >= the model's threshold, compared with the
label's nearest return at a range tolerance; an empty or faint image scores 0. Besides it: the
Chamfer distance between the occupied cells as points (capped, so an empty side costs a defined
penalty), occupancy IoU, and the image metrics MSE and SSIM (equal to scikit-image's; both
reward empty images on sparse labels, so never read them alone).
`peak_range_mae` (each beam read at its column maximum, ignoring confidence) is kept for
comparison with older results. `image_metrics` computes them all.

A label cell counts as a return at `LABEL_THRESHOLD` (labels are 0/1, so any value in (0, 1]
gives the same answer); a predicted cell at the `threshold` argument. Every function works on
any device and batch; results are float64.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .scan import (
    CALIBRATION_THRESHOLDS,
    EXTRA_TOLERANCES_M,
    LABEL_THRESHOLD,
    SCAN_TOLERANCE_M,
    TOLERANCE_KEYS,
    _axis,
    _check_pair,
    _ratio,
    _share,
    first_return_ranges,
    first_return_sweep,
    scan_f1_sweep,
    scan_metrics,
    scan_scores,
    tolerance_suffix,
)

__all__ = [  # the scan metric lives in learn.scan; importing it from here keeps working
    "CALIBRATION_THRESHOLDS",
    "EXTRA_TOLERANCES_M",
    "LABEL_THRESHOLD",
    "SCAN_TOLERANCE_M",
    "TOLERANCE_KEYS",
    "chamfer_distance",
    "first_return_ranges",
    "first_return_sweep",
    "image_metrics",
    "image_points",
    "mse",
    "occupancy_iou",
    "peak_range_mae",
    "predicted_ranges",
    "scan_f1_sweep",
    "scan_metrics",
    "scan_scores",
    "ssim",
    "tolerance_suffix",
]

_CDIST_CHUNK = 4096
"""Rows of a point set per `torch.cdist` call in the Chamfer distance (bounds memory)."""


def mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error per image.

    Args:
        pred: Predicted image, shape (B, R, A).
        target: Label image, shape (B, R, A).

    Returns:
        Mean over the R * A cells of (pred - target)^2, float64, shape (B,).
    """
    _check_pair(pred, target)
    return ((pred.double() - target.double()) ** 2).mean(dim=(-2, -1))


def ssim(pred: torch.Tensor, target: torch.Tensor, *, data_range: float = 1.0, win_size: int = 7) -> torch.Tensor:
    """Structural similarity per image, equal to scikit-image's.

    Same as `skimage.metrics.structural_similarity(target, pred, data_range=data_range,
    win_size=win_size)` with its defaults: local means, variances and covariance over a uniform
    win_size x win_size window, the sample-covariance factor N / (N - 1) with N = win_size^2,
    K1 = 0.01, K2 = 0.03, and the mean of the SSIM map over the cells at least
    (win_size - 1) // 2 from the border (scikit-image crops that border, so its padding mode
    never matters and a 'valid' convolution gives the same map). Symmetric in pred and target.
    Differentiable, in float64; use `1 - ssim(...)` as a loss.

    Args:
        pred: Predicted image, shape (B, R, A).
        target: Label image, shape (B, R, A).
        data_range: Value range of the images (1.0 for [0, 1]).
        win_size: Odd window side [cells], >= 3 and <= min(R, A).

    Returns:
        Mean SSIM, float64, shape (B,); 1 for identical images.
    """
    _check_pair(pred, target)
    if win_size < 3 or win_size % 2 == 0:
        raise ValueError(f"win_size must be odd and >= 3, got {win_size}")
    if min(pred.shape[-2:]) < win_size:
        raise ValueError(f"images {tuple(pred.shape[-2:])} are smaller than the {win_size}-cell window")
    x, y = pred.double(), target.double()
    n = win_size * win_size
    cov_norm = n / (n - 1)
    # The five local means over the window as channels, 'valid' only: (B, 5, R - w + 1, A - w + 1).
    # avg_pool2d with stride 1 is the uniform-window convolution, and much faster than conv2d in float64.
    stack = torch.stack([x, y, x * x, y * y, x * y], dim=1)
    ux, uy, uxx, uyy, uxy = F.avg_pool2d(stack, win_size, stride=1).unbind(dim=1)
    vx = cov_norm * (uxx - ux * ux)
    vy = cov_norm * (uyy - uy * uy)
    vxy = cov_norm * (uxy - ux * uy)
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return s.mean(dim=(-2, -1))


def predicted_ranges(pred: torch.Tensor, range_m: torch.Tensor) -> torch.Tensor:
    """Range [m] of each column's maximum (the nearest one on ties), whatever its value: (B, R, A) -> (B, A)."""
    r = _axis(range_m, pred, dim=-2, name="range_m")
    return r[pred.argmax(dim=-2)]


def peak_range_mae(pred: torch.Tensor, target: torch.Tensor, range_m: torch.Tensor) -> torch.Tensor:
    """Range error of the column peaks, which ignores confidence (kept to compare with older results).

    On each column where the label has a return, |range of the prediction's column maximum -
    true range|, with no threshold: a faint or empty prediction still "returns" at its peak (an
    all-zero column reads as the nearest bin), so this rewards images that commit to nothing.
    Read `scan_f1` instead.

    Returns:
        Mean error [m] over the label's return columns, float64, shape (B,); nan where the label
        has no return.
    """
    _check_pair(pred, target)
    t = first_return_ranges(target, range_m, threshold=LABEL_THRESHOLD)
    has_t = torch.isfinite(t)
    err = torch.where(has_t, (predicted_ranges(pred, range_m) - t).abs(), 0.0).sum(dim=-1)
    return _share(err, has_t.sum(dim=-1))


def image_points(
    image: torch.Tensor, range_m: torch.Tensor, azimuth_rad: torch.Tensor, *, threshold: float = 0.5
) -> list[torch.Tensor]:
    """Sensor-frame points of the cells >= threshold.

    Args:
        image: Image, shape (B, R, A).
        range_m: Range bin centres [m], shape (R,).
        azimuth_rad: Azimuth bin centres [rad], 0 ahead, + to the left, shape (A,).
        threshold: A cell >= threshold is a point.

    Returns:
        B tensors of shape (n_b, 2), float64: (x, y) = (r cos a, r sin a) [m] of each cell, in
        (range, azimuth) row-major order.
    """
    r = _axis(range_m, image, dim=-2, name="range_m")
    a = _axis(azimuth_rad, image, dim=-1, name="azimuth_rad")
    out = []
    for hit in image >= threshold:
        i, j = hit.nonzero(as_tuple=True)
        out.append(torch.stack([r[i] * torch.cos(a[j]), r[i] * torch.sin(a[j])], dim=-1))
    return out


def chamfer_distance(
    pred: torch.Tensor,
    target: torch.Tensor,
    range_m: torch.Tensor,
    azimuth_rad: torch.Tensor,
    *,
    threshold: float = 0.5,
) -> torch.Tensor:
    """Symmetric Chamfer distance between the occupied cells of prediction and label.

    With P the points of the cells pred >= threshold and T those of the label's return cells
    (`image_points`): 0.5 * (mean over p in P of min over t in T |p - t|
    + mean over t in T of min over p in P |p - t|). When one side is empty the distance is
    the penalty 2 x the largest range bin, more than any two cells of the grid are apart, so
    predicting nothing never beats predicting something; both empty is 0.

    Args:
        pred: Predicted image, shape (B, R, A).
        target: Label image, shape (B, R, A).
        range_m: Range bin centres [m], shape (R,).
        azimuth_rad: Azimuth bin centres [rad], shape (A,).
        threshold: A predicted cell >= threshold is a point.

    Returns:
        Chamfer distance [m], float64, shape (B,); never nan.
    """
    _check_pair(pred, target)
    penalty = 2.0 * _axis(range_m, pred, dim=-2, name="range_m").abs().max()
    out = []
    for p, t in zip(
        image_points(pred, range_m, azimuth_rad, threshold=threshold),
        image_points(target, range_m, azimuth_rad, threshold=LABEL_THRESHOLD),
        strict=True,
    ):
        if len(p) == 0 or len(t) == 0:
            out.append(penalty * float(len(p) + len(t) > 0))
        else:
            out.append(0.5 * (_nearest_distance(p, t).mean() + _nearest_distance(t, p).mean()))
    return torch.stack(out)


def occupancy_iou(
    pred: torch.Tensor, target: torch.Tensor, *, threshold: float = 0.5, tolerance_cells: int = 0
) -> torch.Tensor:
    """Intersection over union of the occupied cells, optionally with a tolerance.

    P = cells with pred >= threshold, T = label return cells. With tolerance t = 0 this is
    |P & T| / |P | T|. With t > 0 a predicted cell is "correct" when a label cell lies within t
    cells of it in both range and azimuth (a (2t + 1) x (2t + 1) square, i.e. T dilated by a
    max-pool), and a label cell is "found" when a predicted cell lies within t cells of it. Then

        matched = (correct + found) / 2
        IoU_t = matched / (matched + (|P| - correct) + (|T| - found)),

    the IoU with "intersection" the mean of the two matched counts and the unmatched cells of
    both images in the union. It equals the plain IoU for t = 0, lies in [0, 1], is symmetric
    in P and T, and grows with t.

    Args:
        pred: Predicted image, shape (B, R, A).
        target: Label image, shape (B, R, A).
        threshold: A predicted cell >= threshold is occupied.
        tolerance_cells: t >= 0 [cells].

    Returns:
        IoU, float64, shape (B,); 1 where both P and T are empty (they agree that there is
        nothing), never nan.
    """
    _check_pair(pred, target)
    if tolerance_cells < 0:
        raise ValueError(f"tolerance_cells must be >= 0, got {tolerance_cells}")
    p = (pred >= threshold).double()
    t = (target >= LABEL_THRESHOLD).double()
    if tolerance_cells == 0:
        correct = found = (p * t).sum(dim=(-2, -1))
    else:
        correct = (p * _dilate(t, tolerance_cells)).sum(dim=(-2, -1))
        found = (t * _dilate(p, tolerance_cells)).sum(dim=(-2, -1))
    matched = 0.5 * (correct + found)
    union = matched + (p.sum(dim=(-2, -1)) - correct) + (t.sum(dim=(-2, -1)) - found)
    return _ratio(matched, union, union == 0)


def image_metrics(
    pred: torch.Tensor,
    target: torch.Tensor,
    range_m: torch.Tensor,
    azimuth_rad: torch.Tensor,
    *,
    threshold: float = 0.5,
    iou_tolerance_cells: int = 0,
) -> dict[str, torch.Tensor]:
    """All metrics per image, as evaluation reports them, the primary one first.

    Args:
        pred: Predicted image in [0, 1], shape (B, R, A).
        target: Label image (0/1), shape (B, R, A).
        range_m: Range bin centres [m], ascending, shape (R,).
        azimuth_rad: Azimuth bin centres [rad], shape (A,).
        threshold: A predicted cell >= threshold is a return (the model's calibrated threshold).
        iou_tolerance_cells: Tolerance of the IoU [cells] (see `occupancy_iou`).

    Returns:
        float64 tensors of shape (B,): the `scan_metrics` at 0.10 m ("scan_f1", "beam_accuracy",
        "return_precision", "return_recall", "range_mae_tp_m", "missed", "wrong_range", "false",
        "no_return"),
        "chamfer_m" [m], "iou", the tolerance-dependent scan metrics again at 0.05 and 0.25 m
        (keys ending "_5cm", "_25cm"), "mse", "ssim" (data_range 1, 7 x 7 window) and
        "peak_range_mae_m" [m] (ignores confidence). Only the range errors may be nan (no true
        positive, or no label return): average with nanmean.
    """
    out = scan_metrics(pred, target, range_m, threshold=threshold)
    out["chamfer_m"] = chamfer_distance(pred, target, range_m, azimuth_rad, threshold=threshold)
    out["iou"] = occupancy_iou(pred, target, threshold=threshold, tolerance_cells=iou_tolerance_cells)
    for tolerance_m in EXTRA_TOLERANCES_M:
        extra = scan_metrics(pred, target, range_m, threshold=threshold, tolerance_m=tolerance_m)
        out |= {f"{k}{tolerance_suffix(tolerance_m)}": extra[k] for k in TOLERANCE_KEYS}
    out["mse"] = mse(pred, target)
    out["ssim"] = ssim(pred, target)
    out["peak_range_mae_m"] = peak_range_mae(pred, target, range_m)
    return out


def _nearest_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distance from each point of a (n, 2) to its nearest point of b (m, 2): (n,)."""
    return torch.cat(
        [
            torch.cdist(chunk, b, compute_mode="donot_use_mm_for_euclid_dist").amin(dim=1)
            for chunk in a.split(_CDIST_CHUNK)
        ]
    )


def _dilate(mask: torch.Tensor, cells: int) -> torch.Tensor:
    """1 where mask (B, R, A) has a 1 within `cells` cells in range and azimuth (zero padding)."""
    return F.max_pool2d(mask[:, None], 2 * cells + 1, stride=1, padding=cells)[:, 0]
