"""Checkpoints: written whole or not at all, read without unpickling code, checked before resuming.

A checkpoint is a dict of tensors and plain types: "model" (state dict), "optimizer" (absent in
stripped or packed ones), "state" (epoch, best, history), "threshold" (the calibrated return
threshold), the configs (`learn.config.to_record`), dataset identity and grid it was trained with.
"""

from __future__ import annotations

import dataclasses
import math
from numbers import Integral, Real
from pathlib import Path

import torch

from .config import LearnConfig, from_record
from .data import FORMAT_VERSION, DataConfig, torch_device
from .inputs import check_fits, regular_file
from .models import ModelConfig, build_model, check_model_size

# What a resumed run may change: how long it runs and how its steps execute, not what it learns.
RESUME_MAY_CHANGE = ("epochs", "patience", "max_minutes", "amp", "cuda_graphs")


def check_compatible(ckpt: dict, config: LearnConfig, windows) -> None:
    """Refuse to resume from a checkpoint of another model, window, dataset or training recipe
    (loss, optimiser, split, augmentation: all but RESUME_MAY_CHANGE). Configs are compared as
    configs (`learn.config.from_record`: a field added since the checkpoint was written counts at
    its default, augmentation absent from it as none, which is what such a run trained with)."""
    try:
        saved = from_record(ckpt)
    except ValueError as err:  # a field this version does not know
        raise ValueError(f"--resume: {err}") from None
    if (saved.model, saved.data) != (config.model, config.data):
        raise ValueError("--resume: the checkpoint was trained with another model or data config")
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
            f"--resume: the run was trained with another recipe ({'; '.join(changed)}); resume it with the "
            "settings in its config.json (--config), or start a new run"
        )
    if ckpt["dataset"]["plan_id"] != windows.frames.info.get("plan_id"):
        raise ValueError("--resume: the checkpoint was trained on another dataset")


def save_checkpoint(obj, path: Path) -> None:
    """Write through a temporary file, so a crash never leaves half a checkpoint under `path`."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    tmp.replace(path)


def load_checkpoint(path: str | Path, device: str = "cpu"):
    """(model in eval mode, checkpoint dict) from a .pt file written by `train`."""
    path, device = Path(path), torch_device(device)
    check_checkpoint_file(path)
    try:
        ckpt = torch.load(path, map_location=device, weights_only=True)  # a checkpoint is untrusted: no pickled code
    except Exception as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"{path} is not a checkpoint this learner can read safely: {first}") from None
    meta = ckpt.get("dataset") if isinstance(ckpt, dict) else None
    version = meta.get("format_version") if isinstance(meta, dict) else None
    if version != FORMAT_VERSION:
        raise ValueError(f"{path} is not a learn checkpoint for dataset format {FORMAT_VERSION} (found {version})")
    check_checkpoint_content(ckpt, path)
    try:
        model = build_model(ModelConfig(**ckpt["model_config"])).to(device)
        model.load_state_dict(ckpt["model"])
    except (KeyError, TypeError, RuntimeError) as err:  # missing keys, other sizes: the file does not fit
        first = str(err).strip().splitlines()[0]
        raise ValueError(f"{path}: its weights do not fit the model it names ({first})") from None
    model.eval()
    return model, ckpt


def strip_checkpoint(src: str | Path, dst: str | Path) -> Path:
    """Copy a checkpoint without its optimizer state (a third of the size): for shipping a model
    that is used, not trained further."""
    ckpt = torch.load(src, map_location="cpu", weights_only=True)
    ckpt.pop("optimizer", None)
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(ckpt, dst)
    return dst


# ---------------------------------------------------------------------------------------------
# What a loaded checkpoint must hold before it is used: a damaged, hand-edited or diverged one
# would otherwise give NaN images with exit 0, exhaust memory, or fail deep inside with a bare
# KeyError or "could not convert string to float" that names neither the file nor the field.

USE_ANOTHER = "use a checkpoint written by `learn train` (or learn/pretrained/polar_unet_k5.pt)"


def check_checkpoint_file(path: Path) -> None:
    """A checkpoint path that is a regular file (a FIFO would block torch.load forever) whose
    size fits in memory."""
    regular_file(path, "checkpoint")
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
