"""What fitting round surfaces costs a mesh import: `scenes.from_mesh` of a builder's scene as a bare mesh
(its metadata gone, as a user's file gives it) and of the same written as an OBJ, with the smooth-patch fit
(`scenes.smooth_fit`) and without it (`assemble` alone), medians over repeats in one run, and how many round
surfaces each import found.

    python benchmarks/bench_mesh_import.py --out benchmarks/results/mesh_import
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import scenes  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import write_json  # noqa: E402
from scenes.scene import assemble  # noqa: E402

SCENES = {
    "office (seed 0)": lambda: scenes.office(seed=0),
    "office (seed 1, high clutter)": lambda: scenes.office(seed=1, clutter="high"),
    "random_world (seed 3, 3 pillars)": lambda: scenes.random_world(seed=3, cylinder_count=3, wall_count=3),
}


def median_seconds(call, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=21)
    p.add_argument("--out", type=Path, required=True, help="folder for mesh_import_cpu.json and .md")
    args = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the importer's notes on assumed units: not what is timed
        for name, build in SCENES.items():
            built = build()
            bare = trimesh.Trimesh(built.mesh.vertices, built.mesh.faces, process=False)
            obj = Path(tmp) / "scene.obj"
            bare.export(obj)
            fitted = scenes.from_mesh(bare)
            rows.append(
                {
                    "scene": name,
                    "faces": len(bare.faces),
                    "builder_round_surfaces": len(built.curved),
                    "fitted_round_surfaces": len(fitted.curved),
                    "mesh_plain_ms": 1e3
                    * median_seconds(lambda b=bare: assemble([(b, "painted_wall")], name="m"), args.repeats),
                    "mesh_fitted_ms": 1e3 * median_seconds(lambda b=bare: scenes.from_mesh(b), args.repeats),
                    "obj_fitted_ms": 1e3 * median_seconds(lambda o=obj: scenes.from_mesh(o), args.repeats),
                }
            )
    args.out.mkdir(parents=True, exist_ok=True)
    stamped = write_json(args.out / "mesh_import_cpu.json", {"repeats": args.repeats, "rows": rows}, "cpu")
    lines = [
        "# Mesh import with and without the round-surface fit (CPU)",
        "",
        f"Medians of {args.repeats} imports each, one run. `assemble` alone is the import without the fit; "
        "`from_mesh` adds the frame and unit checks, the material map and the fit.",
        "",
        "| scene | faces | round (builder) | round (fitted) | assemble alone [ms] | from_mesh [ms] | "
        "from_mesh of its OBJ [ms] |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['faces']:,} | {r['builder_round_surfaces']} | {r['fitted_round_surfaces']} | "
            f"{r['mesh_plain_ms']:.2f} | {r['mesh_fitted_ms']:.2f} | {r['obj_fitted_ms']:.2f} |"
        )
    lines += ["", provenance_line(stamped["provenance"]), ""]
    (args.out / "mesh_import_cpu.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
