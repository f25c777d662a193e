"""Rough walls for the `crossengine_rough` test set: diffuse backscatter from random point
scatterers on the wall surfaces, written from the literature and independently of our tracer.

The model is the one of ultrasound simulators such as Field II (Jensen 1996): a surface is a cloud
of point scatterers at uniformly random positions with Gaussian random amplitudes, so the echoes
of the scatterers within a resolution cell add with random phase into speckle. Each scatterer
stands for the wall area dA = 1 / density around it and returns Lambert's diffuse share of the
sound that falls on it: of the energy R^2 a wall reflects, the fraction s (the scattering
coefficient, ISO 17497-1) leaves as Lambert radiance (intensity in proportion to
cos(theta_in) cos(theta_out) dA / pi) and 1 - s stays specular (image sources). A point source
whose pressure is p0(t - r / c) / r (pyroomacoustics' convention) thus gives at a microphone

    p(t) = a R sqrt(s cos(theta_in) cos(theta_out) dA / pi) / (r_in r_out) p0(t - (r_in + r_out) / c)

with a ~ N(0, 1), whose mean energy summed over a plane wall is Lambert's. The walls span floor to
ceiling, so whether a microphone sees a scatterer is decided in the floor plan: a scatterer
contributes when the segment from the sensor to it crosses no other wall (the L, T, U and
junction rooms are not convex). Floor and ceiling stay specular; emitter and microphones are
omnidirectional and the air lossless, as in the image-source engine the echoes are added to.

Each (scatterer, microphone) pair's exact delay becomes a band-limited impulse: linear
interpolation on a grid `OVERSAMPLING` times finer than the recording, then an ideal low-pass to
the recording's band in the FFT that also convolves the call (within the call's band the
interpolation's gain is within cos(pi f / (4 fs)) > 0.996 of 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft

SCATTERING_RANGE = (0.1, 0.4)  # scattering coefficient s, drawn per room (uniform)
DENSITY_PER_M2 = 500.0  # scatterers per m^2 of wall (mean of a Poisson process)
OVERSAMPLING = 4  # impulses are placed on a grid this many times finer than the recording


@dataclass(frozen=True, eq=False)
class RoughWalls:
    """The scatterers on a room's walls (fixed for a drive, so the speckle moves with the robot as
    a real wall's does).

    Attributes:
        scattering: Scattering coefficient s of the walls: the diffuse share of reflected energy.
        density_per_m2: Mean number of scatterers per m^2 of wall.
        corners: Floor plan, counter-clockwise, (W, 2) [m]; wall w runs from corner w to w + 1.
        position_m: Scatterer positions (K, 3) [m], on the walls, 0 <= z <= height.
        wall: Index of each scatterer's wall (K,).
        amplitude: Pressure gain of each scatterer before geometry,
            a R sqrt(s dA / pi) with a ~ N(0, 1) (K,).
    """

    scattering: float
    density_per_m2: float
    corners: np.ndarray
    position_m: np.ndarray
    wall: np.ndarray
    amplitude: np.ndarray

    def record(self) -> dict:
        """What an episode record keeps of the walls (JSON)."""
        return {
            "wall_scattering": self.scattering,
            "scatterer_density_per_m2": self.density_per_m2,
            "scatterer_count": len(self.wall),
        }


def draw_rough_walls(
    corners: np.ndarray,
    height_m: float,
    wall_reflection: float,
    rng: np.random.Generator,
    *,
    density_per_m2: float = DENSITY_PER_M2,
    scattering_range: tuple[float, float] = SCATTERING_RANGE,
) -> RoughWalls:
    """A room's rough walls, from `rng`: s uniform in `scattering_range`, then for each wall a
    Poisson number of scatterers at uniform positions with N(0, 1) amplitudes.

    Args:
        corners: Floor plan, counter-clockwise, (W, 2) [m].
        height_m: Wall height [m] (floor to ceiling).
        wall_reflection: Pressure reflection coefficient R of the walls (specular and diffuse together).
        rng: The generator of every draw.
        density_per_m2: Mean scatterers per m^2 of wall.
        scattering_range: Bounds of the uniform scattering coefficient.
    """
    if not density_per_m2 > 0:
        raise ValueError(f"density_per_m2 must be positive, got {density_per_m2}")
    corners = np.asarray(corners, dtype=np.float64)
    scattering = float(rng.uniform(*scattering_range))
    start, edge = corners, np.roll(corners, -1, axis=0) - corners
    counts = rng.poisson(density_per_m2 * np.linalg.norm(edge, axis=1) * height_m)
    wall = np.repeat(np.arange(len(corners)), counts)
    along, z = rng.uniform(size=len(wall)), rng.uniform(0.0, height_m, size=len(wall))
    xy = start[wall] + along[:, None] * edge[wall]
    amplitude = rng.normal(size=len(wall)) * wall_reflection * np.sqrt(scattering / (density_per_m2 * np.pi))
    return RoughWalls(scattering, density_per_m2, corners, np.column_stack([xy, z]), wall, amplitude)


def inward_normals(corners: np.ndarray) -> np.ndarray:
    """Unit normals (W, 2) of a counter-clockwise floor plan's walls, pointing into the room."""
    edge = np.roll(corners, -1, axis=0) - corners
    return np.stack([-edge[:, 1], edge[:, 0]], axis=1) / np.linalg.norm(edge, axis=1, keepdims=True)


