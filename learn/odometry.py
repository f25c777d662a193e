"""Planar odometry: sensor poses as (x, y, yaw), motion relative to a frame, and a drift model.

A robot knows how it moved, but not exactly. `OdometryNoise` models wheel odometry's error as
what dominates it on a real robot: systematic per drive, so it grows with the distance travelled
and the angle turned, not with the number of frames. Per drive it draws a scale error of the
distance (std `drift`, so after D metres the along-track error has std drift * D), a heading error
per metre travelled (std `heading_per_m` rad/m, a slightly wrong wheel base) and a scale error of
every turn (std `heading_per_rad`, so turning by a radians adds an error of std heading_per_rad * a).

Poses are (..., 3) arrays or tensors: x, y [m] and yaw [rad] of the sensor in the world (or in
another frame), azimuth 0 along the sensor's x axis, positive to the left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch


def planar(pose: np.ndarray) -> np.ndarray:
    """Sensor-to-world 4 x 4 poses (..., 4, 4) -> (..., 3) x, y, yaw (the sensor is level)."""
    pose = np.asarray(pose, dtype=np.float64)
    return np.stack([pose[..., 0, 3], pose[..., 1, 3], np.arctan2(pose[..., 1, 0], pose[..., 0, 0])], axis=-1)


def relative(pose, frame):
    """`pose` (..., 3) expressed in the sensor frame `frame` (..., 3): where a sensor at `pose` is,
    seen from a sensor at `frame` (numpy or torch, broadcasting)."""
    lib = torch if isinstance(pose, torch.Tensor) else np
    dx, dy = pose[..., 0] - frame[..., 0], pose[..., 1] - frame[..., 1]
    c, s = lib.cos(frame[..., 2]), lib.sin(frame[..., 2])
    yaw = _wrap(pose[..., 2] - frame[..., 2], lib)
    return lib.stack([c * dx + s * dy, -s * dx + c * dy, yaw], -1)


def compose(frame, local):
    """The pose `local` (..., 3), given in the sensor frame `frame`, in `frame`'s own frame of
    reference (the inverse of `relative`)."""
    lib = torch if isinstance(local, torch.Tensor) else np
    c, s = lib.cos(frame[..., 2]), lib.sin(frame[..., 2])
    x = frame[..., 0] + c * local[..., 0] - s * local[..., 1]
    y = frame[..., 1] + s * local[..., 0] + c * local[..., 1]
    return lib.stack([x, y, _wrap(frame[..., 2] + local[..., 2], lib)], -1)


def _wrap(angle, lib):
    return lib.remainder(angle + math.pi, 2 * math.pi) - math.pi


@dataclass(frozen=True, kw_only=True)
class OdometryNoise:
    """Systematic odometry error per drive (see the module docstring). All zero: perfect odometry.

    Attributes:
        drift: Std of the distance scale error (0.05: 5 % of the distance travelled).
        heading_per_m: Std of the heading error per metre travelled [rad/m].
        heading_per_rad: Std of the turn scale error [rad per rad turned].
    """

    drift: float = 0.0
    heading_per_m: float = 0.0
    heading_per_rad: float = 0.0

    def __post_init__(self) -> None:
        for name in ("drift", "heading_per_m", "heading_per_rad"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not (0 <= value < math.inf):
                raise ValueError(f"odometry noise {name} must be a finite number >= 0, got {value!r}")

    @classmethod
    def from_drift(cls, drift: float) -> OdometryNoise:
        """One figure for all three: `drift` of the distance, `drift` rad per metre and per radian
        (5 % drift: 2.9 degrees of heading error per metre and per radian turned)."""
        return cls(drift=drift, heading_per_m=drift, heading_per_rad=drift)

    @property
    def active(self) -> bool:
        return bool(self.drift or self.heading_per_m or self.heading_per_rad)

    def corrupt_steps(self, steps: torch.Tensor, errors: torch.Tensor) -> torch.Tensor:
        """Motion steps (..., S, 3) (each the next pose in the previous one's frame) with a drive's
        systematic errors `errors` (..., 3) (standard normal draws, one set per drive) applied."""
        scale = 1.0 + self.drift * errors[..., None, 0]
        distance = torch.linalg.vector_norm(steps[..., :2], dim=-1)
        yaw = steps[..., 2] * (1.0 + self.heading_per_rad * errors[..., None, 2])
        yaw = yaw + self.heading_per_m * errors[..., None, 1] * distance
        return torch.stack([steps[..., 0] * scale, steps[..., 1] * scale, yaw], -1)


def noisy_drive(poses: np.ndarray, noise: OdometryNoise, rng: np.random.Generator) -> np.ndarray:
    """What odometry with `noise` reports for one drive of true poses (T, 3): the first pose
    exact, every later one the sum of corrupted steps (float64)."""
    poses = np.asarray(poses, dtype=np.float64)
    if not noise.active or len(poses) < 2:
        return poses.copy()
    errors = torch.from_numpy(rng.standard_normal(3))
    steps = torch.from_numpy(relative(poses[1:], poses[:-1]))
    steps = noise.corrupt_steps(steps, errors).numpy()
    out = np.empty_like(poses)
    out[0] = poses[0]
    for t, step in enumerate(steps):  # a chain: each pose is the last one moved by its step
        out[t + 1] = compose(out[t], step)
    return out


def noisy_window(motion: torch.Tensor, anchor: int, noise: OdometryNoise, generator: torch.Generator) -> torch.Tensor:
    """Window poses (B, N, 3), each in the frame of pose `anchor` (which is (0, 0, 0)), as odometry
    with `noise` would report them: one draw of errors per window, applied to the steps between
    neighbouring frames, chained outwards from the anchor."""
    if not noise.active:
        return motion
    b, n, _ = motion.shape
    errors = torch.randn(b, 3, generator=generator, device=motion.device, dtype=motion.dtype)
    out = [None] * n
    out[anchor] = motion[:, anchor]
    for i in range(anchor + 1, n):  # forward: frame i seen from frame i - 1
        step = noise.corrupt_steps(relative(motion[:, i], motion[:, i - 1])[:, None], errors)[:, 0]
        out[i] = compose(out[i - 1], step)
    for i in range(anchor - 1, -1, -1):  # backward: frame i seen from frame i + 1
        step = noise.corrupt_steps(relative(motion[:, i], motion[:, i + 1])[:, None], errors)[:, 0]
        out[i] = compose(out[i + 1], step)
    return torch.stack(out, 1)
