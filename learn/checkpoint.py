"""Checkpoints: written whole or not at all, read without unpickling code, checked before resuming.

A checkpoint is a dict of tensors and plain types: "model" (state dict), "optimizer" (absent in
stripped or packed ones), "state" (epoch, best, history), "threshold" (the calibrated return
threshold), the configs (`learn.config.to_record`), dataset identity and grid it was trained with.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from .config import LearnConfig, from_record
from .data import FORMAT_VERSION, torch_device
from .models import ModelConfig, build_model

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
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location=device, weights_only=True)  # a checkpoint is untrusted: no pickled code
    except Exception as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"{path} is not a checkpoint this learner can read safely: {first}") from None
    meta = ckpt.get("dataset") if isinstance(ckpt, dict) else None
    version = meta.get("format_version") if isinstance(meta, dict) else None
    if version != FORMAT_VERSION:
        raise ValueError(f"{path} is not a learn checkpoint for dataset format {FORMAT_VERSION} (found {version})")
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