def in_sight(corners: np.ndarray, wall: np.ndarray, points_xy: np.ndarray, eye_xy: np.ndarray) -> np.ndarray:
    """Whether each point on a wall is seen from `eye_xy` in the floor plan: the segment from the
    eye to the point crosses no other wall and reaches the wall from inside the room.

    Args:
        corners: Floor plan, counter-clockwise, (W, 2) [m].
        wall: The wall each point lies on (K,).
        points_xy: The points (K, 2) [m].
        eye_xy: Where they are seen from (2,) [m].

    Returns:
        bool (K,).
    """
    a, edge = corners, np.roll(corners, -1, axis=0) - corners
    ray = points_xy - eye_xy  # (K, 2): eye + t ray, 0 < t < 1
    rel = a[None, :, :] - eye_xy  # (1, W, 2)

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    denom = cross(ray[:, None, :], edge[None, :, :])  # (K, W)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = cross(rel, edge[None, :, :]) / denom  # along the ray
        u = cross(rel, ray[:, None, :]) / denom  # along the wall
    crosses = (np.abs(denom) > 1e-12) & (t > 0) & (t < 1 - 1e-9) & (u >= 0) & (u <= 1)
    crosses[np.arange(len(wall)), wall] = False  # its own wall, at t = 1
    facing = np.einsum("kd,kd->k", -ray, inward_normals(corners)[wall]) > 0
    return facing & ~crosses.any(axis=1)


