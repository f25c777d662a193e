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

import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from scenes import Scene

from .array import piston_directivity
from .config import SonarConfig, TracerConfig
from .kernels import curved as curved_kernels
from .kernels import lidar as lidar_kernels
from .kernels import paths as kernels
from .poses import check_pose_results, check_poses
from .scene import warp_scene
from .signals import EchoBuffer

KIND_SPECULAR = 0
KIND_SCATTERED = 1
DIRECTIVITY_STEPS = 1024  # steps of the emitter's directivity table over the cosine from its axis


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


class PathTracer:
    """Scene + poses -> echoes of one sonar's call, on a Warp device, batched over poses.

    Holds only what every trace reuses: the rays' directions and energy shares, the emitter's
    directivity table and the device buffers of a batch (allocated once per batch shape, like the
    LiDAR's). Each `trace` builds (or reuses) the scene's BVH; no result depends on an earlier one.

    Args:
        sonar: Emitter position, directivity, call and air.
        config: Rays, bounces, table size, scattering and edge band.
        device: Warp device.
    """

    def __init__(self, sonar: SonarConfig, config: TracerConfig, *, device=None):
        self.sonar = sonar
        self.config = config
        self.edge_width_m = config.edge_width_for(sonar)
        self.device = wp.get_device(device)
        centre_hz, c = sonar.chirp.centre_frequency_hz, sonar.atmosphere.speed_of_sound
        directions = hemisphere_directions(config.ray_count)
        # Each ray carries its share of the half-space (2 pi sr), weighted by the emitter's power
        # directivity at the call's centre frequency.
        theta = np.arccos(np.clip(directions[:, 0], -1.0, 1.0))
        power = piston_directivity(theta, centre_hz, sonar.emitter_radius_m, c) ** 2
        ray_energy = (2 * np.pi / config.ray_count * power).astype(np.float32)
        cosine = np.linspace(0.0, 1.0, DIRECTIVITY_STEPS + 1)
        pattern = piston_directivity(np.arccos(cosine), centre_hz, sonar.emitter_radius_m, c)
        with wp.ScopedDevice(self.device):
            self._ray_energy = wp.array(ray_energy, dtype=float)
            self._ray_dirs = wp.array(directions.astype(np.float32), dtype=wp.vec3)
            self._directivity = wp.array(pattern.astype(np.float32), dtype=float)
        self._buffers: dict[tuple[int, int], _TraceBuffers] = {}  # (pings, table size) -> buffers
        self._curved: _PointEchoes | None = None  # echoes off curved surfaces, (pings, surfaces)

    def trace(self, scene: Scene, poses: np.ndarray, *, batch: int = 64) -> Arrivals:
        """Echoes of one ping from each pose, specular and scattered (see the module docstring).

        Args:
            scene: The world.
            poses: Sensor-to-world transforms (N, 4, 4) or (4, 4).
            batch: Pings traced at once.

        Returns:
            Arrivals sorted by pose, kind, delay.
        """
        poses = check_poses(poses)
        parts = []
        for index, keep, echoes in self.traced(scene, poses, batch):
            found = echoes.arrivals(self.sonar.atmosphere.speed_of_sound)
            found = found.select(keep[found.pose_index])
            found.pose_index = index[found.pose_index]
            parts.append(found)
        found = concatenate(parts)
        return found.select(np.lexsort((found.order, found.delay_s, found.kind, found.pose_index)))

    def traced(self, scene: Scene, poses: np.ndarray, batch: int):
        """Trace checked poses in batches; yields (pose indices, rows to keep, echoes on the device).

        The echoes live in buffers that a later batch reuses: use each before asking for the next.

        A ping whose sequence table overflowed would miss echoes, and which ones would depend on
        thread order: its row is left out and the ping traced again with twice the slots (in
        groups that take no more memory than one batch), until it fits. Each ray adds at most
        one sequence per order, so a table twice that size always fits in practice."""
        table_size = self.config.table_size
        most = self.config.ray_count * (self.config.max_bounces + 1)
        limit = max(table_size, 1 << (2 * most - 1).bit_length())
        budget = batch * table_size  # slots a batch may hold
        todo = [(np.arange(s, min(s + batch, len(poses))), table_size) for s in range(0, len(poses), batch)]
        while todo:
            index, size = todo.pop(0)
            echoes, dropped = self._trace_batch(scene, poses[index], size)
            keep = dropped == 0
            if not keep.all() and size < limit:
                again, per = index[~keep], max(1, budget // (2 * size))
                todo[:0] = [(again[i : i + per], 2 * size) for i in range(0, len(again), per)]
            elif not keep.all():
                warnings.warn(
                    f"{dropped.sum()} reflection sequences did not fit the table of {size} per ping", stacklevel=3
                )
                keep[:] = True
            if keep.any():
                yield index, keep, echoes

    def _buffers_for(self, n: int, size: int) -> _TraceBuffers:
        """Device buffers of a batch of `n` pings with tables of `size`, reused across batches.

        Only batches at the configured table size are cached, one shape at a time (a stream of
        equal batches reuses memory): a batch's echoes live in these buffers until the next batch
        of its shape is traced. Pings traced again with a larger table (rare) get buffers of their
        own, so their echoes never share memory with any other batch's."""
        key = (n, size)
        if key in self._buffers:
            return self._buffers[key]
        tracer = self.config
        capacity = tracer.ray_count * (tracer.max_bounces + 1) if tracer.scattering else 0
        with wp.ScopedDevice(self.device):
            buffers = _TraceBuffers(
                poses=wp.empty(n, dtype=wp.mat44),
                inverse_poses=wp.empty(n, dtype=wp.mat44),
                errors=wp.empty(n, dtype=float),
                behind=wp.empty(n, dtype=wp.int32),
                key=wp.empty((n, size), dtype=wp.uint64),
                planes=wp.empty((n, size, kernels.MAX_ORDER), dtype=wp.int32),
                overflow=wp.empty(n, dtype=wp.int32),
                ray_queries=wp.empty(n, dtype=wp.int32),
                image_table=wp.empty((n, size), dtype=wp.uint64),
                image_rank=wp.empty((n, size), dtype=wp.int32),
                specular=_SpecularEchoes(  # source: image sources; order: the sequence table's orders
                    source=wp.empty((n, size), dtype=wp.vec3),
                    extra_length=wp.zeros((n, size), dtype=float),  # 0 for image sources; no kernel writes it
                    amplitude=wp.empty((n, size), dtype=float),
                    count=wp.full(n, size, dtype=wp.int32),  # every slot counts (amplitude 0: empty)
                    order=wp.empty((n, size), dtype=wp.int32),
                    direction=wp.empty((n, size), dtype=wp.vec3),
                    point=wp.empty((n, size), dtype=wp.vec3),
                ),
                scattered=_PointEchoes(
                    source=wp.empty((n, capacity), dtype=wp.vec3),
                    extra_length=wp.empty((n, capacity), dtype=float),
                    amplitude=wp.empty((n, capacity), dtype=float),
                    count=wp.empty(n, dtype=wp.int32),
                    order=wp.empty((n, capacity), dtype=wp.int32),
                ),
            )
        if size == tracer.table_size:
            self._buffers.clear()
            self._buffers[key] = buffers
        return buffers

    def _curved_buffers_for(self, n: int, surfaces: int) -> _PointEchoes:
        """Buffers of the echoes off a scene's curved surfaces, one slot per surface and ping
        (every slot counts; the kernel writes each), reused while the shape stays."""
        if self._curved is not None and self._curved.source.shape == (n, surfaces):
            return self._curved
        with wp.ScopedDevice(self.device):
            self._curved = _PointEchoes(
                source=wp.empty((n, surfaces), dtype=wp.vec3),
                extra_length=wp.empty((n, surfaces), dtype=float),
                amplitude=wp.empty((n, surfaces), dtype=float),
                count=wp.full(n, surfaces, dtype=wp.int32),
                order=wp.empty((n, surfaces), dtype=wp.int32),
            )
        return self._curved

    def _trace_batch(self, scene: Scene, poses: np.ndarray, size: int) -> tuple[_TracedEchoes, np.ndarray]:
        """Echoes of a batch of checked poses, left on the device (in buffers that the next batch
        of the same shape reuses), and per pose the count of sequence insertions that found no
        slot in its table of `size`."""
        n = len(poses)
        ws = warp_scene(scene, self.device)
        tracer = self.config
        b = self._buffers_for(n, size)
        specular, scattered = b.specular, b.scattered
        emitter = wp.vec3(*self.sonar.emitter_m)
        with wp.ScopedDevice(self.device):
            b.poses.assign(poses.astype(np.float32))
            b.inverse_poses.assign(np.linalg.inv(poses).astype(np.float32))
            # Tables and counters start at zero (ranks at RANK_NONE), as the kernels expect; every
            # other array is read only where a kernel of this batch wrote it.
            for table in (b.key, specular.order, b.planes, b.image_table, b.overflow, b.ray_queries, scattered.count):
                table.zero_()
            b.image_rank.fill_(kernels.RANK_NONE)
            wp.launch(lidar_kernels.pose_error, dim=n, inputs=[ws.mesh.id, b.poses], outputs=[b.errors, b.behind])
            check_pose_results(b.errors.numpy(), b.behind.numpy())
            wp.launch(
                kernels.discover_sequences,
                dim=n * tracer.ray_count,
                inputs=[
                    ws.mesh.id,
                    ws.face_plane,
                    b.poses,
                    b.inverse_poses,
                    emitter,
                    self._ray_dirs,
                    tracer.max_bounces + 1,
                    ws.face_reflection,
                    ws.face_scattering,
                    ws.face_sharp_edges,
                    ws.face_altitudes,
                    self.edge_width_m,
                    self._ray_energy,
                    int(tracer.scattering),
                ],
                outputs=[
                    b.key,
                    scattered.count,
                    specular.order,
                    b.planes,
                    b.overflow,
                    scattered.source,
                    scattered.extra_length,
                    scattered.amplitude,
                    scattered.order,
                    b.ray_queries,
                ],
            )
            wp.launch(
                kernels.validate_sequences,
                dim=(n, size),
                inputs=[
                    ws.mesh.id,
                    ws.face_plane,
                    ws.plane_normal,
                    ws.plane_offset,
                    ws.face_reflection,
                    ws.face_scattering,
                    b.poses,
                    emitter,
                    b.key,
                    specular.order,
                    b.planes,
                    ws.plane_curved,
                    self._directivity,
                ],
                outputs=[specular.amplitude, specular.source, specular.direction, specular.point, b.ray_queries],
            )
            wp.launch(
                kernels.claim_images,
                dim=(n, size),
                inputs=[specular.amplitude, specular.order, specular.source, b.key],
                outputs=[b.image_table, b.image_rank],
            )
            wp.launch(
                kernels.drop_duplicate_images,
                dim=(n, size),
                inputs=[specular.order, specular.source, b.key, b.image_table, b.image_rank],
                outputs=[specular.amplitude],
            )
            curved = self._curved_buffers_for(n, ws.curved.count)
            if ws.curved.count:
                surfaces = ws.curved
                wp.launch(
                    curved_kernels.curved_echoes,
                    dim=(n, surfaces.count),
                    inputs=[
                        ws.mesh.id,
                        surfaces.kind,
                        surfaces.centre,
                        surfaces.radius,
                        surfaces.z_range,
                        surfaces.gain,
                        b.poses,
                        b.inverse_poses,
                        emitter,
                        self._directivity,
                    ],
                    outputs=[curved.source, curved.extra_length, curved.amplitude, curved.order, b.ray_queries],
                )
        traced = _TracedEchoes(specular=specular, scattered=scattered, curved=curved, ray_queries=b.ray_queries)
        return traced, b.overflow.numpy().copy()


@dataclass
class _TraceBuffers:
    """A batch's device arrays (see `PathTracer._buffers_for`): poses and their checks, the
    sequence and image tables, counters, and the echoes found."""

    poses: wp.array  # (pings,) mat44 sensor-to-world
    inverse_poses: wp.array  # (pings,) mat44 world-to-sensor
    errors: wp.array  # (pings,) float, pose_error
    behind: wp.array  # (pings,) int32, pose_error
    key: wp.array  # (pings, size) uint64 sequence hashes, 0 = empty slot
    planes: wp.array  # (pings, size, MAX_ORDER) int32 plane sequence per slot
    overflow: wp.array  # (pings,) int32 insertions that found no slot
    ray_queries: wp.array  # (pings,) int32 BVH ray queries, all stages
    image_table: wp.array  # (pings, size) uint64 image source hashes, 0 = empty slot
    image_rank: wp.array  # (pings, size) int32 lowest sequence rank per image source
    specular: _SpecularEchoes
    scattered: _PointEchoes


@dataclass
class _SpecularEchoes(EchoBuffer):
    """Validated image-source paths in table slots (amplitude 0: empty or invalid)."""

    order: wp.array = None
    direction: wp.array = None
    point: wp.array = None


@dataclass
class _PointEchoes(EchoBuffer):
    """Echoes from a point (source: where the path last reflected or scattered; extra_length: the
    path before it): scattered arrivals, and specular ones off curved surfaces."""

    order: wp.array = None


@dataclass
class _TracedEchoes:
    specular: _SpecularEchoes
    scattered: _PointEchoes
    curved: _PointEchoes  # first-order specular echoes off curved surfaces, one slot per surface
    ray_queries: wp.array  # (pings,) BVH ray queries made per ping, all stages

    @property
    def pose_count(self) -> int:
        return self.specular.amplitude.shape[0]

    def buffers(self) -> list[EchoBuffer]:
        return [self.specular, self.scattered, self.curved]

    def arrivals(self, speed_of_sound: float) -> Arrivals:
        """Copy to the host as Arrivals, sorted by pose, kind, delay (a reproducible order)."""
        spec = self.specular
        amplitude = spec.amplitude.numpy()
        pose_index, slot = np.nonzero(amplitude > 0)
        source = spec.source.numpy()[pose_index, slot].astype(np.float64)
        length = np.linalg.norm(source, axis=1)
        parts = [
            Arrivals(
                pose_index=pose_index.astype(np.int64),
                delay_s=length / speed_of_sound,
                direction=spec.direction.numpy()[pose_index, slot].astype(np.float64),
                amplitude=amplitude[pose_index, slot].astype(np.float64),
                order=spec.order.numpy()[pose_index, slot].astype(np.int64),
                kind=np.full(len(length), KIND_SPECULAR, dtype=np.int64),
                source_m=source,
                length_m=length,
                point_m=spec.point.numpy()[pose_index, slot].astype(np.float64),
            )
        ]
        for echoes, kind in ((self.scattered, KIND_SCATTERED), (self.curved, KIND_SPECULAR)):
            if echoes.slots:
                parts.append(_point_arrivals(echoes, kind, speed_of_sound))
        found = concatenate(parts)
        return found.select(np.lexsort((found.order, found.delay_s, found.kind, found.pose_index)))


def _point_arrivals(echoes: _PointEchoes, kind: int, speed_of_sound: float) -> Arrivals:
    """Arrivals of point echoes (slots below each ping's count with an amplitude)."""
    count = echoes.count.numpy()
    if (count > echoes.slots).any():  # cannot happen: each ray scatters at most once per order
        raise RuntimeError("point echo buffer overflow")
    amplitude = echoes.amplitude.numpy()
    keep = (np.arange(echoes.slots)[None, :] < count[:, None]) & (amplitude > 0)
    pose_index = np.nonzero(keep)[0]
    source = echoes.source.numpy()[keep].astype(np.float64)
    distance = np.linalg.norm(source, axis=1)
    length = echoes.extra_length.numpy()[keep].astype(np.float64) + distance
    return Arrivals(
        pose_index=pose_index.astype(np.int64),
        delay_s=length / speed_of_sound,
        direction=source / distance[:, None],
        amplitude=amplitude[keep].astype(np.float64),
        order=echoes.order.numpy()[keep].astype(np.int64),
        kind=np.full(len(length), kind, dtype=np.int64),
        source_m=source,
        length_m=length,
        point_m=source,
    )


def concatenate(parts: list[Arrivals]) -> Arrivals:
    """Join arrival sets (kept flat; `for_pose` sorts by delay)."""
    return Arrivals(**{k: np.concatenate([getattr(a, k) for a in parts]) for k in Arrivals.__dataclass_fields__})
