"""Streaming latency: one `learn.stream.Stream.step` at batch 1, as a robot runs it, the model with
memory beside the polar UNet.

    python benchmarks/bench_stream.py --device cpu --steps 20
    python benchmarks/bench_stream.py --device cuda --history 8 --stride 2

Writes benchmarks/results/stream_<cpu|cuda>.json and .md. A step is all a robot waits for between
an energyscape (R, A) in host memory and its scan back in host memory: the frame normalised and
put in the ring buffer, the window and its poses gathered, the network (bfloat16 autocast on GPUs,
as `learn predict` runs it), the scan read at the threshold, image and scan copied back. Random
weights and energyscapes on the paper grid (240 x 181) along a drive that moves and turns: speed
does not depend on either. Median and 90th percentile over `--steps` steps after `--warmup`
steps (the first, with its one-off costs, reported apart); every window already full (history
included), so each step runs the whole network.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402
from learn.data import DataConfig  # noqa: E402
from learn.models import ModelConfig, build_model, parameter_count  # noqa: E402
from learn.stream import Stream  # noqa: E402

RANGE_M = 0.21 + 0.02 * np.arange(240)  # the paper grid (learn/pretrained's): 0.21 .. 4.99 m
AZIMUTH_RAD = np.deg2rad(np.arange(-90.0, 91.0))


def bench_stream(
    model_config: ModelConfig, data: DataConfig, device: torch.device, *, steps: int, warmup: int, graphs: bool = True
) -> dict:
    """Seconds per step of a Stream of a randomly initialised `model_config` network."""
    torch.manual_seed(0)
    model = build_model(model_config).to(device).eval()
    ckpt = {
        "data_config": dataclasses.asdict(data),
        "model_config": dataclasses.asdict(model_config),
        "range_m": RANGE_M.tolist(),
        "azimuth_rad": AZIMUTH_RAD.tolist(),
        "threshold": 0.5,
    }
    stream = Stream(model, ckpt, device, graphs=graphs)
    rng = np.random.default_rng(0)
    fill = stream.capacity  # steps until every frame a window reads is there
    count = fill + warmup + steps
    frames = rng.uniform(0, 1, (count, len(RANGE_M), len(AZIMUTH_RAD))).astype(np.float32)
    t = np.arange(count) * 0.1  # [s] at 10 Hz: 0.3 m/s, turning at 0.2 rad/s
    poses = np.stack([0.3 * t * np.cos(0.1 * t), 0.3 * t * np.sin(0.1 * t), 0.2 * t], -1)
    times = []
    for k in range(count):
        t0 = time.perf_counter()
        result = stream.step(frames[k], poses[k])  # returns host arrays: the device has finished
        times.append(time.perf_counter() - t0)
        assert (result is None) == (k < data.frames - 1)
    timed = np.array(times[fill + warmup :])
    return {
        "parameters": parameter_count(model),
        "frames_read": len(data.offsets),
        "first_step_s": times[0],
        "first_prediction_s": times[data.frames - 1],
        "ms_per_step_min": 1e3 * float(timed.min()),  # the least disturbed by other work on a shared machine
        "ms_per_step_median": 1e3 * float(np.median(timed)),
        "ms_per_step_p90": 1e3 * float(np.percentile(timed, 90)),
        "steps": steps,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--steps", type=int, default=50, help="steps timed after the warm-up")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--frames", type=int, default=5, help="window length K of both models")
    parser.add_argument("--history", type=int, default=8, help="polar_memory: frames before the window")
    parser.add_argument("--stride", type=int, default=3, help="polar_memory: frames between two history frames")
    parser.add_argument("--width", type=int, default=16)
    parser.add_argument("--row-contrast", action="store_true", help="both models read row-contrast channels too")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    torch.backends.cudnn.benchmark = True  # as learn.train does on GPUs
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "CPU"
    k, extent = args.frames, (RANGE_M[0], RANGE_M[-1], AZIMUTH_RAD[0], AZIMUTH_RAD[-1])
    common = {"frames": k, "width": args.width, "row_contrast": args.row_contrast}
    arms = {
        f"polar_memory (history {args.history}, stride {args.stride})": (
            ModelConfig(name="polar_memory", history=args.history, extent=extent, **common),
            DataConfig(frames=k, history=args.history, history_stride=args.stride),
        ),
        "polar_unet": (ModelConfig(name="polar_unet", **common), DataConfig(frames=k)),
    }
    variants = ((", CUDA graph", True), (", eager", False)) if device.type == "cuda" else (("", False),)
    res = {
        "device": str(device),
        "device_name": name,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "date": time.strftime("%Y-%m-%d"),
        "grid": [len(RANGE_M), len(AZIMUTH_RAD)],
        "settings": {k: v for k, v in vars(args).items() if k not in ("device", "out")},
        "load_average_before": os.getloadavg()[0],  # other work on a shared machine slows every step
        "models": {
            f"{arm}{how}": bench_stream(m, d, device, steps=args.steps, warmup=args.warmup, graphs=graphs)
            for arm, (m, d) in arms.items()
            for how, graphs in variants
        },
        "load_average_after": os.getloadavg()[0],
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"stream_{device.type}"
    res = write_json(out / f"{stem}.json", res, device=str(device))
    lines = [
        f"# Streaming latency on {name} ({device}, torch {res['torch']}, {res['threads']} threads)",
        "",
        f"`learn.stream.Stream.step` at batch 1: energyscape in, scan out (host to host), K = {k}, width "
        f"{args.width}{', row contrast' if args.row_contrast else ''}, 240 x 181 grid"
        f"{', bfloat16 autocast' if device.type == 'cuda' else ''}, {res['date']}; median and 90th percentile "
        f"of {args.steps} steps after {args.warmup} warm-up steps (and the fastest), every window full.",
        "",
        "| model | frames read | parameters | ms per step (median) | p90 | min | first prediction [s] |",
        "|---|---|---|---|---|---|---|",
    ]
    busy = max(res["load_average_before"], res["load_average_after"]) > (os.cpu_count() or 1)
    for arm, r in res["models"].items():
        lines.append(
            f"| {arm} | {r['frames_read']} | {r['parameters']:,} | {r['ms_per_step_median']:.2f} | "
            f"{r['ms_per_step_p90']:.2f} | {r['ms_per_step_min']:.2f} | {r['first_prediction_s']:.2f} |"
        )
    lines += [
        "",
        f"Load average (1 min) of the machine: {res['load_average_before']:.1f} before, "
        f"{res['load_average_after']:.1f} after"
        + (" (above the core count: other work shared the cores)." if busy else "."),
        "",
        provenance_line(res["provenance"]),
    ]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
