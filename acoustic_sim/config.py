"""The configuration tree: frozen dataclasses, SI units unless a name ends in `_deg`.

    SimConfig
    ├── lidar: LidarConfig          the scanner that makes the labels
    ├── sonar: SonarConfig          array, emitter, call (ChirpConfig) and air (AtmosphereConfig)
    ├── tracer: TracerConfig        how the path tracer searches for echoes
    └── processing: ProcessingConfig  the beamformer: grid, speed of sound, low-pass, normalisation

Each class checks its own fields when built (ConfigError for NaN/inf, ValueError for a value out
of range); `settings.apply_settings` applies `section.field=value` from the command line
(`clitools`'s grammar, shared with the learner).
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .air import chirp, speed_of_sound
from .config_checks import ConfigError as ConfigError  # re-exported: where readers look for it
from .config_checks import check_finite as check_finite
from .config_checks import check_memory_for

NoiseKind = Literal["none", "gaussian", "uniform"]
NOISE_KINDS: tuple[str, ...] = typing.get_args(NoiseKind)
NOISE_CODES: dict[str, int] = {"none": 0, "gaussian": 1, "uniform": 2}
"""Noise kind -> the integer code the kernels take (kernels.common.NOISE_NONE, ...; a test checks they agree)."""
Normalise = Literal[None, "max", "db"]
# The emitter's pattern: "piston", a circular piston of emitter_radius_m in a baffle (the sensor's y-z
# plane: nothing leaves it backwards); "omni", the same pressure in every direction, behind the
# sensor too (a point source, as image-source engines such as pyroomacoustics model one).
EmitterPattern = Literal["piston", "omni"]
NORMALISE: tuple[str | None, ...] = typing.get_args(Normalise)
MAX_BOUNCES = 10
"""Most secondary reflections a path may have (the tracer's kernels store MAX_BOUNCES + 1 planes)."""


@dataclass(frozen=True, kw_only=True)
class PolarGrid:
    """Range x azimuth grid shared by energyscapes and LiDAR images.

    Bins are [range_min_m + k * range_bin_m, ... + range_bin_m); azimuth bins are centred on
    azimuth_min_deg + j * azimuth_step_deg (azimuth 0 ahead, positive to the left).
    """

    range_min_m: float = 0.2  # [m]
    range_max_m: float = 5.0  # [m]
    range_bin_m: float = 0.02  # [m]
    azimuth_min_deg: float = -90.0  # [deg]
    azimuth_max_deg: float = 90.0  # [deg]
    azimuth_step_deg: float = 1.0  # [deg]

    def __post_init__(self) -> None:
        check_finite(self)
        if not 0 <= self.range_min_m < self.range_max_m:
            raise ValueError("PolarGrid needs 0 <= range_min_m < range_max_m")
        if self.range_bin_m <= 0 or self.azimuth_step_deg <= 0:
            raise ValueError("PolarGrid bin sizes must be positive")
        if not -180 <= self.azimuth_min_deg <= self.azimuth_max_deg <= 180:
            raise ValueError("PolarGrid needs -180 <= azimuth_min_deg <= azimuth_max_deg <= 180")
        if self.range_count < 1:  # every image would be empty
            raise ValueError(f"PolarGrid has no range bin: range_bin_m {self.range_bin_m:g} exceeds its range span")
        check_memory_for(  # a frame's float32 energyscape, its label and the beamformer's work: 16 B a cell
            self.range_count * self.azimuth_count * 16,
            f"PolarGrid of {self.range_count:,} x {self.azimuth_count:,} cells (range_bin_m {self.range_bin_m:g}, "
            f"azimuth_step_deg {self.azimuth_step_deg:g}) for one frame",
            "use larger bins (the default grid is 240 x 181)",
        )

    @property
    def range_count(self) -> int:
        return round((self.range_max_m - self.range_min_m) / self.range_bin_m)

    @property
    def azimuth_count(self) -> int:
        return round((self.azimuth_max_deg - self.azimuth_min_deg) / self.azimuth_step_deg) + 1

    @property
    def shape(self) -> tuple[int, int]:
        return self.range_count, self.azimuth_count

    @property
    def range_m(self) -> np.ndarray:
        """Range bin centres [m], shape (range_count,)."""
        return self.range_min_m + (np.arange(self.range_count) + 0.5) * self.range_bin_m

    @property
    def azimuth_rad(self) -> np.ndarray:
        """Azimuth bin centres [rad], shape (azimuth_count,)."""
        return np.deg2rad(self.azimuth_min_deg + np.arange(self.azimuth_count) * self.azimuth_step_deg)


@dataclass(frozen=True, kw_only=True)
class LidarConfig:
    """A scanning LiDAR: beam pattern, range limits and measurement noise.

    Beams form a regular azimuth x elevation pattern in the sensor frame (x forward, y left,
    z up); with one elevation the scan is planar. Returns closer than `range_min_m` or farther
    than `range_max_m` are misses (inf).
    """

    azimuth_min_deg: float  # first beam [deg]
    azimuth_max_deg: float  # last beam [deg]
    azimuth_count: int  # beams per elevation
    elevation_min_deg: float = 0.0  # [deg]
    elevation_max_deg: float = 0.0  # [deg]
    elevation_count: int = 1  # beams per azimuth (1: a planar scan)
    range_min_m: float  # [m]
    range_max_m: float  # [m]
    rate_hz: float  # scans per second [Hz]
    noise: NoiseKind = "none"  # "gaussian" (std noise_m) or "uniform" (+-noise_m, as in the paper)
    noise_m: float = 0.0  # [m]
    dropout_probability: float = 0.0  # share of beams that return nothing, 0..1

    def __post_init__(self) -> None:
        check_finite(self)
        if self.azimuth_count < 1 or self.elevation_count < 1:
            raise ValueError("LidarConfig needs azimuth_count >= 1 and elevation_count >= 1")
        if self.azimuth_max_deg < self.azimuth_min_deg or self.elevation_max_deg < self.elevation_min_deg:
            raise ValueError("LidarConfig angle ranges must have max >= min")
        if not -90 <= self.elevation_min_deg <= self.elevation_max_deg <= 90:
            raise ValueError("LidarConfig elevations must lie in [-90, 90] degrees")
        if not 0 <= self.range_min_m < self.range_max_m:
            raise ValueError("LidarConfig needs 0 <= range_min_m < range_max_m")
        if self.noise not in NOISE_KINDS:
            raise ValueError(f"LidarConfig.noise must be one of {NOISE_KINDS}, got {self.noise!r}")
        if self.noise_m < 0 or not 0 <= self.dropout_probability <= 1:
            raise ValueError("LidarConfig needs noise_m >= 0 and dropout_probability in [0, 1]")
        if self.rate_hz <= 0:
            raise ValueError("LidarConfig.rate_hz must be positive")
        check_memory_for(  # a beam's direction (float64, then float32) and range: 64 B
            self.beam_count * 64,
            f"LidarConfig.azimuth_count x elevation_count {self.azimuth_count:,} x {self.elevation_count:,} (a scan)",
            "use fewer beams (the Hokuyo has 1,081)",
        )

    @classmethod
    def hokuyo_ust20lx(cls, **overrides) -> LidarConfig:
        """Hokuyo UST-20LX planar scanner: 270 deg in 0.25 deg steps (1081 beams), 0.06-20 m, 40 Hz.

        Noise-free by default; e.g. `noise="gaussian", noise_m=0.012` adds the sensor's ~1.2 cm.
        """
        return dataclasses.replace(
            cls(
                azimuth_min_deg=-135.0,
                azimuth_max_deg=135.0,
                azimuth_count=1081,
                range_min_m=0.06,
                range_max_m=20.0,
                rate_hz=40.0,
            ),
            **overrides,
        )

    @classmethod
    def multibeam_64x1024(cls, **overrides) -> LidarConfig:
        """Spinning 3D LiDAR: 64 channels over -22.5..+22.5 deg, 1024 azimuths over 360 deg, 0.3-100 m."""
        step = 360.0 / 1024
        return dataclasses.replace(
            cls(
                azimuth_min_deg=-180.0,
                azimuth_max_deg=180.0 - step,
                azimuth_count=1024,
                elevation_min_deg=-22.5,
                elevation_max_deg=22.5,
                elevation_count=64,
                range_min_m=0.3,
                range_max_m=100.0,
                rate_hz=10.0,
            ),
            **overrides,
        )

    @property
    def beam_count(self) -> int:
        return self.azimuth_count * self.elevation_count

    @property
    def azimuth_rad(self) -> np.ndarray:
        """Beam azimuths [rad], shape (azimuth_count,)."""
        return np.deg2rad(np.linspace(self.azimuth_min_deg, self.azimuth_max_deg, self.azimuth_count))

    @property
    def elevation_rad(self) -> np.ndarray:
        """Beam elevations [rad], shape (elevation_count,)."""
        return np.deg2rad(np.linspace(self.elevation_min_deg, self.elevation_max_deg, self.elevation_count))

    def beam_directions(self) -> np.ndarray:
        """Unit beam directions in the sensor frame, shape (beam_count, 3), elevation-major.

        Beam b = e * azimuth_count + a, so ranges reshape to (elevation_count, azimuth_count).
        """
        el, az = np.meshgrid(self.elevation_rad, self.azimuth_rad, indexing="ij")
        return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)


