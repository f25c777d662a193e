"""Networks that turn K energyscapes into a LiDAR image: energyscapes (B, 1, K, R, A) -> (B, 1, R, A).

    model = build_model(ModelConfig(name="polar_unet", frames=5))
    image = predict_image(model, x)  # (B, 1, R, A), in [0, 1] for logit models

Three models:
- `PaperNet`: the paper's Table 1 network, a 3D convolutional autoencoder over (time, range, azimuth)
  that outputs the image directly (trained with MSE, as in the paper).
- `PolarUNet`: ours, a small 2D UNet with the K frames as channels plus range/azimuth coordinate
  channels; it outputs logits (trained with BCE), has ~60x fewer parameters and is far cheaper to run.
- `PolarMemory` (`learn.memory`): the polar UNet over a window and its history, every frame brought
  into the current sensor frame by odometry; forward(x, motion).

Every model has a class attribute `output`: "image" (forward returns the image) or "logits"
(the image is sigmoid(forward)). R and A are free (the paper grid is 240 x 181); K is fixed per model.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from numbers import Integral, Real

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True, kw_only=True)
class ModelConfig:
    """Which network and its size (stored with every checkpoint).

    Attributes:
        name: "paper" (Table 1 of the paper) or "polar_unet" (ours).
        frames: Window length K, the number of energyscapes in one input. The paper network
            needs an odd K (its time kernels are centred); the paper uses 1, 3 and 5.
        width: Base channel count of polar_unet (ignored by "paper").
        row_contrast: polar_unet only: K more input channels, each frame less the median of its
            range row over azimuth (clamped at 0), the part of an echo that not every azimuth
            shares. Floor and ceiling bands and array sidelobes span all azimuths and are strong
            in another engine's or a real sensor's frames; walls do not. Part of the network, so
            an exported model computes it too.
        history: polar_memory only: frames before the window it reads (`DataConfig.history`).
        extent: polar_memory only: the polar grid it resamples on, first and last range bin centre
            [m] and first and last azimuth centre [rad]; `learn train` sets it from the data.
    """

    name: str = "polar_unet"
    frames: int = 5
    width: int = 16
    row_contrast: bool = False
    history: int = 0
    extent: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or self.name not in MODEL_NAMES:
            raise ValueError(f"model name must be one of {MODEL_NAMES}, got {self.name!r}")
        for name in ("frames", "width"):
            value = getattr(self, name)
            if not isinstance(value, Integral) or isinstance(value, bool):
                raise ValueError(f"{name} must be an integer, got {value!r}")
        if not isinstance(self.row_contrast, bool):
            raise ValueError(f"row_contrast must be true or false, got {self.row_contrast!r}")
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.name == "paper" and self.frames % 2 == 0:
            raise ValueError(f"the paper network needs an odd number of frames (1, 3, 5), got {self.frames}")
        if self.width < 1:
            raise ValueError(f"width must be >= 1, got {self.width}")
        if self.row_contrast and self.name not in ("polar_unet", "polar_memory"):
            raise ValueError(f"row_contrast is a polar_unet input, not one of {self.name!r}")
        if not isinstance(self.history, Integral) or isinstance(self.history, bool) or self.history < 0:
            raise ValueError(f"history must be an integer >= 0, got {self.history!r}")
        if self.history and not self.uses_odometry:
            raise ValueError(f"history frames are read by polar_memory, not by {self.name!r}")
        if self.extent is not None:
            extent = tuple(self.extent) if isinstance(self.extent, list | tuple) else ()
            numbers = len(extent) == 4 and all(isinstance(v, Real) and math.isfinite(v) for v in extent)
            if not (numbers and extent[1] > extent[0] >= 0 and extent[3] > extent[2]):
                raise ValueError(
                    f"extent must be (first range [m], last range [m], first azimuth [rad], last azimuth [rad]), "
                    f"increasing and finite, got {self.extent!r}"
                )
            object.__setattr__(self, "extent", tuple(float(v) for v in extent))

    @property
    def uses_odometry(self) -> bool:
        """Whether the network reads each frame's motion besides the frames (a model with memory)."""
        return self.name == "polar_memory"


# ---------------------------------------------------------------------------------------------
# The paper's network (Table 1)


