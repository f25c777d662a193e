"""Issue 44's sim-to-real experiment, the steps around benchmarks/calibrate_sim2real.sh:

    python benchmarks/calibrate_sim2real.py suite FITS --recordings DATASET --out SUITE.json [--spread 0.05]
        # the calibrated training suite from the fits under FITS (surfaces/, directivity/), and fits.md
        # beside it: each room's fit beside what its engine used (the recordings' episode records)
    python benchmarks/calibrate_sim2real.py summary WORKDIR --out FOLDER
        # both arms, seed by seed, on crossengine past the calibration frames, on reality and on their
        # own validation episodes, paired, beside the baselines that would game the metric

The suite is `randomised` (bounces_3) with the fits' physics on top: `calibration` names every room's
surface fit (R and s spanning them, +-spread), the emitter's radius spans the rooms' directivity fits;
the rest of `randomised`'s draws (emitter offset, objects' surfaces) are restated because a suite's
`vary` and `surfaces` replace the variant's.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.compare_arms import compare, plot, stop_reason  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import provenance, write_json  # noqa: E402

CLASSES = ("walls", "floor", "ceiling")
ARMS = ("randomised", "calibrated")  # the reference first
BASELINES = ("echo peak", "empty")


def _rooms(folder: Path) -> dict[int, dict]:
    """{room: fit JSON} of folder/room*.json."""
    fits = {int(p.stem.removeprefix("room")): json.loads(p.read_text()) for p in folder.glob("room*.json")}
    if not fits:
        raise SystemExit(f"no room*.json under {folder}: run calibrate_sim2real.sh fit first")
    return dict(sorted(fits.items()))


def _truths(recordings: Path) -> dict[int, dict]:
    """Each crossengine room's record (its plan and pressure reflection coefficients)."""
    from acoustic_sim.calibrate.recordings import episode_records

    return {record["index"]: record for record in episode_records(recordings)}


def write_suite(fits: Path, recordings: Path, out: Path, spread: float) -> None:
    from acoustic_sim.datasets.suites import RANDOMISED_PHYSICS, load_suite

    surfaces = _rooms(fits / "surfaces")
    # energy fits (calibrate_sim2real.sh FIT=energy) were told the emitter is omnidirectional: no directivity
    directivity = _rooms(fits / "directivity") if (fits / "directivity").is_dir() else {}
    if directivity and sorted(surfaces) != sorted(directivity):
        raise SystemExit(f"rooms fitted: surfaces {sorted(surfaces)}, directivity {sorted(directivity)}; not the same")
    vary = {"sonar.emitter_m": RANDOMISED_PHYSICS["vary"]["sonar.emitter_m"]}
    if directivity:
        radii = np.array([fit["directivity"]["piston_radius_mm"] * 1e-3 for fit in directivity.values()])
        vary["sonar.emitter_radius_m"] = [float(radii.min() * (1 - spread)), float(radii.max() * (1 + spread))]
    names = [os.path.relpath(fits / "surfaces" / f"room{room}.json", out.parent) for room in surfaces]
    suite = {
        "base": "randomised",
        "name": out.stem,
        "description": "randomised's scenes and drives in the physics fitted to crossengine's ten rooms (issue 44)",
        "physics": {
            "calibration": names,
            "calibration_spread": spread,
            "vary": vary,
            "surfaces": {"objects": RANDOMISED_PHYSICS["surfaces"]["objects"]},
        },
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(suite, indent=1) + "\n")
    physics = load_suite(out).variants["bounces_3"]  # refused here, not on the GPU machine
    truths = _truths(recordings)
    text = fits_markdown(surfaces, directivity, truths, physics)
    (out.parent / "fits.md").write_text(text + "\n" + provenance_line(provenance()) + "\n")
    print(text, end="")
    print(f"wrote {out} and {out.parent / 'fits.md'}")