@dataclass(frozen=True, kw_only=True)
class ChirpConfig:
    """The emitted call: an FM sweep with Hann tapers (see `air.chirp`)."""

    start_frequency_hz: float = 50e3  # [Hz]
    stop_frequency_hz: float = 25e3  # [Hz]
    duration_s: float = 2.5e-3  # [s]
    sample_rate_hz: float = 450e3  # of the microphones too [Hz]
    sweep: Literal["hyperbolic", "linear"] = "hyperbolic"  # hyperbolic: linear in period
    taper_fraction: float = 0.1  # share of the call in the Hann taper at each end, 0..0.5

    def __post_init__(self) -> None:
        check_finite(self)
        if self.duration_s > 0 and self.sample_rate_hz > 0:  # else chirp() says what is wrong
            check_memory_for(  # the call's phase, taper and samples in float64: 48 B a sample
                self.sample_count * 48,
                f"ChirpConfig.duration_s {self.duration_s:g} ({self.sample_count:,} samples)",
                "give a shorter call (the eRTIS calls for 2.5 ms)",
            )
        chirp(**dataclasses.asdict(self))  # validates every field with a clear message

    @classmethod
    def band_20_80khz(cls, **overrides) -> ChirpConfig:
        return dataclasses.replace(cls(start_frequency_hz=80e3, stop_frequency_hz=20e3), **overrides)

    @classmethod
    def band_25_80khz(cls, **overrides) -> ChirpConfig:
        return dataclasses.replace(cls(start_frequency_hz=80e3, stop_frequency_hz=25e3), **overrides)

    @property
    def sample_count(self) -> int:
        return round(self.duration_s * self.sample_rate_hz) + 1

    @property
    def centre_frequency_hz(self) -> float:
        return 0.5 * (self.start_frequency_hz + self.stop_frequency_hz)

    def samples(self) -> np.ndarray:
        """The call, float64 (sample_count,)."""
        return chirp(**dataclasses.asdict(self))


