"""Learner speed: training windows/s and inference time per frame, the paper network beside ours.

    python benchmarks/bench_learn.py --device cpu
    python benchmarks/bench_learn.py --device cuda
    python benchmarks/bench_learn.py --device cuda --ddp   # DDP scaling over the host's GPUs

Writes benchmarks/results/learn_<cpu|cuda>.json and .md. Random weights and inputs on the full
grid (K = 5, 240 x 181): speed does not depend on the weights. Training: Adam steps at batch 12
(bfloat16 autocast on GPUs, as `learn train` does); inference: batch 1 (per frame, as on a
robot) and batch 32. Medians after warm-up steps. `--ddp` instead times DDP training of polar_unet
and the paper network on 1, 2, 4, ... GPUs (torchrun jobs in one run; gloo processes on the CPU) and writes
learn_ddp_<cpu|cuda>.json and .md with the scaling efficiency beside the one-GPU figure.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402
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


def ddp_worker(args) -> None:
    """One rank under torchrun: DDP training steps of `--ddp-model` at `--batch` windows per GPU
    (NCCL on GPUs, gloo on the CPU), as `learn train` runs them; rank 0 writes the rate to
    --worker-out."""
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel

    cuda = args.device.startswith("cuda")
    dist.init_process_group("nccl" if cuda else "gloo")
    rank, world, local = dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", 0))
    device = torch.device(f"cuda:{local}" if cuda else "cpu")
    if cuda:
        torch.cuda.set_device(device)
        torch.backends.cudnn.benchmark = True
    torch.manual_seed(0)  # the same initial weights on every rank, as DDP expects
    model = DistributedDataParallel(
        build_model(ModelConfig(name=args.ddp_model, frames=5)).to(device), device_ids=[local] if cuda else None
    )
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(rank)  # each rank its own windows
    x = torch.rand(args.batch, 1, 5, 240, 181, generator=generator).to(device)
    y = (torch.rand(args.batch, 1, 240, 181, generator=generator) > 0.995).float().to(device)

    def step():
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=cuda):
            out = model(x)
        loss = F.binary_cross_entropy_with_logits(out.float(), y)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()  # the gradient all-reduce across ranks happens here
        optimizer.step()

    sync = (lambda: torch.cuda.synchronize(device)) if cuda else (lambda: None)
    seconds = _timed(step, args.repeats, args.warmup, sync)
    if rank == 0:
        rate = {"gpus" if cuda else "processes": world, "windows_per_s": world * args.batch / seconds}
        rate |= {"batch_per_rank": args.batch, "s_per_step": seconds}
        Path(args.worker_out).write_text(json.dumps(rate))  # not a result: rank 0's rate, for the parent to read
    dist.destroy_process_group()


DDP_MODELS = ("polar_unet", "paper")


def bench_ddp(args, device: torch.device, name: str) -> dict:
    """Windows/s of DDP training of each of DDP_MODELS on 1, 2, 4, ... GPUs of this host (or 1 and 2
    gloo processes on the CPU), each a torchrun job in this one run, and the scaling efficiency
    rate_N / (N x rate_1)."""
    import subprocess
    import tempfile

    most = torch.cuda.device_count() if device.type == "cuda" else 2
    counts = [n for n in (1, 2, 4, 8) if n <= most]
    models = {}
    with tempfile.TemporaryDirectory() as tmp:
        for model in DDP_MODELS:
            runs = models[model] = []
            for n in counts:
                out = Path(tmp) / f"{model}_{n}.json"
                command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(n)]
                command += [__file__, "--ddp-worker", "--ddp-model", model, "--device", str(device.type)]
                command += ["--batch", str(args.batch), "--repeats", str(args.repeats), "--warmup", str(args.warmup)]
                command += ["--worker-out", str(out)]
                done = subprocess.run(command, capture_output=True, text=True)
                if done.returncode != 0:
                    raise RuntimeError(f"torchrun with {n} ranks failed ({model}):\n{done.stderr[-3000:]}")
                runs.append(json.loads(out.read_text()))
                print(f"{model}, {n} rank(s): {runs[-1]['windows_per_s']:,.1f} windows/s", flush=True)
            one = runs[0]["windows_per_s"]
            for n, r in zip(counts, runs, strict=True):
                r["efficiency"] = r["windows_per_s"] / (n * one)
    res = {"device_name": name, "torch": torch.__version__, "date": time.strftime("%Y-%m-%d"), "models": models}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"learn_ddp_{device.type}"
    res = write_json(out / f"{stem}.json", res, device=str(device))
    unit = "GPUs" if device.type == "cuda" else "gloo processes"
    lines = [
        f"# DDP training speed on {name} ({unit}, torch {res['torch']}, {res['date']})",
        "",
        f"K = 5, 240 x 181, Adam at {args.batch} windows per rank"
        f"{', bfloat16 autocast, NCCL' if device.type == 'cuda' else ', gloo'}; medians of {args.repeats} steps, "
        "each model and rank count a torchrun job in the same run.",
        "",
        f"| model | {unit} | training windows/s | efficiency (rate / (N x one)) |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {model} | {n} | {r['windows_per_s']:,.1f} | {r['efficiency']:.0%} |"
        for model, runs in models.items()
        for n, r in zip(counts, runs, strict=True)
    ]
    lines += ["", provenance_line(res["provenance"])]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


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
    parser.add_argument("--ddp", action="store_true", help="DDP scaling over this host's GPUs instead (torchrun)")
    parser.add_argument("--ddp-worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--ddp-model", default="polar_unet", help=argparse.SUPPRESS)
    parser.add_argument("--worker-out", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.ddp_worker:
        return ddp_worker(args)
    device = torch.device(args.device)
    torch.backends.cudnn.benchmark = True  # as learn.train does on GPUs
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "CPU"
    if args.ddp:
        return bench_ddp(args, device, name)
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
    res = write_json(out / f"{stem}.json", res, device=str(device))
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
    lines += ["", provenance_line(res["provenance"])]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
