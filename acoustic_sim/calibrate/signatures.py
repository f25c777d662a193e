"""Traced arrivals taken to unit surfaces and grouped by signature: how many times each arrival
reflected off each surface class (and, for the classes whose scattering is fitted, how many of
those reflections kept their specular share and which one scattered it), so that every arrival
of a signature scales alike with the classes' R and s."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import scenes
from scenes.surfaces import SURFACE_CLASSES, surface_classes


@dataclass
class Signatures:
    """Per arrival, what its amplitude owes to each surface class the paths reflect off.

    Attributes:
        classes: Those classes (of walls, floor, ceiling, objects), K of them.
        nominal, nominal_s: Per class the scene's R and s, averaged over the class's faces.
        scatters: Per class whether it scattered an arrival (its s can be fitted), bool (K,).
        counts: Per arrival its reflections off each class, int (n, K).
        shares: Per arrival, for the S classes that scatter, the reflections that kept their
            specular share and the scatterings (edge bands scatter all: neither), int (n, 2 S).
    """

    classes: tuple[str, ...]
    nominal: np.ndarray
    nominal_s: np.ndarray
    scatters: np.ndarray
    counts: np.ndarray
    shares: np.ndarray


def at_unit_surfaces(arrivals, scene: scenes.Scene) -> Signatures:
    """Divide each arrival's amplitude by what the scene's materials gave it (sqrt(R) a
    reflection; sqrt(1 - s) a reflection keeping its specular share, sqrt(s) a scattering, off the
    classes that scatter), in place, and return their signatures."""
    face_class = surface_classes(scene)
    face_r, face_s = scene.material_table("acoustic_reflection"), scene.material_table("acoustic_scattering")
    reflected, kept, scattered = arrivals.face_roles()
    faces = np.maximum(arrivals.faces, 0)
    factor = np.where(reflected, np.sqrt(face_r[faces]), 1.0)
    by_class = arrivals.surface_factors(face_class, len(SURFACE_CLASSES))
    seen = by_class[0].sum(axis=0) > 0
    seen_classes = np.nonzero(seen)[0]
    # s is fitted for the classes that scattered an arrival; elsewhere (1 - s) stays in the amplitude.
    scatters = by_class[2][:, seen].sum(axis=0) > 0
    if scatters.any():
        fitted = np.isin(face_class[faces], seen_classes[scatters])
        factor *= np.where(kept & fitted, np.sqrt(1.0 - face_s[faces]), 1.0)
        factor *= np.where(scattered & fitted, np.sqrt(face_s[faces]), 1.0)
    arrivals.amplitude = arrivals.amplitude / np.prod(factor, axis=1)
    return Signatures(
        classes=tuple(np.array(SURFACE_CLASSES)[seen]),
        nominal=np.array([face_r[face_class == k].mean() for k in seen_classes]),
        nominal_s=np.array([face_s[face_class == k].mean() for k in seen_classes]),
        scatters=scatters,
        counts=by_class[0][:, seen],
        shares=np.column_stack([by_class[1][:, seen][:, scatters], by_class[2][:, seen][:, scatters]]),
    )