@dataclass(frozen=True, kw_only=True)
class AtmosphereConfig:
    """Air the sound travels through: sets the speed of sound and ISO 9613-1 absorption."""

    temperature_c: float = 20.0  # [deg C]
    relative_humidity: float = 50.0  # [%]
    pressure_kpa: float = 101.325  # [kPa]

    def __post_init__(self) -> None:
        check_finite(self)
        if not -50.0 <= self.temperature_c <= 60.0:
            raise ValueError(f"temperature_c must lie in [-50, 60], got {self.temperature_c}")
        if not 0.0 <= self.relative_humidity <= 100.0:
            raise ValueError(f"relative_humidity must lie in [0, 100], got {self.relative_humidity}")
        if self.pressure_kpa <= 0:
            raise ValueError(f"pressure_kpa must be positive, got {self.pressure_kpa}")

    @property
    def speed_of_sound(self) -> float:
        return speed_of_sound(self.temperature_c)


@dataclass(frozen=True, kw_only=True)
class SonarConfig:
    """An in-air 3D sonar: one emitter, a planar microphone array, its call and the air.

    Positions are in the sensor frame (x forward along the array normal, y left, z up) [m].
    """

    chirp: ChirpConfig = dataclasses.field(default_factory=ChirpConfig)
    atmosphere: AtmosphereConfig = dataclasses.field(default_factory=AtmosphereConfig)
    microphones_m: tuple[tuple[float, float, float], ...] = ()  # [m], sensor frame
    emitter_m: tuple[float, float, float] = (0.0, 0.0, 0.05)  # [m], sensor frame
    emitter_radius_m: float = 0.005  # baffled piston model of the emitter's directivity [m]
    emitter_pattern: EmitterPattern = "piston"  # or "omni": every direction alike, backwards too
    record_samples: int = 16384  # samples per microphone and ping, at the call's sample rate
    # Channel mismatch of a real array (empty: ideal): linear gain and extra delay per microphone.
    microphone_gain: tuple[float, ...] = ()  # linear, one per microphone
    microphone_delay_s: tuple[float, ...] = ()  # extra delay per microphone [s]

    def __post_init__(self) -> None:
        check_finite(self)
        mics = np.asarray(self.microphones_m, dtype=np.float64)
        if mics.ndim != 2 or mics.shape[1] != 3 or len(mics) < 2 or not np.isfinite(mics).all():
            raise ValueError(f"microphones_m must be >= 2 finite (x, y, z) positions, got shape {mics.shape}")
        if len(self.emitter_m) != 3 or not np.isfinite(self.emitter_m).all() or not self.emitter_radius_m > 0:
            raise ValueError("emitter_m must be a finite (x, y, z) position and emitter_radius_m must be positive")
        if self.emitter_pattern not in typing.get_args(EmitterPattern):
            choices = " or ".join(typing.get_args(EmitterPattern))
            raise ValueError(f"emitter_pattern must be {choices}, got {self.emitter_pattern!r}")
        if np.ptp(mics, axis=0).max() <= 0:  # one point has no aperture: no direction can be told
            raise ValueError("microphones_m are all at one point; an array needs microphones at distinct positions")
        if self.record_samples < self.chirp.sample_count:
            raise ValueError(f"record_samples {self.record_samples:,} < the call's {self.chirp.sample_count:,} samples")
        reach = self.atmosphere.speed_of_sound * self.record_samples / self.chirp.sample_rate_hz  # [m] of path
        if (gap := float(np.linalg.norm(mics - np.asarray(self.emitter_m), axis=1).min())) >= reach:  # silent pings
            raise ValueError(
                f"emitter_m is {gap:.3g} m from the nearest microphone, beyond the {reach:.3g} m of path "
                "a recording of record_samples holds: no echo could arrive; put the emitter at the array"
            )
        check_memory_for(  # int64 impulses and float32 signals per mic; absorption filters (complex128): 128 B
            self.record_samples * (12 * len(mics) + 128),
            f"SonarConfig.record_samples {self.record_samples:,} ({len(mics)} microphones) for one ping",
            "record fewer samples (the eRTIS records 16,384: 36 ms, about 6 m of range)",
        )
        for name in ("microphone_gain", "microphone_delay_s"):
            values = np.asarray(getattr(self, name), dtype=np.float64)
            if len(values) not in (0, len(mics)) or not np.isfinite(values).all():
                raise ValueError(f"{name} must be empty or hold one finite value per microphone ({len(mics)})")

    @classmethod
    def ertis(cls, **overrides) -> SonarConfig:
        """The eRTIS (v3D1): 32 MEMS microphones, 50 -> 25 kHz hyperbolic call, 16,384 samples at 450 kHz."""
        from .array import ertis_microphones

        mics = tuple(tuple(float(v) for v in row) for row in ertis_microphones())
        return dataclasses.replace(cls(microphones_m=mics), **overrides)

    @property
    def microphone_count(self) -> int:
        return len(self.microphones_m)

    def channel_gain(self) -> np.ndarray:
        """Linear gain per microphone, float64 (mics,)."""
        return np.asarray(self.microphone_gain or [1.0] * self.microphone_count, dtype=np.float64)

    def channel_delay_s(self) -> np.ndarray:
        """Extra delay per microphone [s], float64 (mics,)."""
        return np.asarray(self.microphone_delay_s or [0.0] * self.microphone_count, dtype=np.float64)

    @property
    def record_duration_s(self) -> float:
        return self.record_samples / self.chirp.sample_rate_hz


