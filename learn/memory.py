"""A model with memory: past energyscapes brought into the current sensor frame by odometry.

A wall stays put in the world while the robot drives; a multipath ghost and a floor band move
with the sensor in a way that does not match its motion. `PolarMemory` resamples every frame of
its window and its history into the label frame's polar grid with the frame's pose relative to
that frame (`polar_warp`, bilinear, so gradients flow to the frames), and reads them with the
polar UNet: a wall heard at normal incidence some frames ago lands where it is now, also when it
is edge-on and silent in the current frame, while echoes that do not stay put do not add up.

    model = PolarMemory(frames=5, history=8, extent=(r0, r1, a0, a1))
    logits = model(x, motion)  # x (B, E, N, R, A), motion (B, N, 4): see learn.data.Windows
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .polar_unet import PolarUNet, row_contrast

BEHIND = 1e-6  # [m]: points this close to straight behind a frame's sensor have no azimuth in view
EDGE = 1e-4  # of the half grid: the outermost bin centres are in view despite float rounding


def polar_warp(frames: torch.Tensor, motion: torch.Tensor, extent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Polar images of N frames resampled into the polar grid of the label frame.

    Args:
        frames: (B, N, R, A) or (B, N, E, R, A) images on the grid of their own sensor pose (E
            elevation beams move with their frame alike).
        motion: (B, N, 4): each frame's sensor pose in the label frame (x, y [m], yaw [rad]) and
            1 where the frame is there, 0 where it is absent.
        extent: (4,) first and last range bin centre [m], first and last azimuth centre [rad]
            (the bins are evenly spaced).

    Returns:
        (warped, shaped as frames, seen (B, N, R, A) 1 where the cell lay in that frame's field of view
        and the frame is there, else 0; warped is 0 there too).
    """
    (b, n), (r, a) = frames.shape[:2], frames.shape[-2:]
    r0, r1, a0, a1 = extent.to(frames.dtype)
    rng = torch.linspace(0.0, 1.0, r, device=frames.device, dtype=frames.dtype) * (r1 - r0) + r0
    azi = torch.linspace(0.0, 1.0, a, device=frames.device, dtype=frames.dtype) * (a1 - a0) + a0
    px, py = rng[:, None] * torch.cos(azi), rng[:, None] * torch.sin(azi)  # (R, A) in the label frame
    x, y, yaw = (motion[..., i, None, None].to(frames.dtype) for i in range(3))  # (B, N, 1, 1)
    c, s = torch.cos(yaw), torch.sin(yaw)
    qx, qy = c * (px - x) + s * (py - y), -s * (px - x) + c * (py - y)  # the cell in frame n's sensor frame
    q = torch.sqrt(qx * qx + qy * qy)
    ahead = q + qx  # 0 only straight behind, where the half-angle form below has no answer
    bearing = 2.0 * torch.atan(qy / ahead.clamp_min(BEHIND))  # atan2(qy, qx), in operators ONNX has
    u = 2.0 * (bearing - a0) / (a1 - a0) - 1.0
    v = 2.0 * (q - r0) / (r1 - r0) - 1.0
    seen = (u.abs() <= 1.0 + EDGE) & (v.abs() <= 1.0 + EDGE) & (ahead > BEHIND) & (motion[..., 3, None, None] > 0)
    grid = torch.stack([u, v], -1).reshape(b * n, r, a, 2)
    warped = F.grid_sample(frames.reshape(b * n, -1, r, a), grid, mode="bilinear", align_corners=True)
    seen = seen.to(frames.dtype)
    return warped.reshape(frames.shape) * seen.reshape(b, n, *[1] * (frames.ndim - 4), r, a), seen


class PolarMemory(nn.Module):
    """The polar UNet over a window and its history, each frame brought into the label frame by
    odometry: x (B, E, N, R, A), motion (B, N, 4) -> logits (B, 1, R, A).

    Its input channels: the N warped frames at each of E elevations, the N masks of where each frame saw (a cell outside
    a past frame's view is unknown, not empty), and with `row_contrast` the warped frames less
    their row medians; then range and azimuth coordinates, as the polar UNet has.

    Args:
        frames: Window length K.
        history: Frames before the window (N = history + K).
        width: Channel count w of the UNet's first level.
        row_contrast: Add each warped frame less its range row's median (see ModelConfig).
        extent: First and last range bin centre [m], first and last azimuth centre [rad].
        elevations: Elevation beams E of each frame.
    """

    output = "logits"
    odometry = True

    def __init__(self, frames: int, history: int, width: int, row_contrast: bool, extent, elevations: int = 1):
        super().__init__()
        self.frames, self.history, self.row_contrast = frames, history, row_contrast
        n = frames + history
        self.register_buffer("extent", torch.tensor(extent, dtype=torch.float32), persistent=False)
        self.unet = PolarUNet(frames=n * (2 * elevations + 1 if row_contrast else elevations + 1), width=width)

    def forward(self, x: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
        warped, seen = polar_warp(x.transpose(1, 2), motion, self.extent)  # (B, N, E, R, A), (B, N, R, A)
        warped = warped.transpose(1, 2).flatten(1, 2)  # (B, E N, R, A), elevation-major
        channels = [warped, seen, row_contrast(warped)] if self.row_contrast else [warped, seen]
        return self.unet(torch.cat(channels, 1)[:, None])
