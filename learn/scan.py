"""The primary metric: a predicted LiDAR image read as a LiDAR would, beam by beam.

Each azimuth column is a beam; its predicted return is the nearest cell >= the model's threshold
(none if no cell reaches it), compared with the label's nearest return at a range tolerance. Its
`scan_f1` at 0.10 m ranks predictors honestly: an empty or faint (below-threshold) image scores 0,
however sparse the labels. Images are (B, R, A) tensors on the polar grid (see `learn.metrics`);
results are float64, per image.
"""

from __future__ import annotations

import torch

LABEL_THRESHOLD = 0.5
"""A label cell >= this is a LiDAR return (labels are 0/1)."""

SCAN_TOLERANCE_M = 0.10
"""Range tolerance [m] of the primary `scan_f1`: a predicted return within it of the true one is correct."""

EXTRA_TOLERANCES_M = (0.05, 0.25)
"""Further tolerances [m] reported beside the primary one, under keys ending `_5cm` and `_25cm`."""

CALIBRATION_THRESHOLDS = tuple(round(0.05 * i, 2) for i in range(1, 20))
"""Return thresholds tried by threshold calibration: 0.05, 0.10, ..., 0.95."""

TOLERANCE_KEYS = ("scan_f1", "beam_accuracy", "return_precision", "return_recall", "range_mae_tp_m")
"""The scan metrics that depend on the range tolerance."""


def tolerance_suffix(tolerance_m: float) -> str:
    """Key suffix of a tolerance: 0.05 -> "_5cm"."""
    return f"_{round(100 * tolerance_m)}cm"


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


def echo_peak_image(frames: torch.Tensor, level: float) -> torch.Tensor:
    """The classic sonar readout of normalised energyscapes (..., R, A): a 0/1 image with each
    beam's strongest cell set where it reaches `level`."""
    peak, where = frames.max(dim=-2, keepdim=True)
    return torch.zeros_like(frames).scatter_(-2, where, (peak >= level).to(frames.dtype))


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
        prediction has none), "wrong_range" (share of the true returns where the prediction
        returns at the wrong range; with recall and missed it adds up to 1 on a scan with
        returns), "false" (share of the empty beams where the prediction returns),
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
        "wrong_range": _ratio((has_t & has_p & ~tp).sum(-1), n_t, False),
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
    if isinstance(agree, bool):  # no host-to-device copy, which would wait for the GPU
        fallback = torch.full_like(den, float(agree))
    else:
        fallback = agree.double().expand_as(den)
    return torch.where(defined, num / torch.where(defined, den, 1.0), fallback)
