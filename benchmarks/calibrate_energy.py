"""The table of benchmarks/calibrate_energy.sh: each room's fit, after the waveform stage and after
the energy stage, beside what its engine used (energy R: the pressure coefficient squared; s: 0 on
smooth surfaces, the rough walls' drawn s).

    python benchmarks/calibrate_energy.py WORKDIR RESULTS    # writes RESULTS/table.md
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acoustic_sim.calibrate.recordings import episode_records  # noqa: E402
from benchmarks.provenance import markdown as provenance_line  # noqa: E402

CLASSES = ("walls", "floor", "ceiling")


def engine_values(record: dict, name: str) -> tuple[float, float]:
    """(R, s) of a class as the engine used them."""
    reflection = record[f"{name.removesuffix('s')}_reflection"] ** 2
    return reflection, record.get("wall_scattering", 0.0) if name == "walls" else 0.0


def table(work: Path, results: Path) -> str:
    lines = [
        "Per room and class: R and s after the waveform stage -> after the energy stage, and the engine's "
        "(R = its pressure coefficient squared). Last columns: the energy stage's loss (mean squared log ratio "
        "of simulated to recorded energy per 1 ms bin) at the waveform's s and at the fitted s.",
        "",
        "| suite | room | plan | " + " | ".join(f"{c}: R, s (engine)" for c in CLASSES) + " | loss |",
        "|---|---|---|" + "---|" * (len(CLASSES) + 1),
    ]
    for path in sorted(results.glob("*_room*.json")):
        suite, room = path.stem.rsplit("_room", 1)
        fit = json.loads(path.read_text())
        record = next(r for r in episode_records(work / suite) if r["index"] == int(room))
        cells = []
        for name in CLASSES:
            after, before = fit["classes"].get(name), fit["energy"]["waveform"].get(name)
            if after is None:
                cells.append("-")
                continue
            r, s = engine_values(record, name)
            cells.append(
                f"{before['reflection']:.3f}, {before['scattering']:.3f} -> **{after['reflection']:.3f}, "
                f"{after['scattering']:.3f}** ({r:.3f}, {s:.3f})"
            )
        loss = " -> ".join(f"{v:.2g}" for v in fit["energy"]["loss"])
        lines.append(f"| {suite} | {room} | {record['plan']} | {' | '.join(cells)} | {loss} |")
    provenance = json.loads((results / "provenance.json").read_text())["provenance"]
    return "\n".join(lines) + "\n\n" + provenance_line(provenance) + "\n"


if __name__ == "__main__":
    work, results = Path(sys.argv[1]), Path(sys.argv[2])
    text = table(work, results)
    (results / "table.md").write_text(text)
    print(text, end="")
