"""learn.models and learn.export: the paper's Table 1 layout, shapes, one-batch overfits, ONNX parity (CPU)."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from learn.models import (
    ModelConfig,
    PaperNet,
    PolarUNet,
    build_model,
    parameter_count,
    predict_image,
)
from learn.polar_unet import polar_pad

PAPER_PARAMETERS_K5 = 13_367_121  # Table 1 + a two-convolution residual block (bias-free before BN) + 1x1 head

# Paper Table 1 (K = 5): layer -> (kernel, stride, padding, filters)
TABLE_1 = {
    "conv_1": ((5, 13, 5), (1, 5, 2), (2, 6, 2), 20),
    "conv_2": ((5, 15, 5), (1, 1, 1), (2, 7, 2), 40),
    "conv_3": ((5, 15, 5), (1, 1, 1), (2, 7, 2), 80),
    "residual_1.conv_1": ((5, 25, 5), (1, 1, 1), (2, 12, 2), 80),
    "residual_1.conv_2": ((5, 25, 5), (1, 1, 1), (2, 12, 2), 80),
    "transp_conv_1": ((5, 15, 5), (1, 1, 1), (2, 7, 2), 80),
    "transp_conv_2": ((5, 15, 5), (1, 1, 1), (2, 7, 2), 40),
    "transp_conv_3": ((5, 13, 5), (1, 5, 2), (4, 6, 2), 20),
}


@pytest.fixture
def flush_denormal():
    """Flush denormal floats to zero: PaperNet's vanishing gradients otherwise make CPU steps ~60x slower."""
    torch.set_flush_denormal(True)
    yield
    torch.set_flush_denormal(False)


def sparse_target(batch: int, range_count: int, azimuth_count: int, generator: torch.Generator):
    """A LiDAR-like 0/1 image: one return per azimuth column at a random range bin.

    Returns:
        Image (batch, 1, R, A) and the range bin of each column (batch, A).
    """
    rows = torch.randint(0, range_count, (batch, azimuth_count), generator=generator)
    image = torch.zeros(batch, 1, range_count, azimuth_count)
    image.scatter_(2, rows[:, None, None, :], 1.0)
    return image, rows


def test_paper_parameter_count():
    """K = 5: 13,367,121 trainable parameters, the ~13.4 M the paper's layout implies."""
    count = parameter_count(build_model(ModelConfig(name="paper", frames=5)))
    assert count == PAPER_PARAMETERS_K5
    assert 13.3e6 <= count <= 13.5e6


def test_paper_layers_match_table_1():
    """Kernel, stride, padding and filters of every named layer equal Table 1 (K = 5)."""
    modules = dict(PaperNet(frames=5).named_modules())
    for name, (kernel, stride, padding, filters) in TABLE_1.items():
        layer = modules[name]
        assert (layer.kernel_size, layer.stride, layer.padding, layer.out_channels) == (
            kernel,
            stride,
            padding,
            filters,
        ), name
    assert isinstance(modules["transp_conv_3"], torch.nn.ConvTranspose3d)
    assert modules["head"].out_channels == 1 and modules["head"].kernel_size == (1, 1, 1)


def test_paper_time_kernels_follow_frames():
    """K = 3: time kernels of depth 3, time padding 1, and 2 in transp_conv_3 (collapses 3 frames to 1)."""
    net = PaperNet(frames=3)
    assert net.conv_2.kernel_size[0] == 3 and net.conv_2.padding[0] == 1
    assert net.transp_conv_3.kernel_size[0] == 3 and net.transp_conv_3.padding[0] == 2


@pytest.mark.parametrize("frames", [1, 3, 5])
@pytest.mark.parametrize("name", ["paper", "polar_unet"])
def test_shapes(name, frames):
    """(2, 1, K, 60, 45) -> (2, 1, 60, 45); the predicted images of both kinds lie in [0, 1]."""
    torch.manual_seed(0)
    model = build_model(ModelConfig(name=name, frames=frames, width=8)).eval()
    x = torch.rand(2, 1, frames, 60, 45)
    with torch.no_grad():
        out = model(x)
        image = predict_image(model, x)
    assert out.shape == image.shape == (2, 1, 60, 45)
    assert torch.isfinite(out).all()
    assert image.min() >= 0 and image.max() <= 1


