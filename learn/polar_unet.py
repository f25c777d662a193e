"""Our network: a polar-aware 2D UNet, energyscapes (B, E, K, R, A) -> logits (B, 1, R, A).

Its parts (polar padding, convolutions, the dilated context) are shared with the model with
memory (`learn.memory`), which reads warped frames with the same UNet.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


def polar_pad(x: torch.Tensor, pad: int) -> torch.Tensor:
    """Pad (B, C, R, A) by `pad` cells: zeros along range, edge copies along azimuth.

    Beyond the last range bin there is nothing (zeros). The two azimuth edges of the field of view
    are not neighbours, so there is no wrap-around; replicating the edge column avoids the false
    "empty" border that zero padding would put at the sides.
    """
    x = F.pad(x, (pad, pad, 0, 0), mode="replicate")
    return F.pad(x, (0, 0, pad, pad))


class PolarConv(nn.Module):
    """3x3 convolution with polar padding -> BatchNorm -> ReLU; (B, C_in, R, A) -> (B, C_out, R, A)."""

    def __init__(self, in_channels: int, out_channels: int, dilation: int = 1):
        super().__init__()
        self.dilation = dilation
        self.conv = nn.Conv2d(in_channels, out_channels, 3, dilation=dilation, bias=False)
        self.bn = nn.BatchNorm2d(out_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.bn(self.conv(polar_pad(x, self.dilation))))


def polar_block(in_channels: int, out_channels: int) -> nn.Sequential:
    """Two PolarConv layers: one resolution level of the UNet."""
    return nn.Sequential(PolarConv(in_channels, out_channels), PolarConv(out_channels, out_channels))


class PolarContext(nn.Module):
    """Dilated residual convolutions at the coarsest level, so the receptive field spans most of the image.

    Walls between sparse reflectors must be interpolated from echoes far apart: at 1/4 resolution
    dilations 2, 4, 8 add ~110 range bins and ~110 azimuth degrees to the receptive field.
    """

    def __init__(self, channels: int, dilations=(2, 4, 8)):
        super().__init__()
        self.layers = nn.ModuleList(PolarConv(channels, channels, dilation=d) for d in dilations)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.layers:
            x = x + layer(x)
        return x


class PolarUNet(nn.Module):
    """A polar-aware 2D UNet: (B, E, K, R, A) energyscapes -> (B, 1, R, A) logits; 230,145 parameters at width 16.

    The K frames at each of E elevations are input channels (time is short and already aligned; 3D kernels would cost
    K times more), plus two coordinate channels, range 0..1 and azimuth -1..1: echo strength,
    beam width and the sonar's blind zones depend on where a cell is, which a plain convolution
    cannot know. Three levels (widths w, 2w, 4w) joined by 2x2 max-pooling and bilinear upsampling
    to the exact skip size (odd sizes such as A = 181 work), a dilated context block at the bottom,
    and a 1x1 convolution to one channel of logits.

    Args:
        frames: Window length K.
        width: Channel count w of the first level.
        row_contrast: Add each frame less its per-range-row median over azimuth (see ModelConfig).
        elevations: Elevation beams E of each frame.
    """

    output = "logits"

    def __init__(self, frames: int = 5, width: int = 16, row_contrast: bool = False, elevations: int = 1):
        super().__init__()
        w = width
        self.frames = frames
        self.row_contrast = row_contrast
        self.enc_0 = polar_block(elevations * frames * (2 if row_contrast else 1) + 2, w)
        self.enc_1 = polar_block(w, 2 * w)
        self.enc_2 = polar_block(2 * w, 4 * w)
        self.context = PolarContext(4 * w)
        self.dec_1 = polar_block(4 * w + 2 * w, 2 * w)
        self.dec_0 = polar_block(2 * w + w, w)
        self.head = nn.Conv2d(w, 1, 1)
        # Start at the prior: ~1 % of the cells hold a return, so the first logits are log(0.01 / 0.99)
        # and early training is not spent pushing every cell down.
        nn.init.constant_(self.head.bias, math.log(0.01 / 0.99))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Energyscapes (B, E, K, R, A) -> logits of the lidar image (B, 1, R, A)."""
        b, _, _, r, a = x.shape
        rng = torch.linspace(0.0, 1.0, r, device=x.device, dtype=x.dtype).view(1, 1, r, 1).expand(b, 1, r, a)
        azi = torch.linspace(-1.0, 1.0, a, device=x.device, dtype=x.dtype).view(1, 1, 1, a).expand(b, 1, r, a)
        channels = x.flatten(1, 2)  # (B, E K, R, A), elevation-major
        frames = [channels, row_contrast(channels)] if self.row_contrast else [channels]  # (B, EK or 2EK, R, A)
        h0 = self.enc_0(torch.cat([*frames, rng, azi], dim=1))  # (B, w, R, A)
        h1 = self.enc_1(F.max_pool2d(h0, 2, ceil_mode=True))  # (B, 2w, ceil(R/2), ceil(A/2))
        h2 = self.context(self.enc_2(F.max_pool2d(h1, 2, ceil_mode=True)))  # (B, 4w, R/4, A/4)
        h = self.dec_1(torch.cat([_upsample_to(h2, h1), h1], dim=1))  # (B, 2w, R/2, A/2)
        h = self.dec_0(torch.cat([_upsample_to(h, h0), h0], dim=1))  # (B, w, R, A)
        return self.head(h)


def row_contrast(frames: torch.Tensor) -> torch.Tensor:
    """(..., R, A) frames less the median of each range row over azimuth, clamped at 0: what
    echoes from some directions and not from all. The median comes from a sort, which exports to
    ONNX (TopK); torch.median does not."""
    middle = frames.shape[-1] // 2
    median = frames.sort(dim=-1).values[..., middle : middle + 1]
    return (frames - median).clamp_min(0.0)


def _upsample_to(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)
