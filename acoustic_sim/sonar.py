"""The simulated sonar: path tracer, recorder and beamformer composed into one sensor.

Sonar.trace       scene + poses -> Arrivals           (paths.PathTracer)
Sonar.record      Arrivals -> microphone signals      (signals.record)
Sonar.energyscape signals -> energyscapes             (beamform.energyscape)
Sonar.simulate    all three on the device, batch by batch, without host round trips
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import warp as wp
from tqdm.auto import tqdm

from scenes import Scene

from .beamform import beamformer, energyscape
from .config import ProcessingConfig, SonarConfig, TracerConfig
from .paths import Arrivals, PathTracer
from .poses import check_poses
from .signals import ping_seeds, record
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
        **tracer_settings: TracerConfig fields to change, e.g. `max_bounces=1`, `ray_count=5000`.
    """

    def __init__(
        self,
        config: SonarConfig,
        tracer: TracerConfig | None = None,
        *,
        device=None,
        cpu_threads: int | None = None,
        **tracer_settings,
    ):
        self.config = config
        tracer = dataclasses.replace(tracer or TracerConfig(), **tracer_settings)
        self.tracer = PathTracer(config, tracer, device=device, cpu_threads=cpu_threads)
        self.cpu_threads = self.tracer.cpu_threads
        self.device = self.tracer.device

    @property
    def edge_width_m(self) -> float:
        """The edge band the tracer uses [m] (TracerConfig.edge_width_m resolved for this call)."""
        return self.tracer.edge_width_m

    def trace(self, scene: Scene, poses: np.ndarray, *, batch: int = 64) -> Arrivals:
        """Echoes of one ping from each pose; see `PathTracer.trace`."""
        return self.tracer.trace(scene, poses, batch=batch)

    def record(self, arrivals: Arrivals, *, pose_count: int | None = None, **options) -> np.ndarray:
        """Microphone signals (N, mics, samples) of traced pings; see `signals.record` for options."""
        return record(arrivals, self.config, pose_count=pose_count, device=self.device, **options)

    def energyscape(self, signals: np.ndarray, processing: ProcessingConfig | None = None, **settings) -> np.ndarray:
        """Energyscapes (N, R, A) of signals recorded with this sonar; see `beamform.energyscape`."""
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
        """
        poses = check_poses(poses)
        batch = batch or (256 if self.device.is_cuda else 8)
        recorder = signals_recorder(self.config, absorption, str(self.device))
        former = beamformer(
            assumed_array or self.config, samples=self.config.record_samples, processing=processing, device=self.device
        )
        # On a GPU the energyscapes go straight into page-locked host memory, each batch by an
        # asynchronous copy that the next batch's work queues behind: no pageable staging, no host
        # copy between batches (the GPU idled ~22 % of the time in both, profile_sonar.py).
        host = wp.empty((len(poses), *former.output_shape), dtype=float, device="cpu", pinned=self.device.is_cuda)
        images = host.numpy()
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
            if mine.all() and at[-1] - at[0] == len(at) - 1:  # consecutive poses: one copy into place
                wp.copy(host[int(at[0]) : int(at[-1]) + 1], out)
            else:  # a batch with rows to trace again
                images[at[mine]] = out.numpy()[mine]
            if kept is not None:
                kept[at[mine]] = signals.numpy()[mine]

        bar = tqdm(total=len(poses), unit="ping", disable=not progress, desc="sonar")
        with ThreadPoolExecutor(threads) as pool:
            for index, keep, echoes in self.tracer.traced(scene, poses, batch):
                # The echoes are used up here, before the next batch reuses their buffers. Rows left out
                # (to be traced again) are recorded too, at no extra launch, and dropped.
                batch_rows = functools.partial(finish, index, keep, echoes, ping_seeds(seed, index))
                edges = np.linspace(0, len(index), min(threads, len(index)) + 1).round().astype(int).tolist()
                list(pool.map(batch_rows, edges[:-1], edges[1:]))  # list(): raise a thread's error here
                bar.update(int(keep.sum()))
                if on_pings:
                    on_pings(int(keep.sum()))
        wp.synchronize_device(self.device)  # the last copies into `images`
        bar.close()
        return SonarFrames(energyscape=images, signals=kept)


@dataclass
class SonarFrames:
    """Output of `Sonar.simulate`: energyscapes (N, R, A) and, if kept, signals (N, mics, samples)."""

    energyscape: np.ndarray
    signals: np.ndarray | None = None
