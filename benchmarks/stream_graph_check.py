"""On a GPU: a Stream replaying CUDA graphs gives the images and scans the eager Stream gives, step
by step along a drive (the graph is captured once and fed by copies: a stale input would show).

    python benchmarks/stream_graph_check.py --device cuda
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_stream import AZIMUTH_RAD, RANGE_M  # noqa: E402
from learn.data import DataConfig  # noqa: E402
from learn.models import ModelConfig, build_model  # noqa: E402
from learn.stream import Stream  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--device", default="cuda")
    args = p.parse_args()
    extent = (RANGE_M[0], RANGE_M[-1], AZIMUTH_RAD[0], AZIMUTH_RAD[-1])
    torch.manual_seed(0)
    config, data = ModelConfig(name="polar_memory", history=8, extent=extent), DataConfig(history=8, history_stride=3)
    model = build_model(config).to(args.device).eval()
    for m in model.modules():  # He weights: at the prior bias every image is near the same
        if isinstance(m, torch.nn.Conv2d):
            torch.nn.init.kaiming_normal_(m.weight)
    ckpt = {
        "data_config": dataclasses.asdict(data),
        "model_config": dataclasses.asdict(config),
        "range_m": RANGE_M.tolist(),
        "azimuth_rad": AZIMUTH_RAD.tolist(),
        "threshold": 0.5,
    }
    graphed, eager = Stream(model, ckpt, args.device), Stream(model, ckpt, args.device, graphs=False)
    rng, worst, steps, differing = np.random.default_rng(0), 0.0, 40, []
    for k in range(steps):
        frame = rng.uniform(0, 1, (len(RANGE_M), len(AZIMUTH_RAD))).astype(np.float32)
        pose = (0.03 * k, 0.01 * k, 0.02 * k)
        a, b = graphed.step(frame, pose), eager.step(frame, pose)
        if a is None:
            assert b is None
            continue
        worst = max(worst, float(np.abs(a.image.astype(np.float32) - b.image.astype(np.float32)).max()))
        differing.append(float(np.mean(a.ranges != b.ranges)))
    share = max(differing)
    print(
        f"CUDA graph stream against the eager one over {steps} steps: largest image difference {worst:.2e}, "
        f"at most {share:.1%} of a scan's beams differ"
    )
    assert worst < 1e-2 and share < 0.01


if __name__ == "__main__":
    main()