def fits_markdown(surfaces: dict, directivity: dict, truths: dict, physics) -> str:
    """Each room's fitted R and s beside its engine's (energy R = the pressure coefficient squared; s: 0
    where its surfaces are image sources' mirrors, the rough variant's walls their drawn s), its piston
    radius and how much of the recording the fit explains."""
    head = " | ".join(f"{c} R fitted / engine's" for c in CLASSES)
    lines = [
        "Each room's fit beside what its engine used (energy R: the pressure coefficient squared; the engine's s: "
        "0, or the rough walls' drawn s). Relative error: the error energy over the recording's, before and after "
        "the fit.",
        "",
        f"| room | plan | {head} | s fitted (walls, floor, ceiling) | engine's wall s | piston radius [mm] "
        "| relative error |",
        "|---|---|" + "---|" * (len(CLASSES) + 4),
    ]
    misses = {c: [] for c in CLASSES}
    for room, fit in surfaces.items():
        truth = truths[room]
        cells, s = [], []
        for c in CLASSES:
            engine = truth[f"{c.removesuffix('s')}_reflection"] ** 2
            got = fit["classes"].get(c)
            if got is None or engine == 0:  # an open top: no ceiling to fit
                cells.append("-" if got is None else f"{got['reflection']:.3f} / open")
                continue
            cells.append(f"{got['reflection']:.3f} / {engine:.3f}")
            s.append(f"{got.get('scattering', float('nan')):.3f}")
            misses[c].append(got["reflection"] / engine - 1)
        radius = f"{directivity[room]['directivity']['piston_radius_mm']:g}" if directivity else "omni"
        loss = f"{fit['loss'][0]:.2f} -> {fit['loss'][-1]:.2f}"
        fitted = f"{' | '.join(cells)} | {', '.join(s)} | {truth.get('wall_scattering', 0.0):.3f}"
        lines.append(f"| {room} | {truth['plan']} | {fitted} | {radius} | {loss} |")
    worst = ", ".join(f"{c} {100 * np.max(np.abs(m)):.1f} %" for c, m in misses.items() if m)
    lines += [
        "",
        f"Largest miss of R: {worst}.",
        "",
        "The suite draws per episode (`randomised` bounces_3 with these on top): "
        + "; ".join(f"{c} {v}" for c, v in physics.surfaces.items())
        + f"; emitter {physics.vary.get('sonar.emitter_pattern') or physics.vary['sonar.emitter_radius_m']}"
        + "; air absorption "
        + ("on" if physics.air_absorption else "off")
        + ".",
    ]
    return "\n".join(lines) + "\n"


def summarise(work: Path, out: Path, test: str = "crossengine") -> None:
    sets = ("validation", "reality", test)
    seeds = sorted(int(p.name.removeprefix("seed")) for p in (work / "scores").glob("seed*"))
    if not seeds:
        raise SystemExit(f"no scores under {work / 'scores'}: run calibrate_sim2real.sh score first")
    arms = {arm: {} for arm in ARMS}
    baselines, windows = {}, {}
    for seed in seeds:
        where = work / "scores" / f"seed{seed}"
        for arm in ARMS:
            own = json.loads((where / f"validation_{arm}" / "metrics.json").read_text())
            arms[arm][seed] = {"validation": own["results"]["model"]["all"]}
        for name in sets[1:]:
            report = json.loads((where / name / "metrics.json").read_text())
            windows[name] = report["windows"]
            for arm in ARMS:
                arms[arm][seed][name] = report["results"][arm]["all"]
            baselines[name] = {b: report["results"][b]["all"]["scan_f1"]["mean"] for b in BASELINES}
    table = compare(arms, ARMS[0], list(sets))
    stops = {arm: [stop_reason(work / "runs" / f"seed{s}" / arm) for s in seeds] for arm in ARMS}
    text = summary_markdown(table, baselines, windows, stops, seeds, sets) + "\n" + per_plan_markdown(work, seeds, test)
    out.mkdir(parents=True, exist_ok=True)
    (out / "calibrate_sim2real.md").write_text(text + "\n" + provenance_line(provenance()) + "\n")
    record = {
        arm: {s: {"seeds": dict(zip(seeds, v["seeds"].tolist(), strict=True))} for s, v in row.items()}
        for arm, row in table.items()
    }
    write_json(out / "calibrate_sim2real.json", {"scan_f1": record, "baselines": baselines})
    plot(table, ARMS[0], list(sets[1:]), out / "calibrate_sim2real.png")
    print(text, end="")
    print(f"wrote {out / 'calibrate_sim2real.md'} and its picture")


