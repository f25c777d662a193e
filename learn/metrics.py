"""Metrics of predicted LiDAR images on the polar grid, per image: (B, R, A) tensors -> (B,).

Images are (range, azimuth) with bin centres `range_m` (R,) and `azimuth_rad` (A,); labels are
0/1 LiDAR images, predictions lie in [0, 1]. Image metrics (MSE, SSIM) follow the paper; the
physical ones read the images as scans: per-beam range error, Chamfer distance between the scans'
points, and occupancy IoU.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

# A predicted cell or beam counts as a return at this value (labels are 0/1). Below 0.5 on
# purpose: models trained with MSE on sparse labels rarely predict 0.5 where they are right.
THRESHOLD = 0.3


def mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return ((pred.double() - target.double()) ** 2).mean(dim=(-2, -1))


def ssim(pred: torch.Tensor, target: torch.Tensor, *, data_range: float = 1.0, win_size: int = 7) -> torch.Tensor:
    """Structural similarity per image, as skimage.metrics.structural_similarity with its defaults
    (uniform win_size window, sample covariance, K1 = 0.01, K2 = 0.03, borders cropped)."""
    x, y = pred.double()[:, None], target.double()[:, None]
    window = torch.full((1, 1, win_size, win_size), 1.0 / win_size**2, dtype=x.dtype, device=x.device)
    n = win_size**2
    cov_norm = n / (n - 1)

    def filt(z):
        return F.conv2d(z, window)

    ux, uy = filt(x), filt(y)
    vx = cov_norm * (filt(x * x) - ux * ux)
    vy = cov_norm * (filt(y * y) - uy * uy)
    vxy = cov_norm * (filt(x * y) - ux * uy)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux**2 + uy**2 + c1) * (vx + vy + c2))
    return s.mean(dim=(-3, -2, -1))


def first_return_ranges(image: torch.Tensor, range_m: torch.Tensor, *, threshold: float = 0.5) -> torch.Tensor:
    """Range [m] of the nearest cell >= threshold in each azimuth column, inf where none: (B, A)."""
    hit = image >= threshold
    r = torch.as_tensor(range_m, dtype=torch.float64, device=image.device)[None, :, None]
    return torch.where(hit, r, torch.inf).amin(dim=-2)


def predicted_ranges(pred: torch.Tensor, range_m: torch.Tensor, *, threshold: float = THRESHOLD) -> torch.Tensor:
    """One return per beam: the range of each column's maximum if it is >= threshold, else inf."""
    peak, where = pred.max(dim=-2)
    r = torch.as_tensor(range_m, dtype=torch.float64, device=pred.device)[where]
    return torch.where(peak >= threshold, r, torch.inf)


def range_mae(pred, target, range_m, *, threshold: float = THRESHOLD) -> dict[str, torch.Tensor]:
    """Per-beam range error and detection shares.

    Returns (B,) tensors: "mae_m", the mean absolute difference between the range of each
    column's maximum (no threshold: every beam is read out) and the label's first return, over
    the beams where the label has a return (nan if none has); "missed", the share of those
    beams where the prediction's maximum stays below `threshold`; "false", the share of
    label-empty beams where it reaches `threshold` (0 if there is no such beam).
    """
    r = torch.as_tensor(range_m, dtype=torch.float64, device=pred.device)
    peak, where = pred.max(dim=-2)
    t = first_return_ranges(target, range_m, threshold=0.5)
    has_t, has_p = torch.isfinite(t), peak >= threshold
    err = torch.where(has_t, (r[where] - t).abs(), torch.zeros_like(t)).sum(-1) / has_t.sum(-1)
    missed = (has_t & ~has_p).sum(-1) / has_t.sum(-1).clamp_min(1)
    false = (has_p & ~has_t).sum(-1) / (~has_t).sum(-1).clamp_min(1)
    return {"mae_m": err, "missed": missed.double(), "false": false.double()}


def beam_points(ranges: torch.Tensor, azimuth_rad) -> list[torch.Tensor]:
    """xy points [m] (sensor frame) of per-beam ranges (B, A), inf = no return: (n, 2) per image."""
    a = torch.as_tensor(azimuth_rad, dtype=torch.float64, device=ranges.device)
    out = []
    for r in ranges:
        keep = torch.isfinite(r)
        out.append(torch.stack([r[keep] * torch.cos(a[keep]), r[keep] * torch.sin(a[keep])], dim=-1))
    return out


def chamfer_distance(pred, target, range_m, azimuth_rad, *, threshold: float = THRESHOLD) -> torch.Tensor:
    """Symmetric Chamfer distance [m] between the scans as point sets: one point per beam, at the
    prediction's per-beam return (`predicted_ranges`) and at the label's first return. It is the
    mean of (mean distance of predicted points to the nearest true point) and (mean distance of
    true points to the nearest predicted point); nan when either scan is empty."""
    out = []
    for p, t in zip(
        beam_points(predicted_ranges(pred, range_m, threshold=threshold), azimuth_rad),
        beam_points(first_return_ranges(target, range_m, threshold=0.5), azimuth_rad),
        strict=True,
    ):
        if len(p) == 0 or len(t) == 0:
            out.append(torch.tensor(float("nan"), dtype=torch.float64, device=pred.device))
            continue
        d = torch.cdist(p, t)
        out.append(0.5 * (d.min(dim=1).values.mean() + d.min(dim=0).values.mean()))
    return torch.stack(out)


def occupancy_iou(pred, target, *, threshold: float = THRESHOLD, tolerance_cells: int = 0) -> torch.Tensor:
    """Intersection over union of the occupied cells (prediction >= threshold, label >= 0.5).

    With tolerance t > 0, a predicted cell is correct when a label cell lies within t cells
    (in range and azimuth), and a label cell is found when a predicted cell lies within t
    cells; matched = (correct + found) / 2 and IoU = matched / (matched + wrong predicted cells
    + missed label cells), which is the plain IoU for t = 0. 1.0 when both images are empty.
    """
    p, t = (pred >= threshold).double(), (target >= 0.5).double()
    if tolerance_cells > 0:
        k = 2 * tolerance_cells + 1

        def dilate(z):
            return F.max_pool2d(z[:, None], k, stride=1, padding=tolerance_cells)[:, 0]

        correct = (p * dilate(t)).sum((-2, -1))  # predicted cells near a label cell
        found = (t * dilate(p)).sum((-2, -1))  # label cells near a predicted cell
        wrong = p.sum((-2, -1)) - correct
        missed = t.sum((-2, -1)) - found
        matched = 0.5 * (correct + found)
        union = matched + wrong + missed
    else:
        matched = (p * t).sum((-2, -1))
        union = ((p + t) > 0).double().sum((-2, -1))
    return torch.where(union > 0, matched / union.clamp_min(1e-12), torch.ones_like(union))


def image_metrics(pred, target, range_m, azimuth_rad, *, threshold: float = THRESHOLD) -> dict[str, torch.Tensor]:
    """All metrics per image: mse, ssim, range_mae_m, missed, false, chamfer_m, iou (2-cell tolerance)."""
    ranges = range_mae(pred, target, range_m, threshold=threshold)
    return {
        "mse": mse(pred, target),
        "ssim": ssim(pred, target),
        "range_mae_m": ranges["mae_m"],
        "missed": ranges["missed"],
        "false": ranges["false"],
        "chamfer_m": chamfer_distance(pred, target, range_m, azimuth_rad, threshold=threshold),
        "iou": occupancy_iou(pred, target, threshold=threshold, tolerance_cells=2),
    }
