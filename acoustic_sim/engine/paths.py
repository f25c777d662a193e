"""Acoustic path tracer: echoes of the sonar's call in a 3D scene, batched over poses.

Specular paths (orders 1 .. max_bounces + 1) are exact: rays from the emitter discover which
planes a path reflects off, and the image-source method turns every discovered sequence into
an exact path, or rejects it. Scattered arrivals are Monte Carlo "diffuse rain": at every hit
of every ray, the material's scattered share of the ray's energy goes to the array along a
Lambert lobe if nothing is in the way; a band of half a wavelength along sharp edges scatters
everything it reflects, a simple stand-in for edge diffraction that makes edges and corners
echo.

PathTracer batches the pings and keeps their buffers; `path_stages` launches the kernels of a batch.
"""

from __future__ import annotations

import functools
import threading
import warnings
import weakref
from collections import defaultdict, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import warp as wp

from scenes import Scene

from ..array import emitter_directivity
from ..config import SonarConfig, TracerConfig
from ..devices import cpu_cores, device_calls, warp_device
from .echoes import (
    KIND_SCATTERED,
    KIND_SPECULAR,
    Arrivals,
    PointEchoes,
    SpecularEchoes,
    TraceBuffers,
    concatenate,
)
from .kernels import lidar as lidar_kernels
from .kernels import paths as kernels
from .path_stages import BatchStages, TracerInputs, reset_tables
from .poses import check_poses, raise_for_bad_poses, warn_poses_behind
from .scene import warp_scene

DIRECTIVITY_STEPS = 1024  # steps of the emitter's directivity table per unit of the cosine from its axis
BAFFLE_SLACK = 1.0e-6  # [cosine] how far behind a baffled emitter's plane a path may leave it
__all__ = ["KIND_SCATTERED", "KIND_SPECULAR", "Arrivals", "PathTracer", "concatenate", "ray_directions"]


def ray_directions(count: int, sphere: bool = False) -> np.ndarray:
    """`count` near-uniform unit vectors (Fibonacci lattice) over the front hemisphere x > 0, or
    with `sphere` over the whole sphere, (count, 3), in Z-order of their (y, z) (the front ones
    first where there are both): rays next to each other in the array leave in neighbouring
    directions.

    A GPU runs 32 consecutive rays as one warp. In the lattice's own order neighbours differ by the
    golden angle in azimuth, so a warp's rays walk different branches of the BVH and their scattered
    echoes land at unrelated times; in Z-order they hit one patch of wall. The set of rays, and so
    every echo, is the same in any order."""
    return _ray_directions(count, sphere).copy()


@functools.lru_cache(maxsize=4)
def _ray_directions(count: int, sphere: bool) -> np.ndarray:
    """`ray_directions`, computed once per count (~35 ms at 20k rays: every episode of a dataset
    builds a tracer)."""
    i = np.arange(count) + 0.5
    x = 1.0 - (2.0 if sphere else 1.0) * i / count  # uniform in cos(theta) from the +x axis
    rho = np.sqrt(1.0 - x * x)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    directions = np.c_[x, rho * np.cos(phi), rho * np.sin(phi)]
    directions = directions[np.lexsort((_z_order(directions[:, 1:]), x < 0))]  # stable: each half in Z-order
    directions.setflags(write=False)  # shared by every caller
    return directions


def _z_order(points: np.ndarray, bits: int = 16) -> np.ndarray:
    """Morton codes of 2D points in [-1, 1]^2: the bits of the two quantised coordinates interleaved."""
    cells = np.clip((points + 1.0) * 0.5 * (1 << bits), 0, (1 << bits) - 1).astype(np.uint64)
    code = np.zeros(len(points), dtype=np.uint64)
    for b in range(bits):
        for axis in range(2):
            code |= ((cells[:, axis] >> np.uint64(b)) & np.uint64(1)) << np.uint64(2 * b + axis)
    return code


