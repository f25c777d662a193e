"""Were the walls a model misses ever heard? For every true LiDAR return of each window's label
frame t, its incidence band (as `recall_by_incidence.py` defines it, from the true scan) and its
point in the world; then whether that point was *heard* from some pose in a set of frames: one of
them has a true return within NEAR_M of it (so it was in view and not hidden) met within HEARD_DEG
of the wall's normal (from that frame's own true scan), where a specular wall sends an echo back.

The sets: the K = 5 window (t-2..t+2), the frames a model with memory reads (its history frames
every stride frames back, then the window), every frame of that span, every frame of the drive up
to t+2, and (for reference) the whole drive. A share near 0 at 30-50 degrees says no memory of
the drive can recall those walls from echoes heard; a share near 1 says the echoes were there.
With `--model`, each checkpoint's recall (as `recall_by_incidence.py` counts it) is split into the
returns heard within the frames it reads and those not.

    python benchmarks/heard_before.py --test crossengine=data/crossengine --out heard_before.md \
        [--model learn/pretrained/polar_memory_k5.pt]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import provenance, relative, write_json  # noqa: E402
from benchmarks.recall_by_incidence import BANDS_DEG, NEIGHBOURS, found, incidence_deg  # noqa: E402
from learn.checkpoint import load_checkpoint  # noqa: E402
from learn.cli import named_folder  # noqa: E402
from learn.data import DataConfig, Windows, load_frames  # noqa: E402
from learn.evaluate import model_predictor, model_windows  # noqa: E402
from learn.scan import LABEL_THRESHOLD, SCAN_TOLERANCE_M, first_return_ranges  # noqa: E402

HEARD_DEG = 30.0  # a return met closer than this to the wall's normal echoes off a specular wall [deg]
NEAR_M = SCAN_TOLERANCE_M  # two returns this close [m] are the same point of a wall
BAND_NAMES = [f"{lo}-{hi} deg" for lo, hi in itertools.pairwise(BANDS_DEG)] + ["no angle"]


def world_points(ranges: np.ndarray, azimuth_rad: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Each beam's return in the world, (T, A, 2) [m] (inf where the beam has none).

    Args:
        ranges: True first-return ranges [m], (T, A), inf for none.
        azimuth_rad: Beam azimuths [rad] in the sensor frame, 0 along its x axis, positive to the left, (A,).
        pose: Planar sensor poses (x, y [m], yaw [rad]) in the world, (T, 3).
    """
    heading = pose[:, 2, None] + azimuth_rad[None, :]
    with np.errstate(invalid="ignore"):  # inf * 0 where a beam points along an axis: not a return anyway
        x = pose[:, 0, None] + ranges * np.cos(heading)
        y = pose[:, 1, None] + ranges * np.sin(heading)
    points = np.stack([x, y], -1)
    points[~np.isfinite(ranges)] = np.inf
    return points


def frame_sets(config: DataConfig, drive_frames: int) -> dict[str, np.ndarray]:
    """Frame offsets from the label frame t of each set of frames a return may have been heard from.

    Args:
        config: The memory model's windows (K, label position, history and its stride).
        drive_frames: The longest drive's length: offsets reach back (and on) that far.
    """
    model = config.offsets - config.label_offset
    after = config.frames - 1 - config.label_offset  # frames of the window after t
    return {
        "window": np.arange(-config.label_offset, after + 1),
        "model": model,
        "span": np.arange(model.min(), after + 1),
        "before": np.arange(-drive_frames, after + 1),
        "drive": np.arange(-drive_frames, drive_frames + 1),
    }


