"""Sonar-to-LiDAR learning (PyTorch). Reads dataset shards only; never imports warp.

`learn.config` (LearnConfig, the root of the settings: model, data, augment, train),
`learn.data` (windows of K energyscapes), `learn.models` (the paper's network, our polar UNet),
`learn.train`, `learn.metrics` (the scan metric first), `learn.evaluate`, `learn.predict`,
`learn.export`, `learn.studies`; `python -m learn --help` for the command line.
"""

from pathlib import Path

PRETRAINED_CHECKPOINT = Path(__file__).parent / "pretrained" / "polar_unet_k5.pt"
"""Our polar UNet (K = 5) trained on the H100 by benchmarks/learner_converged.sh (seed 0), with its
calibrated return threshold; load it with `learn.checkpoint.load_checkpoint`."""


class MissingExtra(ImportError):
    """An optional extra (onnx, ros, tensorboard) is not installed; the message names what to
    install. `python -m learn` shows it as one `error:` line; any other ImportError keeps its trace."""
