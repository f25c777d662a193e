"""Emitter and microphone geometry of the sonar, and the emitter's directivity."""

from __future__ import annotations

from functools import lru_cache
from importlib import resources

import numpy as np
from scipy.special import j1


@lru_cache(maxsize=1)
def ertis_microphones() -> np.ndarray:
    """The 32 eRTIS_v3D1 microphone positions in the sensor frame [m], shape (32, 3), read-only.

    Converted from the public MIT-licensed Cosys-Lab/SonoTraceUE file
    TestData/ReceiverCoordinates_eRTIS_v3D1.csv; origin at the microphones' centroid, x along the
    array normal (forward), y left, z up.
    """
    text = resources.files("acoustic_sim").joinpath("data/ertis_v3d1_mics.csv").read_text()
    rows = [line.split(",") for line in text.splitlines() if line and not line.startswith(("#", "mic"))]
    positions = np.array([[float(v) for v in row[1:4]] for row in rows])
    positions.flags.writeable = False
    return positions


def piston_directivity(
    theta: np.ndarray, frequency_hz: np.ndarray | float, radius_m: float, speed_of_sound: float
) -> np.ndarray:
    """Pressure directivity of a baffled circular piston, 2 J1(ka sin t) / (ka sin t); 1 on axis.

    Args:
        theta: Angle from the piston axis [rad].
        frequency_hz: Frequency [Hz] (broadcasts with theta).
        radius_m: Piston radius [m].
        speed_of_sound: [m/s].
    """
    x = 2 * np.pi * np.asarray(frequency_hz) / speed_of_sound * radius_m * np.sin(np.asarray(theta))
    safe = np.where(np.abs(x) < 1e-8, 1.0, x)
    return np.where(np.abs(x) < 1e-8, 1.0, 2.0 * j1(safe) / safe)


def emitter_directivity(sonar, cosine: np.ndarray | float) -> np.ndarray:
    """Pressure the emitter of `sonar` (a SonarConfig) sends at the call's centre frequency
    towards directions at `cosine` from its axis (the sensor's x), relative to on axis: its
    baffled piston's pattern in front and nothing behind the baffle, or 1 everywhere ("omni")."""
    cosine = np.asarray(cosine, dtype=np.float64)
    if sonar.emitter_pattern == "omni":
        return np.ones_like(cosine)
    centre, air = sonar.chirp.centre_frequency_hz, sonar.atmosphere.speed_of_sound
    front = piston_directivity(np.arccos(np.clip(cosine, 0.0, 1.0)), centre, sonar.emitter_radius_m, air)
    return np.where(cosine >= 0.0, front, 0.0)