class PaperResidual(nn.Module):
    """Residual block: Conv3d -> BN -> ReLU -> Conv3d -> BN, plus the input, then ReLU.

    The convolutions have no bias: the batch norm right after them has its own shift.
    """

    def __init__(self, channels: int, kernel_size, padding):
        super().__init__()
        self.conv_1 = nn.Conv3d(channels, channels, kernel_size, padding=padding, bias=False)
        self.bn_1 = nn.BatchNorm3d(channels)
        self.conv_2 = nn.Conv3d(channels, channels, kernel_size, padding=padding, bias=False)
        self.bn_2 = nn.BatchNorm3d(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = F.relu(self.bn_1(self.conv_1(x)))
        return F.relu(x + self.bn_2(self.conv_2(h)))


class PaperNet(nn.Module):
    """The paper's stacked convolutional autoencoder (Table 1), exactly; 13,367,121 parameters at K = 5.

    3D convolutions over (time K, range, azimuth); ReLU after every (de)convolution. conv_1 strides
    5 in range and 2 in azimuth (240 x 181 -> 48 x 91), the middle keeps that size, transp_conv_3
    strides back up and, with time padding K - 1, collapses time from K to 1. A 1x1x1 convolution
    then maps its 20 filters to the one output image. That head is ours (the table ends at 20
    filters) and linear: with a ReLU after it, MSE on sparse labels drives the output below zero
    everywhere within an epoch and the dead ReLU passes no gradient again (seen on the H100: the
    same constant output every epoch). `predict_image` clamps the readout to [0, 1].

    Parameters by frame count: K = 1: 2,673,921; K = 3: 8,020,521; K = 5: 13,367,121.
    On a CPU, train with torch.set_flush_denormal(True) (`learn.train` does): small gradients
    become denormal floats, which makes steps many times slower.

    Args:
        frames: Window length K (odd).
    """

    output = "image"

    def __init__(self, frames: int = 5):
        super().__init__()
        if frames < 1 or frames % 2 == 0:
            raise ValueError(f"PaperNet needs an odd number of frames >= 1, got {frames}")
        k, p = frames, (frames - 1) // 2  # time kernel depth and the padding that keeps K frames
        self.frames = frames
        self.conv_1 = nn.Conv3d(1, 20, (k, 13, 5), stride=(1, 5, 2), padding=(p, 6, 2))
        self.conv_2 = nn.Conv3d(20, 40, (k, 15, 5), padding=(p, 7, 2))
        self.conv_3 = nn.Conv3d(40, 80, (k, 15, 5), padding=(p, 7, 2))
        self.residual_1 = PaperResidual(80, (k, 25, 5), padding=(p, 12, 2))
        self.transp_conv_1 = nn.ConvTranspose3d(80, 80, (k, 15, 5), padding=(p, 7, 2))
        self.transp_conv_2 = nn.ConvTranspose3d(80, 40, (k, 15, 5), padding=(p, 7, 2))
        # time: (K - 1) * 1 - 2 (K - 1) + K = 1 output frame
        self.transp_conv_3 = nn.ConvTranspose3d(40, 20, (k, 13, 5), stride=(1, 5, 2), padding=(k - 1, 6, 2))
        self.head = nn.Conv3d(20, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Energyscapes (B, 1, K, R, A) -> lidar image (B, 1, R, A), unbounded (trained towards 0/1)."""
        _, _, _, r, a = x.shape
        h = F.relu(self.conv_1(x))  # (B, 20, K, R', A'), R' = ceil(R / 5), A' = ceil(A / 2)
        h = F.relu(self.conv_2(h))
        h = F.relu(self.conv_3(h))
        h = self.residual_1(h)
        h = F.relu(self.transp_conv_1(h))
        h = F.relu(self.transp_conv_2(h))
        # output_size picks the output padding (0..4 in range) that restores exactly R x A
        h = F.relu(self.transp_conv_3(h, output_size=(1, r, a)))  # (B, 20, 1, R, A)
        return self.head(h)[:, :, 0]


# ---------------------------------------------------------------------------------------------
# Our network: a polar-aware 2D UNet


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
    """A polar-aware 2D UNet: (B, 1, K, R, A) energyscapes -> (B, 1, R, A) logits; 230,145 parameters at width 16.

    The K frames are input channels (time is short and already aligned; 3D kernels would cost
    K times more), plus two coordinate channels, range 0..1 and azimuth -1..1: echo strength,
    beam width and the sonar's blind zones depend on where a cell is, which a plain convolution
    cannot know. Three levels (widths w, 2w, 4w) joined by 2x2 max-pooling and bilinear upsampling
    to the exact skip size (odd sizes such as A = 181 work), a dilated context block at the bottom,
    and a 1x1 convolution to one channel of logits.

    Args:
        frames: Window length K.
        width: Channel count w of the first level.
        row_contrast: Add each frame less its per-range-row median over azimuth (see ModelConfig).
    """

    output = "logits"

    def __init__(self, frames: int = 5, width: int = 16, row_contrast: bool = False):
        super().__init__()
        w = width
        self.frames = frames
        self.row_contrast = row_contrast
        self.enc_0 = polar_block(frames * (2 if row_contrast else 1) + 2, w)
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
        """Energyscapes (B, 1, K, R, A) -> logits of the lidar image (B, 1, R, A)."""
        b, _, _, r, a = x.shape
        rng = torch.linspace(0.0, 1.0, r, device=x.device, dtype=x.dtype).view(1, 1, r, 1).expand(b, 1, r, a)
        azi = torch.linspace(-1.0, 1.0, a, device=x.device, dtype=x.dtype).view(1, 1, 1, a).expand(b, 1, r, a)
        frames = [x[:, 0], row_contrast(x[:, 0])] if self.row_contrast else [x[:, 0]]  # (B, K or 2K, R, A)
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


# ---------------------------------------------------------------------------------------------


# The model registry: a name -> a builder from ModelConfig. It drives `build_model`, the CLI's
# --model choices and ModelConfig's check; a new network is one line here.
MODELS: dict[str, Callable[[ModelConfig], nn.Module]] = {
    "paper": lambda config: PaperNet(frames=config.frames),
    "polar_unet": lambda config: PolarUNet(frames=config.frames, width=config.width, row_contrast=config.row_contrast),
    "polar_memory": lambda config: _polar_memory(config),
}


def _polar_memory(config: ModelConfig) -> nn.Module:
    from .memory import PolarMemory  # it builds on this module's UNet

    if config.extent is None:
        raise ValueError("polar_memory needs the polar grid it resamples on (model.extent): `learn train` sets it")
    return PolarMemory(config.frames, config.history, config.width, config.row_contrast, config.extent)


MODEL_NAMES = tuple(MODELS)


def build_model(config: ModelConfig) -> nn.Module:
    """The network named by `config`, freshly initialised (seed torch for reproducible weights);
    refused before any weight is allocated where they would not fit in memory (`check_model_size`)."""
    check_model_size(config)
    return MODELS[config.name](config)


def check_model_size(config: ModelConfig) -> int:
    """The float32 bytes of `config`'s weights (and batch-norm buffers), counted on torch's meta
    device (nothing allocated); ValueError (`learn.inputs.TooLarge`) where they exceed the memory
    available, naming the figure."""
    from .inputs import check_fits

    with torch.device("meta"):
        model = MODELS[config.name](config)
    count = sum(t.numel() for t in (*model.parameters(), *model.buffers()))
    size = 4 * count
    what = f"model {config.name} (frames {config.frames}, width {config.width}: {count:,} weights)"
    advice = "use a smaller width or fewer frames (the shipped model: width 16, 5 frames)"
    check_fits(size, what, advice)
    return size


def parameter_count(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def run_model(model: nn.Module, x) -> torch.Tensor:
    """The model's output for x as `learn.data.Windows.batch` gives it: the frames, or (frames,
    motion) for a model with memory."""
    return model(*x) if isinstance(x, tuple) else model(x)


def predict_image(model: nn.Module, x) -> torch.Tensor:
    """The predicted lidar image of any model: x (see `run_model`) -> (B, 1, R, A).

    Logit models are passed through a sigmoid; image models are clamped to [0, 1].
    """
    out = run_model(model, x)
    kind = getattr(model, "module", model).output  # DistributedDataParallel wraps the model
    return torch.sigmoid(out) if kind == "logits" else out.clamp(0.0, 1.0)
