"""Checkpoints: written whole or not at all, read without unpickling code, checked before use.

A checkpoint is a dict of tensors and plain types: "model" (state dict), "optimizer" (absent in
stripped or packed ones), "state" (epoch, best, history), "threshold" (the calibrated return
threshold), the configs (`learn.config.to_record`), dataset identity and grid it was trained with.
A file that is not one, or does not fit the model it names or the run that reads it, is refused
with one line naming the file and what differs (a ValueError), never a loader's traceback.
"""

from __future__ import annotations

import dataclasses
import errno
import itertools
import math
import zipfile
from numbers import Integral, Real
from pathlib import Path

import numpy as np
import torch

from .config import LearnConfig, from_record
from .data import DataConfig, Frames
from .devices import torch_device
from .elevations import missing_elevations
from .inputs import check_fits, regular_file
from .models import LEVEL_SLICE, ModelConfig, build_model, check_model_size, trained_elevations
from .shardfile import READABLE_VERSIONS

# What a resumed run may change: how long it runs and how its steps execute, not what it learns.
RESUME_MAY_CHANGE = ("epochs", "patience", "max_minutes", "amp", "cuda_graphs")


def check_compatible(ckpt: dict, config: LearnConfig, windows, *, path: str | Path = "the checkpoint") -> None:
    """Refuse to resume from a checkpoint of another model, window, dataset or training recipe
    (loss, optimiser, split, augmentation: all but RESUME_MAY_CHANGE). Configs are compared as
    configs (`learn.config.from_record`: a field added since the checkpoint was written counts at
    its default, augmentation absent from it as none, which is what such a run trained with)."""
    try:
        saved = from_record(ckpt)
    except ValueError as err:  # a field this version does not know
        raise ValueError(f"--resume: {path}: {err}") from None
    changed = config_changes(saved.model, config.model, "model") + config_changes(saved.data, config.data, "data")
    if changed:
        raise ValueError(
            f"--resume: {path} was trained with another model or windows ({'; '.join(changed)}); resume it with "
            "the settings in its config.json (--config), or start a new run"
        )
    # split_seed None means "the seed's": compare the split each draws, not how it was named
    same_split = saved.train.split_seed_or_seed == config.train.split_seed_or_seed
    changed = [
        f"{f.name} {getattr(saved.train, f.name)} -> {getattr(config.train, f.name)}"
        for f in dataclasses.fields(config.train)
        if f.name not in RESUME_MAY_CHANGE
        and not (f.name == "split_seed" and same_split)
        and getattr(saved.train, f.name) != getattr(config.train, f.name)
    ]
    if saved.augment != config.augment:
        changed.append(f"augment {saved.augment} -> {config.augment}")
    if changed:
        raise ValueError(
            f"--resume: {path} was trained with another recipe ({'; '.join(changed)}); resume it with the "
            "settings in its config.json (--config), or start a new run"
        )
    trained_on, given = ckpt["dataset"]["plan_id"], windows.frames.info.get("plan_id")
    if trained_on != given:
        raise ValueError(f"--resume: {path} was trained on another dataset (plan {trained_on}, not {given})")


def config_changes(saved, wanted, section: str) -> list[str]:
    """'section.field saved -> wanted' for every field two configs of one class disagree on."""
    return [
        f"{section}.{f.name} {getattr(saved, f.name)} -> {getattr(wanted, f.name)}"
        for f in dataclasses.fields(wanted)
        if getattr(saved, f.name) != getattr(wanted, f.name)
    ]


