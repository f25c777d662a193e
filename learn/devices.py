"""Which device torch runs on: a name checked against this machine, its GPU made current."""

from __future__ import annotations

import torch


def torch_device(name: str | torch.device) -> torch.device:
    """The torch device `name` ("cpu", "cuda", "cuda:1", ...), refused with a clear message when this
    machine cannot provide it (torch's own errors name a deserialiser or a driver call instead).
    A GPU named by index becomes this process's current one: nine study runs spread over two GPUs
    each opened a ~0.5 GB context on cuda:0 otherwise (benchmarks/results/multi_gpu/session30)."""
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"device {name!r} is not a torch device: use cpu, cuda or cuda:i") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            built = f"CUDA {torch.version.cuda}" if torch.version.cuda else "no CUDA"
            raise ValueError(
                f"device {name!r}: no CUDA GPU is usable here (torch {torch.__version__}, {built}); use cpu"
            )
        if device.index is not None and device.index >= count:
            raise ValueError(f"device {name!r}: this machine has {count} CUDA GPU(s), cuda:0..cuda:{count - 1}")
        if device.index is not None:  # what torch does without naming a GPU then stays on this one
            torch.cuda.set_device(device)
    elif device.type != "cpu":
        raise ValueError(f"device {name!r} is not supported: use cpu, cuda or cuda:i")
    return device
