"""The package used as a library (not through a command line) is quiet: Warp's start-up banner,
its module-load lines and the missing-driver notice of a CPU-only machine stay off unless
SONAR2LIDAR_WARP_VERBOSE=1 asks for them."""

from __future__ import annotations

import os
import subprocess
import sys

SCRIPT = """
import acoustic_sim, scenes
scene = scenes.box_room()
poses = scenes.trajectory(scene, frames=1, seed=0)
sonar = acoustic_sim.Sonar(acoustic_sim.SonarConfig.ertis(), ray_count=2000, max_bounces=0, device="cpu")
frames = sonar.simulate(scene, poses)
assert frames.energyscape.shape == (1, 240, 181), frames.energyscape.shape
"""


def _run(**env) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if k != "SONAR2LIDAR_WARP_VERBOSE"}
    return subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300, env=base | env, check=True
    )


def test_a_script_that_simulates_a_ping_prints_nothing():
    done = _run()
    assert done.stdout == "" and done.stderr == "", done.stdout + done.stderr


def test_warps_messages_come_back_on_request():
    done = _run(SONAR2LIDAR_WARP_VERBOSE="1")
    assert "Warp" in done.stdout + done.stderr, done.stdout + done.stderr
