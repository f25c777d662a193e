"""The fit: signature signals and their Gram products, the loss and its gradient, L-BFGS."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

import scenes
from scenes.surfaces import with_surfaces

from ..array import piston_directivity
from ..config import SonarConfig, TracerConfig
from .directivity import by_knot
from .signatures import at_unit_surfaces

BLOCK_BYTES = 512e6  # the signature signals held at once (float64: signatures x pings x mics x samples)
MAX_DELAY_S = 20e-6  # how far a microphone's fitted delay may go either way (9 samples at 450 kHz)
BAND_FLOOR = 1e-3  # the call's band: frequencies within 60 dB of its spectrum's peak
SKIP_TAPER_S = 0.1e-3  # a skipped start ends in a raised-cosine ramp this long, not a step


@dataclass
class SignalGram:
    """The fit's data: per microphone m, the inner products of the signature signals U_g (summed
    over the pings) with each other (`gram[m]`, G x G) and with the recording x (`cross[m]`, G),
    and the recording's energy `energy[m]`. Every simulated recording y_m = g_m sum_g c_g U_gm
    has squared error g_m^2 c' gram[m] c - 2 g_m c' cross[m] + energy[m].

    With delays, U_gm delayed by tau_m samples meets the recording in `cross_at(tau)`: the
    cross-spectrum `spectra[m, g]` over the call's band (angular frequencies `omega` [rad per
    sample], Hermitian weights `weight` over the FFT length) turned back into a correlation at tau.

    With a fitted directivity a group is a (signature, knot) pair: `knot` (G,) the knot its
    arrivals share (0 on the axis, pinned to 1), its scale c_g times that knot's value.

    With fitted scattering, a signature also counts per scattering class the reflections that keep
    their specular share (`kept`, a factor sqrt(1 - s) each) and the scatterings (`scattered`,
    sqrt(s) each): c_g = prod_k R_k^(n_k / 2) (1 - s_k)^(kept_k / 2) s_k^(scattered_k / 2).

    Attributes:
        signatures: Reflections off each fitted class per signature, int (G, K).
        gram, cross, energy: (M, G, G), (M, G), (M,), float64.
        spectra, omega, weight: (M, G, F) complex128, (F,), (F,); None where not kept.
        knot, knot_deg: (G,) int and the knots' angles from the emitter axis [deg]; None without.
        kept, scattered: (G, S) int for the S classes whose scattering is fitted; None without.
        scattering_class: (S,) those classes, as indices into the fit's classes; None without.
    """

    signatures: np.ndarray
    gram: np.ndarray
    cross: np.ndarray
    energy: np.ndarray
    spectra: np.ndarray | None = None
    omega: np.ndarray | None = None
    weight: np.ndarray | None = None
    knot: np.ndarray | None = None
    knot_deg: np.ndarray | None = None
    kept: np.ndarray | None = None
    scattered: np.ndarray | None = None
    scattering_class: np.ndarray | None = None

    @property
    def fitted_knots(self) -> int:
        """The knots whose values are fitted (every one but the axis')."""
        return 0 if self.knot_deg is None else len(self.knot_deg) - 1

    @property
    def fitted_scattering(self) -> int:
        """The classes whose scattering coefficient is fitted."""
        return 0 if self.kept is None else self.kept.shape[1]

    def cross_at(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inner products of the signature signals delayed by tau (M,) samples with the recording,
        and their derivatives in tau: (M, G) each."""
        turn = self.weight * np.exp(1j * self.omega * tau[:, None])  # (M, F)
        at = np.einsum("mgf,mf->mg", self.spectra, turn)
        slope = np.einsum("mgf,mf->mg", self.spectra, turn * (1j * self.omega))
        return at.real, slope.real


@dataclass
class SurfaceFit:
    """A calibration's result.

    Attributes:
        classes: The surface classes the paths reflect off (of walls, floor, ceiling, objects).
        reflection: Fitted energy reflection coefficient R per class, as `classes`.
        nominal: Where the fit started: per class the scene's R, averaged over the class's faces.
        mic_gain_db: Fitted gain per microphone [dB] (0 where gains were not fitted).
        mic_delay_s: Fitted extra delay per microphone [s] (0 where delays were not fitted).
        directivity_deg, directivity, directivity_nominal: The knots' angles from the emitter's
            axis [deg], the fitted pressure there (1 on the axis) and the nominal piston's; empty
            where the directivity was not fitted.
        loss: The relative squared error (error energy over the recording's) at each step.
        signatures: How many signatures (groups of arrivals scaling together) the fit saw.
        scattering, scattering_nominal: Per class the fitted energy scattering coefficient s and
            where it started (the class's faces' mean); empty where scattering was not fitted,
            and nominal wherever no scattered arrival came off the class.
        scattering_fitted: Per class whether its s was fitted (bool); empty without.
        energy: The energy stage's bins and fit, where s was fitted to echo energies.
    """

    classes: tuple[str, ...]
    reflection: np.ndarray
    nominal: np.ndarray
    mic_gain_db: np.ndarray
    mic_delay_s: np.ndarray
    loss: list[float]
    signatures: int
    directivity_deg: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    directivity: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    directivity_nominal: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    scattering: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    scattering_nominal: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    scattering_fitted: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=bool))
    energy: object = None  # an energy.EnergyFit where s was fitted to echo energies (`fit_scattering_energy`)

    def surfaces(self) -> dict[str, dict[str, float]]:
        """The fit as acoustics per surface class, e.g. {"walls": {"reflection": 0.8, "scattering": 0.1}}
        (scattering where it was fitted)."""
        found = {name: {"reflection": float(r)} for name, r in zip(self.classes, self.reflection, strict=True)}
        for name, (s, _) in self.fitted_scattering().items():
            found[name]["scattering"] = s
        return found

    def fitted_scattering(self) -> dict[str, tuple[float, float]]:
        """Per class whose s was fitted: (fitted s, where it started)."""
        return {
            name: (float(s), float(s0))
            for name, s, s0, fitted in zip(
                self.classes, self.scattering, self.scattering_nominal, self.scattering_fitted, strict=False
            )
            if fitted
        }

    def scene(self, scene: scenes.Scene) -> scenes.Scene:
        """`scene` with every material of a fitted class reflecting the fitted R (and scattering the
        fitted s, where it was fitted)."""
        return with_surfaces(scene, self.surfaces())

    def sonar(self, config: SonarConfig) -> SonarConfig:
        """`config` with the fitted gain and delay of each microphone and, where the directivity
        was fitted, the baffled piston closest to it (`piston_radius_m`)."""
        emitter = {"emitter_radius_m": self.piston_radius_m(config)} if len(self.directivity) else {}
        return dataclasses.replace(
            config,
            microphone_gain=tuple(float(g) for g in 10 ** (self.mic_gain_db / 20)),
            microphone_delay_s=tuple(float(d) for d in self.mic_delay_s),
            **emitter,
        )

    def piston_radius_m(self, config: SonarConfig) -> float:
        """The radius of the baffled piston whose directivity at the call's centre frequency is
        closest (least squares over the knots) to the fitted one, 0.5-20 mm in steps of 0.05 mm."""
        if not len(self.directivity):
            raise ValueError("the directivity was not fitted (directivity_knots = 0)")
        radii = np.arange(0.5e-3, 20e-3 + 1e-9, 0.05e-3)
        centre, air = config.chirp.centre_frequency_hz, config.atmosphere.speed_of_sound
        shapes = piston_directivity(np.radians(self.directivity_deg)[None, :], centre, radii[:, None], air)
        return float(radii[((shapes - self.directivity) ** 2).sum(axis=1).argmin()])


def signal_gram(
    scene: scenes.Scene,
    poses: np.ndarray,
    signals: np.ndarray,
    config: SonarConfig,
    tracer: TracerConfig | None = None,
    *,
    absorption: bool = True,
    directivity_knots: int = 0,
    scattering: bool = False,
    skip_s: float = 0.0,
    device=None,
    progress: bool = False,
) -> tuple[SignalGram, tuple[str, ...], np.ndarray, np.ndarray]:
    """Trace `poses` in `scene` once (specular paths, and with `scattering` the scattered ones
    too), group the arrivals by signature (and, with `directivity_knots` > 0, by knot of the
    emitter's directivity, that many every 90 / knots degrees from the axis) and reduce the
    recorded `signals` (pings, mics, samples) against each group's signals, both weighted by
    `skip_window(skip_s)`; returns the Gram data, the surface classes the paths reflect off, their
    nominal R and their nominal s."""
    from ..engine.sonar import Sonar

    poses = np.asarray(poses, dtype=np.float64)
    signals = np.asarray(signals, dtype=np.float32)
    shape = (len(poses), config.microphone_count, config.record_samples)
    if signals.shape != shape:
        raise ValueError(
            f"signals must be (pings, microphones, samples) = {shape} for these poses, got {signals.shape}"
        )
    if not np.isfinite(signals).all():
        raise ValueError("signals hold non-finite samples")
    if scattering and directivity_knots > 0:
        raise ValueError("fitting scattering and the emitter's directivity together is not supported yet: choose one")
    if directivity_knots > 0 and config.emitter_pattern != "piston":
        raise ValueError("the directivity knots shape a baffled piston: this emitter is omni (sonar.emitter_pattern)")
    window = skip_window(config, skip_s)
    signals = signals * window  # a copy: the caller's recording stays as it was
    tracer = dataclasses.replace(tracer or TracerConfig(), scattering=scattering)
    sonar = Sonar(config, tracer, device=device, scattered_faces=scattering)
    arrivals = sonar.trace(scene, poses)
    found = at_unit_surfaces(arrivals, scene)  # each arrival at R = 1 (and s's factors at 1) on its faces
    classes, nominal, nominal_s, scatters = found.classes, found.nominal, found.nominal_s, found.scatters
    counts, shares = found.counts, found.shares
    knot = knot_deg = None
    if directivity_knots > 0:
        arrivals, counts, knot, knot_deg = by_knot(arrivals, counts, scene, poses, config, directivity_knots)
        keys, group = np.unique(np.column_stack([counts, knot]), axis=0, return_inverse=True)
        signatures, knot = keys[:, : counts.shape[1]], keys[:, -1]
    else:
        keys, group = np.unique(np.column_stack([counts, shares]), axis=0, return_inverse=True)
        signatures, shares = keys[:, : counts.shape[1]], keys[:, counts.shape[1] :]
    group = group.reshape(-1)
    mics, count = config.microphone_count, len(signatures)
    gram = np.zeros((mics, count, count))
    cross = np.zeros((mics, count))
    energy = np.zeros(mics)
    size, band = _delay_band(config)
    spectra = np.zeros((mics, count, len(band)), dtype=np.complex128)
    per_block = max(1, int(BLOCK_BYTES // (count * mics * config.record_samples * 8)))
    blocks = range(0, len(poses), per_block)
    for first in tqdm(blocks, desc="signature signals", unit="block", disable=not progress):
        last = min(first + per_block, len(poses))
        mine = (arrivals.pose_index >= first) & (arrivals.pose_index < last)
        block = np.zeros((count, mics, (last - first) * config.record_samples))
        heard = np.fft.rfft(signals[first:last].astype(np.float64), n=size, axis=-1)[..., band]  # (pings, mics, F)
        # Every group's pings in one call (whose pings the CPU splits over its cores), each (group, ping)
        # a ping of its own; one with no arrival stays silent, unrecorded.
        chosen = arrivals.select(mine)
        pings = last - first
        heard_in, chosen.pose_index = np.unique(group[mine] * pings + chosen.pose_index - first, return_inverse=True)
        recorded = np.zeros((count * pings, mics, config.record_samples), dtype=np.float32)
        recorded[heard_in] = sonar.record(chosen, pose_count=len(heard_in), absorption=absorption)
        recorded *= window
        recorded = recorded.reshape(count, pings, mics, -1)  # (G, pings, mics, samples)
        for g in range(count):
            block[g] = recorded[g].transpose(1, 0, 2).reshape(mics, -1)
            made = np.fft.rfft(recorded[g].astype(np.float64), n=size, axis=-1)[..., band]
            spectra[:, g] += np.einsum("pmf,pmf->mf", made.conj(), heard)
        measured = signals[first:last].transpose(1, 0, 2).reshape(mics, -1).astype(np.float64)
        by_mic = block.transpose(1, 0, 2)  # (mics, G, samples)
        gram += by_mic @ by_mic.transpose(0, 2, 1)
        cross += np.einsum("mgt,mt->mg", by_mic, measured)
        energy += np.einsum("mt,mt->m", measured, measured)
    weight = np.where((band == 0) | (2 * band == size), 1.0, 2.0) / size  # rfft's bins stand for two but DC, Nyquist
    omega = 2 * np.pi * band / size
    data = SignalGram(signatures, gram, cross, energy, spectra, omega, weight, knot, knot_deg)
    if scatters.any():
        data.kept, data.scattered = np.split(shares, 2, axis=1)
        data.scattering_class = np.nonzero(scatters)[0]
    return data, classes, nominal, nominal_s


def skip_window(config: SonarConfig, skip_s: float) -> np.ndarray:
    """Weights (samples,) float32 that leave out a recording's first `skip_s` seconds (the
    emitter's direct sound and ringing, which no traced path explains), rising to 1 over
    SKIP_TAPER_S after them; all ones for skip_s = 0."""
    if not 0.0 <= skip_s < config.record_samples / config.chirp.sample_rate_hz:
        raise ValueError(f"skip_s must be in [0, the recording's length), got {skip_s}")
    if skip_s == 0.0:
        return np.ones(config.record_samples, dtype=np.float32)
    t = np.arange(config.record_samples) / config.chirp.sample_rate_hz - skip_s
    ramp = 0.5 - 0.5 * np.cos(np.pi * np.clip(t / SKIP_TAPER_S, 0.0, 1.0))
    return ramp.astype(np.float32)


def _delay_band(config: SonarConfig) -> tuple[int, np.ndarray]:
    """The FFT length that holds a ping's samples and the largest delay, and the bins of the call's
    band in it (where the simulated signals have their energy)."""
    from scipy.fft import next_fast_len

    reach = int(np.ceil(MAX_DELAY_S * config.chirp.sample_rate_hz)) + 1
    size = next_fast_len(config.record_samples + 2 * reach)
    call = np.abs(np.fft.rfft(config.chirp.samples(), n=size))
    return size, np.nonzero(call >= BAND_FLOOR * call.max())[0]


def loss_and_gradient(theta: np.ndarray, data: SignalGram, fit_gains: bool, fit_delays: bool = False):
    """The relative squared error and its gradient at theta = (log R per class, then s per class
    whose scattering is fitted where the data have such classes, then the directivity at each
    fitted knot where the data have knots, then log gain per microphone where `fit_gains`, then
    delay per microphone [samples] where `fit_delays`)."""
    classes, scattering = data.signatures.shape[1], data.fitted_scattering
    knots, mics = data.fitted_knots, len(data.energy)
    log_r = theta[:classes]
    s = theta[classes : classes + scattering]
    first_knot = classes + scattering
    log_g = theta[first_knot + knots : first_knot + knots + mics] if fit_gains else np.zeros(mics)
    tau = theta[len(theta) - mics :] if fit_delays else None
    gains = np.exp(log_g)
    base = _signature_scale(data, log_r, s)
    at_knot = np.concatenate([[1.0], theta[first_knot : first_knot + knots]])[data.knot] if knots else 1.0
    scale = base * at_knot  # c_g (G,)
    quad = np.einsum("g,mgh,h->m", scale, data.gram, scale)  # c' A_m c
    cross, slope = data.cross_at(tau) if fit_delays else (data.cross, None)
    lin = cross @ scale  # c' b_m
    total = data.energy.sum()
    loss = (gains**2 * quad - 2 * gains * lin + data.energy).sum() / total
    d_scale = 2 * np.einsum("m,mgh,h->g", gains**2, data.gram, scale) - 2 * (gains[:, None] * cross).sum(axis=0)
    grad = [data.signatures.T @ (d_scale * scale) * 0.5 / total]
    if scattering:  # d log c_g / d s_k = (scattered_gk / s_k - kept_gk / (1 - s_k)) / 2
        per_s = data.scattered / s - data.kept / (1.0 - s)
        grad.append(per_s.T @ (d_scale * scale) * 0.5 / total)
    if knots:
        grad.append(np.bincount(data.knot, weights=d_scale * base, minlength=knots + 1)[1:] / total)
    if fit_gains:
        grad.append((2 * gains**2 * quad - 2 * gains * lin) / total)
    if fit_delays:
        grad.append(-2 * gains * (slope @ scale) / total)
    return loss, np.concatenate(grad)


def _signature_scale(data: SignalGram, log_r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Each signature's scale at these log R and s (the signature signals are at R = 1 and s's
    factors 1), (G,)."""
    exponent = data.signatures @ (0.5 * log_r)
    if data.fitted_scattering:
        exponent = exponent + data.kept @ (0.5 * np.log1p(-s)) + data.scattered @ (0.5 * np.log(s))
    return np.exp(exponent)


def _coarse_delays(data: SignalGram, scale: np.ndarray, reach: float) -> np.ndarray:
    """Per microphone, the lag [samples] within +-reach (steps of a quarter sample) at which the
    nominal simulation correlates best with the recording: the fit's start, on the carrier's right
    cycle."""
    lags = np.arange(-reach, reach + 1e-9, 0.25)
    total = np.einsum("mgf,g->mf", data.spectra, scale) * data.weight  # (M, F)
    correlation = (total[:, None, :] * np.exp(1j * data.omega * lags[:, None])).sum(axis=-1).real  # (M, lags)
    return lags[correlation.argmax(axis=1)]


def fit_surfaces(
    scene: scenes.Scene,
    poses: np.ndarray,
    signals: np.ndarray,
    config: SonarConfig,
    tracer: TracerConfig | None = None,
    *,
    fit_gains: bool = True,
    fit_delays: bool = True,
    directivity_knots: int = 0,
    fit_scattering: bool = False,
    absorption: bool = True,
    skip_s: float = 0.0,
    device=None,
    progress: bool = False,
    max_steps: int = 500,
) -> SurfaceFit:
    """Fit the energy reflection coefficient of each surface class of the scene (walls, floor,
    ceiling, objects: `scenes.surfaces`) that these pings' specular paths reflect off and, with
    `fit_gains`, each microphone's gain and, with `fit_delays`, its delay (within +-MAX_DELAY_S) to
    recorded `signals` (pings, mics, samples) made at `poses`
    (sensor-to-world (N, 4, 4)) by a sonar `config` in the room `scene` describes (its geometry
    right; its materials' R the starting point, their scattering taken as known unless
    `fit_scattering`).

    Minimises the squared error between simulated and recorded signals, relative to the
    recording's energy, by L-BFGS on log R (R within (0, 1]), log gain and delay. With
    `directivity_knots` > 0 the emitter's directivity too (module docstring), from the nominal
    piston's. With `fit_scattering` the paths include scattered arrivals (`tracer`'s rays rain
    them) and each class's energy scattering coefficient s is fitted too, from its faces' mean;
    a class whose materials scatter nothing (s = 0) sends no scattered arrival to fit it by and
    keeps its s. `absorption`: whether the recording's air absorbs (real air does; a simulation
    may have left it out). `skip_s`: the first seconds of every recording left out of the error
    (the emitter's direct sound; the simulation's too), `skip_window`."""
    from scipy.optimize import minimize

    if directivity_knots < 0:
        raise ValueError(f"directivity_knots must be >= 0 (0: the nominal directivity), got {directivity_knots}")
    data, classes, nominal, nominal_s = signal_gram(
        scene,
        poses,
        signals,
        config,
        tracer,
        absorption=absorption,
        directivity_knots=directivity_knots,
        scattering=fit_scattering,
        skip_s=skip_s,
        device=device,
        progress=progress,
    )
    s0 = nominal_s[data.scattering_class] if data.fitted_scattering else np.zeros(0)
    mics, fs = config.microphone_count, config.chirp.sample_rate_hz
    reach = MAX_DELAY_S * fs
    air, centre = config.atmosphere.speed_of_sound, config.chirp.centre_frequency_hz
    piston = (
        piston_directivity(np.radians(data.knot_deg), centre, config.emitter_radius_m, air)
        if data.knot_deg is not None
        else np.zeros(0)
    )
    theta0 = [np.log(nominal), s0, piston[1:], np.zeros(mics if fit_gains else 0)]
    bounds = [(np.log(1e-4), 0.0)] * len(classes) + [(1e-4, 1.0 - 1e-4)] * len(s0)
    bounds += [(-2.0, 2.0)] * data.fitted_knots + [(None, None)] * (mics if fit_gains else 0)
    if fit_delays:
        start = _signature_scale(data, np.log(nominal), s0)
        if data.fitted_knots:
            start = start * piston[data.knot]
        theta0.append(_coarse_delays(data, start, reach))
        bounds += [(-reach, reach)] * mics
    theta0 = np.concatenate(theta0)
    losses: list[float] = []
    bar = tqdm(total=max_steps, desc="fit", unit="step", disable=not progress)

    def step(theta):
        loss, grad = loss_and_gradient(theta, data, fit_gains, fit_delays)
        losses.append(float(loss))
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.3g}")
        return loss, grad

    done = minimize(step, theta0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxfun": max_steps})
    bar.total = bar.n  # converged before the step budget: the bar ends full
    bar.close()
    k, knots, first_knot = len(classes), data.fitted_knots, len(classes) + len(s0)
    reflection = np.exp(done.x[:k])
    gains_db = 20 / np.log(10) * done.x[first_knot + knots : first_knot + knots + mics] if fit_gains else np.zeros(mics)
    delays_s = done.x[len(done.x) - mics :] / fs if fit_delays else np.zeros(mics)
    signatures = len(np.unique(data.signatures, axis=0))
    fit = SurfaceFit(classes, reflection, nominal, gains_db, delays_s, losses, signatures)
    if knots:
        fit.directivity_deg, fit.directivity_nominal = data.knot_deg, piston
        fit.directivity = np.concatenate([[1.0], done.x[first_knot : first_knot + knots]])
    if fit_scattering:
        fit.scattering, fit.scattering_nominal = nominal_s.copy(), nominal_s
        fit.scattering_fitted = np.zeros(k, dtype=bool)
        if data.fitted_scattering:
            fit.scattering[data.scattering_class] = done.x[k:first_knot]
            fit.scattering_fitted[data.scattering_class] = True
    return fit