def heard(
    ranges: np.ndarray,
    azimuth_rad: np.ndarray,
    pose: np.ndarray,
    episode: np.ndarray,
    label_frames: np.ndarray,
    sets: dict[str, np.ndarray],
    *,
    heard_deg: float = HEARD_DEG,
    near_m: float = NEAR_M,
) -> dict[str, np.ndarray]:
    """Whether each true return of each label frame was heard from a frame of each set.

    Args:
        ranges: True first-return ranges [m] of every frame, (T, A), inf for none.
        azimuth_rad: Beam azimuths [rad], (A,).
        pose: Planar sensor poses (x, y [m], yaw [rad]), (T, 3).
        episode: Drive of each frame, (T,); frames of a drive are contiguous and in time order.
        label_frames: The frame t of each window, (W,).
        sets: Name -> offsets from t of the frames that count (see `frame_sets`); frames outside
            t's drive never count.
        heard_deg: A frame hears a wall point it meets closer than this to the normal [deg].
        near_m: A frame's return this close [m] to a point is that point.

    Returns:
        Name -> (W, A) bool, True where the label frame's return at that beam was heard (False
        where the beam has no return).
    """
    angle = incidence_deg(ranges, azimuth_rad)
    points = world_points(ranges, azimuth_rad, pose)
    with np.errstate(invalid="ignore"):
        loud = angle < heard_deg  # nan (no angle) is not heard
    out = {name: np.zeros((len(label_frames), ranges.shape[1]), bool) for name in sets}
    for drive in np.unique(episode[label_frames]):
        windows = np.flatnonzero(episode[label_frames] == drive)
        source_frame, source_beam = np.nonzero(loud & (episode == drive)[:, None])
        query_window, query_beam = np.nonzero(np.isfinite(ranges[label_frames[windows]]))
        if len(source_frame) == 0 or len(query_window) == 0:
            continue
        query_window = windows[query_window]
        queries = cKDTree(points[label_frames[query_window], query_beam])
        sources = cKDTree(points[source_frame, source_beam])
        pairs = queries.sparse_distance_matrix(sources, near_m, output_type="ndarray")
        query, offset = pairs["i"], source_frame[pairs["j"]] - label_frames[query_window[pairs["i"]]]
        for name, offsets in sets.items():
            hit = np.zeros(len(query_window), bool)
            hit[query[np.isin(offset, offsets)]] = True
            out[name][query_window, query_beam] = hit
    return out


def band_of(angle: np.ndarray) -> np.ndarray:
    """Index into BAND_NAMES of each incidence angle [deg] (the last: no angle), as `recall_by_incidence.banded`."""
    band = np.full(angle.shape, len(BANDS_DEG) - 1)
    for i, (lo, hi) in enumerate(itertools.pairwise(BANDS_DEG)):
        with np.errstate(invalid="ignore"):
            band[(angle >= lo) & (angle < hi if hi < 90 else angle <= hi)] = i
    return band


def tabulate(band, has, family_of, found: dict[str, np.ndarray]) -> dict:
    """{family: {band: {"returns", "share_of_returns", name: share heard}}} over all windows and per family."""
    table = {}
    for family in ["all", *sorted(set(family_of))]:
        mask = has if family == "all" else has & (family_of == family)[:, None]
        rows = {}
        for i, name in enumerate(BAND_NAMES):
            sel = mask & (band == i)
            row = {"returns": int(sel.sum()), "share_of_returns": float(sel.sum() / max(mask.sum(), 1))}
            row |= {s: float(h[sel].mean()) if sel.any() else float("nan") for s, h in found.items()}
            rows[name] = row
        table[family] = rows
    return table


SENSITIVITY = ((HEARD_DEG, 0.05), (HEARD_DEG, 0.15), (20.0, NEAR_M), (40.0, NEAR_M))  # (heard_deg, near_m)


def sensitivity(ranges, azimuth, pose, episode, label_frames, sets, band, has) -> list[dict]:
    """Share of returns heard within the model's frames per band at other (heard_deg, near_m)."""
    rows = []
    for heard_deg, near_m in SENSITIVITY:
        found = heard(
            ranges, azimuth, pose, episode, label_frames, {"model": sets["model"]}, heard_deg=heard_deg, near_m=near_m
        )
        shares = {
            name: float(found["model"][has & (band == i)].mean()) if (has & (band == i)).any() else float("nan")
            for i, name in enumerate(BAND_NAMES)
        }
        rows.append({"heard_deg": heard_deg, "near_m": near_m, "model": shares})
    return rows


def recall_split(band, has, heard_by_model: np.ndarray, hits: list[np.ndarray]) -> dict:
    """{band: {"heard", "unheard": mean recall over the models}} of the returns heard within the
    model's frames and of those not (nan where a band has none)."""
    rows = {}
    for i, name in enumerate(BAND_NAMES):
        row = {}
        for key, sel in (("heard", heard_by_model), ("unheard", ~heard_by_model)):
            sel = sel & has & (band == i)
            row[key] = float(np.mean([h[sel].mean() for h in hits])) if sel.any() else float("nan")
            row[f"{key}_returns"] = int(sel.sum())
        rows[name] = row
    return rows