def test_shapes_odd_sizes():
    """Sizes that do not divide the strides (R = 61, A = 46; tiny 7 x 3) come back exactly."""
    for model in (PaperNet(frames=1), PolarUNet(frames=1, width=4)):
        for size in ((61, 46), (7, 3)):
            with torch.no_grad():
                assert model.eval()(torch.rand(1, 1, 1, *size)).shape == (1, 1, *size)


def test_paper_output_never_dead():
    """The head is linear: even with every output pushed below zero, gradient reaches conv_1.
    (A final ReLU would pass none here; it died this way in MSE training.)"""
    torch.manual_seed(0)
    model = PaperNet(frames=1)
    with torch.no_grad():
        model.head.bias.fill_(-10.0)
    out = model(torch.rand(2, 1, 1, 20, 12))
    assert (out < 0).all()
    torch.nn.functional.mse_loss(out, torch.zeros_like(out)).backward()
    assert model.conv_1.weight.grad.abs().sum() > 0


def test_paper_full_size():
    """The paper grid, 240 range x 181 azimuth bins, K = 5, batch 1 (~2.5 s on 2 CPU cores)."""
    model = PaperNet(frames=5).eval()
    with torch.no_grad():
        assert model(torch.rand(1, 1, 5, 240, 181)).shape == (1, 1, 240, 181)


def test_polar_pad():
    """Range (rows) is padded with zeros, azimuth (columns) with copies of the edge columns."""
    x = torch.arange(1.0, 7.0).view(1, 1, 2, 3)  # [[1, 2, 3], [4, 5, 6]]
    expected = torch.tensor(
        [[0, 0, 0, 0, 0], [1, 1, 2, 3, 3], [4, 4, 5, 6, 6], [0, 0, 0, 0, 0]], dtype=torch.float32
    ).view(1, 1, 4, 5)
    torch.testing.assert_close(polar_pad(x, 1), expected)


def fit(model, loss_fn, *, lr: float, steps: int) -> list[float]:
    """Adam steps on loss_fn(); the loss before each step."""
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        optimizer.zero_grad()
        loss = loss_fn()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    return losses


def test_polar_unet_overfits_one_batch():
    """150 Adam steps (BCE) on 2 fixed random inputs: loss < 10 % of its start, returns at the right range."""
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 1, 3, 48, 40, generator=g)
    y, rows = sparse_target(2, 48, 40, g)
    model = PolarUNet(frames=3, width=8)
    losses = fit(model, lambda: F.binary_cross_entropy_with_logits(model(x), y), lr=3e-3, steps=150)
    assert losses[-1] < 0.1 * losses[0]
    with torch.no_grad():
        hit = predict_image(model, x)[:, 0].argmax(dim=1) == rows  # (2, A): per-column strongest range bin
    assert hit.float().mean() >= 0.9


def test_paper_overfits_one_batch(flush_denormal):
    """60 Adam steps (MSE, the paper's lr 1e-4) on 2 fixed random inputs, K = 1, 30 x 16: same criteria."""
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 1, 1, 30, 16, generator=g)
    y, rows = sparse_target(2, 30, 16, g)
    model = PaperNet(frames=1)
    losses = fit(model, lambda: F.mse_loss(model(x), y), lr=1e-4, steps=60)
    assert losses[-1] < 0.1 * losses[0]
    with torch.no_grad():  # train mode: batch statistics, as optimised (running statistics lag behind)
        hit = predict_image(model, x)[:, 0].argmax(dim=1) == rows
    assert hit.float().mean() >= 0.9


