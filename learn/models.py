"""Networks that turn K energyscapes into a LiDAR image: energyscapes (B, E, K, R, A) -> (B, 1, R, A),
E the elevation beams of each frame (1: the level slice).

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

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from numbers import Integral, Real

import torch
import torch.nn.functional as F
from torch import nn

from .polar_unet import PolarUNet, row_contrast  # noqa: F401 (row_contrast: part of the models' API)


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
        elevation_deg: The elevations [deg] of the energyscapes it reads, increasing: each is an
            input channel of every frame (the planar array resolves elevation: a floor echo
            below, the ceiling above, a wall at the level). None: every elevation of the data
            (`learn train` sets it); a subset of the data's reads those alone (e.g. [0], the
            level slice). Data without them is refused by name.
    """

    name: str = "polar_unet"
    frames: int = 5
    width: int = 16
    row_contrast: bool = False
    history: int = 0
    extent: tuple[float, float, float, float] | None = None
    elevation_deg: tuple[float, ...] | None = None

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
        elevations = self.elevation_deg
        if elevations is None:
            return
        if not (
            isinstance(elevations, list | tuple)
            and elevations
            and all(isinstance(v, Real) and not isinstance(v, bool) and abs(v) <= 90 for v in elevations)
            and all(b > a for a, b in itertools.pairwise(elevations))
        ):
            raise ValueError(f"elevation_deg must be increasing angles in [-90, 90] deg, got {elevations!r}")
        object.__setattr__(self, "elevation_deg", tuple(float(v) for v in elevations))

    @property
    def elevations(self) -> int:
        """Elevation beams a frame has: the input channels of each frame."""
        return len(trained_elevations(self.elevation_deg))

    @property
    def uses_odometry(self) -> bool:
        """Whether the network reads each frame's motion besides the frames (a model with memory)."""
        return self.name == "polar_memory"


LEVEL_SLICE = (0.0,)  # the elevations of format-1 data, and so of every model trained before elevations


def trained_elevations(elevation_deg) -> tuple[float, ...]:
    """The elevations [deg] a model reads: its config's, or the level slice for a model of before
    elevations (format-1 data held that alone)."""
    return tuple(float(e) for e in (elevation_deg or LEVEL_SLICE))


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
        elevations: Elevation beams E of each frame: the input channels of its first convolution.
    """

    output = "image"

    def __init__(self, frames: int = 5, elevations: int = 1):
        super().__init__()
        if frames < 1 or frames % 2 == 0:
            raise ValueError(f"PaperNet needs an odd number of frames >= 1, got {frames}")
        k, p = frames, (frames - 1) // 2  # time kernel depth and the padding that keeps K frames
        self.frames = frames
        self.conv_1 = nn.Conv3d(elevations, 20, (k, 13, 5), stride=(1, 5, 2), padding=(p, 6, 2))
        self.conv_2 = nn.Conv3d(20, 40, (k, 15, 5), padding=(p, 7, 2))
        self.conv_3 = nn.Conv3d(40, 80, (k, 15, 5), padding=(p, 7, 2))
        self.residual_1 = PaperResidual(80, (k, 25, 5), padding=(p, 12, 2))
        self.transp_conv_1 = nn.ConvTranspose3d(80, 80, (k, 15, 5), padding=(p, 7, 2))
        self.transp_conv_2 = nn.ConvTranspose3d(80, 40, (k, 15, 5), padding=(p, 7, 2))
        # time: (K - 1) * 1 - 2 (K - 1) + K = 1 output frame
        self.transp_conv_3 = nn.ConvTranspose3d(40, 20, (k, 13, 5), stride=(1, 5, 2), padding=(k - 1, 6, 2))
        self.head = nn.Conv3d(20, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Energyscapes (B, E, K, R, A) -> lidar image (B, 1, R, A), unbounded (trained towards 0/1)."""
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


# The model registry: a name -> a builder from ModelConfig. It drives `build_model`, the CLI's
# --model choices and ModelConfig's check; a new network is one line here.
MODELS: dict[str, Callable[[ModelConfig], nn.Module]] = {
    "paper": lambda config: PaperNet(frames=config.frames, elevations=config.elevations),
    "polar_unet": lambda config: PolarUNet(
        frames=config.frames, width=config.width, row_contrast=config.row_contrast, elevations=config.elevations
    ),
    "polar_memory": lambda config: _polar_memory(config),
}


def _polar_memory(config: ModelConfig) -> nn.Module:
    from .memory import PolarMemory

    if config.extent is None:
        raise ValueError("polar_memory needs the polar grid it resamples on (model.extent): `learn train` sets it")
    return PolarMemory(
        config.frames, config.history, config.width, config.row_contrast, config.extent, elevations=config.elevations
    )


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
