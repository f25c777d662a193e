"""The simulated sonar: path tracer, recorder and beamformer composed into one sensor.

Sonar.trace       scene + poses -> Arrivals           (paths.PathTracer)
Sonar.record      Arrivals -> microphone signals      (signals.record)
Sonar.energyscape signals -> energyscapes             (beamform.energyscape)
Sonar.simulate    all three on the device, batch by batch, without host round trips
"""

from __future__ import annotations

import dataclasses
import functools
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import warp as wp
from tqdm.auto import tqdm

from scenes import Scene

from ..config import ProcessingConfig, SonarConfig, TracerConfig
from ..devices import current_in_thread, sleeping_event
from .beamform import beamformer, energyscape
from .kernels import beamform as beam_kernels
from .paths import Arrivals, PathTracer
from .poses import check_poses
from .seeds import ping_seeds
from .signals import record
from .signals import recorder as signals_recorder


class Sonar:
    """Simulated in-air sonar: emitter, microphone array, call, path tracer and processing.

    Args:
        config: The sensor, e.g. `SonarConfig.ertis()`.
        tracer: How echoes are searched for (`TracerConfig`: bounces, rays, table size,
            scattering, edge band); default `TracerConfig()`.
        device: Warp device.
        cpu_threads: On the CPU, the pings of a batch are traced, recorded and beamformed in this
            many threads (default: every core this process may use); Warp runs each CPU launch
            on one core.
        scattered_faces: Record the faces of scattered arrivals' paths (see `PathTracer`).
        **tracer_settings: TracerConfig fields to change, e.g. `max_bounces=1`, `ray_count=5000`.
    """

    def __init__(
        self,
        config: SonarConfig,
        tracer: TracerConfig | None = None,
        *,
        device=None,
        cpu_threads: int | None = None,
        scattered_faces: bool = False,
        **tracer_settings,
    ):
        self.config = config
        tracer = dataclasses.replace(tracer or TracerConfig(), **tracer_settings)
        self.tracer = PathTracer(
            config, tracer, device=device, cpu_threads=cpu_threads, scattered_faces=scattered_faces
        )
        self.cpu_threads = self.tracer.cpu_threads
        self.device = self.tracer.device

    @property
    def edge_width_m(self) -> float:
        """The edge band the tracer uses [m] (TracerConfig.edge_width_m resolved for this call)."""
        return self.tracer.edge_width_m

    def recorder(self, absorption: bool = True):
        """The recorder `simulate` uses (`signals.Recorder`), built on first use, when its tables
        (~0.5 MB for the eRTIS) go to the device from pageable memory: a caller that queues other
        work first may build it before (py-spy saw that upload wait behind an episode's LiDAR scan)."""
        return signals_recorder(self.config, absorption, str(self.device))

    def trace(self, scene: Scene, poses: np.ndarray, *, batch: int = 64) -> Arrivals:
        """Echoes of one ping from each pose; see `PathTracer.trace`."""
        return self.tracer.trace(scene, poses, batch=batch)

    def record(self, arrivals: Arrivals, *, pose_count: int | None = None, **options) -> np.ndarray:
        """Microphone signals (N, mics, samples) of traced pings; see `signals.record` for options."""
        return record(arrivals, self.config, pose_count=pose_count, device=self.device, **options)

    def energyscape(self, signals: np.ndarray, processing: ProcessingConfig | None = None, **settings) -> np.ndarray:
        """Energyscapes (N, R, A) (or (N, E, R, A)) of signals recorded with this sonar; see `beamform.energyscape`."""
        return energyscape(signals, self.config, processing, device=self.device, **settings)

    def simulate(
        self,
        scene: Scene,
        poses: np.ndarray,
        *,
        noise: str = "none",
        snr_db: float = 40.0,
        seed: int = 0,
        absorption: bool = True,
        batch: int | None = None,
        keep_signals: bool = False,
        progress: bool = False,
        on_pings: Callable[[int], None] | None = None,
        processing: ProcessingConfig | None = None,
        assumed_array: SonarConfig | None = None,
        dtype=np.float32,
    ) -> SonarFrames:
        """Trace, record and beamform every pose on the device, batch by batch (the fast path).

        The same as `energyscape(record(trace(scene, poses)))` but without the host round trips.

        Args:
            scene, poses: As for `trace`.
            noise, snr_db, seed, absorption: As for `signals.record`; ping i's noise comes
                from (seed, i).
            batch: Pings at once (default 256 on a GPU, 8 on the CPU).
            keep_signals: Also return the microphone signals (N, mics, samples).
            progress: Show a progress bar.
            on_pings: Called with the number of pings finished after each batch (progress of
                a caller that shows its own bar, e.g. `generate`).
            processing: The beamformer's settings (`ProcessingConfig`); default the eRTIS's.
            assumed_array: The array geometry and call the beamformer assumes, if not the
                simulated one (e.g. the nominal array while simulating a mismatched one).
            dtype: Of the energyscapes, float32 or float16 (what datasets store: on a GPU
                converted there, so half the bytes cross to the host; the same values as
                numpy's conversion).
        """
        poses = check_poses(poses)
        dtype = np.dtype(dtype)
        if dtype not in (np.float32, np.float16):
            raise ValueError(f"dtype must be float32 or float16, got {dtype}")
        batch = batch or (256 if self.device.is_cuda else 8)
        recorder = self.recorder(absorption)
        former = beamformer(
            assumed_array or self.config, samples=self.config.record_samples, processing=processing, device=self.device
        )
        images = np.empty((len(poses), *former.output_shape), dtype=dtype)
        copies = batch_copies(self.device, (batch, *former.output_shape), dtype) if self.device.is_cuda else None
        if copies is not None:
            copies.drop()  # a batch left by a call that failed midway
        kept = None
        if keep_signals:
            kept = np.empty((len(poses), self.config.microphone_count, self.config.record_samples), np.float32)
        threads = min(self.cpu_threads, batch) if self.device.is_cpu else 1

        def finish(index, keep, echoes, seeds, first: int, last: int) -> None:
            """Record and beamform rows first..last-1 of a traced batch (each ping on its own)."""
            rows = [e.rows(first, last) for e in echoes.buffers()]
            signals = recorder(rows, last - first, noise=noise, snr_db=snr_db, seeds=seeds[first:last])
            out = former(signals).reshape((last - first, *former.output_shape))
            mine, at = keep[first:last], index[first:last]
            if copies is not None:  # rows to trace again are left out when the copy lands
                copies.put(out, at, images, mine)
            else:  # CPU: out is host memory already
                images[at[mine]] = out.numpy()[mine]
            if kept is not None:
                kept[at[mine]] = signals.numpy()[mine]

        bar = tqdm(total=len(poses), unit="ping", disable=not progress, desc="sonar")
        pool = recording_threads(self.device, threads)
        for index, keep, echoes in self.tracer.traced(scene, poses, batch):
            # The echoes are used up here, before the next batch reuses their buffers. Rows left out
            # (to be traced again) are recorded too, at no extra launch, and dropped.
            batch_rows = functools.partial(finish, index, keep, echoes, ping_seeds(seed, index))
            edges = np.linspace(0, len(index), min(threads, len(index)) + 1).round().astype(int).tolist()
            list(pool.map(batch_rows, edges[:-1], edges[1:]))  # list(): raise a thread's error here
            bar.update(int(keep.sum()))
            if on_pings:
                on_pings(int(keep.sum()))
        if copies is not None:
            copies.land(images)
        bar.close()
        return SonarFrames(energyscape=images, signals=kept)