def save_checkpoint(obj, path: Path, *, then: str = "run it again") -> None:
    """Write through a temporary file, so a crash never leaves half a checkpoint under `path`; a
    failed write (a full disk, Ctrl-C) removes the temporary file and leaves `path` as it was
    (an OSError whose message ends with `then`, what to do next)."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:  # a Python file: a full disk is an OSError, not torch's "unexpected pos"
            torch.save(obj, f)
        tmp.replace(path)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        if not isinstance(err, OSError | RuntimeError):
            raise
        reason = err.strerror if isinstance(err, OSError) and err.strerror else _first_line(err)
        hint = "free space on that disk, then " if getattr(err, "errno", None) == errno.ENOSPC else ""
        raise OSError(f"could not write {path} ({reason}); {path.name} is as it was before: {hint}{then}") from None


def read_checkpoint(path: str | Path, device: str | torch.device = "cpu", *, role: str = "checkpoint") -> dict:
    """The dict of a .pt file written by `train`, read without unpickling code, refused by name
    (`role` says which option gave it: "--resume", "--init-from") when it is not one: not a
    PyTorch file, not a dict of weights and configs, another dataset format, window lengths of
    the model and the data that disagree."""
    path = Path(path)
    check_checkpoint_file(path, role)
    if not zipfile.is_zipfile(path):  # torch.save writes a zip archive; anything else is not ours
        raise ValueError(f"{role} {path} is not a checkpoint this learner can read safely: not a PyTorch file")
    try:
        ckpt = torch.load(path, map_location=device, weights_only=True)  # untrusted: no pickled code
    except Exception as err:
        raise ValueError(
            f"{role} {path} is not a checkpoint this learner can read safely: {_first_line(err)}"
        ) from None
    meta = ckpt.get("dataset") if isinstance(ckpt, dict) else None
    version = meta.get("format_version") if isinstance(meta, dict) else None
    if version not in READABLE_VERSIONS:  # format 1's models read the level slice: elevation_deg's default
        raise ValueError(
            f"{role} {path} is not a learn checkpoint for dataset format "
            f"{' or '.join(map(str, READABLE_VERSIONS))} (found {version})"
        )
    missing = [k for k in ("model", "model_config", "data_config") if not isinstance(ckpt.get(k), dict)]
    if missing:
        raise ValueError(f"{role} {path} is not a whole learn checkpoint: it has no {', '.join(missing)}")
    ckpt["model_config"].setdefault("elevation_deg", list(LEVEL_SLICE))  # what a model of before elevations read
    try:
        model, data = ModelConfig(**ckpt["model_config"]), DataConfig(**ckpt["data_config"])
    except (TypeError, ValueError) as err:
        raise ValueError(f"{role} {path}: its model or data config is not this version's ({err})") from None
    if model.frames != data.frames:
        raise ValueError(
            f"{role} {path} is inconsistent: its model reads windows of {model.frames} frames, its data config "
            f"cuts {data.frames}"
        )
    check_checkpoint_content(ckpt, path)  # finite weights, grid and threshold; a model that fits in memory
    return ckpt


def load_weights(model: torch.nn.Module, ckpt: dict, path: str | Path, *, role: str = "checkpoint") -> None:
    """Load the checkpoint's weights into `model`, or refuse naming the first tensor that differs
    (a checkpoint whose config says one window length or width and whose weights another)."""
    own = model.state_dict()
    saved = ckpt["model"]
    described = ModelConfig(**ckpt["model_config"])
    what = f"{described.name}, frames {described.frames}, width {described.width}"
    for key, tensor in own.items():
        if key not in saved:
            raise ValueError(f"{role} {path}: its weights do not fit the model it names ({what}): no {key}")
        theirs = saved[key]
        if isinstance(theirs, torch.Tensor) and theirs.is_floating_point() != tensor.is_floating_point():
            # load_state_dict would cast silently: integer weights lose their fractions
            raise ValueError(
                f"{role} {path}: its weights do not fit the model it names ({what}): {key} holds {theirs.dtype} "
                f"in the file, {tensor.dtype} in that model"
            )
        if not isinstance(theirs, torch.Tensor) or theirs.shape != tensor.shape:
            shape = list(theirs.shape) if isinstance(theirs, torch.Tensor) else type(theirs).__name__
            raise ValueError(
                f"{role} {path}: its weights do not fit the model it names ({what}): {key} is {shape} in the "
                f"file, {list(tensor.shape)} in that model"
            )
    extra = sorted(set(saved) - set(own))
    if extra:
        raise ValueError(f"{role} {path}: its weights do not fit the model it names ({what}): {extra[0]} is extra")
    try:
        model.load_state_dict(saved)
    except RuntimeError as err:
        raise ValueError(f"{role} {path}: its weights do not fit the model it names ({_first_line(err)})") from None


def load_checkpoint(path: str | Path, device: str = "cpu"):
    """(model in eval mode, checkpoint dict) from a .pt file written by `train`."""
    device = torch_device(device)
    ckpt = read_checkpoint(path, device)
    model = build_model(ModelConfig(**ckpt["model_config"])).to(device)
    load_weights(model, ckpt, path)
    model.eval()
    return model, ckpt


def strip_checkpoint(src: str | Path, dst: str | Path) -> Path:
    """Copy a checkpoint without its optimizer state (a third of the size): for shipping a model
    that is used, not trained further."""
    ckpt = read_checkpoint(src)
    ckpt.pop("optimizer", None)
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(ckpt, dst)
    return dst


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


# ---------------------------------------------------------------------------------------------
# What a loaded checkpoint must hold before it is used: a damaged, hand-edited or diverged one
# would otherwise give NaN images with exit 0, exhaust memory, or fail deep inside with a bare
# KeyError or "could not convert string to float" that names neither the file nor the field.

USE_ANOTHER = "use a checkpoint written by `learn train` (or learn/pretrained/polar_unet_k5.pt)"


def check_checkpoint_file(path: Path, role: str = "checkpoint") -> None:
    """A checkpoint path that is a regular file (a FIFO would block torch.load forever) whose
    size fits in memory."""
    regular_file(path, role)
    size = path.stat().st_size
    check_fits(size, f"checkpoint {path} ({size:,} bytes)", USE_ANOTHER)


def check_checkpoint_content(ckpt: dict, path: Path) -> None:
    """Every field a loaded checkpoint is read for, refused with the file and field named:
    configs that build (and fit in memory), finite weights, a finite grid, threshold and floor."""
    for key, kind in (("model", dict), ("model_config", dict), ("data_config", dict), ("dataset", dict)):
        if not isinstance(ckpt.get(key), kind):
            raise ValueError(f"{path}: {key} is {_found(ckpt.get(key))}, not a {kind.__name__}: {USE_ANOTHER}")
    try:
        model_config, data_config = ModelConfig(**ckpt["model_config"]), DataConfig(**ckpt["data_config"])
    except (TypeError, ValueError) as err:  # an unknown field, a wrong type or value
        raise ValueError(f"{path}: its configs do not build ({err}): {USE_ANOTHER}") from None
    if model_config.frames != data_config.frames:
        raise ValueError(
            f"{path}: model_config.frames {model_config.frames} but data_config.frames {data_config.frames} "
            f"(windows the network cannot take): {USE_ANOTHER}"
        )
    try:
        check_model_size(model_config)
    except ValueError as err:
        raise ValueError(f"{path}: model_config: {err}") from None
    for key in ("range_m", "azimuth_rad"):
        axis = ckpt.get(key)
        if not (isinstance(axis, list | tuple) and axis and all(_finite_number(v) for v in axis)):
            raise ValueError(f"{path}: {key} is {_found(axis)}, not a list of finite numbers: {USE_ANOTHER}")
        if any(b <= a for a, b in itertools.pairwise(axis)):  # scans read ranges in this order
            raise ValueError(f"{path}: {key} is not increasing, as every grid axis is: {USE_ANOTHER}")
    if "threshold" in ckpt and not (_finite_number(ckpt["threshold"]) and 0 < ckpt["threshold"] <= 1):
        raise ValueError(f"{path}: threshold is {_found(ckpt['threshold'])}, not a number in (0, 1]: {USE_ANOTHER}")
    if not isinstance(ckpt.get("parameters"), Integral):
        raise ValueError(f"{path}: parameters is {_found(ckpt.get('parameters'))}, not a count: {USE_ANOTHER}")
    dataset = ckpt["dataset"]
    if not isinstance(dataset.get("plan_id"), str | None):
        raise ValueError(f"{path}: dataset.plan_id is {_found(dataset.get('plan_id'))}, not text: {USE_ANOTHER}")
    episodes = dataset.get("val_episodes", [])
    if not (isinstance(episodes, list) and all(isinstance(e, Integral) for e in episodes)):
        raise ValueError(f"{path}: dataset.val_episodes is {_found(episodes)}, not episode numbers: {USE_ANOTHER}")
    check_finite_weights(ckpt["model"], path)


def check_finite_weights(weights: dict, path: Path) -> None:
    """Refuse a state dict holding anything but tensors, or NaN or inf in a floating one (a run
    that diverged writes such weights, and they predict NaN images)."""
    for name, tensor in weights.items():
        if not isinstance(tensor, torch.Tensor):
            raise ValueError(f"{path}: model weight {name} is {_found(tensor)}, not a tensor: {USE_ANOTHER}")
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            bad = int((~torch.isfinite(tensor)).sum())
            raise ValueError(
                f"{path}: model weight {name} holds {bad:,} NaN or inf values (the run diverged): use an earlier "
                "checkpoint of the run, or train again with a lower learning rate"
            )


def _finite_number(value) -> bool:
    return isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)


def _found(value) -> str:
    """A field's value in a message, cut short."""
    if isinstance(value, dict | list | tuple) and len(value) > 4:
        return f"a {type(value).__name__} of {len(value)} items"
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _elevation_text(elevation_deg) -> str:
    values = ", ".join(f"{e:g}" for e in elevation_deg)
    return f"{len(elevation_deg)} elevation{'s' if len(elevation_deg) > 1 else ''} ({values} deg)"


