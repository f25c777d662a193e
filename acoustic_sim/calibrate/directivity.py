"""The emitter's directivity in a calibration: the angle each path left the emitter at, and the
arrivals taken back to an omnidirectional emitter and shared between directivity knots."""

from __future__ import annotations

import numpy as np

import scenes

from ..array import piston_directivity
from ..config import SonarConfig

QUIET_DIRECTIVITY = 1e-3  # arrivals the nominal emitter sends less pressure than this are left out of a directivity fit


def departure_cosine(arrivals, scene: scenes.Scene, poses: np.ndarray, config: SonarConfig) -> np.ndarray:
    """Per arrival, the cosine of the angle from the emitter's axis (the sensor's x) at which its
    path left the emitter: its arrival direction reflected back through its faces, last first
    (off a sphere or cylinder: towards the point it reflects at)."""
    normals = np.asarray(scene.mesh.face_normals, dtype=np.float64)
    to_world = poses[arrivals.pose_index, :3, :3]
    leaving = -np.asarray(arrivals.direction, dtype=np.float64)  # the last leg's way, reversed below
    for j in reversed(range(arrivals.faces.shape[1])):
        face = arrivals.faces[:, j]
        on = face >= 0
        normal = np.einsum("nji,nj->ni", to_world[on], normals[face[on]])  # in the sensor frame
        leaving[on] -= 2 * np.einsum("ni,ni->n", leaving[on], normal)[:, None] * normal
    curved = (arrivals.order == 1) & np.all(arrivals.source_m == arrivals.point_m, axis=1)
    leaving[curved] = arrivals.point_m[curved] - np.asarray(config.emitter_m)
    return leaving[:, 0] / np.linalg.norm(leaving, axis=1)


def by_knot(arrivals, counts: np.ndarray, scene, poses, config: SonarConfig, knots: int):
    """The arrivals taken back to an omnidirectional emitter and split between the two knots
    around the angle they left at (each copy carrying its share), with their counts and knots, and
    the knots' angles [deg]."""
    cosine = np.clip(departure_cosine(arrivals, scene, poses, config), -1.0, 1.0)
    angle = np.degrees(np.arccos(cosine))
    air = config.atmosphere.speed_of_sound
    nominal = piston_directivity(np.radians(angle), config.chirp.centre_frequency_hz, config.emitter_radius_m, air)
    heard = np.abs(nominal) >= QUIET_DIRECTIVITY
    arrivals, counts, angle = arrivals.select(heard), counts[heard], angle[heard]
    arrivals.amplitude = arrivals.amplitude / nominal[heard]
    step = 90.0 / knots
    below = np.minimum(np.floor(angle / step).astype(int), knots - 1)
    share = np.clip(angle / step - below, 0.0, 1.0)  # of the knot above
    both = np.concatenate([np.arange(len(angle))] * 2)
    split = arrivals.select(both)
    split.amplitude = split.amplitude * np.concatenate([1.0 - share, share])
    return split, counts[both], np.concatenate([below, below + 1]), np.arange(knots + 1) * step
