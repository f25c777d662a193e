"""Metrics of predicted LiDAR images on the polar grid, per image: (B, R, A) tensors -> (B,).

Images are (range, azimuth) with bin centres `range_m` (R,) [m], ascending, and `azimuth_rad`
(A,) [rad], 0 ahead and positive to the left; cell (r, a) is the sensor-frame point
(r cos a, r sin a) (x forward, y left). Labels are 0/1 LiDAR images (1 where a return falls in
the cell); predictions are floats in [0, 1].

The primary metric reads a prediction as a LiDAR would (`scan_metrics`): each azimuth column is
a beam whose return is the nearest cell >= the model's threshold (none if no cell reaches it),
compared with the label's nearest return at a range tolerance. Its `scan_f1` at 0.10 m ranks
predictors honestly: an empty or faint (below-threshold) image scores 0, however sparse the
labels. Besides it: the Chamfer distance between the occupied cells as points (capped, so an
empty side costs a defined penalty), occupancy IoU, and the image metrics MSE and SSIM (equal to
scikit-image's; both reward empty images on sparse labels, so never read them alone).
`peak_range_mae` (each beam read at its column maximum, ignoring confidence) is kept for
comparison with older results. `image_metrics` computes them all.

A label cell counts as a return at `LABEL_THRESHOLD` (labels are 0/1, so any value in (0, 1]
gives the same answer); a predicted cell at the `threshold` argument. Every function works on
any device and batch; results are float64.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

LABEL_THRESHOLD = 0.5
"""A label cell >= this is a LiDAR return (labels are 0/1)."""

SCAN_TOLERANCE_M = 0.10
"""Range tolerance [m] of the primary `scan_f1`: a predicted return within it of the true one is correct."""

EXTRA_TOLERANCES_M = (0.05, 0.25)
"""Further tolerances [m] reported beside the primary one, under keys ending `_5cm` and `_25cm`."""

CALIBRATION_THRESHOLDS = tuple(round(0.05 * i, 2) for i in range(1, 20))
"""Return thresholds tried by threshold calibration: 0.05, 0.10, ..., 0.95."""

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


def first_return_ranges(image: torch.Tensor, range_m: torch.Tensor, *, threshold: float = 0.5) -> torch.Tensor:
    """Range of the nearest return per azimuth column of a label-like image.

    Args:
        image: Image, shape (B, R, A).
        range_m: Range bin centres [m], ascending, shape (R,).
        threshold: A cell >= threshold is a return.

    Returns:
        Range [m] of the nearest cell >= threshold in each column, inf where there is none,
        float64, shape (B, A).
    """
    r = _axis(range_m, image, dim=-2, name="range_m")
    hit = image >= threshold
    return torch.where(hit, r[:, None], torch.inf).amin(dim=-2)


def first_return_sweep(image: torch.Tensor, range_m: torch.Tensor, thresholds) -> torch.Tensor:
    """`first_return_ranges` at many thresholds at once.

    The nearest cell >= t of a column is the first cell where the running maximum from the
    sensor outwards reaches t; that running maximum is sorted, so one binary search per
    threshold finds it.

    Args:
        image: Image, shape (B, R, A).
        range_m: Range bin centres [m], ascending, shape (R,).
        thresholds: Thresholds, shape (n,).

    Returns:
        Range [m] of the nearest cell >= each threshold, inf where there is none, float64,
        shape (n, B, A); equal to `first_return_ranges(image, range_m, threshold=t)` for each t.
    """
    r = _axis(range_m, image, dim=-2, name="range_m")
    t = torch.as_tensor(thresholds, dtype=image.dtype, device=image.device).reshape(-1)
    running = image.cummax(dim=-2).values.transpose(-2, -1).contiguous()  # (B, A, R), non-decreasing
    b, a, n = running.shape[0], running.shape[1], t.numel()
    index = torch.searchsorted(running, t.expand(b, a, n).contiguous())  # first cell >= t; R if none
    ranges = torch.where(index < len(r), r[index.clamp(max=len(r) - 1)], torch.inf)
    return ranges.permute(2, 0, 1)


def scan_scores(pred_ranges: torch.Tensor, true_ranges: torch.Tensor, *, tolerance_m: float) -> dict[str, torch.Tensor]:
    """Beam-by-beam comparison of two scans (one range or inf per beam), per scan.

    Each beam is one of: a true positive (both return, |dr| <= tolerance_m), a correct empty
    (neither returns), a missed return (only the label returns), a false return (only the
    prediction returns), or a return at the wrong range (both return, |dr| > tolerance_m),
    which counts against precision and recall alike. A ratio whose denominator is zero is 1
    when prediction and label agree that there is nothing to find, else 0 (never nan), so an
    empty prediction scores 0 on a scan with returns and 1 on an empty one.

    Args:
        pred_ranges: Predicted range per beam [m], inf = no return, shape (..., A).
        true_ranges: True range per beam [m], inf = no return, shape (..., A).
        tolerance_m: Largest |dr| [m] of a correct return (inclusive).

    Returns:
        float64 tensors of shape (...,): "scan_f1" (2 TP / (predicted + true returns)),
        "beam_accuracy" ((TP + correct empties) / beams), "return_precision" (TP / predicted
        returns), "return_recall" (TP / true returns), "range_mae_tp_m" (mean |dr| [m] over the
        true positives; nan if there is none), "missed" (share of the true returns where the
        prediction has none), "false" (share of the empty beams where the prediction returns),
        "no_return" (share of all beams where the prediction has no return).
    """
    if pred_ranges.shape != true_ranges.shape:
        raise ValueError(f"scans differ in shape: {tuple(pred_ranges.shape)} and {tuple(true_ranges.shape)}")
    p, t = pred_ranges.double(), true_ranges.double()
    has_p, has_t = torch.isfinite(p), torch.isfinite(t)
    error = torch.where(has_p & has_t, (p - t).abs(), torch.inf)
    tp = error <= tolerance_m + 1e-9  # bin centres differ by float rounding: 0.31 - 0.21 > 0.1
    n_tp, n_p, n_t = tp.sum(-1).double(), has_p.sum(-1).double(), has_t.sum(-1).double()
    n_empty = (~has_t).sum(-1).double()
    beams = p.shape[-1]
    return {
        "scan_f1": _ratio(2 * n_tp, n_p + n_t, n_p + n_t == 0),
        "beam_accuracy": (n_tp + (~has_p & ~has_t).sum(-1)) / beams,
        "return_precision": _ratio(n_tp, n_p, n_t == 0),
        "return_recall": _ratio(n_tp, n_t, n_p == 0),
        "range_mae_tp_m": _share(torch.where(tp, error, 0.0).sum(-1), n_tp),
        "missed": _ratio((has_t & ~has_p).sum(-1), n_t, False),  # nothing to miss: 0
        "false": _ratio((has_p & ~has_t).sum(-1), n_empty, False),
        "no_return": (~has_p).sum(-1).double() / beams,
    }


def scan_metrics(
    pred: torch.Tensor,
    target: torch.Tensor,
    range_m: torch.Tensor,
    *,
    threshold: float = 0.5,
    tolerance_m: float = SCAN_TOLERANCE_M,
) -> dict[str, torch.Tensor]:
    """A prediction read as a LiDAR scan and compared beam by beam with the label's scan.

    Each azimuth column is a beam; its predicted return is the nearest cell >= threshold
    (none if no cell reaches it), its true return the label's nearest return
    (`first_return_ranges`). See `scan_scores` for the keys and how each beam counts.

    Args:
        pred: Predicted image, shape (B, R, A).
        target: Label image, shape (B, R, A).
        range_m: Range bin centres [m], ascending, shape (R,).
        threshold: A predicted cell >= threshold is a return (the model's calibrated threshold).
        tolerance_m: Largest range error [m] of a correct return.

    Returns:
        float64 tensors of shape (B,), keys as `scan_scores`.
    """
    _check_pair(pred, target)
    return scan_scores(
        first_return_ranges(pred, range_m, threshold=threshold),
        first_return_ranges(target, range_m, threshold=LABEL_THRESHOLD),
        tolerance_m=tolerance_m,
    )


def scan_f1_sweep(
    pred: torch.Tensor,
    target: torch.Tensor,
    range_m: torch.Tensor,
    thresholds=CALIBRATION_THRESHOLDS,
    *,
    tolerance_m: float = SCAN_TOLERANCE_M,
) -> torch.Tensor:
    """`scan_f1` of each image at each threshold (for calibrating a model's return threshold).

    Args:
        pred: Predicted image, shape (B, R, A).
        target: Label image, shape (B, R, A).
        range_m: Range bin centres [m], ascending, shape (R,).
        thresholds: Return thresholds, shape (n,).
        tolerance_m: Largest range error [m] of a correct return.

    Returns:
        scan_f1, float64, shape (n, B).
    """
    _check_pair(pred, target)
    truth = first_return_ranges(target, range_m, threshold=LABEL_THRESHOLD)
    swept = first_return_sweep(pred, range_m, thresholds)
    return scan_scores(swept, truth.expand_as(swept), tolerance_m=tolerance_m)["scan_f1"]


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
        "return_precision", "return_recall", "range_mae_tp_m", "missed", "false", "no_return"),
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


TOLERANCE_KEYS = ("scan_f1", "beam_accuracy", "return_precision", "return_recall", "range_mae_tp_m")
"""The scan metrics that depend on the range tolerance."""


def tolerance_suffix(tolerance_m: float) -> str:
    """Key suffix of a tolerance: 0.05 -> "_5cm"."""
    return f"_{round(100 * tolerance_m)}cm"


def _check_pair(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.ndim != 3 or pred.shape != target.shape:
        raise ValueError(
            f"expected two (B, R, A) images of one shape, got {tuple(pred.shape)} and {tuple(target.shape)}"
        )


def _axis(values, image: torch.Tensor, *, dim: int, name: str) -> torch.Tensor:
    """Bin centres as float64 on the image's device, checked against the image's axis `dim`."""
    if image.ndim != 3:
        raise ValueError(f"expected a (B, R, A) image, got shape {tuple(image.shape)}")
    v = torch.as_tensor(values, dtype=torch.float64, device=image.device)
    if v.shape != (image.shape[dim],):
        raise ValueError(f"{name} has shape {tuple(v.shape)}, the image axis has {image.shape[dim]} bins")
    return v


def _share(num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
    """num / den in float64, nan where den == 0."""
    num, den = num.double(), den.double()
    defined = den > 0
    return torch.where(defined, num / torch.where(defined, den, 1.0), torch.nan)


def _ratio(num: torch.Tensor, den: torch.Tensor, agree) -> torch.Tensor:
    """num / den in float64; where den == 0, 1 if `agree` (bool, or (B,)) else 0."""
    num, den = num.double(), den.double()
    defined = den > 0
    fallback = torch.as_tensor(agree, device=den.device).double().expand_as(den)
    return torch.where(defined, num / torch.where(defined, den, 1.0), fallback)


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
