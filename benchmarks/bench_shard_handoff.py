"""What handing a full shard to a writer process costs: pickled through a pipe, or in shared memory.

    python benchmarks/bench_shard_handoff.py --out benchmarks/results/shard_handoff

A rendering process hands each full shard to a helper process that compresses and writes it
(`datasets.runner`). A `paper` shard of 250 frames gathered from three episodes is handed to one
forked helper, which joins its energyscapes as the writer does, either pickled through the pool's
pipe (before 5eac9ec) or as a `SharedFrames` file in /dev/shm (since). Medians of --repeats
rounds of --shards shards: wall time a shard and the CPU time of both processes (getrusage).
Writes DIR/shard_handoff.json and .md.
"""

from __future__ import annotations

import argparse
import itertools
import multiprocessing
import os
import resource
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acoustic_sim.datasets.shards import ShardFrames  # noqa: E402
from acoustic_sim.datasets.shared_frames import SharedFrames  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402

FRAMES, EPISODES = 250, 3
RANGE_BINS, AZIMUTHS, BEAMS = 240, 181, 1081  # the paper suite's grid and LiDAR


def paper_like_shard(seed: int = 0) -> ShardFrames:
    """A shard of the paper suite's shapes and dtypes, its frames in three episodes' arrays."""
    rng = np.random.default_rng(seed)
    cuts = np.linspace(0, FRAMES, EPISODES + 1).astype(int)
    parts = [slice(a, b) for a, b in itertools.pairwise(cuts)]
    energy = rng.random((FRAMES, 1, RANGE_BINS, AZIMUTHS), dtype=np.float32).astype(np.float16)
    image = (rng.random((FRAMES, RANGE_BINS, AZIMUTHS)) < 0.01).astype(np.uint8)
    ranges = rng.uniform(0.1, 20.0, (FRAMES, BEAMS)).astype(np.float32)
    return ShardFrames(
        energyscape=[energy[s] for s in parts],
        lidar_ranges=[ranges[s] for s in parts],
        lidar_image=[image[s] for s in parts],
        pose=[np.tile(np.eye(4), (s.stop - s.start, 1, 1)) for s in parts],
        time=[np.arange(s.stop - s.start) * 0.1 for s in parts],
        episode=[np.full(s.stop - s.start, i) for i, s in enumerate(parts)],
        scenario=[np.zeros(s.stop - s.start, np.int16) for s in parts],
    )


def receive(shard) -> int:
    """The writer's side up to its compression: the frames at hand, the energyscapes joined."""
    frames = shard.open() if isinstance(shard, SharedFrames) else shard
    parts = frames.energyscape
    joined = parts[0] if len(parts) == 1 else np.concatenate(parts)
    return int(joined.shape[0])


def cpu_seconds() -> tuple[float, float]:
    here, children = (resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return here.ru_utime + here.ru_stime, children.ru_utime + children.ru_stime


def one_round(frames: ShardFrames, mode: str, shards: int) -> dict:
    """`shards` handoffs to a fresh helper; its CPU time is known once it has exited."""
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork"))
    pool.submit(int, 0).result()  # forked and idle
    t0, (here0, there0) = time.perf_counter(), cpu_seconds()
    for _ in range(shards):
        sent = SharedFrames.share(frames) if mode == "shared" else frames
        assert pool.submit(receive, sent).result() == FRAMES
        if mode == "shared":
            sent.release()
    wall, here = time.perf_counter() - t0, cpu_seconds()[0] - here0
    pool.shutdown(wait=True)
    there = cpu_seconds()[1] - there0
    return {"wall_ms": 1e3 * wall / shards, "sender_cpu_ms": 1e3 * here / shards, "writer_cpu_ms": 1e3 * there / shards}


def markdown(res: dict) -> str:
    lines = [
        "# Handing a full shard to its writer process",
        "",
        f"A `paper`-shaped shard of {FRAMES} frames from {EPISODES} episodes (~{res['megabytes']:.0f} MB), handed to "
        f"one forked helper that joins its energyscapes; medians of {res['repeats']} rounds of {res['shards']} shards, "
        f"on {res['cpu_count']} cores.",
        "",
        "| handed | wall ms a shard | sender CPU ms | writer CPU ms | CPU ms a frame, both |",
        "|---|---|---|---|---|",
    ]
    for mode, row in res["modes"].items():
        both = (row["sender_cpu_ms"] + row["writer_cpu_ms"]) / FRAMES
        lines.append(
            f"| {mode} | {row['wall_ms']:.1f} | {row['sender_cpu_ms']:.1f} | {row['writer_cpu_ms']:.1f} | {both:.3f} |"
        )
    return "\n".join(lines) + "\n\n" + provenance_line(res["provenance"]) + "\n"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shards", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "shard_handoff"))
    args = parser.parse_args(argv)
    frames = paper_like_shard()
    rounds = {mode: [] for mode in ("pickled", "shared")}
    for _ in range(args.repeats):
        for mode in rounds:
            rounds[mode].append(one_round(frames, mode, args.shards))
    modes = {mode: {k: statistics.median(r[k] for r in runs) for k in runs[0]} for mode, runs in rounds.items()}
    megabytes = sum(a.nbytes for name in ("energyscape", "lidar_image", "lidar_ranges") for a in getattr(frames, name))
    res = {"shards": args.shards, "repeats": args.repeats, "modes": modes, "rounds": rounds}
    res |= {"megabytes": megabytes / 1e6, "cpu_count": os.cpu_count()}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = write_json(out / "shard_handoff.json", res, device="cpu")
    (out / "shard_handoff.md").write_text(markdown(res))
    print((out / "shard_handoff.md").read_text())
    return res


if __name__ == "__main__":
    main()
