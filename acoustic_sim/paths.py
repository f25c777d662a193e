"""Acoustic path tracer: echoes of the sonar's call in a 3D scene, batched over poses.

Specular paths (orders 1 .. max_bounces + 1) are exact: rays from the emitter discover which
planes a path reflects off, and the image-source method turns every discovered sequence into
an exact path, or rejects it. Scattered arrivals are Monte Carlo "diffuse rain": at every hit
of every ray, the material's scattered share of the ray's energy goes to the array along a
Lambert lobe if nothing is in the way; a band of half a wavelength along sharp edges scatters
everything it reflects, a simple stand-in for edge diffraction that makes edges and corners
echo.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from scenes import Scene

from .array import piston_directivity
from .config import SonarConfig
from .kernels import lidar as lidar_kernels
from .kernels import paths as kernels
from .lidar import check_poses, raise_for_pose_error
from .scene import warp_scene

KIND_SPECULAR = 0
KIND_SCATTERED = 1


@dataclass
class Arrivals:
    """Echoes of a batch of pings, flat over all poses (numpy, float64 unless noted).

    Attributes:
        pose_index: Ping each arrival belongs to, int64 (n,).
        delay_s: Emitter -> scene -> array centre travel time [s], (n,).
        direction: Unit direction the echo arrives from, sensor frame, (n, 3).
        amplitude: Pressure amplitude relative to 1 at 1 m on the emitter axis: spherical
            spreading, reflection factors and emitter directivity at the call's centre frequency
            (no air absorption: it depends on frequency and is applied when recording), (n,).
        order: Number of reflections, int64 (n,).
        kind: KIND_SPECULAR or KIND_SCATTERED, int64 (n,).
        source_m: Where the echo seems to come from, sensor frame [m] (the image source for
            specular paths): per-microphone delays are |source - mic| / c, (n, 3).
        length_m: Path length [m], (n,).
        point_m: Where the echo last reflected or scattered, sensor frame [m], (n, 3).
    """

    pose_index: np.ndarray
    delay_s: np.ndarray
    direction: np.ndarray
    amplitude: np.ndarray
    order: np.ndarray
    kind: np.ndarray
    source_m: np.ndarray
    length_m: np.ndarray
    point_m: np.ndarray

    def __len__(self) -> int:
        return len(self.delay_s)

    def select(self, mask: np.ndarray) -> Arrivals:
        return Arrivals(**{k: v[mask] for k, v in self.__dict__.items()})

    def for_pose(self, i: int) -> Arrivals:
        """The arrivals of ping i, sorted by delay."""
        sub = self.select(self.pose_index == i)
        return sub.select(np.argsort(sub.delay_s, kind="stable"))


def hemisphere_directions(count: int) -> np.ndarray:
    """`count` near-uniform unit vectors over the front hemisphere x > 0 (Fibonacci lattice), (count, 3)."""
    i = np.arange(count) + 0.5
    x = 1.0 - i / count  # uniform in cos(theta) from the +x axis over (0, 1]
    rho = np.sqrt(1.0 - x * x)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.c_[x, rho * np.cos(phi), rho * np.sin(phi)]


class Sonar:
    """Simulated in-air sonar: emitter, microphone array, call and processing.

    Args:
        config: The sensor, e.g. `SonarConfig.ertis()`.
        max_bounces: Secondary reflections after the first (0 = first-order echoes only, <= 10).
        ray_count: Rays per ping used to discover reflection sequences (front hemisphere; a
            baffled emitter radiates nothing backwards).
        table_size: Distinct reflection sequences kept per ping (power of two).
        scattering: Trace scattered (diffuse) arrivals as well as specular ones.
        edge_width_m: Band along sharp mesh edges (> 20 deg) that scatters everything it reflects,
            a simple stand-in for edge diffraction; default half a wavelength at the call's centre
            frequency; 0 turns edge echoes off.
        device: Warp device.
    """

    def __init__(
        self,
        config: SonarConfig,
        *,
        max_bounces: int = 3,
        ray_count: int = 20_000,
        table_size: int = 16384,
        scattering: bool = True,
        edge_width_m: float | None = None,
        device=None,
    ):
        if not 0 <= max_bounces <= kernels.MAX_ORDER - 1:
            raise ValueError(f"max_bounces must lie in 0..{kernels.MAX_ORDER - 1}, got {max_bounces}")
        if ray_count < 1 or table_size < 16 or table_size & (table_size - 1):
            raise ValueError("ray_count must be >= 1 and table_size a power of two >= 16")
        self.config = config
        self.max_bounces = max_bounces
        self.ray_count = ray_count
        self.table_size = table_size
        self.scattering = scattering
        wavelength = config.atmosphere.speed_of_sound / self._centre_hz
        self.edge_width_m = 0.5 * wavelength if edge_width_m is None else float(edge_width_m)
        if self.edge_width_m < 0:
            raise ValueError(f"edge_width_m must be >= 0, got {edge_width_m}")
        self.device = wp.get_device(device)
        directions = hemisphere_directions(ray_count)
        # Each ray carries its share of the half-space (2 pi sr), weighted by the emitter's power
        # directivity at the call's centre frequency.
        theta = np.arccos(np.clip(directions[:, 0], -1.0, 1.0))
        power = (
            piston_directivity(theta, self._centre_hz, config.emitter_radius_m, config.atmosphere.speed_of_sound) ** 2
        )
        self._ray_energy = wp.array((2 * np.pi / ray_count * power).astype(np.float32), dtype=float, device=self.device)
        self._ray_dirs = wp.array(directions.astype(np.float32), dtype=wp.vec3, device=self.device)

    def record(self, arrivals: Arrivals, *, pose_count: int | None = None, **options) -> np.ndarray:
        """Microphone signals (N, mics, samples) of traced pings; see `signals.record` for options."""
        from .signals import record

        return record(arrivals, self.config, pose_count=pose_count, device=self.device, **options)

    def energyscape(self, signals: np.ndarray, **options) -> np.ndarray:
        """Energyscapes (N, R, A) of signals recorded with this sonar; see `beamform.energyscape`."""
        from .beamform import energyscape

        return energyscape(signals, self.config, **options)

    @property
    def _centre_hz(self) -> float:
        return 0.5 * (self.config.chirp.start_frequency_hz + self.config.chirp.stop_frequency_hz)

    def trace(self, scene: Scene, poses: np.ndarray) -> Arrivals:
        """Echoes of one ping from each pose, specular and scattered (see the module docstring).

        Args:
            scene: The world.
            poses: Sensor-to-world transforms (N, 4, 4) or (4, 4).
        """
        poses = check_poses(poses)
        n, size = len(poses), self.table_size
        ws = warp_scene(scene, self.device)
        launch = functools.partial(wp.launch, device=self.device)
        with wp.ScopedDevice(self.device):
            pose_buf = wp.array(poses.astype(np.float32), dtype=wp.mat44)
            errors = wp.empty(n, dtype=float)
            key = wp.zeros((n, size), dtype=wp.uint64)
            order = wp.zeros((n, size), dtype=wp.int32)
            planes = wp.zeros((n, size, kernels.MAX_ORDER), dtype=wp.int32)
            overflow = wp.zeros(1, dtype=wp.int32)
            valid = wp.empty((n, size), dtype=wp.int32)
            length = wp.empty((n, size), dtype=float)
            gain = wp.empty((n, size), dtype=float)
            image = wp.empty((n, size), dtype=wp.vec3)
            arrival_dir = wp.empty((n, size), dtype=wp.vec3)
            emit_dir = wp.empty((n, size), dtype=wp.vec3)
            last_point = wp.empty((n, size), dtype=wp.vec3)
            capacity = self.ray_count * (self.max_bounces + 1) if self.scattering else 1
            scatter_count = wp.zeros(n, dtype=wp.int32)
            scatter_point = wp.empty((n, capacity), dtype=wp.vec3)
            scatter_length = wp.empty((n, capacity), dtype=float)
            scatter_energy = wp.empty((n, capacity), dtype=float)
            scatter_order = wp.empty((n, capacity), dtype=wp.int32)
        emitter = wp.vec3(*self.config.emitter_m)
        launch(lidar_kernels.pose_error, dim=n, inputs=[pose_buf], outputs=[errors])
        raise_for_pose_error(errors.numpy())
        launch(
            kernels.discover_sequences,
            dim=n * self.ray_count,
            inputs=[
                ws.mesh.id,
                ws.face_plane,
                pose_buf,
                emitter,
                self._ray_dirs,
                self.max_bounces + 1,
                ws.face_reflection,
                ws.face_scattering,
                ws.face_sharp_edges,
                ws.face_altitudes,
                self.edge_width_m,
                self._ray_energy,
                int(self.scattering),
            ],
            outputs=[
                key,
                order,
                planes,
                overflow,
                scatter_count,
                scatter_point,
                scatter_length,
                scatter_energy,
                scatter_order,
            ],
        )
        launch(
            kernels.validate_sequences,
            dim=(n, size),
            inputs=[
                ws.mesh.id,
                ws.face_plane,
                ws.plane_normal,
                ws.plane_offset,
                ws.face_reflection,
                ws.face_scattering,
                pose_buf,
                emitter,
                key,
                order,
                planes,
            ],
            outputs=[valid, length, gain, image, arrival_dir, emit_dir, last_point],
        )
        if (dropped := int(overflow.numpy()[0])) > 0:
            warnings.warn(
                f"{dropped} reflection sequences did not fit the table of {size} per ping; raise table_size",
                stacklevel=2,
            )
        ok = valid.numpy().astype(bool)
        # Two orders of reflection in perpendicular planes give the same image source; where both
        # validate, the path runs into the edge between the planes and is one echo, not two.
        pose_index, slot = np.nonzero(ok)
        keys = np.c_[pose_index, order.numpy()[ok], np.rint(image.numpy()[ok] / 1e-4)].astype(np.int64)
        _, first = np.unique(keys, axis=0, return_index=True)
        ok[:] = False
        ok[pose_index[first], slot[first]] = True
        pose_index = np.nonzero(ok)[0]
        length_m = length.numpy()[ok].astype(np.float64)
        emit = emit_dir.numpy()[ok].astype(np.float64)
        cfg = self.config
        c = cfg.atmosphere.speed_of_sound
        # Angle from the emitter axis (sensor +x).
        theta = np.arccos(np.clip(emit[:, 0], -1.0, 1.0))
        directivity = piston_directivity(theta, self._centre_hz, cfg.emitter_radius_m, c)
        specular = Arrivals(
            pose_index=pose_index.astype(np.int64),
            delay_s=length_m / c,
            direction=arrival_dir.numpy()[ok].astype(np.float64),
            amplitude=gain.numpy()[ok].astype(np.float64) * directivity / length_m,
            order=order.numpy()[ok].astype(np.int64),
            kind=np.full(len(length_m), KIND_SPECULAR, dtype=np.int64),
            source_m=image.numpy()[ok].astype(np.float64),
            length_m=length_m,
            point_m=last_point.numpy()[ok].astype(np.float64),
        )
        specular = specular.select(specular.amplitude > 0)  # e.g. fully scattering surfaces
        if not self.scattering:
            return specular
        return concatenate(
            [
                specular,
                self._scattered(poses, scatter_count, scatter_point, scatter_length, scatter_energy, scatter_order),
            ]
        )

    def _scattered(self, poses, count, point, length, energy, order) -> Arrivals:
        """Compact the per-pose scattered arrival buffers into Arrivals (sensor frame)."""
        count = count.numpy()
        capacity = point.shape[1]
        if (count > capacity).any():  # cannot happen: each ray scatters at most once per order
            raise RuntimeError("scattered arrival buffer overflow")
        keep = np.arange(capacity)[None, :] < count[:, None]
        pose_index = np.nonzero(keep)[0]
        world = point.numpy()[keep].astype(np.float64)
        rotation, origin = poses[pose_index, :3, :3], poses[pose_index, :3, 3]
        local = np.einsum("nji,nj->ni", rotation, world - origin)
        distance = np.linalg.norm(local, axis=1)
        length_m = length.numpy()[keep].astype(np.float64)
        return Arrivals(
            pose_index=pose_index.astype(np.int64),
            delay_s=length_m / self.config.atmosphere.speed_of_sound,
            direction=local / distance[:, None],
            amplitude=np.sqrt(energy.numpy()[keep].astype(np.float64)),
            order=order.numpy()[keep].astype(np.int64),
            kind=np.full(len(length_m), KIND_SCATTERED, dtype=np.int64),
            source_m=local,
            length_m=length_m,
            point_m=local,
        )


def concatenate(parts: list[Arrivals]) -> Arrivals:
    """Join arrival sets (kept flat; `for_pose` sorts by delay)."""
    return Arrivals(**{k: np.concatenate([getattr(a, k) for a in parts]) for k in Arrivals.__dataclass_fields__})
