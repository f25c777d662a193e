"""What a `generate` run's rendering threads spend their CPU on, from py-spy recordings.

    py-spy record --nonblocking --subprocesses --rate 100 --format raw -o spy.txt -- \\
        python -m acoustic_sim generate --suite paper --frames 80000 --workers 5 --device cuda:0 --out D
    python benchmarks/spy_rendering.py "before:spy_before.txt.gz:800" "after:spy.txt:800" > table.md

Each argument is LABEL:RECORDING:EPISODES (raw, or gzipped). A rendering thread's samples are those
whose stack runs through `run_tasks` in a worker, without the helper processes it forks (their stacks
inherit the fork's frames: a `BaseProcess._bootstrap` below it), the thread that moves energyscapes to
the host (`BatchCopies._land`) or the shard hand-over thread (`_hand_over`). Per function in FUNCTIONS:
the share of those samples whose stack holds it, and milliseconds an episode (samples / rate /
episodes). py-spy leaves idle threads out; a CUDA wait that spins counts as busy.
"""

from __future__ import annotations

import gzip
import re
import sys

FUNCTIONS = {
    "SAH trees (`wp.Mesh` built on the host)": "Mesh.__init__",
    "of which the LiDAR's own tree": "WarpScene.lidar_mesh",
    "shard into shared memory": "SharedFrames.share",
    "page-locked frees": "CpuPinnedAllocator.deallocate",
    "recorder built (a drawn sonar)": "Recorder.__init__",
    "tracer built (a drawn sonar)": "PathTracer.__init__",
    "the rig looked up (made once a physics)": "SuiteRenderer.rig",
    "ping seeds": "ping_seeds",
    "LiDAR image": "lidar_image",
    "waiting on the GPU (spinning)": "synchronize_event",
}
"""Row label -> the function (py-spy's qualified name) whose presence in a stack counts the sample."""


def rendering_samples(lines) -> tuple[int, dict[str, int]]:
    """(samples of rendering threads, samples whose stack holds each of FUNCTIONS) of raw py-spy lines."""
    total, held = 0, dict.fromkeys(FUNCTIONS.values(), 0)
    for line in lines:
        stack, _, count = line.rstrip().rpartition(" ")
        if not count.isdigit() or "run_tasks (" not in stack:
            continue
        below = stack.split("run_tasks (", 1)[1]
        if "BaseProcess._bootstrap" in below or "_land (" in below or "_hand_over (" in below:
            continue
        total += int(count)
        names = {re.sub(r" \(.*", "", frame) for frame in stack.split(";")}
        for function in held:
            held[function] += int(count) * (function in names)
    return total, held


def table(runs: list[tuple[str, str, int]], rate: float = 100.0) -> str:
    """Markdown: a column per (label, recording, episodes)."""
    rows = []
    for label, path, episodes in runs:
        with gzip.open(path, "rt") if path.endswith(".gz") else open(path) as f:
            rows.append((label, episodes, *rendering_samples(f)))
    ms = 1e3 / rate
    lines = [
        "| rendering threads' CPU samples | " + " | ".join(label for label, *_ in rows) + " |",
        "|---|" + "---|" * len(rows),
        "| all, ms an episode | " + " | ".join(f"{ms * total / n:.1f}" for _, n, total, _ in rows) + " |",
    ]
    for name, function in FUNCTIONS.items():
        cells = [f"{100 * held[function] / total:.1f} % ({ms * held[function] / n:.1f})" for _, n, total, held in rows]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    runs = []
    for spec in argv if argv is not None else sys.argv[1:]:
        label, path, episodes = spec.rsplit(":", 2)
        runs.append((label, path, int(episodes)))
    sys.stdout.write(table(runs))


if __name__ == "__main__":
    main()
