"""`learn train --tensorboard`: each epoch's numbers and a few validation windows as pictures,
under RUN/tensorboard (open with `tensorboard --logdir RUN`). TensorBoard is an optional extra.

Scalars are the epoch's history row, grouped as train/..., val/... and speed/... (flushed every
epoch, so a run that stops early keeps what it logged); each picture is
one validation window: the sonar frame of the label | the LiDAR label | the prediction, range upwards.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from . import MissingExtra

EXAMPLES = 3
"""Validation windows shown each epoch (the same ones, spread over the validation set)."""


SPEED = ("samples_per_s", "train_seconds")  # history columns about speed, not learning


def summary_writer():
    """torch's SummaryWriter class; it needs the tensorboard package (the optional extra)."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        raise MissingExtra("--tensorboard needs TensorBoard: pip install 'sonar2lidar[tensorboard]'") from None
    return SummaryWriter


class TensorBoardLog:
    def __init__(self, out: Path, val_indices: np.ndarray):
        self.writer = summary_writer()(str(Path(out) / "tensorboard"))
        picks = np.linspace(0, len(val_indices) - 1, min(EXAMPLES, len(val_indices))).round().astype(int)
        self.examples = np.asarray(val_indices)[np.unique(picks)]

    def epoch(self, row: dict, predict, windows) -> None:
        """Log one epoch's history row and the examples as `predict` (x -> image in [0, 1]) sees them."""
        step = row["epoch"]
        for key, value in row.items():
            if key in ("epoch", "step"):
                continue
            group, name = ("speed", key) if key in SPEED else key.split("_", 1)  # train_loss, val_...
            self.writer.add_scalar(f"{group}/{name}", value, step)
        with torch.no_grad():
            x, y = windows.batch(self.examples)
            pred = predict(x).float().clamp(0, 1)
        for i, index in enumerate(self.examples):
            panels = [x[i, 0, windows.config.label_offset], y[i, 0], pred[i, 0]]  # input as the model reads it
            picture = torch.cat([p.float().cpu() for p in panels], dim=1).flip(0)  # near range at the bottom
            self.writer.add_image(f"examples/window_{int(index)}", picture[None], step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()