@dataclass(frozen=True, kw_only=True)
class TracerConfig:
    """How the acoustic path tracer searches for echoes (see `paths.PathTracer`).

    Attributes:
        max_bounces: Secondary reflections after the first (0 = first-order echoes only),
            0..MAX_BOUNCES.
        ray_count: Rays per ping that discover reflection sequences (front hemisphere: a
            baffled emitter radiates nothing backwards).
        table_size: Slots per ping for the distinct sequences the rays discover (a power of two
            >= 16). A ping that overflows it is traced again with twice the slots, so no echo is
            lost; a larger table only saves those retries.
        scattering: Trace scattered (diffuse and edge) arrivals as well as specular ones.
        edge_width_m: Band along sharp mesh edges (> 20 deg) that scatters everything it
            reflects, a stand-in for edge diffraction [m]; None: half a wavelength at the call's
            centre frequency; 0: no edge echoes.
    """

    max_bounces: int = 3
    ray_count: int = 20_000
    table_size: int = 32768
    scattering: bool = True
    edge_width_m: float | None = None

    def __post_init__(self) -> None:
        check_finite(self)
        if not 0 <= self.max_bounces <= MAX_BOUNCES:
            raise ValueError(f"max_bounces must lie in 0..{MAX_BOUNCES}, got {self.max_bounces}")
        if self.ray_count < 1 or self.table_size < 16 or self.table_size & (self.table_size - 1):
            raise ValueError("ray_count must be >= 1 and table_size a power of two >= 16")
        if self.edge_width_m is not None and not self.edge_width_m >= 0:
            raise ValueError(f"edge_width_m must be >= 0 (or None), got {self.edge_width_m}")
        check_memory_for(  # a ray (direction, energy): 80 B, and 24 B per bounce for its scattered echo;
            # a table slot (key, planes, image source, direction, point): 112 B
            self.ray_count * (80 + 24 * (self.max_bounces + 1)) + self.table_size * 112,
            f"TracerConfig.ray_count {self.ray_count:,} (max_bounces {self.max_bounces}) and table_size "
            f"{self.table_size:,} for one ping",
            "use fewer rays and a smaller table (the defaults are 20,000 and 32,768)",
        )

    def edge_width_for(self, sonar: SonarConfig) -> float:
        """The edge band [m] for `sonar`'s call and air (None resolved to half a wavelength)."""
        if self.edge_width_m is not None:
            return float(self.edge_width_m)
        return 0.5 * (sonar.atmosphere.speed_of_sound / sonar.chirp.centre_frequency_hz)