class BatchCopies:
    """A GPU's energyscapes to host memory behind its computation: each batch is copied on a side
    stream into one of a ring of reused page-locked buffers, then moved into its rows on the host
    by a helper thread once its copy is done, so that the calling thread goes on queueing GPU work
    meanwhile (that move is a host copy of 44 MB per batch of 256 pings and elevation, into fresh
    pages of the output: tens of ms at E = 3 that used to leave the GPU idle).

    The ring has DEPTH buffers so that a call waits only for the move of the batch DEPTH puts ago:
    at 3 bounces nearly every batch is followed by a small group of pings traced again, and with
    two buffers each full batch waited for the one before it to reach the host (~20 ms at 20k rays
    per ping, with nothing queued behind: the GPU idled ~30 % of the time).
    """

    DEPTH = 4

    def __init__(self, device, shape: tuple[int, ...], dtype=np.float32):
        self.stream = wp.Stream(device)
        self.dtype = wp.float16 if np.dtype(dtype) == np.float16 else wp.float32
        self.buffers = [wp.empty(shape, dtype=self.dtype, device="cpu", pinned=True) for _ in range(self.DEPTH)]
        self.landings: list[Future | None] = [None] * self.DEPTH  # the helper thread's move out of each buffer
        self.copied = [sleeping_event(device) for _ in range(self.DEPTH)]  # each buffer's copy done: its mover sleeps
        self.mover = ThreadPoolExecutor(  # one thread: moves land in order
            1, thread_name_prefix="batch-copies", initializer=current_in_thread, initargs=(device,)
        )
        self.turn = 0

    def put(self, out: wp.array, rows: np.ndarray, images: np.ndarray, keep: np.ndarray) -> None:
        """Queue the copy of `out` (n, ...) for images[rows[keep]] after the work queued so far,
        and its move into place once the copy is done. Rows not kept (traced again later) are
        never written, so a batch with some never waits for the GPU."""
        turn, self.turn = self.turn, (self.turn + 1) % self.DEPTH
        self._wait(turn)  # the move out of the buffer about to be refilled
        buffer = self.buffers[turn]
        if out.dtype != self.dtype:  # float16 on the device: half the bytes to copy and to land
            half = wp.empty(out.shape, dtype=self.dtype, device=out.device)
            convert = beam_kernels.to_float16
            wp.launch(convert, dim=out.size, inputs=[out.flatten()], outputs=[half.flatten()], device=out.device)
            out = half
        self.stream.wait_stream(wp.get_stream(out.device))
        wp.copy(buffer[: out.shape[0]], out, stream=self.stream)
        copied = (self.stream.record_event(self.copied[turn]), out, buffer, rows, keep)  # out: alive until copied
        self.landings[turn] = self.mover.submit(self._land, copied, images)

    def land(self, images: np.ndarray) -> None:
        """Wait until every queued batch is in place (raising a move's error here)."""
        for turn in self._in_order():
            self._wait(turn)

    def drop(self) -> None:
        """Let the moves of a call that failed midway finish (into its own output), so that
        their buffers can be reused; their errors belonged to that call."""
        for turn in self._in_order():
            if self.landings[turn] is not None:
                self.landings[turn].exception()  # waits
                self.landings[turn] = None

    def _in_order(self) -> list[int]:
        return [(self.turn + i) % self.DEPTH for i in range(self.DEPTH)]

    def _wait(self, turn: int) -> None:
        landing, self.landings[turn] = self.landings[turn], None
        if landing is not None:
            landing.result()  # raises the helper thread's error here

    @staticmethod
    def _land(copied, images: np.ndarray) -> None:
        event, _, buffer, rows, keep = copied
        wp.synchronize_event(event)
        batch = buffer.numpy()[: len(rows)]
        if keep.all() and len(rows) and (np.diff(rows) == 1).all():  # the usual case: a plain copy, without the GIL
            images[rows[0] : rows[0] + len(rows)] = batch
        elif keep.all():  # no masked temporary of the whole batch
            images[rows] = batch
        else:
            images[rows[keep]] = batch[keep]


