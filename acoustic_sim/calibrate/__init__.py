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

Each microphone's delay is fitted too: delaying a simulated signal leaves its Gram products as
they are and turns its inner product with the recording into their cross-correlation at that lag,
kept as a cross-spectrum over the call's band (`SignalGram.spectra`) and evaluated at any
fractional lag, with its derivative, at each step. A coarse search over lags (the correlation of
the nominal simulation with the recording, per microphone) starts each delay on the right cycle
of the carrier.

The emitter's directivity can be fitted as well (`directivity_knots`): its pressure at the call's
centre frequency, piecewise linear over the angle from its axis between knots (1 on the axis, the
knots' values fitted). Each arrival is taken back to an omnidirectional emitter (its amplitude over
the nominal baffled piston's directivity towards the direction it left in, found by reflecting its
arrival direction back through its faces) and shared between the two knots around that angle, so
the recording stays linear in each (signature, knot) group's scale.

Scattering coefficients can be fitted too (`fit_scattering`): the paths then include the scattered
arrivals, traced with the faces each ray met (`PathTracer(scattered_faces=True)`). A scattered
arrival owes sqrt(R (1 - s)) to each face its ray reflected off before and sqrt(R s) to the face
that scattered it (sqrt(R) where an edge band scattered all it reflected), so a signature also
counts, per class, the factors of (1 - s) and of s, and the recording stays linear in each
signature's scale. Without it the specular fit takes s as known, and a recording whose scattered
echoes it leaves out pulls R away from the truth.

A recording's first milliseconds can be left out of the error (`skip_s`, on both sides alike): an
emitter's direct sound, a real sensor's crosstalk or an omnidirectional source's call at the array,
overlaps the first floor echoes and no traced path explains it.

Recordings another engine or a real room made need the scattering fitted again by echo energy
(`fit_scattering_energy`, `calibrate --scattering energy`): their diffuse echoes share no phase with
our scattered arrivals, so the waveform fit returns s = 0 and R at the specular share R (1 - s). The
energy stage holds each class's specular share as the waveform fit found it and fits s and the
recordings' noise to the echo energy in 1 ms bins (`energy` module docstring).

Paths leaving the emitter backwards are in the fit only with an omnidirectional emitter
(`SonarConfig.emitter_pattern` "omni", as image-source engines model one): a baffled piston sends
none. What this fit leaves out: the directivity of an "omni" emitter (the knots shape the baffled
piston), and the directivity and scattering fitted together (a scattered arrival's departure
angle is its ray's, not recorded).
"""

from .directivity import departure_cosine
from .energy import EnergyFit, fit_scattering_energy
from .fit import SignalGram, SurfaceFit, fit_surfaces, loss_and_gradient, signal_gram
from .recordings import load_recordings, recorded_scene, recordings_and_sonar

__all__ = [
    "EnergyFit",
    "SignalGram",
    "SurfaceFit",
    "departure_cosine",
    "fit_scattering_energy",
    "fit_surfaces",
    "load_recordings",
    "loss_and_gradient",
    "recorded_scene",
    "recordings_and_sonar",
    "signal_gram",
]
