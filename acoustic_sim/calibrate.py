"""Calibrate the simulator to recordings of a known room: the reflection coefficient of each surface
class (walls, floor, ceiling, objects: `scenes.surfaces`) and the microphones' gains, fitted by
gradient to recorded microphone signals.

The paths are traced once, with the scene's own coefficients. A specular path off planes owes its
amplitude to the faces it reflects off (`Arrivals.faces`): a factor sqrt(R (1 - s)) each. Each
arrival is taken back to R = 1 on its faces (its amplitude over the product of their sqrt(R)), so
that with the classes' R it scales by the product of R_k^(n_k / 2), n_k its reflections off class k.
The arrivals with the same n (one *signature*) scale together, and a recording is linear in those
scale factors. Each signature's signals are recorded once, and the squared error between simulated
and recorded signals reduces to a small Gram matrix per microphone (`SignalGram`), so every step of
the fit costs microseconds whatever the number of pings. A fit sets every material of a class to
one R (`scenes.surfaces.with_surfaces`), as a suite's `surfaces` physics does.

What this fit leaves out (to come): scattered echoes (their faces are not recorded yet, so the
tracer runs without them and a recording that holds them biases R upwards), the emitter's
directivity and the microphones' delays.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

import scenes
from scenes.surfaces import SURFACE_CLASSES, surface_classes, with_surfaces

from .config import SonarConfig, TracerConfig

BLOCK_BYTES = 512e6  # the signature signals held at once (float64: signatures x pings x mics x samples)


@dataclass
class SignalGram:
    """The fit's data: per microphone m, the inner products of the signature signals U_g (summed
    over the pings) with each other (`gram[m]`, G x G) and with the recording x (`cross[m]`, G),
    and the recording's energy `energy[m]`. Every simulated recording y_m = g_m sum_g c_g U_gm
    has squared error g_m^2 c' gram[m] c - 2 g_m c' cross[m] + energy[m].

    Attributes:
        signatures: Reflections off each fitted class per signature, int (G, K).
        gram, cross, energy: (M, G, G), (M, G), (M,), float64.
    """

    signatures: np.ndarray
    gram: np.ndarray
    cross: np.ndarray
    energy: np.ndarray


@dataclass
class SurfaceFit:
    """A calibration's result.

    Attributes:
        classes: The surface classes the paths reflect off (of walls, floor, ceiling, objects).
        reflection: Fitted energy reflection coefficient R per class, as `classes`.
        nominal: Where the fit started: per class the scene's R, averaged over the class's faces.
        mic_gain_db: Fitted gain per microphone [dB] (0 where gains were not fitted).
        loss: The relative squared error (error energy over the recording's) at each step.
        signatures: How many signatures (groups of arrivals scaling together) the fit saw.
    """

    classes: tuple[str, ...]
    reflection: np.ndarray
    nominal: np.ndarray
    mic_gain_db: np.ndarray
    loss: list[float]
    signatures: int

    def surfaces(self) -> dict[str, dict[str, float]]:
        """The fit as acoustics per surface class, e.g. {"walls": {"reflection": 0.8}}."""
        return {name: {"reflection": float(r)} for name, r in zip(self.classes, self.reflection, strict=True)}

    def scene(self, scene: scenes.Scene) -> scenes.Scene:
        """`scene` with every material of a fitted class reflecting the fitted R."""
        return with_surfaces(scene, self.surfaces())


def load_recordings(path, pings: int | None = None, episode: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 4, 4) and microphone signals (N, mics, samples) float32 of recorded pings, from a
    .npz holding `poses` and `signals`, or from a dataset folder (or one shard) made with
    `generate --signals`: the frames of one `episode` (one room; required where the data hold
    several). With `pings`, at most that many, evenly spaced."""
    path = Path(path)
    if path.suffix == ".npz":
        poses, signals = _npz_recordings(path)
    elif path.is_dir() or path.suffix == ".h5":
        poses, signals = _shard_recordings(path, episode)
    else:
        raise ValueError(
            f"{path}: recordings come as a .npz with `poses` (N, 4, 4) and `signals` (N, mics, samples), or a "
            "dataset folder (or shard) made with generate --signals"
        )
    if pings is not None and pings < len(poses):
        if pings < 1:
            raise ValueError(f"pings must be >= 1, got {pings}")
        chosen = np.linspace(0, len(poses) - 1, pings).round().astype(int)
        poses, signals = poses[chosen], signals[chosen]
    return poses, signals


def _npz_recordings(path) -> tuple[np.ndarray, np.ndarray]:
    with np.load(path) as data:
        missing = [k for k in ("poses", "signals") if k not in data]
        if missing:
            raise ValueError(f"{path} lacks {' and '.join(missing)}; it holds {', '.join(data.files) or 'nothing'}")
        poses, signals = np.asarray(data["poses"], np.float64), np.asarray(data["signals"], np.float32)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or signals.ndim != 3 or len(signals) != len(poses):
        raise ValueError(
            f"{path}: poses {poses.shape} and signals {signals.shape} must be (N, 4, 4) and (N, mics, samples)"
        )
    return poses, signals


def _shard_recordings(path, episode: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The poses and signals of one episode of a dataset folder or shard."""
    import h5py

    from .datasets.shards import dataset_shards

    shards = dataset_shards(path) if path.is_dir() else [path]
    found = []
    for shard in shards:
        with h5py.File(shard, "r") as f:
            if "signals" not in f:
                raise ValueError(f"{shard} holds no microphone signals: make the dataset with generate --signals")
            episodes = f["episode"][()]
            if episode is None and len(set(episodes.tolist()) | {e for e, *_ in found}) > 1:
                listed = sorted(set(episodes.tolist()) | {e for e, *_ in found})
                raise ValueError(f"{path} holds episodes {listed[:10]}: give one (--episode), one room a fit")
            rows = episodes == (episodes[0] if episode is None else episode)
            if rows.any():
                found.append((int(episodes[rows][0]), f["pose"][rows], f["signals"][rows]))
    if not found:
        raise ValueError(f"{path} holds no frames of episode {episode}")
    poses = np.concatenate([p for _, p, _ in found]).astype(np.float64)
    signals = np.concatenate([s for _, _, s in found]).astype(np.float32)
    return poses, signals


def signal_gram(
    scene: scenes.Scene,
    poses: np.ndarray,
    signals: np.ndarray,
    config: SonarConfig,
    tracer: TracerConfig | None = None,
    *,
    absorption: bool = True,
    device=None,
    progress: bool = False,
) -> tuple[SignalGram, tuple[str, ...], np.ndarray]:
    """Trace `poses` in `scene` once (specular paths), group the arrivals by signature and reduce
    the recorded `signals` (pings, mics, samples) against each signature's signals; returns the
    Gram data, the surface classes the paths reflect off and their nominal R."""
    from .engine.sonar import Sonar

    poses = np.asarray(poses, dtype=np.float64)
    signals = np.asarray(signals, dtype=np.float32)
    shape = (len(poses), config.microphone_count, config.record_samples)
    if signals.shape != shape:
        raise ValueError(
            f"signals must be (pings, microphones, samples) = {shape} for these poses, got {signals.shape}"
        )
    if not np.isfinite(signals).all():
        raise ValueError("signals hold non-finite samples")
    tracer = dataclasses.replace(tracer or TracerConfig(), scattering=False)
    sonar = Sonar(config, tracer, device=device)
    arrivals = sonar.trace(scene, poses)
    face_class = surface_classes(scene)
    face_r = scene.material_table("acoustic_reflection")
    reflecting = arrivals.faces >= 0
    # Each arrival at R = 1 on its faces: its amplitude over the product of their sqrt(R).
    arrivals.amplitude = arrivals.amplitude / np.prod(
        np.sqrt(np.where(reflecting, face_r[arrivals.faces], 1.0)), axis=1
    )
    counts = arrivals.surface_counts(face_class, len(SURFACE_CLASSES))
    seen = counts.sum(axis=0) > 0
    classes = tuple(np.array(SURFACE_CLASSES)[seen])
    nominal = np.array([face_r[face_class == k].mean() for k in np.nonzero(seen)[0]])
    signatures, group = np.unique(counts[:, seen], axis=0, return_inverse=True)
    group = group.reshape(-1)
    mics, count = config.microphone_count, len(signatures)
    gram = np.zeros((mics, count, count))
    cross = np.zeros((mics, count))
    energy = np.zeros(mics)
    per_block = max(1, int(BLOCK_BYTES // (count * mics * config.record_samples * 8)))
    blocks = range(0, len(poses), per_block)
    for first in tqdm(blocks, desc="signature signals", unit="block", disable=not progress):
        last = min(first + per_block, len(poses))
        mine = (arrivals.pose_index >= first) & (arrivals.pose_index < last)
        block = np.zeros((count, mics, (last - first) * config.record_samples))
        for g in range(count):
            chosen = arrivals.select(mine & (group == g))
            chosen.pose_index = chosen.pose_index - first
            recorded = sonar.record(chosen, pose_count=last - first, absorption=absorption)  # (pings, mics, samples)
            block[g] = recorded.transpose(1, 0, 2).reshape(mics, -1)
        measured = signals[first:last].transpose(1, 0, 2).reshape(mics, -1).astype(np.float64)
        by_mic = block.transpose(1, 0, 2)  # (mics, G, samples)
        gram += by_mic @ by_mic.transpose(0, 2, 1)
        cross += np.einsum("mgt,mt->mg", by_mic, measured)
        energy += np.einsum("mt,mt->m", measured, measured)
    return SignalGram(signatures, gram, cross, energy), classes, nominal


def loss_and_gradient(theta: np.ndarray, data: SignalGram, fit_gains: bool):
    """The relative squared error and its gradient at theta = (log R per class, then log gain per
    microphone where `fit_gains`)."""
    classes = data.signatures.shape[1]
    log_r = theta[:classes]
    log_g = theta[classes:] if fit_gains else np.zeros(len(data.energy))
    gains = np.exp(log_g)
    scale = np.exp(data.signatures @ (0.5 * log_r))  # c_g (G,): the signature signals are at R = 1
    quad = np.einsum("g,mgh,h->m", scale, data.gram, scale)  # c' A_m c
    lin = data.cross @ scale  # c' b_m
    total = data.energy.sum()
    loss = (gains**2 * quad - 2 * gains * lin + data.energy).sum() / total
    d_scale = 2 * np.einsum("m,mgh,h->g", gains**2, data.gram, scale) - 2 * (gains[:, None] * data.cross).sum(axis=0)
    d_log_r = data.signatures.T @ (d_scale * scale) * 0.5 / total
    if not fit_gains:
        return loss, d_log_r
    d_log_g = (2 * gains**2 * quad - 2 * gains * lin) / total
    return loss, np.concatenate([d_log_r, d_log_g])


def fit_surfaces(
    scene: scenes.Scene,
    poses: np.ndarray,
    signals: np.ndarray,
    config: SonarConfig,
    tracer: TracerConfig | None = None,
    *,
    fit_gains: bool = True,
    absorption: bool = True,
    device=None,
    progress: bool = False,
    max_steps: int = 500,
) -> SurfaceFit:
    """Fit the energy reflection coefficient of each surface class of the scene (walls, floor,
    ceiling, objects: `scenes.surfaces`) that these pings' specular paths reflect off and, with
    `fit_gains`, each microphone's gain to recorded `signals` (pings, mics, samples) made at `poses`
    (sensor-to-world (N, 4, 4)) by a sonar `config` in the room `scene` describes (its geometry
    right; its materials' R the starting point, their scattering taken as known).

    Minimises the squared error between simulated and recorded signals, relative to the
    recording's energy, by L-BFGS on log R (R within (0, 1]) and log gain. `absorption`: whether the
    recording's air absorbs (real air does; a simulation may have left it out)."""
    from scipy.optimize import minimize

    data, classes, nominal = signal_gram(
        scene, poses, signals, config, tracer, absorption=absorption, device=device, progress=progress
    )
    mics = config.microphone_count
    theta0 = np.concatenate([np.log(nominal), np.zeros(mics if fit_gains else 0)])
    bounds = [(np.log(1e-4), 0.0)] * len(classes) + [(None, None)] * (mics if fit_gains else 0)
    losses: list[float] = []
    bar = tqdm(total=max_steps, desc="fit", unit="step", disable=not progress)

    def step(theta):
        loss, grad = loss_and_gradient(theta, data, fit_gains)
        losses.append(float(loss))
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.3g}")
        return loss, grad

    done = minimize(step, theta0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxfun": max_steps})
    bar.close()
    reflection = np.exp(done.x[: len(classes)])
    gains_db = 20 / np.log(10) * done.x[len(classes) :] if fit_gains else np.zeros(mics)
    return SurfaceFit(classes, reflection, nominal, gains_db, losses, len(data.signatures))
