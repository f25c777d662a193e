"""Scattering coefficients from echo energies, for recordings another engine or a real room made.

The waveform fit (`fit_surfaces(fit_scattering=True)`) compares signals sample by sample: it
recovers s from recordings our tracer made, whose scattered echoes are its own, but another
engine's diffuse echoes (random point scatterers, a real wall's texture) share no phase with
ours, their products with our scattered signals average to nothing, and s comes back 0 with R at
the specular share R (1 - s) (benchmarks/results/calibrate_sim2real_rough). Their energy does not
average away. This stage keeps each class's specular share rho = R (1 - s) as the waveform fit
found it and fits s (hence R = rho / (1 - s)) and the recordings' noise to their energy in bins of
ENERGY_BIN_S, summed over microphones and pings, on a log scale:

    E_b(s) = c(s)' G_b c(s) + N

with G_b the products of the signature signals' samples in bin b (echoes of one ping add as
pressures, so the cross terms stay), c(s) the signatures' scales and N the noise energy of a bin
(white noise: the same in every bin). Without N the bins between echoes, which hold only noise,
pulled s towards 1 (a smooth room of `crossengine` came back with s = 0.87).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

import scenes

from ..config import SonarConfig, TracerConfig
from ..config_checks import check_memory_for
from .fit import SKIP_TAPER_S, SurfaceFit, skip_window
from .signatures import at_unit_surfaces

ENERGY_BIN_S = 1e-3  # [s] the recordings' energy is compared in bins this long
S_BOUNDS = (1e-4, 0.95)  # where s is searched: log s and log (1 - s) stay finite
S_START = 0.1


@dataclass
class EnergyFit:
    """The energy stage's data and result: per bin (starting at `bin_start_s`) the recordings'
    energy and the simulation's plus the noise, at the waveform fit's s (`before`) and at the
    fitted s (`after`); `noise` the fitted noise energy of a bin; the losses (mean squared log
    ratio) before and after."""

    bin_start_s: np.ndarray
    recorded: np.ndarray
    before: np.ndarray
    after: np.ndarray
    noise: float
    loss_before: float
    loss_after: float


def fit_scattering_energy(
    scene: scenes.Scene,
    poses: np.ndarray,
    signals: np.ndarray,
    config: SonarConfig,
    fit: SurfaceFit,
    tracer: TracerConfig | None = None,
    *,
    absorption: bool = True,
    skip_s: float = 0.0,
    bin_s: float = ENERGY_BIN_S,
    device=None,
    progress: bool = False,
) -> SurfaceFit:
    """`fit` (from `fit_surfaces(..., fit_scattering=True)` on these pings) with each scattering
    class's s fitted to the recordings' echo energy and its R = rho / (1 - s), rho = R (1 - s) as
    `fit` found it (module docstring); its microphones' gains and delays are used as fitted, the
    other classes' values kept, and the stage's data kept in `energy`."""
    from scipy.optimize import minimize

    from ..engine.sonar import Sonar

    if not fit.scattering_fitted.any():
        raise ValueError("fit s by energy after a waveform fit of scattering (fit_scattering=True) that found some")
    signals = np.asarray(signals, dtype=np.float32)
    if signals.shape != (len(poses), config.microphone_count, config.record_samples):
        raise ValueError(f"signals must be (pings, microphones, samples) for these poses, got {signals.shape}")
    fs, window = config.chirp.sample_rate_hz, skip_window(config, skip_s)
    first = int(np.ceil((skip_s + (SKIP_TAPER_S if skip_s else 0.0)) * fs))  # past the skip's ramp
    length = max(1, round(bin_s * fs))
    bins = (config.record_samples - first) // length
    if bins < 2:
        raise ValueError(f"bin_s {bin_s} leaves {bins} bins after the skipped {skip_s} s: give shorter bins")
    span = slice(first, first + bins * length)
    recorded = np.zeros(bins)  # ping by ping: a float64 copy of every ping at once would be the recording's size x 2
    for ping in signals:
        heard = (ping[:, span] * window[span]).astype(np.float64)
        recorded += (heard.reshape(-1, bins, length) ** 2).sum(axis=(0, 2))
    if not (recorded > 0).all():
        raise ValueError("a bin of the recordings holds no energy at all: no noise, no echo; fit by the waveform")
    tracer = dataclasses.replace(tracer or TracerConfig(), scattering=True)
    sonar = Sonar(fit.sonar(config), tracer, device=device, scattered_faces=True)  # the fitted gains and delays
    arrivals = sonar.trace(scene, np.asarray(poses, dtype=np.float64))
    found = at_unit_surfaces(arrivals, scene)
    if found.classes != fit.classes or not np.array_equal(found.scatters, fit.scattering_fitted):
        raise ValueError(f"these pings reflect off {found.classes}, the fit's off {fit.classes}: fit them first")
    keys, group = np.unique(np.column_stack([found.counts, found.shares]), axis=0, return_inverse=True)
    group = group.reshape(-1)
    classes = len(fit.classes)
    reflections, (kept, scattered) = keys[:, :classes], np.split(keys[:, classes:], 2, axis=1)
    scatters = found.scatters
    check_memory_for(
        len(keys) * config.microphone_count * config.record_samples * 8,
        f"the energy fit's signature signals of one ping ({len(keys)} signatures)",
        "fit fewer bounces (--max-bounces) or fewer surface classes at once",
    )
    gram = np.zeros((bins, len(keys), len(keys)))
    for ping in tqdm(range(len(poses)), desc="echo energy", unit="ping", disable=not progress):
        mine = arrivals.pose_index == ping
        chosen = arrivals.select(mine)
        present, chosen.pose_index = np.unique(group[mine], return_inverse=True)
        made = sonar.record(chosen, pose_count=len(present), absorption=absorption) * window
        binned = made[:, :, span].reshape(len(present), -1, bins, length).transpose(2, 0, 1, 3)
        binned = binned.reshape(bins, len(present), -1)  # (bins, present, mics x samples of a bin)
        gram[:, present[:, None], present[None, :]] += binned @ binned.transpose(0, 2, 1)
    # log R per class; for a scattering class its specular share log (R (1 - s)) as fitted, held
    # (elsewhere the arrivals kept their (1 - s) at unit surfaces)
    rho = np.log(fit.reflection)
    rho[scatters] += np.log1p(-fit.scattering[scatters])

    def energy(s: np.ndarray) -> np.ndarray:
        log_scale = reflections @ (0.5 * rho)
        log_scale += (kept - reflections[:, scatters]) @ (0.5 * np.log1p(-s)) + scattered @ (0.5 * np.log(s))
        scale = np.exp(log_scale)
        return np.einsum("g,bgh,h->b", scale, gram, scale)

    def loss(theta: np.ndarray) -> float:
        return float(np.mean((np.log(energy(theta[:-1]) + np.exp(theta[-1])) - np.log(recorded)) ** 2))

    highest = np.maximum(np.minimum(S_BOUNDS[1], 1.0 - np.exp(rho[scatters])), S_BOUNDS[0])  # R stays <= 1
    s_before = np.clip(fit.scattering[scatters], S_BOUNDS[0], highest)
    start = np.r_[np.minimum(S_START, highest), np.log(np.percentile(recorded, 5))]
    bounds = [(S_BOUNDS[0], top) for top in highest] + [(None, None)]
    best = minimize(loss, start, method="L-BFGS-B", bounds=bounds)
    s, noise = best.x[:-1], float(np.exp(best.x[-1]))
    before = loss(np.r_[s_before, best.x[-1]])
    done = dataclasses.replace(fit, reflection=fit.reflection.copy(), scattering=fit.scattering.copy())
    done.scattering[scatters] = s
    done.reflection[scatters] = np.exp(rho[scatters]) / (1.0 - s)
    starts = (first + np.arange(bins) * length) / fs
    done.energy = EnergyFit(
        starts, recorded, energy(s_before) + noise, energy(s) + noise, noise, before, float(best.fun)
    )
    return done
