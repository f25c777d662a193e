"""How far two datasets of the same plan differ: one made by the code before a change, one after.

    python benchmarks/dataset_before_after.py BEFORE AFTER --out benchmarks/results/NAME

For every shard of the two folders (matched by name) and every array in it: whether it is the same
bits, and for the ones that are not, by how much. Energyscapes: the largest difference over the
frame's peak (each frame is normalised by its own peak before training); LiDAR ranges: the beams
whose return changed (hit or miss, or range by more than 1 mm) and the largest change; every other
array: the count of differing elements. Writes before_after.json and .md under --out.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import relative, write_json  # noqa: E402
from benchmarks.same_shards import arrays  # noqa: E402


def compare(name: str, a: np.ndarray, b: np.ndarray) -> dict:
    """One array's difference, as the module docstring says."""
    if a.shape != b.shape:
        return {"same": False, "shape": [list(a.shape), list(b.shape)]}
    out = {"same": bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f")), "elements": int(a.size)}
    if out["same"]:
        return out
    if name.endswith("/energyscape"):
        a64, b64 = a.astype(np.float64), b.astype(np.float64)
        peak = np.abs(a64).reshape(len(a64), -1).max(axis=1)
        diff = np.abs(a64 - b64).reshape(len(a64), -1).max(axis=1)
        out["max_difference_over_frame_peak"] = float((diff / np.maximum(peak, 1e-30)).max())
        out["frames_differing"] = int((diff > 0).sum())
    elif name.endswith("lidar/ranges"):
        hit_a, hit_b = np.isfinite(a), np.isfinite(b)
        both = hit_a & hit_b
        moved = np.abs(a[both].astype(np.float64) - b[both]) > 1e-3
        out["beams_hit_or_miss_changed"] = int((hit_a != hit_b).sum())
        out["beams_moved_over_1mm"] = int(moved.sum())
        out["largest_range_change_m"] = float(np.abs(a[both].astype(np.float64) - b[both]).max(initial=0.0))
    else:
        out["elements_differing"] = int((a != b).sum())
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("before")
    parser.add_argument("after")
    parser.add_argument("--out", required=True)
    parser.add_argument("--device", default=None, help="the device both datasets were made on (for the record)")
    args = parser.parse_args(argv)
    a, b = arrays(args.before), arrays(args.after)
    if not a or a.keys() != b.keys():
        raise SystemExit(f"the folders hold different shards or arrays: {sorted(a.keys() ^ b.keys())[:5]}")
    rows = {name: compare(name, a[name], b[name]) for name in sorted(a)}
    with h5py.File(next(Path(args.after).glob("shard-*.h5"))) as f:
        made_on = str(f.attrs.get("device", "?"))
    res = {"before": relative(args.before), "after": relative(args.after), "made_on": made_on, "arrays": rows}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = write_json(out / "before_after.json", res, device=args.device)
    kinds: dict[str, list[dict]] = {}
    for name, row in rows.items():
        kinds.setdefault(name.split("/", 1)[1], []).append(row)
    lines = [
        f"# The dataset before and after: {res['before']} against {res['after']} (made on {made_on})",
        "",
        "| array | shards identical | what differs |",
        "|---|---|---|",
    ]
    for kind, found in kinds.items():
        same = sum(r["same"] for r in found)
        notes = []
        for key in (
            "max_difference_over_frame_peak",
            "largest_range_change_m",
            "beams_hit_or_miss_changed",
            "beams_moved_over_1mm",
            "frames_differing",
            "elements_differing",
        ):
            values = [r[key] for r in found if key in r]
            if values:
                notes.append(
                    f"{key.replace('_', ' ')} {max(values):.3g}"
                    if isinstance(values[0], float)
                    else f"{key.replace('_', ' ')} {sum(values):,}"
                )
        lines.append(f"| {kind} | {same} of {len(found)} | {'; '.join(notes) or '-'} |")
    lines += ["", provenance_line(res["provenance"])]
    (out / "before_after.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