class PathTracer:
    """Scene + poses -> echoes of one sonar's call, on a Warp device, batched over poses.

    Holds only what every trace reuses: the rays' directions and energy shares, the emitter's
    directivity table and the device buffers of a batch (allocated once per batch shape, like the
    LiDAR's). Each `trace` builds (or reuses) the scene's BVH; no result depends on an earlier one.

    Args:
        sonar: Emitter position, directivity, call and air.
        config: Rays, bounces, table size, scattering and edge band.
        device: Warp device.
        cpu_threads: On the CPU, a batch's pings are traced in this many threads (default: every
            core this process may use); Warp runs each CPU launch on one core.
        scattered_faces: Record the faces of each scattered arrival's path (`Arrivals.faces`,
            `Arrivals.edge`), as calibration needs: a face per hit of every ray is kept on the
            device (4 B x rays x orders a ping).
    """

    def __init__(
        self,
        sonar: SonarConfig,
        config: TracerConfig,
        *,
        device=None,
        cpu_threads: int | None = None,
        scattered_faces: bool = False,
    ):
        if cpu_threads is not None and cpu_threads < 1:
            raise ValueError(f"cpu_threads must be >= 1, got {cpu_threads}")
        self.cpu_threads = cpu_threads or cpu_cores()
        self.scattered_faces = scattered_faces and config.scattering
        self.sonar = sonar
        self.config = config
        self.edge_width_m = config.edge_width_for(sonar)
        self.device = warp_device(device)
        sphere = sonar.emitter_pattern == "omni"  # else a baffled piston: nothing leaves backwards
        directions = ray_directions(config.ray_count, sphere)
        # Each ray carries its share of the solid angle the emitter fills (2 pi sr in front of its
        # baffle, 4 pi sr without one), weighted by its power directivity at the call's centre frequency.
        power = emitter_directivity(sonar, directions[:, 0]) ** 2
        ray_energy = ((4 if sphere else 2) * np.pi / config.ray_count * power).astype(np.float32)
        cosine = np.linspace(-1.0, 1.0, 2 * DIRECTIVITY_STEPS + 1)
        # Behind a baffle the table holds the pattern's value at 90 degrees: the kernels read it
        # only for paths leaving within BAFFLE_SLACK behind the baffle's plane and cut the rest.
        pattern = emitter_directivity(sonar, cosine if sphere else np.maximum(cosine, 0.0))
        self._emit_min_cosine = -2.0 if sphere else -BAFFLE_SLACK
        with wp.ScopedDevice(self.device):
            self._ray_energy = wp.array(ray_energy, dtype=float)
            self._ray_dirs = wp.array(directions.astype(np.float32), dtype=wp.vec3)
            self._directivity = wp.array(pattern.astype(np.float32), dtype=float)
        self._buffer_key: tuple[int, int, int] | None = None  # (pings, table size, curved surfaces)
        self._buffer_sets: list[TraceBuffers] = []  # up to two, taking turns
        self._check_sets: list[HostChecks] = []  # up to two, never the batch in flight's
        weakref.finalize(self, _keep_spare, _SPARE_CHECKS[str(self.device)], self._check_sets)

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
            found = echoes.arrivals(self.sonar.atmosphere.speed_of_sound, warp_scene(scene, self.device).curved.face)
            found = found.select(keep[found.pose_index])
            found.pose_index = index[found.pose_index]
            parts.append(found)
        found = concatenate(parts)
        return found.select(np.lexsort((found.order, found.delay_s, found.kind, found.pose_index)))

    def traced(self, scene: Scene, poses: np.ndarray, batch: int):
        """Trace checked poses in batches; yields (pose indices, rows to keep, echoes on the device).

        The echoes live in buffers that a later batch reuses: use each (queue the work that reads
        them) before asking for the next. The batches are pipelined: the next batch is queued
        before this one's overflow counts are read, so on a GPU the host's wait for them leaves
        the next trace running, and what the caller queues with this batch's echoes runs behind
        it (two buffer sets take turns; a set is traced into again only behind the work the
        caller queued with its echoes, in stream order).

        A ping whose sequence table overflowed would miss echoes, and which ones would depend on
        thread order: its row is left out and the ping traced again with twice the slots (in
        groups that take no more memory than one batch), until it fits. Each ray adds at most
        one sequence per order, so a table twice that size always fits in practice."""
        table_size = self.config.table_size
        most = self.config.ray_count * (self.config.max_bounces + 1)
        limit = max(table_size, 1 << (2 * most - 1).bit_length())
        budget = batch * table_size  # slots a batch may hold
        on_device = PosesOnDevice.upload(poses, self.device)  # all at once: no copy per batch
        todo = deque((np.arange(s, min(s + batch, len(poses))), table_size) for s in range(0, len(poses), batch))
        queued: deque[QueuedBatch] = deque()
        behind = np.zeros(len(poses), dtype=bool)  # warned about once, for the whole trace
        while todo or queued:
            while todo and len(queued) < 2:  # this batch and the next
                index, size = todo.popleft()
                busy = queued[0] if queued else None
                queued.append(self._queue_batch(scene, on_device, index, size, busy))
            done = queued.popleft()
            index, size = done.index, done.size
            dropped = self._checked(done, behind)
            keep = dropped == 0
            if not keep.all() and size < limit:
                again, per = index[~keep], max(1, budget // (2 * size))
                todo.extendleft(reversed([(again[i : i + per], 2 * size) for i in range(0, len(again), per)]))
            elif not keep.all():
                warnings.warn(
                    f"{dropped.sum()} reflection sequences did not fit the table of {size} per ping", stacklevel=3
                )
                keep[:] = True
            if keep.any():
                yield index, keep, done.buffers.echoes
        warn_poses_behind(behind)

    def _buffers_for(self, n: int, size: int, surfaces: int, busy: TraceBuffers | None) -> TraceBuffers:
        """Device buffers of a batch of `n` pings with tables of `size` and `surfaces` curved
        surfaces, other than `busy` (the batch still in flight).

        Batches at the configured table size take turns in two cached sets, one shape at a
        time (a stream of equal batches reuses memory): a batch's echoes live in its set until
        the batch after the next is traced. Pings traced again with a larger table get device
        buffers of their own, so their echoes never share memory with any other batch's."""
        key = (n, size, surfaces)
        cached = size == self.config.table_size
        if cached and self._buffer_key != key:
            self._buffer_key, self._buffer_sets = key, []  # a set in flight stays alive with its batch
        if cached:
            for buffers in self._buffer_sets:
                if buffers is not busy:
                    return buffers
        tracer = self.config
        capacity = tracer.ray_count * (tracer.max_bounces + 1) if tracer.scattering else 0
        recorded = self.scattered_faces  # else empty: the kernel writes no faces
        with wp.ScopedDevice(self.device):
            planes = wp.empty((n, size, kernels.MAX_ORDER), dtype=wp.int32)
            buffers = TraceBuffers(
                errors=wp.empty(n, dtype=float),
                behind=wp.empty(n, dtype=wp.int32),
                key=wp.empty((n, size), dtype=wp.uint64),
                planes=planes,
                overflow=wp.empty(n, dtype=wp.int32),
                ray_queries=wp.empty(n, dtype=wp.int32),
                image_table=wp.empty((n, size), dtype=wp.uint64),
                image_rank=wp.empty((n, size), dtype=wp.int32),
                specular=SpecularEchoes(  # source: image sources; order: the sequence table's orders
                    source=wp.empty((n, size), dtype=wp.vec3),
                    extra_length=wp.zeros((n, size), dtype=float),  # 0 for image sources; no kernel writes it
                    amplitude=wp.empty((n, size), dtype=float),
                    count=wp.full(n, size, dtype=wp.int32),  # every slot counts (amplitude 0: empty)
                    order=wp.empty((n, size), dtype=wp.int32),
                    direction=wp.empty((n, size), dtype=wp.vec3),
                    point=wp.empty((n, size), dtype=wp.vec3),
                    faces=planes,  # the validation turns a valid slot's planes into its faces
                ),
                scattered=PointEchoes(
                    source=wp.empty((n, capacity), dtype=wp.vec3),
                    extra_length=wp.empty((n, capacity), dtype=float),
                    amplitude=wp.empty((n, capacity), dtype=float),
                    count=wp.empty(n, dtype=wp.int32),
                    order=wp.empty((n, capacity), dtype=wp.int32),
                    ray=wp.empty((n, capacity if recorded else 0), dtype=wp.int32),
                ),
                hit_faces=wp.empty((n, tracer.ray_count if recorded else 0, kernels.MAX_ORDER), dtype=wp.int32),
                curved=PointEchoes(  # every slot counts; the kernel writes each
                    source=wp.empty((n, surfaces), dtype=wp.vec3),
                    extra_length=wp.empty((n, surfaces), dtype=float),
                    amplitude=wp.empty((n, surfaces), dtype=float),
                    count=wp.full(n, surfaces, dtype=wp.int32),
                    order=wp.empty((n, surfaces), dtype=wp.int32),
                ),
            )
        if cached:
            self._buffer_sets.append(buffers)
        return buffers

    def _host_checks_for(self, n: int, busy: HostChecks | None) -> HostChecks:
        """Host arrays for a batch's pose errors, poses behind a surface and overflow counts: the
        first n rows of one of two reused sets (page-locked on a GPU), never `busy`, those of the
        one batch whose checks may still be unread. Allocating page-locked memory is slow and
        freeing it waits for the GPU: batch shapes change with a scene's curved surfaces, the last
        batch of a trace and every group of pings traced again, and each used to bring new ones."""
        free = [k for k, checks in enumerate(self._check_sets) if busy is None or checks[0].ptr != busy[0].ptr]
        fits = [k for k in free if self._check_sets[k][0].shape[0] >= n]
        if fits:
            return tuple(a[:n] for a in self._check_sets[fits[0]])
        with _SPARE_LOCK:  # those of tracers that are gone (threads may trace on one device at once)
            spare = _SPARE_CHECKS[str(self.device)]
            large = next((k for k, held in enumerate(spare) if held[0].shape[0] >= n), None)
            checks = spare.pop(large) if large is not None else None
        if checks is None:
            pinned = self.device.is_cuda  # the GPU writes them behind its work
            checks = (
                wp.empty(n, dtype=float, device="cpu", pinned=pinned),
                wp.empty(n, dtype=wp.int32, device="cpu", pinned=pinned),
                wp.empty(n, dtype=wp.int32, device="cpu", pinned=pinned),
            )
        if len(self._check_sets) < 2:
            self._check_sets.append(checks)
        else:  # the set not in flight is too small: a larger one takes its place
            self._check_sets[free[0]] = checks
        return tuple(a[:n] for a in checks)

    def _queue_batch(
        self, scene: Scene, poses: PosesOnDevice, index: np.ndarray, size: int, busy: QueuedBatch | None
    ) -> QueuedBatch:
        """Queue the trace of the checked poses[index] with tables of `size` (into buffers and host
        copies other than those of `busy`, the batch in flight) and the copies of its pose checks
        and overflow counts to the host."""
        n = len(index)
        ws = warp_scene(scene, self.device)
        b = self._buffers_for(n, size, ws.curved.count, busy.buffers if busy else None)
        checks = self._host_checks_for(n, busy.checks if busy else None)
        emitter = wp.vec3(*self.sonar.emitter_m)
        with wp.ScopedDevice(self.device):
            batch_poses, batch_inverse = poses.select(index)
            reset_tables(b)
            # Read by the host after the trace (`_checked`): a bad pose still raises before any of
            # its echoes are used.
            wp.launch(lidar_kernels.pose_error, dim=n, inputs=[ws.mesh.id, batch_poses], outputs=[b.errors, b.behind])
            stages = BatchStages(
                scene=ws,
                buffers=b,
                poses=batch_poses,
                inverse=batch_inverse,
                size=size,
                inputs=self._stage_inputs(emitter),
                launch=device_calls(self.device)[2],  # the stages run in worker threads too
            )
            self._in_slices(stages.trace_rows, n)
            ready = self._copy_checks_to_host(b, checks)
        return QueuedBatch(index, size, b, checks, ready)

    def _stage_inputs(self, emitter: wp.vec3) -> TracerInputs:
        """What every batch's stages read of this tracer (the rays as they are now)."""
        tracer = self.config
        return TracerInputs(
            emitter=emitter,
            ray_dirs=self._ray_dirs,
            ray_energy=self._ray_energy,
            directivity=self._directivity,
            emit_min_cosine=self._emit_min_cosine,
            ray_count=tracer.ray_count,
            max_order=tracer.max_bounces + 1,
            edge_width_m=self.edge_width_m,
            scattering=tracer.scattering,
        )

    def _in_slices(self, trace_rows: Callable[[int, int], None], n: int) -> None:
        """Run trace_rows(first, last) over the n pings of a batch: in one call on a GPU, in
        slices in threads on the CPU (Warp runs a CPU launch on one core)."""
        threads = min(self.cpu_threads, n) if self.device.is_cpu else 1
        edges = np.linspace(0, n, threads + 1).round().astype(int).tolist()
        if threads == 1:
            trace_rows(0, n)
        else:
            with ThreadPoolExecutor(threads) as pool:
                list(pool.map(trace_rows, edges[:-1], edges[1:]))  # list(): raise a thread's error here

    def _copy_checks_to_host(self, b: TraceBuffers, checks: HostChecks) -> wp.Event | None:
        """Queue the copies of a batch's pose checks and overflow counts to the host, behind its
        trace in stream order; returns the event after them (None on the CPU)."""
        for device_array, host_array in zip((b.errors, b.behind, b.overflow), checks, strict=True):
            wp.copy(host_array, device_array)
        return wp.get_stream(self.device).record_event() if self.device.is_cuda else None

    @staticmethod
    def _checked(batch: QueuedBatch, behind: np.ndarray | None = None) -> np.ndarray:
        """Wait for a queued batch's trace (not for what was queued after it), check its poses
        (an error names the pose by its index in the trace; those behind a surface are marked in
        `behind`), and return per pose the count of sequence insertions that found no slot."""
        if batch.ready is not None:
            wp.synchronize_event(batch.ready)
        errors, behind_now, overflow = (a.numpy() for a in batch.checks)
        raise_for_bad_poses(errors, batch.index)
        if behind is not None:
            behind[batch.index] |= behind_now > 0
        return overflow.copy()


@dataclass
class PosesOnDevice:
    """The checked poses of one trace (N, 4, 4) on the host, and uploaded once: sensor-to-world
    and world-to-sensor, float32 mat44 (N,)."""

    host: np.ndarray
    poses: wp.array
    inverse: wp.array

    @staticmethod
    def upload(poses: np.ndarray, device) -> PosesOnDevice:
        with wp.ScopedDevice(device):
            return PosesOnDevice(
                poses,
                wp.array(poses.astype(np.float32), dtype=wp.mat44),
                wp.array(np.linalg.inv(poses).astype(np.float32), dtype=wp.mat44),
            )

    def select(self, index: np.ndarray) -> tuple[wp.array, wp.array]:
        """Poses and inverses of poses[index] on the device: a view of the uploaded ones for a run
        of consecutive indices; else (pings traced again, rare) gathered on the host and uploaded
        to the current device."""
        if index[-1] - index[0] + 1 == len(index):
            run = slice(int(index[0]), int(index[-1]) + 1)
            return self.poses[run], self.inverse[run]
        gathered = self.host[index]
        return (
            wp.array(gathered.astype(np.float32), dtype=wp.mat44),
            wp.array(np.linalg.inv(gathered).astype(np.float32), dtype=wp.mat44),
        )


HostChecks = tuple[wp.array, wp.array, wp.array]  # a batch's pose errors, poses behind, overflow counts
# Host check sets of tracers that are gone, by device, for new tracers to take: a suite that draws
# its sonar per episode (`randomised`) builds a tracer per episode, and freeing page-locked memory
# waits for the GPU (a tracer is gone only once its traces are: their copies are queued before any
# of the next tracer's, on the device's one stream).
_SPARE_CHECKS: defaultdict[str, list[HostChecks]] = defaultdict(list)
SPARE_CHECKS_KEPT = 8  # per device: what a few tracers at once leave; more are freed


_SPARE_LOCK = threading.Lock()


def _keep_spare(spare: list[HostChecks], sets: list[HostChecks]) -> None:
    with _SPARE_LOCK:
        spare.extend(sets[: max(SPARE_CHECKS_KEPT - len(spare), 0)])


@dataclass
class QueuedBatch:
    """A batch whose trace is queued: its pose indices, table size, buffers (and echoes), the host
    copies of its checks, and the event after them (None on the CPU, where launches finish before
    they return)."""

    index: np.ndarray
    size: int
    buffers: TraceBuffers
    checks: HostChecks
    ready: object | None
