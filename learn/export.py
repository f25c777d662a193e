"""ONNX export of a trained model, checked against torch with onnxruntime.

    info = export_onnx(model, "runs/unet/model.onnx", frames=5)  # {"path", "max_abs_diff", "opset", ...}

The ONNX graph takes float32 energyscapes (batch, E, K, R, A) named "energyscapes", E the
elevations the model was trained on (a model with memory: (batch, E, N, R, A), its history
first, and "motion" (batch, N, 4), each frame's pose in the label frame and whether it is there,
as `learn.data.Windows` gives them) and returns the model's raw output (batch, 1, R, A) named
"output": the image for "image" models (clip it to [0, 1]), logits for "logits" models (apply a
sigmoid). The batch dimension is dynamic; E, K, R and A are fixed.
The file's metadata carries "output_kind" ("image" or "logits") and "return_threshold": a cell
of the image at or above it is a return, and the nearest such cell of each azimuth column is the
beam's range, as `learn predict` reads it; "elevation_deg" (JSON) names the elevation of each input channel.
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from clitools.outputs import atomic_output, check_output

from . import MissingExtra

OPSET = 18  # the lowest opset the torch.export-based exporter writes natively
# float32 sums of up to ~10^5 terms (PaperNet: 80 channels x 625-tap kernels) in a different order
# differ by ~1e-6 of the output scale; 1e-4 of it is far above that and far below a real error
# (a wrong padding, a missed batch norm, a shifted upsampling changes outputs by ~1e-1 of it).
RELATIVE_TOLERANCE = 1e-4


def _import_onnx():
    try:
        import onnx
        import onnxruntime
        import onnxscript  # noqa: F401  (used by torch.onnx.export)
    except ImportError as e:
        raise MissingExtra(f'ONNX export needs onnx, onnxruntime and onnxscript: pip install -e ".[onnx]" ({e})') from e
    return onnx, onnxruntime


def export_onnx(
    model: nn.Module,
    path: str | Path,
    *,
    frames: int,
    range_count: int = 240,
    azimuth_count: int = 181,
    elevation_deg: tuple[float, ...] = (0.0,),
    check: bool = True,
    threshold: float | None = None,
    verbose: bool = False,
    overwrite: bool = False,
    inputs: tuple = (),
) -> dict:
    """Write `model` (in eval mode) as ONNX with a dynamic batch and, if `check`, compare with torch.

    The check runs a seeded random batch of 2 energyscapes in [0, 1] through torch and through
    onnxruntime (CPU) and fails if they differ by more than RELATIVE_TOLERANCE x max(1, max |torch output|):
    relative to the output scale because the output of an untrained network can be any size.

    Args:
        model: A model from `build_model`, on any device; its train/eval mode is restored afterwards.
        path: Output .onnx file (parent folders are created).
        frames: Window length K.
        range_count: Range bins R.
        azimuth_count: Azimuth bins A.
        elevation_deg: The elevations [deg] of the E channels of each frame, in order
            (`learn.models.trained_elevations`); written to the metadata.
        check: Compare onnxruntime with torch.
        threshold: The model's return threshold on the [0, 1] image (the checkpoint's calibrated
            one), written to the metadata; None writes none.
        verbose: Let torch's exporter log its warnings (e.g. that torchvision, which we do not
            use, is missing).
        overwrite: Replace an existing `path`. The file is written under a temporary name and
            renamed only once checked (`clitools.outputs`), so a failed export leaves nothing.
        inputs: Files the model came from (its checkpoint): `path` never replaces one of them.

    Returns:
        {"path", "max_abs_diff" (None without a check), "tolerance", "opset", "return_threshold"}.

    Raises:
        ImportError: onnx, onnxruntime or onnxscript is not installed.
        RuntimeError: onnxruntime and torch differ by more than the tolerance.
    """
    _import_onnx()  # a missing extra is refused first
    path = check_output(path, overwrite=overwrite, inputs=inputs)
    if threshold is not None and not 0 < threshold <= 1:
        raise ValueError(f"the return threshold must lie in (0, 1], got {threshold}")
    shape = (len(elevation_deg), frames, range_count, azimuth_count)
    with atomic_output(path, overwrite=overwrite, inputs=inputs) as tmp:
        info = _export_checked(model, tmp, shape, elevation_deg, check=check, threshold=threshold, verbose=verbose)
    return info | {"path": str(path)}


def _export_checked(
    model: nn.Module, path: Path, shape: tuple, elevation_deg, *, check: bool, threshold, verbose: bool
) -> dict:
    """`export_onnx` into `path` (its temporary file); `shape` is (E, K, R, A)."""
    onnx, onnxruntime = _import_onnx()
    device = next(model.parameters()).device
    sample, names = _sample_inputs(model, *shape)

    was_training = model.training
    model.eval()
    exporter_log = logging.getLogger("torch.onnx")
    level = exporter_log.level
    if not verbose:
        exporter_log.setLevel(logging.ERROR)
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*LeafSpec", category=FutureWarning)  # inside torch 2.13
            warnings.filterwarnings("ignore", message="# The axis name")  # one batch axis for two inputs
            # The torch.export-based exporter (the default since torch 2.9; the TorchScript one is
            # deprecated) handles every layer we use: BatchNorm, ConvTranspose3d with output_size,
            # replicate padding, bilinear resize. One self-contained file, no external weights.
            batch = torch.export.Dim("batch")
            torch.onnx.export(
                model,
                tuple(t.to(device) for t in sample),
                str(path),
                input_names=names,
                output_names=["output"],
                dynamic_shapes=tuple({0: batch} for _ in sample),
                opset_version=OPSET,
                dynamo=True,
                external_data=False,
                verbose=False,
            )
            expected = model(*(t.to(device) for t in sample)).float().cpu().numpy() if check else None
    finally:
        model.train(was_training)
        exporter_log.setLevel(level)
    metadata = {"output_kind": getattr(model, "output", "image"), "elevation_deg": json.dumps(list(elevation_deg))}
    if threshold is not None:
        metadata["return_threshold"] = f"{threshold:g}"
    proto = onnx.load(str(path))
    onnx.helper.set_model_props(proto, metadata)
    onnx.save(proto, str(path))
    onnx.checker.check_model(str(path))
    info = {"path": str(path), "max_abs_diff": None, "tolerance": None, "opset": OPSET, "return_threshold": threshold}
    if not check:
        return info

    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (got,) = session.run(None, {name: t.numpy() for name, t in zip(names, sample, strict=True)})
    diff = float(np.max(np.abs(got - expected)))
    tolerance = RELATIVE_TOLERANCE * max(1.0, float(np.max(np.abs(expected))))
    info.update(max_abs_diff=diff, tolerance=tolerance)
    if not diff <= tolerance:  # also catches NaN
        raise RuntimeError(f"ONNX output differs from torch by {diff:.3g} > tolerance {tolerance:.3g} ({path})")
    return info


def _sample_inputs(model: nn.Module, elevations: int, frames: int, range_count: int, azimuth_count: int):
    """Inputs the export traces and checks with, and their names: energyscapes, and for a model
    with memory the motion of each frame (some absent, some turned and moved)."""
    draw = torch.Generator().manual_seed(0)
    n = frames + getattr(model, "history", 0)
    x = torch.rand(2, elevations, n, range_count, azimuth_count, generator=draw)
    if not getattr(model, "odometry", False):
        return (x,), ["energyscapes"]
    motion = torch.rand(2, n, 4, generator=draw) - 0.5  # up to 0.5 m and 0.5 rad away
    motion[..., 3] = (torch.arange(n) >= n // 4).float()  # the oldest quarter absent
    return (x, motion), ["energyscapes", "motion"]