def summary_markdown(table: dict, baselines: dict, windows: dict, stops: dict, seeds: list[int], sets) -> str:
    seed_names, test = " / ".join(str(s) for s in seeds), sets[-1]
    lines = [
        f"Scan F1 (0.10 m), mean ± std over seeds {seed_names}; `{test}` only past each room's calibration "
        f"frames ({windows[test]} windows), `reality` whole ({windows['reality']} windows), validation: "
        "each arm's own held-out episodes.",
        "",
        "| arm | " + " | ".join(f"`{s}`" for s in sets) + " | stopped by, sub-epochs (kept) |",
        "|---|" + "---|" * (len(sets) + 1),
    ]
    for arm, row in table.items():
        cells = " | ".join(f"{row[s]['mean']:.3f} ± {row[s]['std']:.3f}" for s in sets)
        lines.append(f"| {arm} | {cells} | {'; '.join(stops[arm])} |")
    for name in BASELINES:
        cells = " | ".join(f"{baselines[s][name]:.3f}" if s in baselines else "-" for s in sets)
        lines.append(f"| {name} baseline | {cells} | - |")
    paired = {s: " / ".join(f"{d:+.3f}" for d in table[ARMS[1]][s]["paired"]) for s in sets}
    lines += [
        "",
        f"Paired by seed ({seed_names}), {ARMS[1]} minus {ARMS[0]}: "
        + "; ".join(f"`{s}` {paired[s]}" for s in sets)
        + ".",
    ]
    return "\n".join(lines) + "\n"


def per_plan_markdown(work: Path, seeds: list[int], test: str) -> str:
    """The test set's scan F1 per floor-plan family (two rooms each): each arm's mean over seeds, the
    echo peak's, and the paired differences."""
    per: dict[str, dict[str, list[float]]] = {}
    for seed in seeds:
        with open(work / "scores" / f"seed{seed}" / test / "per_scenario.csv", newline="") as f:
            for row in csv.DictReader(f):
                if row["scenario"] != "all":
                    by_predictor = per.setdefault(row["scenario"], {})
                    by_predictor.setdefault(row["predictor"], []).append(float(row["scan_f1_mean"]))
    lines = [
        f"`{test}` per floor-plan family (two rooms each, past the calibration frames), mean over seeds:",
        "",
        f"| plan | {ARMS[0]} | {ARMS[1]} | {ARMS[1]} minus {ARMS[0]}, seed by seed | echo peak |",
        "|---|---|---|---|---|",
    ]
    for plan, scores in per.items():
        paired = " / ".join(f"{b - a:+.3f}" for a, b in zip(scores[ARMS[0]], scores[ARMS[1]], strict=True))
        cells = " | ".join(f"{np.mean(scores[arm]):.3f}" for arm in ARMS)
        lines.append(f"| {plan} | {cells} | {paired} | {np.mean(scores['echo peak']):.3f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="step", required=True)
    s = sub.add_parser("suite", help="the calibrated suite from the fits under FITS, and fits.md beside it")
    s.add_argument("fits", type=Path, help="folder of surfaces/room*.json and directivity/room*.json")
    s.add_argument("--recordings", type=Path, required=True, help="the dataset the fits were made of (its records)")
    s.add_argument("--out", type=Path, required=True, help="the suite file to write (.json)")
    s.add_argument("--spread", type=float, default=0.05, help="calibration_spread (default 0.05)")
    s = sub.add_parser("summary", help="both arms per seed from WORKDIR/scores")
    s.add_argument("work", type=Path)
    s.add_argument("--test", default="crossengine", help="the rooms calibrated to: crossengine or crossengine_rough")
    s.add_argument("--out", type=Path, required=True, help="folder for calibrate_sim2real.md, .json and .png")
    args = p.parse_args()
    if args.step == "suite":
        write_suite(args.fits, args.recordings, args.out, args.spread)
    else:
        summarise(args.work, args.out, args.test)


if __name__ == "__main__":
    main()