@pytest.mark.parametrize(
    ("name", "contrast"), [("paper", False), ("polar_unet", False), ("polar_unet", True), ("polar_memory", False)]
)
def test_onnx_matches_torch(name, contrast, tmp_path):
    """ONNX export (K = 3, 40 x 30) checks itself; onnxruntime on another batch size (3) equals torch
    (the model with memory: 2 history frames, some absent, each frame moved and turned)."""
    pytest.importorskip("onnxruntime")
    from learn.export import export_onnx

    torch.manual_seed(0)
    memory = {"history": 2, "extent": (0.1, 4.0, -1.5, 1.5)} if name == "polar_memory" else {}
    model = build_model(ModelConfig(name=name, frames=3, width=8, row_contrast=contrast, **memory))
    with torch.no_grad():  # non-trivial batch-norm statistics, so eval mode differs from train mode
        for module in model.modules():
            if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                module.running_mean.uniform_(-0.1, 0.1)
                module.running_var.uniform_(0.5, 2.0)
    info = export_onnx(model, tmp_path / "model.onnx", frames=3, range_count=40, azimuth_count=30, threshold=0.35)
    assert info["path"] == str(tmp_path / "model.onnx") and info["opset"] >= 17
    assert info["max_abs_diff"] <= info["tolerance"]
    assert model.training  # mode restored

    import onnxruntime

    draw = torch.Generator().manual_seed(1)
    frames = 3 + memory.get("history", 0)
    inputs = {"energyscapes": torch.rand(3, 1, frames, 40, 30, generator=draw)}
    if memory:
        inputs["motion"] = torch.cat([torch.rand(3, frames, 3, generator=draw) - 0.5, torch.ones(3, frames, 1)], -1)
        inputs["motion"][:, 0, 3] = 0.0  # the oldest frame absent
    session = onnxruntime.InferenceSession(info["path"], providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    assert meta == {"output_kind": model.output, "return_threshold": "0.35", "elevation_deg": "[0.0]"}
    (got,) = session.run(None, {k: v.numpy() for k, v in inputs.items()})
    with torch.no_grad():
        expected = model.eval()(*inputs.values()).numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"name": "resnet"},
        {"frames": 0},
        {"width": 0},
        {"name": "paper", "frames": 4},
        {"name": "paper", "row_contrast": True},
    ],
)
def test_bad_config_raises(kwargs):
    with pytest.raises(ValueError):
        ModelConfig(**kwargs)


def test_export_is_quiet_unless_verbose(tmp_path):
    """`learn export` prints its result, not torch's exporter warnings (torchvision, which we do
    not use, missing); `--verbose` lets them through."""
    pytest.importorskip("onnxruntime")
    import importlib.util
    import subprocess
    import sys

    import learn

    command = [sys.executable, "-m", "learn", "export", "--checkpoint", str(learn.PRETRAINED_CHECKPOINT)]
    quiet = subprocess.run([*command, "--out", str(tmp_path / "q.onnx")], capture_output=True, text=True, timeout=300)
    assert quiet.returncode == 0 and quiet.stderr.strip() == "", quiet.stderr
    if importlib.util.find_spec("torchvision") is None:  # the exporter warns about it once per process
        loud = [*command, "--out", str(tmp_path / "v.onnx"), "--verbose"]
        assert "torchvision" in subprocess.run(loud, capture_output=True, text=True, timeout=300).stderr


def test_row_contrast_removes_what_every_azimuth_shares():
    """A floor band across all 181 azimuths vanishes from the contrast channel; a wall echo over
    20 azimuths keeps its height above the row's background, and the background is 0."""
    from learn.models import row_contrast

    frame = torch.full((2, 1, 60, 181), 0.1)
    frame[:, :, 12] = 0.8  # floor band
    frame[:, :, 30, 40:60] = 0.9  # wall
    frame[1, :, 30, 100:110] = 0.4  # second sample: a fainter echo in the same row
    got = row_contrast(frame)
    assert got.shape == frame.shape and got[:, :, 12].abs().max() == 0
    torch.testing.assert_close(got[:, :, 30, 40:60], torch.full((2, 1, 20), 0.8))
    torch.testing.assert_close(got[1, :, 30, 100:110], torch.full((1, 10), 0.3))
    assert got[0, :, 30, 100:110].abs().max() == 0 and got[:, :, :12].abs().max() == 0
    model = build_model(ModelConfig(frames=3, width=4, row_contrast=True))
    assert model.enc_0[0].conv.in_channels == 3 + 3 + 2  # frames, their contrast, range and azimuth
    assert model(torch.rand(2, 1, 3, 60, 181)).shape == (2, 1, 60, 181)