def halves(angle: np.ndarray, has: np.ndarray, found: dict[str, np.ndarray]) -> dict:
    """The 30-50 degree band split at 40 degrees: {half: {"returns", name: share heard}} (how much of
    what is heard lies just past the 30-degree limit)."""
    rows = {}
    for lo, hi in ((30, 40), (40, 50)):
        with np.errstate(invalid="ignore"):
            sel = has & (angle >= lo) & (angle < hi)
        row = {"returns": int(sel.sum())}
        rows[f"{lo}-{hi} deg"] = row | {
            s: float(h[sel].mean()) if sel.any() else float("nan") for s, h in found.items()
        }
    return rows


def report(
    name: str, table: dict, config: DataConfig, sets: dict, seconds: tuple, prov: dict, models=(), split=None, others=()
) -> list[str]:
    """The markdown: all windows by band, each family's bands, then (with models) their recall split."""
    model = ", ".join(f"t{o:+d}" if o else "t" for o in sets["model"])
    lines = [
        f"# Were the missed walls ever heard? (`{name}`)",
        "",
        "Each true LiDAR return of a window's label frame t (K = 5, label in the middle) is put in the world with "
        "the shards' poses; it counts as *heard* from a set of frames when one of them has a true return within "
        f"{NEAR_M} m of it (in view, not hidden) met less than {HEARD_DEG:g} degrees off the wall's normal (from that "
        "frame's own true scan), where a specular wall echoes. Incidence bands of the label frame as "
        f"`benchmarks/recall_by_incidence.py` defines them (true scan, {NEIGHBOURS} beams either side; 'no angle' = "
        "corners, surface ends and lone returns). Scans are the label images' first returns on the polar grid.",
        "",
        "Sets of frames (none before the drive began):",
        "",
        "- **K = 5**: the window, t-2..t+2.",
        f"- **model**: the frames the memory model reads (history {config.history}, stride {config.history_stride}): "
        f"{model}.",
        f"- **span**: every frame t{sets['span'].min():+d}..t{sets['span'].max():+d}.",
        "- **before**: every frame of the drive up to t+2.",
        "- **drive**: every frame of the drive (later ones too), for reference.",
        "",
        "## All windows",
        "",
        "Share of each band's returns heard from each set ('of which' rows: the 30-50 band split at 40 degrees).",
        "",
        "| incidence at t | returns (share) | K = 5 | model | span | before | drive |",
        "|---|---|---|---|---|---|---|",
    ]
    total = sum(row["returns"] for row in table["all"].values())
    named = [(band, row) for band, row in table["all"].items()]
    named[2:2] = [(f"of which {band}", row) for band, row in table["all_30_50_halves"].items()]
    for band, row in named:
        shares = " | ".join(f"{row[s]:.2f}" for s in ("window", "model", "span", "before", "drive"))
        lines.append(f"| {band} | {row['returns']} ({100 * row['returns'] / max(total, 1):.0f} %) | {shares} |")
    lines += [
        "",
        "## Per scenario family",
        "",
        "Each cell: share heard within K = 5 / the model's frames / before t+2 (returns in the band).",
        "",
        "| family | " + " | ".join(BAND_NAMES) + " |",
        "|---|" + "---|" * len(BAND_NAMES),
    ]
    for family, rows in ((f, r) for f, r in table.items() if f != "all_30_50_halves"):
        cells = [f"{r['window']:.2f} / {r['model']:.2f} / {r['before']:.2f} ({r['returns']})" for r in rows.values()]
        lines.append(f"| {family} | " + " | ".join(cells) + " |")
    if others:
        lines += [
            "",
            "## Sensitivity",
            "",
            "Share heard within the model's frames, all windows, with another incidence limit or distance.",
            "",
            "| heard below | within | " + " | ".join(BAND_NAMES) + " |",
            "|---|---|" + "---|" * len(BAND_NAMES),
        ]
        row = table["all"]
        lines.append(
            f"| {HEARD_DEG:g} deg | {NEAR_M} m | " + " | ".join(f"{row[b]['model']:.2f}" for b in BAND_NAMES) + " |"
        )
        for other in others:
            cells = " | ".join(f"{other['model'][b]:.2f}" for b in BAND_NAMES)
            lines.append(f"| {other['heard_deg']:g} deg | {other['near_m']} m | {cells} |")
    if split:
        lines += [
            "",
            "## Recall of the model, heard or not",
            "",
            f"Recall of {', '.join(f'`{m}`' for m in models)} (each at its own threshold, averaged; a return is found "
            f"when the prediction's nearest return in its beam lies within {SCAN_TOLERANCE_M} m, as "
            "`recall_by_incidence.py` counts) on the returns heard within the model's frames and on those not "
            "(returns).",
            "",
            "| incidence at t | heard within the model's frames | not heard there |",
            "|---|---|---|",
        ]
        for band, row in split.items():
            heard_cell, unheard_cell = (f"{row[k]:.2f} ({row[k + '_returns']})" for k in ("heard", "unheard"))
            lines.append(f"| {band} | {heard_cell} | {unheard_cell} |")
    geometry, total = seconds
    ran = f"Read and searched in {geometry:.0f} s" + (f", {total:.0f} s with the models" if split else "")
    lines += ["", ran + ".", "", provenance_line(prov)]
    return lines


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--test", type=named_folder, required=True, help="NAME=FOLDER of the test set (with poses)")
    p.add_argument("--out", type=Path, required=True, help="markdown file to write (and .json beside it)")
    p.add_argument("--history", type=int, default=8, help="history frames of the memory model (the study's: 8)")
    p.add_argument("--history-stride", type=int, default=3, help="frames between them (the study's: 3)")
    p.add_argument("--model", type=Path, action="append", default=[], help="checkpoint whose recall to split")
    p.add_argument("--device", default="cpu", help="where models run")
    args = p.parse_args()
    begun = time.perf_counter()
    name, folder = args.test
    frames = load_frames(folder)
    if frames.pose is None:
        raise SystemExit(f"error: {name} holds no poses; this needs data with odometry")
    config = DataConfig(frames=5, history=args.history, history_stride=args.history_stride)
    windows = Windows(frames, DataConfig(frames=config.frames), "cpu")  # the study's windows of the label frames
    label_frames = windows.starts + config.label_offset
    range_m = torch.as_tensor(frames.range_m)
    ranges = np.concatenate(
        [
            first_return_ranges(torch.from_numpy(frames.label[i : i + 256]).float(), range_m, threshold=LABEL_THRESHOLD)
            .cpu()
            .numpy()
            for i in range(0, len(frames), 256)
        ]
    )
    azimuth = np.asarray(frames.azimuth_rad, dtype=np.float64)
    drive_frames = int(np.unique(frames.episode, return_counts=True)[1].max())
    sets = frame_sets(config, drive_frames)
    heard_from = heard(ranges, azimuth, frames.pose, frames.episode, label_frames, sets)
    true = ranges[label_frames]
    angle = incidence_deg(true, azimuth)
    band = band_of(angle)
    family_of = np.asarray(frames.scenarios)[windows.scenario]
    has = np.isfinite(true)
    table = tabulate(band, has, family_of, heard_from)
    table["all_30_50_halves"] = halves(angle, has, heard_from)
    others = sensitivity(ranges, azimuth, frames.pose, frames.episode, label_frames, sets, band, has)
    geometry_seconds = time.perf_counter() - begun  # reading the data and finding what was heard
    hits = []
    for path in args.model:
        model, ckpt = load_checkpoint(path, args.device)
        if DataConfig(**ckpt["data_config"]) != config:
            raise SystemExit(
                f"error: {path} reads other windows ({ckpt['data_config']}) than --history/--history-stride"
            )
        windows_of_model = model_windows(frames, ckpt, args.device)
        model_true, hit = found(model_predictor(model), windows_of_model, float(ckpt["threshold"]))
        if not np.array_equal(model_true, true):  # the same windows, in the same order
            raise SystemExit(f"error: {path}'s windows are not this script's")
        hits.append(hit)
    split = recall_split(band, has, heard_from["model"], hits) if hits else None
    seconds = time.perf_counter() - begun
    prov = provenance(args.device if hits else "cpu")
    models = [relative(m) for m in args.model]
    lines = report(name, table, config, sets, (geometry_seconds, seconds), prov, models, split, others)
    args.out.write_text("\n".join(lines) + "\n")
    record = {
        "test": name,
        "plan_id": frames.info.get("plan_id"),
        "windows": len(windows),
        "heard_deg": HEARD_DEG,
        "near_m": NEAR_M,
        "sets": {k: v.tolist() if k in ("window", "model") else [int(v.min()), int(v.max())] for k, v in sets.items()},
        "data_config": {"frames": config.frames, "history": config.history, "history_stride": config.history_stride},
        "seconds": {"heard": geometry_seconds, "total": seconds},
        "table": table,
        "models": models,
        "recall_heard_or_not": split,
        "sensitivity": others,
    }
    write_json(args.out.with_suffix(".json"), record, "cpu")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
