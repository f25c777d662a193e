"""torch is the `[learn]` extra: with torch unimportable the simulator still imports, records and
beamforms, and `python -m learn` answers with one line on how to install it (exit status 2).

The subprocesses find a `torch` module first on PYTHONPATH whose import raises what a missing
package raises (ModuleNotFoundError naming torch). In a fresh venv that never had torch (a plain
`pip install .`), `generate --suite tiny` and `learn train` were checked by hand to do the same."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def without(tmp_path: Path, missing: str = "torch") -> dict[str, str]:
    """Environment in which `import torch` fails with ModuleNotFoundError naming `missing`:
    "torch" where torch is not installed, a module of torch's own where torch is broken."""
    stub = tmp_path / "stub"
    stub.mkdir()
    message = f"No module named {missing!r}"
    (stub / "torch.py").write_text(f"raise ModuleNotFoundError({message!r}, name={missing!r})\n")
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(stub), os.environ.get("PYTHONPATH")]))}


def learn(argv: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "learn", *argv], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120
    )


def test_torch_is_the_learn_extra_not_a_dependency():
    """The hint's extra exists and brings torch; the package itself does not need it."""
    assert not [d for d in PYPROJECT["dependencies"] if re.match(r"torch\b", d)]
    assert [d for d in PYPROJECT["optional-dependencies"]["learn"] if re.match(r"torch\b", d)]


@pytest.mark.parametrize("argv", [["train", "--data", "data/tiny", "--out", "RUN"], ["evaluate", "--help"], []])
def test_learn_without_torch_prints_the_install_hint_and_exits_2(tmp_path, argv):
    """Any command (its --help too, whose choices come from torch modules) answers with one line:
    the extra to install and the CPU build of torch that the Makefile pins; nothing is written."""
    run = tmp_path / "run"
    done = learn([str(run) if a == "RUN" else a for a in argv], without(tmp_path))
    assert done.returncode == 2, done.stderr
    assert done.stdout == ""
    assert len(done.stderr.splitlines()) == 1, done.stderr
    hint = done.stderr.strip()
    assert hint.startswith("error: the learner needs PyTorch: "), hint
    assert 'pip install "sonar2lidar[learn]"' in hint and 'pip install ".[learn]"' in hint, hint
    torch_spec = re.search(r"^TORCH_SPEC \?= (\S+)$", (ROOT / "Makefile").read_text(), re.M)[1]
    assert f"pip install {torch_spec} " in hint, (torch_spec, hint)
    assert not run.exists()


def test_learn_with_a_broken_torch_shows_what_is_missing(tmp_path):
    """torch installed but missing a module of its own is not reported as torch not installed."""
    done = learn(["train", "--help"], without(tmp_path, missing="torch._C"))
    assert done.returncode == 1
    assert "ModuleNotFoundError: No module named 'torch._C'" in done.stderr
    assert "sonar2lidar[learn]" not in done.stderr


SIMULATE = """
import sys

import numpy as np

import acoustic_sim as sim
import acoustic_sim.datasets.generate
import acoustic_sim.engine.beamform
import scenes
from acoustic_sim.engine.paths import KIND_SPECULAR, Arrivals
from acoustic_sim.engine.signals import record

config = sim.SonarConfig.ertis()
r, azimuth = 2.0, np.deg2rad(30.0)
source = 2 * r * np.array([[np.cos(azimuth), np.sin(azimuth), 0.0]])  # a point reflector's image source
one = np.ones(1)
arrivals = Arrivals(
    pose_index=np.zeros(1, np.int64), delay_s=2 * r / config.atmosphere.speed_of_sound * one,
    direction=source / (2 * r), amplitude=one / (2 * r), order=np.ones(1, np.int64),
    kind=np.full(1, KIND_SPECULAR), source_m=source, length_m=2 * r * one, point_m=source / 2,
)
image = sim.energyscape(record(arrivals, config, device=sys.argv[1]), config)[0]
i, j = np.unravel_index(np.argmax(image), image.shape)
grid = sim.PolarGrid()
print(grid.range_m[i], np.rad2deg(grid.azimuth_rad[j]), grid.range_bin_m, "torch" in sys.modules)
"""


def test_simulator_records_and_beamforms_without_torch(tmp_path, device):
    """With torch unimportable: the package, generate, the beamformer and scenes import, and one
    point reflector at 2 m, 30 deg azimuth is recorded and imaged within a range bin and 2 deg."""
    done = subprocess.run(
        [sys.executable, "-c", SIMULATE, device],
        cwd=ROOT,
        env=without(tmp_path),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    range_m, azimuth_deg, bin_m, torch_loaded = done.stdout.splitlines()[-1].split()  # after Warp's banner
    assert abs(float(range_m) - 2.0) <= float(bin_m)
    assert abs(float(azimuth_deg) - 30.0) <= 2.0
    assert torch_loaded == "False"