def _grid_text(range_m, azimuth_rad) -> str:
    r, a = np.asarray(range_m), np.rad2deg(np.asarray(azimuth_rad))
    return f"{len(r)} ranges {r[0]:.3f}..{r[-1]:.3f} m x {len(a)} azimuths {a[0]:.1f}..{a[-1]:.1f} deg"


def check_grid(frames: Frames, ckpt: dict, name: str = "the model") -> None:
    """Refuse data on another range/azimuth grid or at other elevations than the checkpoint's,
    naming both."""
    trained = trained_elevations(ckpt["model_config"].get("elevation_deg"))
    if missing_elevations(frames.elevation_deg, trained):
        raise ValueError(
            f"{frames.info.get('folder')} holds energyscapes at {_elevation_text(frames.elevation_deg)}, but {name} "
            f"was trained on {_elevation_text(trained)}: give it data beamformed at those elevations "
            "(processing.elevation_deg)"
        )
    same = len(frames.range_m) == len(ckpt["range_m"]) and len(frames.azimuth_rad) == len(ckpt["azimuth_rad"])
    if not (
        same and np.allclose(frames.range_m, ckpt["range_m"]) and np.allclose(frames.azimuth_rad, ckpt["azimuth_rad"])
    ):
        raise ValueError(
            f"{frames.info.get('folder')} is on the grid {_grid_text(frames.range_m, frames.azimuth_rad)}, but "
            f"{name} was trained on {_grid_text(ckpt['range_m'], ckpt['azimuth_rad'])}"
        )


def return_threshold(ckpt: dict, override: float | None = None, name: str = "the checkpoint") -> float:
    """The return threshold to read a checkpoint's predictions at: `override`, else its calibrated one."""
    if override is None and "threshold" not in ckpt:
        raise ValueError(
            f"{name} has no calibrated return threshold (it predates calibration): give one with --threshold"
        )
    threshold = float(ckpt["threshold"] if override is None else override)
    if not 0 < threshold <= 1:
        raise ValueError(f"the return threshold must lie in (0, 1], got {threshold}")
    return threshold