@dataclass(frozen=True, kw_only=True)
class ProcessingConfig:
    """The beamformer's settings, as on the eRTIS (see `beamform.energyscape`).

    Attributes:
        grid: Output range x azimuth grid.
        speed_of_sound: Assumed for the steering delays and the range axis [m/s] (the sensor
            assumes 343 m/s whatever the air).
        elevation_deg: Elevation of the beams [deg]; an increasing tuple gives one image per elevation.
        lowpass_hz: Zero-phase low-pass of the envelope [Hz]; None: off.
        normalise: None; "max" scales each ping to a peak of 1; "db": 20 log10 of that.
    """

    grid: PolarGrid = dataclasses.field(default_factory=PolarGrid)
    speed_of_sound: float = 343.0
    elevation_deg: float | tuple[float, ...] = 0.0
    lowpass_hz: float | None = 1e3
    normalise: Normalise = None

    def __post_init__(self) -> None:
        if self.grid is None or isinstance(self.grid, dict):  # default, or read back from JSON
            object.__setattr__(self, "grid", PolarGrid(**(self.grid or {})))
        if np.ndim(self.elevation_deg) == 0:
            object.__setattr__(self, "elevation_deg", float(self.elevation_deg))
        else:
            object.__setattr__(self, "elevation_deg", tuple(float(e) for e in np.ravel(self.elevation_deg)))
        check_finite(self)
        if self.normalise not in NORMALISE:
            raise ValueError(f"normalise must be one of {NORMALISE}, got {self.normalise!r}")
        if not self.speed_of_sound > 0:
            raise ValueError(f"speed_of_sound must be positive, got {self.speed_of_sound}")
        if not np.all(np.abs(self.elevation_deg) <= 90) or np.size(self.elevation_deg) == 0:
            raise ValueError("elevation_deg must be an angle or a non-empty sequence of angles in [-90, 90]")
        if np.any(np.diff(np.atleast_1d(self.elevation_deg)) <= 0):  # one order: shards, models
            raise ValueError(f"elevation_deg must increase from the lowest beam up, got {list(self.elevation_deg)}")
        if self.lowpass_hz is not None and not self.lowpass_hz > 0:
            raise ValueError(f"lowpass_hz must be positive (or None), got {self.lowpass_hz}")

    @property
    def elevations_deg(self) -> tuple[float, ...]:
        """The beams' elevations [deg], one or more: a shard's `elevation_deg` axis."""
        return tuple(np.atleast_1d(self.elevation_deg).tolist())


def level_index(elevation_deg) -> int:
    """Index of the elevation [deg] nearest 0: the LiDAR's plane, the one a planar sonar images."""
    return int(np.argmin(np.abs(np.asarray(elevation_deg, dtype=np.float64))))


@dataclass(frozen=True, kw_only=True)
class SimConfig:
    """The whole simulated rig: the root of the configuration tree (defaults: Hokuyo UST-20LX,
    eRTIS, 3 bounces with 20k rays, the eRTIS processing on the training grid)."""

    lidar: LidarConfig = dataclasses.field(default_factory=LidarConfig.hokuyo_ust20lx)
    sonar: SonarConfig = dataclasses.field(default_factory=SonarConfig.ertis)
    tracer: TracerConfig = dataclasses.field(default_factory=TracerConfig)
    processing: ProcessingConfig = dataclasses.field(default_factory=ProcessingConfig)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
