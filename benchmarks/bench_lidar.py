"""LiDAR throughput on the reference office (85k triangles), with ray-casting peers in the same run.

    python benchmarks/bench_lidar.py --device cpu
    python benchmarks/bench_lidar.py --device cuda:0 --bare ~/bench/bare_warp_bench.py

Writes benchmarks/results/lidar_<cpu|cuda>.json and .md. Times are medians over repeats after a
first call that is reported apart (kernel compile or cache load, BVH build). "device-resident"
means results left on the device (what a GPU pipeline consumes); "to host" adds the copy to numpy.
Peers get exactly the same rays: Open3D's RaycastingScene (Embree, all CPU threads) and embreex
(Embree through Cython, one thread), whichever is installed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

import acoustic_sim as sim
import scenes

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402

SCENE_CANDIDATES = [
    os.environ.get("OFFICE_85K", ""),
    str(ROOT.parent / "shared" / "bench" / "office_85k.npz"),
    str(Path.home() / "bench" / "office_85k.npz"),
]


def load_office() -> scenes.Scene:
    for path in SCENE_CANDIDATES:
        if path and Path(path).exists():
            data = np.load(path)
            import trimesh

            mesh = trimesh.Trimesh(data["vertices"], data["faces"], process=False)
            return scenes.from_mesh(mesh, name="office_85k")
    raise SystemExit(f"office_85k.npz not found; set OFFICE_85K or place it at one of {SCENE_CANDIDATES[1:]}")


def random_poses(count: int, seed: int) -> np.ndarray:
    """Sensors at 0.3 m height, uniformly over the 10 x 8 m office (1 m from the walls), any yaw."""
    rng = np.random.default_rng(seed)
    xy = np.c_[rng.uniform(1, 9, count), rng.uniform(1, 7, count)]
    return scenes.poses(xy, rng.uniform(-np.pi, np.pi, count), 0.3)


def median_time(fn, repeats: int, device) -> tuple[float, float]:
    """(first call [s], median of `repeats` later calls [s]), synchronising the device each time."""
    times = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return times[0], float(np.median(times[1:]))


def rays_for(poses: np.ndarray, config: sim.LidarConfig) -> tuple[np.ndarray, np.ndarray]:
    dirs = np.einsum("nij,bj->nbi", poses[:, :3, :3], config.beam_directions()).reshape(-1, 3)
    origins = np.repeat(poses[:, :3, 3], config.beam_count, axis=0)
    return origins.astype(np.float32), dirs.astype(np.float32)


def peer_open3d(scene: scenes.Scene, origins, dirs, repeats: int) -> dict | None:
    try:
        import open3d as o3d
    except Exception:  # not installed, or missing libusb
        return None
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(
        o3d.core.Tensor(scene.mesh.vertices.astype(np.float32)), o3d.core.Tensor(scene.mesh.faces.astype(np.uint32))
    )
    rays = o3d.core.Tensor(np.concatenate([origins, dirs], axis=1))
    times, t_hit = [], None
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        t_hit = rc.cast_rays(rays)["t_hit"].numpy()
        times.append(time.perf_counter() - t0)
    dt = float(np.median(times[1:]))
    return {
        "name": "Open3D RaycastingScene",
        "threads": os.cpu_count(),
        "rays": len(origins),
        "s": dt,
        "mrays_per_s": len(origins) / dt / 1e6,
        "t": t_hit,
    }


def peer_embreex(scene: scenes.Scene, origins, dirs, repeats: int) -> dict | None:
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except Exception:
        return None
    es = rtcore_scene.EmbreeScene()
    TriangleMesh(es, scene.mesh.triangles.astype(np.float32))
    times, t = [], None
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        out = es.run(origins, dirs, output=1)
        times.append(time.perf_counter() - t0)
        t = np.where(out["geomID"] >= 0, out["tfar"], np.inf)
    dt = float(np.median(times[1:]))
    return {
        "name": "embreex (Embree)",
        "threads": 1,
        "rays": len(origins),
        "s": dt,
        "mrays_per_s": len(origins) / dt / 1e6,
        "t": t,
    }


def bench_scan(lidar: sim.Lidar, scene, poses, repeats: int, peer_rays: int, peer_repeats: int) -> dict:
    cast_first, cast_s = median_time(lambda: lidar.cast(scene, poses), repeats, lidar.device)
    _, scan_s = median_time(lambda: lidar.scan(scene, poses), max(1, repeats // 2), lidar.device)
    rays = len(poses) * lidar.beam_count
    ours = lidar.scan(scene, poses).ravel()
    result = {
        "poses": len(poses),
        "beams": lidar.beam_count,
        "rays": rays,
        "first_call_s": cast_first,
        "device_resident_s": cast_s,
        "mrays_per_s": rays / cast_s / 1e6,
        "to_host_s": scan_s,
        "mrays_per_s_to_host": rays / scan_s / 1e6,
        "hit_fraction": float(np.isfinite(ours).mean()),
        "peers": [],
    }
    if lidar.device.is_cpu:  # the same scan with one launch thread: what the threads add
        single = sim.Lidar(lidar.config, device=lidar.device, cpu_threads=1)
        _, single_s = median_time(lambda: single.cast(scene, poses), repeats, lidar.device)
        result |= {"cpu_threads": lidar.cpu_threads, "mrays_per_s_one_thread": rays / single_s / 1e6}
        result["threads_speedup"] = result["mrays_per_s"] / result["mrays_per_s_one_thread"]
    # Peers on the first `peer_rays` rays (CPU peers are slow on a full GPU-sized batch).
    n_poses = max(1, peer_rays // lidar.beam_count)
    origins, dirs = rays_for(poses[:n_poses], lidar.config)
    ref_ours = ours[: len(origins)]
    for peer in (peer_open3d, peer_embreex):
        found = peer(scene, origins, dirs, peer_repeats)
        if found is None:
            continue
        t = found.pop("t")
        t = np.where((t >= lidar.config.range_min_m) & (t <= lidar.config.range_max_m), t, np.inf)
        both = np.isfinite(t) & np.isfinite(ref_ours)
        found["hit_miss_agreement"] = float((np.isfinite(t) == np.isfinite(ref_ours)).mean())
        diff = np.abs(t[both] - ref_ours[both])
        found["max_abs_range_diff_m"] = float(diff.max())
        found["rays_off_by_more_than_1e-4_m"] = int((diff > 1e-4).sum())
        worst = np.flatnonzero(both)[np.argsort(diff)[::-1][:3]]
        found["worst_rays"] = [
            {
                "origin": origins[i].tolist(),
                "dir": dirs[i].tolist(),
                "ours_m": float(ref_ours[i]),
                "peer_m": float(t[i]),
            }
            for i in worst
        ]
        found["ours_over_peer"] = result["mrays_per_s"] / found["mrays_per_s"]
        result["peers"].append(found)
    return result


def run_bare(path: str, device: str) -> dict | None:
    done = subprocess.run([sys.executable, path, device], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        print(done.stderr[-2000:], file=sys.stderr)
        return None
    return json.loads(done.stdout[done.stdout.index("{") :])


def to_markdown(res: dict) -> str:
    lines = [
        f"# LiDAR throughput on {res['device_name']} ({res['device']})",
        "",
        f"Scene: reference office, {res['triangles']:,} triangles; warp {res['warp']}; "
        f"BVH build {1e3 * res['bvh_build_s']:.1f} ms; {res['date']}. Medians of {res['repeats']} runs.",
        "",
        "| scan | rays per launch | first call [s] | ours, device-resident [M rays/s] | ours, to host "
        "[M rays/s] | peer | peer [M rays/s] | ours / peer |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, label in (("lidar2d", "2D 1081 beams"), ("lidar3d", "3D 64x1024")):
        r = res[key]
        peers = r["peers"] or [
            {"name": "none installed", "mrays_per_s": float("nan"), "ours_over_peer": float("nan"), "threads": 0}
        ]
        for p in peers:
            threads = f"{p['threads']} thread" + ("s" if p["threads"] != 1 else "")
            lines.append(
                f"| {label} | {r['rays']:,} | {r['first_call_s']:.2f} | {r['mrays_per_s']:,.1f} | "
                f"{r['mrays_per_s_to_host']:,.1f} | {p['name']} ({threads}) | "
                f"{p['mrays_per_s']:,.1f} | {p['ours_over_peer']:,.1f}x |"
            )
    if "threads_speedup" in res["lidar2d"]:
        lines += [
            "",
            "Our CPU launches split over threads by pose (`Lidar(cpu_threads=...)`, default: every core this "
            "process may use), against one launch thread in the same run:",
            "",
            "| scan | threads | ours [M rays/s] | ours, 1 thread [M rays/s] | speed-up |",
            "|---|---|---|---|---|",
        ]
        for key in ("lidar2d", "lidar3d"):
            r = res[key]
            lines.append(
                f"| {key} | {r['cpu_threads']} | {r['mrays_per_s']:,.2f} | {r['mrays_per_s_one_thread']:,.2f} | "
                f"{r['threads_speedup']:.2f}x |"
            )
    bare = res.get("bare")
    if bare:
        lines += [
            "",
            "Bare Warp kernel (../shared/bench/bare_warp_bench.py) in the same run:",
            "",
            "| scan | bare [M rays/s] | ours [M rays/s] | ours / bare |",
            "|---|---|---|---|",
        ]
        for key, bkey in (("lidar2d", "lidar2d_1081"), ("lidar3d", "lidar3d_64x1024")):
            b = bare[bkey]["Mrays_per_s"]
            lines.append(f"| {key} | {b:,.0f} | {res[key]['mrays_per_s']:,.0f} | {res[key]['mrays_per_s'] / b:.2f} |")
    lines += [
        "",
        "Agreement with the peers on the rays they cast (hit/miss; max range difference; rays off by "
        "more than 0.1 mm):",
        "",
    ]
    lines += [
        f"- {key} vs {p['name']}: {100 * p['hit_miss_agreement']:.4f} %; {p['max_abs_range_diff_m']:.1e} m; "
        f"{p['rays_off_by_more_than_1e-4_m']} of {p['rays']:,}"
        for key in ("lidar2d", "lidar3d")
        for p in res[key]["peers"]
    ]
    if "provenance" in res:
        lines += ["", provenance_line(res["provenance"])]
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--poses-2d", type=int, default=20_000, help="as in bare_warp_bench.py")
    parser.add_argument("--poses-3d", type=int, default=None, help="default: 300 on CUDA, 30 on CPU")
    parser.add_argument("--repeats", type=int, default=None, help="default: 20 on CUDA, 5 on CPU")
    parser.add_argument("--peer-rays", type=int, default=2_000_000, help="rays given to each CPU peer")
    parser.add_argument("--bare", default=None, help="path of bare_warp_bench.py to run in the same job")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args(argv)

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    device = wp.get_device(args.device)
    cuda = device.is_cuda
    repeats = args.repeats or (20 if cuda else 5)
    scene = load_office()
    t0 = time.perf_counter()
    sim.warp_scene(scene, device)
    wp.synchronize_device(device)
    res = {
        "device": str(device),
        "device_name": device.name if cuda else platform.processor() or "CPU",
        "warp": wp.__version__,
        "triangles": scene.face_count,
        "bvh_build_s": time.perf_counter() - t0,
        "repeats": repeats,
        "date": time.strftime("%Y-%m-%d"),
        "cpu_count": os.cpu_count(),
    }
    print(f"device {res['device']} ({res['device_name']}), {scene.face_count} triangles", flush=True)
    lidar2d = sim.Lidar(sim.LidarConfig.hokuyo_ust20lx(range_min_m=0.0, range_max_m=30.0), device=device)
    res["lidar2d"] = bench_scan(lidar2d, scene, random_poses(args.poses_2d, 1), repeats, args.peer_rays, 3)
    print(f"2D: {res['lidar2d']['mrays_per_s']:,.1f} M rays/s", flush=True)
    lidar3d = sim.Lidar(sim.LidarConfig.multibeam_64x1024(range_min_m=0.0, range_max_m=30.0), device=device)
    poses3d = args.poses_3d or (300 if cuda else 30)
    res["lidar3d"] = bench_scan(lidar3d, scene, random_poses(poses3d, 2), repeats, args.peer_rays, 3)
    print(f"3D: {res['lidar3d']['mrays_per_s']:,.1f} M rays/s", flush=True)
    if args.bare:
        res["bare"] = run_bare(args.bare, str(device))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"lidar_{'cuda' if cuda else 'cpu'}"
    res = write_json(out / f"{stem}.json", res, device=str(device))
    (out / f"{stem}.md").write_text(to_markdown(res))
    print(to_markdown(res))
    return res


if __name__ == "__main__":
    main()