def _this_thread() -> tuple[int, int]:
    """The key of objects kept per calling thread that hold threads of their own: per process too,
    since a forked child has none of its parent's threads and its main thread the same ident (the
    parent's pool would take its work and never run it)."""
    return os.getpid(), threading.get_ident()


@functools.lru_cache(maxsize=4)
def _batch_copies(device: str, shape: tuple[int, ...], dtype, thread: tuple[int, int]) -> BatchCopies:
    return BatchCopies(device, shape, dtype)


@functools.lru_cache(maxsize=8)
def _recording_threads(device: str, threads: int, caller: tuple[int, int]) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(
        threads, thread_name_prefix="sonar-record", initializer=current_in_thread, initargs=(device,)
    )


def recording_threads(device, threads: int) -> ThreadPoolExecutor:
    """The threads `simulate` records and beamforms a batch's rows in, each with the device's
    context current (a thread without one made CUDA's runtime open a context on GPU 0), kept per
    device, count and calling thread (`_this_thread`): a pool made per call cost a `generate` worker
    its thread's start every episode (~2 ms under load, py-spy of `randomised`, multi_gpu/session37)."""
    return _recording_threads(str(device), threads, _this_thread())


def batch_copies(device, shape: tuple[int, ...], dtype=np.float32) -> BatchCopies:
    """Reused BatchCopies for a device and batch shape (page-locked memory is slow to allocate);
    one per thread (`_this_thread`), so that two threads simulating on one GPU never share buffers."""
    return _batch_copies(str(device), tuple(shape), np.dtype(dtype), _this_thread())


@dataclass
class SonarFrames:
    """Output of `Sonar.simulate`: energyscapes (N, R, A), or (N, E, R, A) at E elevations, and,
    if kept, signals (N, mics, samples)."""

    energyscape: np.ndarray
    signals: np.ndarray | None = None
