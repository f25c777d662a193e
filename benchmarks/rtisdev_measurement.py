"""A real eRTIS measurement through our processing, beside a simulated ping.

    python benchmarks/rtisdev_measurement.py [--out benchmarks/results/rtisdev_measurement]

The public package `rtisdev` (Cosys-Lab, CC BY-NC-SA 4.0) ships one raw measurement of an eRTIS
(`simulate.bin`: 163,840 words of 32 PDM bits at 4.5 MHz). This script fetches the package with
pip at run time into a temporary folder (it is never a dependency, and the file is never
committed), imports the measurement with `python -m acoustic_sim import --format pdm` (both bit
orders, since the package does not document which bit is which microphone, and two calls, since
it does not say which call was emitted), and draws the energyscapes beside one simulated ping of
our office scene. Writes rtisdev.png and README.md into --out.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.provenance import markdown as provenance_line  # noqa: E402
from benchmarks.provenance import provenance  # noqa: E402

PACKAGE = "rtisdev==2.16.0"
CALLS = {"50 -> 25 kHz (our default)": (50e3, 25e3), "80 -> 20 kHz": (80e3, 20e3)}


def fetch_measurement(folder: Path) -> Path:
    """simulate.bin out of the rtisdev wheel, downloaded into `folder`."""
    subprocess.run(
        [sys.executable, "-m", "pip", "download", PACKAGE, "--no-deps", "--quiet", "-d", str(folder)], check=True
    )
    wheel = next(folder.glob("rtisdev-*.whl"))
    with zipfile.ZipFile(wheel) as z:
        data = z.read("rtisdev/simulate.bin")
    path = folder / "simulate.bin"
    path.write_bytes(data)
    return path


def simulated_ping():
    """One ping of our office scene (seed 0) from its trajectory's first pose, on the CPU."""
    import scenes
    from acoustic_sim import Sonar, SonarConfig

    scene = scenes.BUILDERS["office"](seed=0)
    poses = scenes.trajectory(scene, frames=1, seed=0)
    frames = Sonar(SonarConfig.ertis(), device="cpu").simulate(scene, poses, noise="gaussian", snr_db=30.0)
    return frames.energyscape[0]


def main(argv=None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "rtisdev_measurement"))
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from acoustic_sim import PolarGrid
    from acoustic_sim.cli import main as sim_cli
    from acoustic_sim.render import draw_energyscape

    panels = []
    with tempfile.TemporaryDirectory() as tmp:
        raw = fetch_measurement(Path(tmp))
        for order in ("lsb", "msb"):
            for name, (start, stop) in CALLS.items():
                npy = Path(tmp) / f"{order}_{stop:.0f}.npy"
                call = [f"sonar.chirp.start_frequency_hz={start}", f"sonar.chirp.stop_frequency_hz={stop}"]
                argv = ["import", str(raw), "--format", "pdm", "--bit-order", order, "--out", str(npy)]
                if sim_cli([*argv, *(x for s in call for x in ("--set", s))]) != 0:
                    raise SystemExit("import failed")
                panels.append((f"rtisdev measurement, bits {order}, call {name}", np.load(npy)[0]))
    panels.append(("simulated: our office, first pose, 3 bounces", simulated_ping()))
    grid = PolarGrid()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.8))
    for ax, (title, image) in zip(axes, panels, strict=True):
        draw_energyscape(ax, image, None, grid, title=title)
        ax.title.set_fontsize(9)
    fig.tight_layout()
    picture = out / "rtisdev.png"
    fig.savefig(picture, dpi=80)
    plt.close(fig)
    (out / "README.md").write_text(
        "# A real eRTIS measurement through our processing\n\n"
        f"`python benchmarks/rtisdev_measurement.py` fetches `{PACKAGE}` (CC BY-NC-SA 4.0) at run time, decodes\n"
        "its one raw measurement (`simulate.bin`, 32 channels of 1-bit PDM at 4.5 MHz) with\n"
        "`python -m acoustic_sim import --format pdm`, and draws the energyscapes (dB below each image's peak)\n"
        "beside one simulated ping of our office. The package says neither which bit is which microphone\n"
        "nor which call was emitted, so both bit orders and two calls are shown. Read with bit i as\n"
        "microphone i of the eRTIS_v3D1 layout (`lsb`, the order of rtisdev's own `mic_coordinates.mat`, which\n"
        "is ours), the array focuses: echoes are spots and arcs at a few azimuths. Read the other way\n"
        "(`msb`), the delays no longer fit the array and only full-width range bands remain. Both the real\n"
        "and the simulated pings show such bands (floor, ceiling, the array's sidelobes of strong echoes).\n\n"
        "![energyscapes](rtisdev.png)\n\n"
        f"{provenance_line(provenance('cpu'))}\n"
    )
    print(f"wrote {picture}")
    return picture


if __name__ == "__main__":
    main()
