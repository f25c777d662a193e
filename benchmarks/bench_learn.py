"""Learner speed: training windows/s and inference time per frame, the paper network beside ours.

    python benchmarks/bench_learn.py --device cpu
    python benchmarks/bench_learn.py --device cuda

Writes benchmarks/results/learn_<cpu|cuda>.json and .md. Random weights and inputs on the full
grid (K = 5, 240 x 181): speed does not depend on the weights. Training: Adam steps at batch 12
(bfloat16 autocast on GPUs, as `learn train` does); inference: batch 1 (per frame, as on a
robot) and batch 32. Medians after warm-up steps.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from learn.models import ModelConfig, build_model, parameter_count, predict_image  # noqa: E402


def _timed(fn, repeats: int, warmup: int, sync) -> float:
    times = []
    for i in range(warmup + repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        if i >= warmup:
            times.append(time.perf_counter() - t0)
    return float(np.median(times))


def bench_model(
    name: str,
    device: torch.device,
    *,
    repeats: int,
    batch: int = 12,
    warmup: int = 2,
    channels_last: bool = False,
    cuda_graphs: bool = False,
) -> dict:
    torch.manual_seed(0)
    model = build_model(ModelConfig(name=name, frames=5)).to(device)
    layout = torch.channels_last_3d if name == "paper" else torch.channels_last
    if channels_last:  # the layout tensor cores read without transposes
        model = model.to(memory_format=layout)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    amp = device.type == "cuda"
    x = torch.rand(batch, 1, 5, 240, 181, device=device)
    if channels_last and name == "paper":
        x = x.contiguous(memory_format=layout)
    y = (torch.rand(batch, 1, 240, 181, device=device) > 0.995).float()

    stepper = torch.compile(model, mode="reduce-overhead") if cuda_graphs else model  # as train.cuda_graphs

    def step():
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp):
            out = stepper(x)
        loss = F.mse_loss(out.float(), y)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    model.train()
    train_s = _timed(step, repeats, warmup + (3 if cuda_graphs else 0), sync)  # graphs: compile, record, replay
    model.eval()

    def infer(inp):
        with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp):
            predict_image(model, inp)

    one = _timed(lambda: infer(x[:1]), repeats, warmup, sync)
    many_x = torch.rand(32, 1, 5, 240, 181, device=device)
    many = _timed(lambda: infer(many_x), max(1, repeats // 2), 1, sync)
    return {
        "parameters": parameter_count(model),
        "train_windows_per_s": batch / train_s,
        "ms_per_frame_batch1": 1e3 * one,
        "frames_per_s_batch32": 32 / many,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--batch", type=int, default=12, help="training batch (the paper's 12; less on a slow CPU)")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    parser.add_argument(
        "--channels-last", action="store_true", help="also time the paper network in channels-last layout"
    )
    parser.add_argument(
        "--cuda-graphs", action="store_true", help="also time polar_unet's training steps as CUDA graphs"
    )
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    torch.backends.cudnn.benchmark = True  # as learn.train does on GPUs
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "CPU"
    res = {
        "device": str(device),
        "device_name": name,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "date": time.strftime("%Y-%m-%d"),
        "models": {
            m: bench_model(m, device, repeats=args.repeats, batch=args.batch, warmup=args.warmup)
            for m in ("paper", "polar_unet")
        },
    }
    if args.channels_last:
        res["models"]["paper_channels_last"] = bench_model(
            "paper", device, repeats=args.repeats, batch=args.batch, warmup=args.warmup, channels_last=True
        )
    if args.cuda_graphs:
        res["models"]["polar_unet_cuda_graphs"] = bench_model(
            "polar_unet", device, repeats=args.repeats, batch=args.batch, warmup=args.warmup, cuda_graphs=True
        )
    paper, ours = res["models"]["paper"], res["models"]["polar_unet"]
    res["train_speedup"] = ours["train_windows_per_s"] / paper["train_windows_per_s"]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"learn_{device.type}"
    (out / f"{stem}.json").write_text(json.dumps(res, indent=1))
    lines = [
        f"# Learner speed on {name} ({device}, torch {res['torch']}, {res['threads']} threads)",
        "",
        f"K = 5, 240 x 181 grid, {res['date']}; medians of {args.repeats}. Training: Adam at batch {args.batch}"
        f"{' with bfloat16 autocast' if device.type == 'cuda' else ''}.",
        "",
        "| model | parameters | training windows/s | inference ms/frame (batch 1) | inference frames/s (batch 32) |",
        "|---|---|---|---|---|",
    ]
    for m, r in res["models"].items():
        lines.append(
            f"| {m} | {r['parameters']:,} | {r['train_windows_per_s']:,.1f} | {r['ms_per_frame_batch1']:.2f} | "
            f"{r['frames_per_s_batch32']:,.1f} |"
        )
    lines += ["", f"polar_unet trains **{res['train_speedup']:.1f}x** as many windows per second as the paper network."]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
