"""Training-time changes to windows, so a model trained on one simulator reads walls off echoes of
another: azimuth mirroring (input and label together), a jittered dB floor, a gain tilted over
range, and masked range bands. Drawn per window from a seeded generator; never applied to
validation or test windows."""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Integral, Real

import torch

from .data import Windows, normalise
from .odometry import OdometryNoise, noisy_window

MAX_AUGMENT_DB = 100.0  # a jitter or tilt of 100 dB is already 10^5 in amplitude
MAX_BAND_MASKS = 100  # each masks up to a tenth of the grid: 100 cover it many times over


def _is_number(value) -> bool:
    return isinstance(value, Real) and not isinstance(value, bool) and value == value


@dataclass(frozen=True, kw_only=True)
class AugmentConfig:
    """What `augmented_batch` changes (stored with every checkpoint). The defaults are what the
    sim-to-real study kept (benchmarks/results/sim2real_study/randomised_part4/): trained with
    them, the polar UNet scored higher on another engine's echoes in every seed pair (+0.018 to
    +0.047 scan F1) and no lower on `reality`. `AugmentConfig.none()` turns all of it off.

    Attributes:
        mirror: Probability of mirroring a window and its label in azimuth (the grid is
            symmetric about straight ahead).
        floor_jitter_db: The input's dB floor drawn per window in floor_db +- this [dB].
        range_tilt_db: A gain linear in range, drawn per window between -this and +this [dB] at
            the far end of the grid (0 dB at the near end): spreading and absorption differ
            between engines and sensors.
        band_masks: Range bands per window (each up to a tenth of the grid) set to the floor.
        odometry_drift: Models with memory: the motion of each window as odometry with this
            drift reports it (`learn.odometry.OdometryNoise.from_drift`, drawn per window).
    """

    mirror: float = 0.5
    floor_jitter_db: float = 5.0
    range_tilt_db: float = 6.0
    band_masks: int = 2
    odometry_drift: float = 0.0

    def __post_init__(self) -> None:
        if not (_is_number(self.mirror) and 0.0 <= self.mirror <= 1.0):
            raise ValueError(f"augment.mirror is a probability in 0..1, got {self.mirror!r}")
        # Upper bounds: a gain of 10^(dB/20) beyond them overflows float32 to inf (NaN windows and a
        # NaN loss that reads as a learning-rate problem), and every band mask is one pass per batch.
        for name in ("floor_jitter_db", "range_tilt_db"):
            value = getattr(self, name)
            if not (_is_number(value) and 0 <= value <= MAX_AUGMENT_DB):
                raise ValueError(f"augment.{name} must be a number of dB in 0..{MAX_AUGMENT_DB:g}, got {value!r}")
        masks = self.band_masks
        if not (isinstance(masks, Integral) and not isinstance(masks, bool) and 0 <= masks <= MAX_BAND_MASKS):
            raise ValueError(f"augment.band_masks must be an integer in 0..{MAX_BAND_MASKS}, got {masks!r}")
        drift = self.odometry_drift
        if not (_is_number(drift) and 0 <= drift <= 1):
            raise ValueError(f"augment.odometry_drift must be a fraction in 0..1, got {drift!r}")

    @classmethod
    def none(cls) -> AugmentConfig:
        """No augmentation: the paper's training, and every run's before the study kept it."""
        return cls(mirror=0.0, floor_jitter_db=0.0, range_tilt_db=0.0, band_masks=0, odometry_drift=0.0)

    @property
    def active(self) -> bool:
        changes = (self.mirror, self.floor_jitter_db, self.range_tilt_db, self.band_masks, self.odometry_drift)
        return any(bool(v) for v in changes)


def augmented_batch(windows: Windows, indices, config: AugmentConfig, generator: torch.Generator):
    """`windows.batch(indices)` with this window's draws applied: (x, y) as `Windows.batch` gives
    them, the frames in [0, 1]; a mirrored window's motion is mirrored too, and drifts."""
    energy, y, motion = windows.raw(indices)  # (B, N, E, R, A) linear, (B, R, A), (B, N, 4) or None
    b, r = energy.shape[0], energy.shape[-2]
    dev = energy.device
    per_window = (b, 1, 1, 1, 1)

    def uniform(*shape):
        return torch.rand(*shape, generator=generator, device=dev)

    if config.range_tilt_db:
        tilt = (2 * uniform(*per_window) - 1) * config.range_tilt_db * torch.linspace(0, 1, r, device=dev)[:, None]
        energy = energy * 10.0 ** (tilt / 20.0)
    floor = windows.config.floor_db + (2 * uniform(*per_window) - 1) * config.floor_jitter_db
    x = normalise(energy, floor.clamp_min(1.0))
    if config.band_masks:
        rows = torch.arange(r, device=dev)
        for _ in range(config.band_masks):
            start = uniform(*per_window) * r
            width = uniform(*per_window) * (r / 10)
            x = torch.where((rows[:, None] >= start) & (rows[:, None] < start + width), 0.0, x)
    if config.mirror:
        flip = uniform(b) < config.mirror
        x = torch.where(flip[:, None, None, None, None], x.flip(-1), x)
        y = torch.where(flip[:, None, None], y.flip(-1), y)
        if motion is not None:  # the mirror image of a drive turns the other way: y and yaw change sign
            sign = torch.tensor([1.0, -1.0, -1.0, 1.0], device=dev)
            motion = torch.where(flip[:, None, None], motion * sign, motion)
    x = x.transpose(1, 2)  # (B, E, N, R, A), as Windows.batch gives it
    if motion is None:
        return x, y[:, None]
    noise = OdometryNoise.from_drift(config.odometry_drift)
    moved = noisy_window(motion[..., :3], windows.config.anchor, noise, generator)
    return (x, torch.cat([moved, motion[..., 3:]], -1)), y[:, None]
