"""Where one generation episode's time goes on a GPU: host preparation, rendering, GPU time per kernel.

    python benchmarks/profile_episode.py --device cuda:0 --suite paper

Generation renders one episode (a drive of `episode_frames` frames, 100 in the paper suite) per
`Sonar.simulate` call, so per-episode costs that a long benchmark drive hides show here: this
prepares --episodes episodes of the suite's plan on the host (`SuiteRenderer.prepare`: scene, drive,
draws), builds their device scenes, renders them one after another (LiDAR and sonar, as a worker
does), then renders ten of them again under Warp's CUDA activity timing for the GPU-busy time and
the kernels' share. With --host-profile N the timed renders run under cProfile and the N functions
with the most own time in the rendering thread are printed: the host work that leaves a GPU
idle unless another process has work queued on it (waits for the GPU show as Warp's synchronize
calls and copies to the host). Prints its figures (an experiment's readout, not a tracked result).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
import warnings
from collections import defaultdict
from pathlib import Path

import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acoustic_sim.datasets.generate import SuiteRenderer  # noqa: E402
from acoustic_sim.datasets.plan import plan  # noqa: E402
from acoustic_sim.datasets.suites import load_suite  # noqa: E402
from acoustic_sim.engine import scene as scene_module  # noqa: E402

# Functions whose own time is the rendering thread waiting (for the GPU, a helper thread, a lock)
WAITS = ("synchronize", "acquire", "wait")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--suite", default="paper")
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--host-profile", type=int, default=0, metavar="N", help="print the N costliest functions")
    args = parser.parse_args(argv)
    wp.config.quiet = True
    warnings.simplefilter("ignore")  # the suite's scenes say what they leave out
    suite = load_suite(args.suite)
    with tempfile.TemporaryDirectory() as folder:
        tasks = plan(suite, folder, frames=args.episodes * suite.episode_frames)
    renderer = SuiteRenderer({})
    jobs = [(t, e) for t in tasks for e in t.episodes][: args.episodes]
    t0 = time.perf_counter()
    prepared = [renderer.prepare(t, e) for t, e in jobs]
    print(f"prepare: {1e3 * (time.perf_counter() - t0) / len(jobs):.1f} ms an episode (host, one thread)")
    renderer.render(jobs[0][0], prepared[0], device=args.device, on_frames=None, seconds={})  # kernels loaded
    t0 = time.perf_counter()
    for p in prepared[1:11]:
        scene_module.warp_scene(p.scene, args.device)
    wp.synchronize_device(args.device)
    print(f"device scene: {1e3 * (time.perf_counter() - t0) / 10:.1f} ms an episode")
    seconds: dict[str, float] = defaultdict(float)
    profile = cProfile.Profile() if args.host_profile else None
    t0 = time.perf_counter()
    for (task, _), p in zip(jobs[11:], prepared[11:], strict=True):
        if profile:
            profile.enable()
        renderer.render(task, p, device=args.device, on_frames=None, seconds=seconds)
        if profile:
            profile.disable()
    wp.synchronize_device(args.device)
    n = len(jobs) - 11
    parts = ", ".join(f"{k} {1e3 * v / n:.1f}" for k, v in seconds.items())
    print(f"render: {1e3 * (time.perf_counter() - t0) / n:.1f} ms an episode ({parts})")
    if profile:
        stats = pstats.Stats(profile, stream=sys.stdout)
        busy = sum(row[2] for key, row in stats.stats.items() if not any(w in key[2] for w in WAITS))
        print(f"host profile of those {n} renders: {1e3 * busy / n:.1f} ms an episode outside waits")
        stats.sort_stats("tottime").print_stats(args.host_profile)
        stats.sort_stats("cumulative").print_stats(args.host_profile)
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    t0 = time.perf_counter()
    for (task, _), p in zip(jobs[1:11], prepared[1:11], strict=True):
        renderer.render(task, p, device=args.device, on_frames=None, seconds={})
    wp.synchronize_device(args.device)
    wall = time.perf_counter() - t0
    by_kernel = defaultdict(float)
    for record in wp.timing_end():
        by_kernel[record.name.removeprefix("forward kernel ")] += record.elapsed
    print(
        f"10 episodes again: {1e3 * wall / 10:.1f} ms wall, {sum(by_kernel.values()) / 10:.1f} ms GPU busy an episode"
    )
    for name, ms in sorted(by_kernel.items(), key=lambda kv: -kv[1])[:16]:
        print(f"  {name}: {ms / 10:.2f} ms an episode")


if __name__ == "__main__":
    main()