def band_limited_echoes(
    delay_s: np.ndarray, gain: np.ndarray, call: np.ndarray, *, sample_rate_hz: float, samples: int
) -> np.ndarray:
    """Sum of delayed, scaled copies of `call` per microphone, band-limited to the recording's rate.

    Args:
        delay_s: Delay of each echo at each microphone (K, M) [s], >= 0.
        gain: Pressure gain of each echo at each microphone (K, M).
        call: The emitted waveform (C,), at `sample_rate_hz`.
        sample_rate_hz: Sample rate of the call and of the result [Hz].
        samples: Samples per microphone of the result (sample 0 at the start of the call).

    Returns:
        float64 (M, samples).
    """
    mics = delay_s.shape[1]
    size = scipy.fft.next_fast_len(samples + len(call), real=True)  # no echo in the recording wraps around
    fine = OVERSAMPLING * size
    position = np.minimum(delay_s * (OVERSAMPLING * sample_rate_hz), fine - 2.0)  # later ones are muted below
    index = position.astype(np.int64)  # floor: delays are >= 0
    frac = position - index
    weight = np.where(index < OVERSAMPLING * samples, gain, 0.0)  # later echoes start after the recording
    index += np.arange(mics) * fine  # row of each microphone
    impulses = np.bincount(index.ravel(), (weight * (1.0 - frac)).ravel(), minlength=mics * fine)
    impulses[1:] += np.bincount(index.ravel(), (weight * frac).ravel(), minlength=mics * fine - 1)
    spectrum = scipy.fft.rfft(impulses.reshape(mics, fine), axis=1)[:, : size // 2 + 1]  # the band of the recording
    echoes = scipy.fft.irfft(spectrum * scipy.fft.rfft(call, size), size, axis=1)
    return echoes[:, :samples]


def scatterer_paths(
    walls: RoughWalls, emitter_m: np.ndarray, microphones_m: np.ndarray, *, speed_of_sound: float, reach_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Delay and pressure gain of each scatterer's echo at each microphone (module docstring's
    model), for the scatterers in sight of the emitter whose path may fit in the recording.

    Args:
        walls: The scatterers.
        emitter_m: Emitter position in the room (3,) [m].
        microphones_m: Microphone positions in the room (M, 3) [m].
        speed_of_sound: [m/s].
        reach_m: Longest path a recording holds [m]; scatterers farther than half of it (plus a
            margin for the array's size) are left out.

    Returns:
        Indices of those scatterers into `walls` (K,), their delays (K, M) [s] and gains (K, M).
    """
    emitter_m, microphones_m = np.asarray(emitter_m, np.float64), np.asarray(microphones_m, np.float64)
    r_in = np.linalg.norm(walls.position_m - emitter_m, axis=1)
    near = np.flatnonzero(2.0 * r_in < reach_m + 0.5)  # the array is a few cm across
    near = near[in_sight(walls.corners, walls.wall[near], walls.position_m[near, :2], emitter_m[:2])]
    position, r_in = walls.position_m[near], r_in[near]
    normal = np.pad(inward_normals(walls.corners)[walls.wall[near]], ((0, 0), (0, 1)))  # walls are vertical
    cos_in = np.einsum("kd,kd->k", emitter_m - position, normal) / r_in
    # |m - x|^2 and n . (m - x) as products (K, 3) x (3, M): no (K, M, 3) arrays
    centre = microphones_m.mean(axis=0)
    x, m = position - centre, microphones_m - centre
    r_out = np.sqrt(np.maximum(np.einsum("kd,kd->k", x, x)[:, None] - 2.0 * x @ m.T + np.einsum("md,md->m", m, m), 0.0))
    cos_out = (normal @ m.T - np.einsum("kd,kd->k", normal, x)[:, None]) / r_out
    lambert = np.sqrt(np.clip(cos_in[:, None] * cos_out, 0.0, None))
    gain = walls.amplitude[near, None] * lambert / (r_in[:, None] * r_out)
    return near, (r_in[:, None] + r_out) / speed_of_sound, gain


def scattered_echoes(
    walls: RoughWalls,
    emitter_m: np.ndarray,
    microphones_m: np.ndarray,
    call: np.ndarray,
    *,
    sample_rate_hz: float,
    speed_of_sound: float,
    samples: int,
) -> np.ndarray:
    """The diffuse echoes of the rough walls at each microphone (`scatterer_paths`, then
    `band_limited_echoes`).

    Args:
        walls: The scatterers.
        emitter_m: Emitter position in the room (3,) [m].
        microphones_m: Microphone positions in the room (M, 3) [m].
        call: The emitted waveform (C,), at `sample_rate_hz`, as the specular engine is given it.
        sample_rate_hz: Sample rate [Hz].
        speed_of_sound: [m/s], the specular engine's.
        samples: Samples per microphone (sample 0 at the start of the call).

    Returns:
        float64 (M, samples), in the specular engine's units (a direct path of length r is
        call / r).
    """
    reach_m = speed_of_sound * samples / sample_rate_hz
    _, delay, gain = scatterer_paths(walls, emitter_m, microphones_m, speed_of_sound=speed_of_sound, reach_m=reach_m)
    return band_limited_echoes(delay, gain, call, sample_rate_hz=sample_rate_hz, samples=samples)
