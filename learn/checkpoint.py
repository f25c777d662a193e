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
import zipfile
from pathlib import Path

import torch

from .config import LearnConfig, from_record
from .data import FORMAT_VERSION, DataConfig, torch_device
from .models import ModelConfig, build_model

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
    if not path.is_file():
        raise FileNotFoundError(f"{role} {path} does not exist")
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
    if version != FORMAT_VERSION:
        raise ValueError(
            f"{role} {path} is not a learn checkpoint for dataset format {FORMAT_VERSION} (found {version})"
        )
    missing = [k for k in ("model", "model_config", "data_config") if not isinstance(ckpt.get(k), dict)]
    if missing:
        raise ValueError(f"{role} {path} is not a whole learn checkpoint: it has no {', '.join(missing)}")
    try:
        model, data = ModelConfig(**ckpt["model_config"]), DataConfig(**ckpt["data_config"])
    except (TypeError, ValueError) as err:
        raise ValueError(f"{role} {path}: its model or data config is not this version's ({err})") from None
    if model.frames != data.frames:
        raise ValueError(
            f"{role} {path} is inconsistent: its model reads windows of {model.frames} frames, its data config "
            f"cuts {data.frames}"
        )
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
